//! Shared test helpers: run the binary, locate robots, read programs back.

#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The shared folder of public robots and measured data, `../shared` beside the checkout (never
/// copied into the project; the library's unit tests look there too).
pub fn shared() -> PathBuf {
    let dir = root().join("../shared");
    assert!(
        dir.join("robots").is_dir(),
        "the shared robots are not at {}: the checkout must sit beside shared/",
        dir.display()
    );
    dir
}

/// A shared public robot's URDF (`shared()/robots/NAME/robot.urdf`).
pub fn shared_robot(name: &str) -> PathBuf {
    shared().join("robots").join(name).join("robot.urdf")
}

pub const SHARED_ROBOTS: &[&str] = &[
    "abb_irb6700_200_260",
    "kuka_kr210_l150",
    "kuka_kr120_r2500pro",
    "fanuc_r2000ic_165f",
];

pub fn nj130_dh() -> PathBuf {
    root().join("robots/comau_nj130/robot.dh.toml")
}

pub fn nj130_urdf() -> PathBuf {
    root().join("robots/comau_nj130/robot.urdf")
}

pub struct Run {
    pub code: i32,
    pub stdout: String,
    pub stderr: String,
}

pub fn edbbgen<I, S>(args: I) -> Run
where
    I: IntoIterator<Item = S>,
    S: AsRef<std::ffi::OsStr>,
{
    edbbgen_env(args, &[])
}

pub fn edbbgen_env<I, S>(args: I, env: &[(&str, &str)]) -> Run
where
    I: IntoIterator<Item = S>,
    S: AsRef<std::ffi::OsStr>,
{
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_edbbgen"));
    cmd.args(args);
    for (k, v) in env {
        cmd.env(k, v);
    }
    let Output {
        status,
        stdout,
        stderr,
    } = cmd.output().expect("run edbbgen");
    Run {
        code: status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&stdout).into_owned(),
        stderr: String::from_utf8_lossy(&stderr).into_owned(),
    }
}

pub fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().expect("temp dir")
}

/// Joint vectors (degrees) of every motion line (G0/G1) of an emitted ngc program, read back
/// from the text, independently of the compiler's memory.
pub fn program_poses(text: &str) -> Vec<[f64; 6]> {
    let mut out = Vec::new();
    for line in text.lines() {
        let code = line.split('(').next().unwrap_or("").trim();
        if !(code.starts_with("G0 ") || code.starts_with("G1 ")) {
            continue;
        }
        let mut q = [f64::NAN; 6];
        for word in code.split_whitespace().skip(1) {
            let (letter, value) = word.split_at(1);
            if let Some(i) = "XYZABC".find(letter) {
                q[i] = value.parse().expect("number");
            }
        }
        assert!(
            q.iter().all(|v| v.is_finite()),
            "incomplete motion line: {line}"
        );
        out.push(q);
    }
    out
}

pub fn load(path: &Path) -> edbbgen::robot::Robot {
    edbbgen::robot::load(path, &Default::default()).expect("robot loads")
}

/// Asserts that every pose of `text` lies in the bar shell [min, max] mm around `fixture_mm`
/// (the MAP computed by FK of `robot` with `tool_mm` in the flange frame) and within the limits.
pub fn assert_in_shell(
    robot: &edbbgen::robot::Robot,
    text: &str,
    fixture_mm: [f64; 3],
    tool_mm: [f64; 3],
    bar_mm: (f64, f64),
) -> usize {
    use nalgebra::Vector3;
    let poses = program_poses(text);
    assert!(!poses.is_empty(), "program has no poses");
    let fix = Vector3::from(fixture_mm) * 1e-3;
    let tool = Vector3::from(tool_mm) * 1e-3;
    let (lo, hi) = robot.limits();
    for q in &poses {
        let q: [f64; 6] = q.map(|d| d.to_radians());
        for i in 0..6 {
            // Emitted values lie on the 0.001 deg grid the plan itself uses.
            assert!(
                q[i] >= lo[i] - 1e-6 && q[i] <= hi[i] + 1e-6,
                "joint {} outside its limits: {q:?}",
                i + 1
            );
        }
        let p = robot.point(&q, &tool);
        let l = (p - fix).norm() * 1e3;
        // The plan is checked on exactly these values; 0.01 mm allows for the FK here.
        assert!(
            l >= bar_mm.0 - 0.01 && l <= bar_mm.1 + 0.01,
            "bar length {l} mm outside {bar_mm:?} at {q:?}"
        );
        assert!(p.z > 0.0, "MAP below the floor");
    }
    poses.len()
}

//! The determinism sweep: every output kind (programs in every dialect, the compile report and
//! page, the simulated data, the diagnosis and calibration reports, plots and pages, the
//! calibrated robot file, the ISO circle, the LDBB program, data and report, the placement
//! report and the cells it writes, and the JSON
//! printed by model, verify and dialects) is byte-identical on 1 and 2 threads and across two
//! runs in different directories.

use crate::common::*;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::Command;

/// Runs the whole loop in `dir` (relative output paths) with `threads` rayon threads and returns
/// every output: files by name, printed JSON by command.
fn run_all(dir: &Path, threads: &str) -> BTreeMap<String, Vec<u8>> {
    let nj = nj130_dh().display().to_string();
    let abb = shared_robot("abb_irb6700_200_260").display().to_string();
    std::fs::write(
        dir.join("truth.toml"),
        "noise_um = 0.5\n[geometric]\na2 = 0.12\ntheta3 = 0.01\n[cyclic_error]\njoint = 4\ncos_deg = [0.002]\n",
    )
    .unwrap();
    let setup = std::fs::read_to_string(root().join("examples/ldbb/setup.toml"))
        .unwrap()
        .replace(
            "../../../shared/robots/abb_irb6700_200_260/robot.urdf",
            &abb,
        )
        .replace("[125.0, 250.0, 375.0, 500.0, 625.0]", "[125.0, 250.0]")
        .replace("repeats = 3", "repeats = 1");
    std::fs::write(dir.join("setup.toml"), setup).unwrap();
    std::fs::copy(
        root().join("examples/ldbb/truth.toml"),
        dir.join("ldbb_truth.toml"),
    )
    .unwrap();

    let fix = "258,1468,708";
    let mut printed = BTreeMap::new();
    let mut run = |name: &str, args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_edbbgen"))
            .args(args)
            .arg("-q")
            .current_dir(dir)
            .env("RAYON_NUM_THREADS", threads)
            .output()
            .expect("run edbbgen");
        assert!(
            out.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        printed.insert(format!("stdout of {name}"), out.stdout);
    };
    run(
        "compile",
        &[
            &nj,
            "--fixture",
            fix,
            "-o",
            "nj130.nc",
            "--json",
            "report.json",
            "--html",
            "report.html",
        ],
    );
    for (dialect, file) in [
        ("sinumerik", "NJ130.MPF"),
        ("krl", "nj130.src"),
        ("rapid", "nj130.mod"),
        ("urscript", "nj130.script"),
        ("fanuc", "NJ130.LS"),
    ] {
        run(
            dialect,
            &[&nj, "--fixture", fix, "--dialect", dialect, "-o", file],
        );
    }
    run(
        "model",
        &["model", &nj, "--fixture", fix, "--json", "--samples", "100"],
    );
    run("verify", &["verify", &nj, "nj130.nc", "--json"]);
    run("dialects", &["dialects", "--json"]);
    run(
        "simulate",
        &[
            "simulate",
            &nj,
            "nj130.nc",
            "--truth",
            "truth.toml",
            "-o",
            "m.csv",
        ],
    );
    run(
        "diagnose",
        &[
            "diagnose",
            &nj,
            "--fixture",
            fix,
            "--measured",
            "m.csv",
            "--json",
            "d.json",
            "--plot",
            "d.svg",
            "--html",
            "d.html",
        ],
    );
    run(
        "calibrate",
        &[
            "calibrate",
            &nj,
            "--measured",
            "m.csv",
            "--fixture",
            fix,
            "-o",
            "cal.dh.toml",
            "--json",
            "c.json",
            "--plot",
            "c.svg",
            "--html",
            "c.html",
        ],
    );
    run(
        "circle",
        &["circle", &nj, "--fixture", fix, "-o", "circle.nc"],
    );
    run(
        "ldbb-circle",
        &[
            "ldbb-circle",
            &abb,
            "--setup",
            "setup.toml",
            "--step",
            "5",
            "-o",
            "ldbb.nc",
        ],
    );
    run(
        "simulate-ldbb",
        &[
            "simulate-ldbb",
            "--setup",
            "setup.toml",
            "--truth",
            "ldbb_truth.toml",
            "-o",
            "loaded.csv",
            "--reference",
            "lt.csv",
        ],
    );
    run(
        "ldbb",
        &[
            "ldbb",
            "loaded.csv",
            "--setup",
            "setup.toml",
            "--reference",
            "lt.csv",
            "--json",
            "l.json",
            "--plot",
            "l.svg",
            "--html",
            "l.html",
        ],
    );

    let cell = root()
        .join("robots/comau_nj130/cell.toml")
        .display()
        .to_string();
    run(
        "place",
        &[
            "place",
            &nj,
            "--cell",
            &cell,
            "--grid",
            "3,3,2",
            "--top",
            "2",
            "--count",
            "2",
            "--json",
            "p.json",
            "--html",
            "p.html",
            "--write-cell",
            "pc",
        ],
    );
    let mut all = printed;
    for e in std::fs::read_dir(dir).unwrap() {
        let e = e.unwrap();
        all.insert(
            e.file_name().to_string_lossy().into_owned(),
            std::fs::read(e.path()).unwrap(),
        );
    }
    all
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn every_output_is_byte_identical_on_any_thread_count_and_run() {
    let (a, b, c) = (tempdir(), tempdir(), tempdir());
    let one = run_all(a.path(), "1");
    let two = run_all(b.path(), "2");
    let again = run_all(c.path(), "2");
    // Every kind is there: 6 dialects, 3 pages, 3 plots, the calibrated file, the data.
    for name in [
        "nj130.nc",
        "NJ130.MPF",
        "nj130.src",
        "nj130.mod",
        "nj130.script",
        "NJ130.LS",
        "report.json",
        "report.html",
        "m.csv",
        "d.json",
        "d.svg",
        "d.html",
        "cal.dh.toml",
        "c.json",
        "c.svg",
        "c.html",
        "circle.nc",
        "ldbb.nc",
        "loaded.csv",
        "lt.csv",
        "l.json",
        "l.svg",
        "l.html",
        "p.json",
        "p.html",
        "pc-1.cell.toml",
        "pc-2.cell.toml",
    ] {
        assert!(one.contains_key(name), "{name} was not written");
    }
    assert_eq!(
        one.keys().collect::<Vec<_>>(),
        two.keys().collect::<Vec<_>>()
    );
    let differ = |x: &BTreeMap<String, Vec<u8>>, y: &BTreeMap<String, Vec<u8>>| -> Vec<String> {
        x.iter()
            .filter(|(k, v)| y.get(*k) != Some(*v))
            .map(|(k, _)| k.clone())
            .collect()
    };
    assert!(
        differ(&one, &two).is_empty(),
        "1 vs 2 threads: {:?}",
        differ(&one, &two)
    );
    assert!(
        differ(&two, &again).is_empty(),
        "run to run: {:?}",
        differ(&two, &again)
    );
}

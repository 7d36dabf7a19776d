//! Controller dialects (issue 11): every bundled dialect for every shipped cell — the NJ-130's
//! and the shared robots' test cells — compiled once per cell (coarse grid) and written in each
//! dialect from that one plan. For each program: an insta snapshot (`<dialect>@<cell>`), the
//! read-back through the dialect's reader (same joint values to the printed precision, same
//! blend/exact-stop pattern, same pauses, same support marks), `verify` (in the compiler, and
//! the CLI on the written file), a strict structural check per language that owes nothing to
//! edbbgen's readers (`structure`), LinuxCNC's `rs274` on the ngc programs and `rapidchecker`
//! on the RAPID modules.

use crate::common::*;
use crate::snapshots::assert_golden;
use crate::structure;
use edbbgen::dialect::{self, Step};
use edbbgen::ir::Program;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

pub const DIALECTS: [&str; 6] = ["ngc", "sinumerik", "krl", "rapid", "urscript", "fanuc"];

/// One shipped cell, compiled once, written in every dialect.
pub struct Cell {
    pub case: &'static str,
    pub robot_path: PathBuf,
    pub cell_path: PathBuf,
    pub robot: edbbgen::robot::Robot,
    pub opts: edbbgen::pipeline::CompileOptions,
    /// (dialect, program, text), in [`DIALECTS`] order.
    pub programs: Vec<(&'static str, Program, String)>,
}

fn compile_cell(case: &'static str, robot_path: PathBuf, cell_path: PathBuf) -> Cell {
    let spec = edbbgen::cell::load(&cell_path).expect("cell");
    let robot = edbbgen::robot::load(
        &robot_path,
        &edbbgen::robot::LoadOptions {
            speeds: spec.speeds,
            ..Default::default()
        },
    )
    .expect("robot");
    let mut opts = edbbgen::pipeline::CompileOptions::new(spec.fixture.expect("fixture"));
    opts.cell = spec;
    opts.step = [20f64.to_radians(); 6];
    opts.max_candidates = 600;
    let ngc = edbbgen::emit::dialect("ngc").unwrap();
    let compiled = edbbgen::pipeline::compile(&robot, &opts, ngc, &edbbgen::sample::NoProgress)
        .unwrap_or_else(|e| panic!("{case}: {e}"));
    // The compiler's own text is the ngc program; every other dialect is the same plan
    // written for its controller (and verified like the compiler's).
    let programs = DIALECTS
        .iter()
        .map(|d| {
            if *d == "ngc" {
                return (*d, compiled.program.clone(), compiled.text.clone());
            }
            let (p, t) = edbbgen::pipeline::retarget(
                &robot,
                &opts,
                &compiled,
                edbbgen::emit::dialect(d).unwrap(),
            )
            .unwrap_or_else(|e| panic!("{case} in {d}: {e}"));
            (*d, p, t)
        })
        .collect();
    Cell {
        case,
        robot_path,
        cell_path,
        robot,
        opts,
        programs,
    }
}

/// Every shipped cell, compiled once for the whole test binary.
pub fn cells() -> &'static [Cell] {
    static CELLS: OnceLock<Vec<Cell>> = OnceLock::new();
    CELLS.get_or_init(|| {
        let mut v = vec![compile_cell(
            "nj130_cell",
            nj130_dh(),
            root().join("robots/comau_nj130/cell.toml"),
        )];
        for name in SHARED_ROBOTS {
            v.push(compile_cell(
                name,
                shared_robot(name),
                root().join("tests/cells").join(format!("{name}.toml")),
            ));
        }
        v
    })
}

pub fn cell(case: &str) -> &'static Cell {
    cells().iter().find(|c| c.case == case).expect("case")
}

impl Cell {
    pub fn text(&self, d: &str) -> &str {
        &self.programs.iter().find(|p| p.0 == d).unwrap().2
    }
    pub fn program(&self, d: &str) -> &Program {
        &self.programs.iter().find(|p| p.0 == d).unwrap().1
    }
}

/// The file a program is written to: the dialect's usual extension, the program's name as stem.
pub fn file_for(dir: &Path, d: &str, program: &Program) -> PathBuf {
    let ext = &dialect::by_name(d).unwrap().extensions[0];
    dir.join(format!("{}.{ext}", program.header.program_name))
}

/// The events of a program as the plan says: M = move (with S when a support pose, B when it
/// ends in a blend), P = the operator's pause.
fn planned_events(p: &Program) -> Vec<String> {
    let mut ev = Vec::new();
    for m in &p.moves {
        if m.remove_before {
            ev.push("P".to_string());
        }
        ev.push(format!(
            "M{}{}",
            if m.support { "S" } else { "" },
            if m.blend_mm > 0.0 { "B" } else { "" }
        ));
        if m.mount_after {
            ev.push("P".to_string());
        }
    }
    ev.push("P".to_string());
    ev
}

fn read_events(parsed: &dialect::Parsed) -> Vec<String> {
    parsed
        .lines
        .iter()
        .filter_map(|l| match &l.step {
            Step::Move { blend, .. } => Some(format!(
                "M{}{}",
                if l.comment.as_deref().is_some_and(|c| c.contains("support")) {
                    "S"
                } else {
                    ""
                },
                if blend.is_some() { "B" } else { "" }
            )),
            Step::Pause => Some("P".to_string()),
            _ => None,
        })
        .collect()
}

#[test]
fn every_dialect_of_every_cell_is_golden_and_reads_back_as_planned() {
    for c in cells() {
        let base = &c.programs[0].1;
        for (d, program, text) in &c.programs {
            let label = format!("{d}@{}", c.case);
            assert_golden(&label, text);
            // The same plan in every dialect: poses, order, blends, times.
            assert_eq!(program.moves.len(), base.moves.len(), "{label}");
            for (a, b) in program.moves.iter().zip(&base.moves) {
                assert_eq!(
                    (a.q_deg, a.blend_mm, a.time_s),
                    (b.q_deg, b.blend_mm, b.time_s),
                    "{label}"
                );
            }
            let dl = dialect::by_name(d).unwrap();
            let map = edbbgen::controller::ControllerMap::resolve(
                c.opts.cell.controller.as_ref(),
                &dl.defaults(),
                d,
                &c.robot,
            )
            .unwrap();
            let parsed = dl
                .read(text, &map)
                .unwrap_or_else(|e| panic!("{label}: {e}"));
            // Joint values: to the printed precision (half a unit of the last printed digit,
            // through the unit conversion for radians).
            let tol = match map.units {
                edbbgen::controller::Units::Deg => 1e-9,
                // Radians are cut toward zero at 7 decimals (see emit::target).
                edbbgen::controller::Units::Rad => (1e-7f64).to_degrees() * 1.001,
            };
            let targets: Vec<[f64; 6]> = parsed.targets().map(|(_, t)| *t).collect();
            assert_eq!(targets.len(), program.moves.len(), "{label}: motion count");
            for (k, (t, m)) in targets.iter().zip(&program.moves).enumerate() {
                for i in 0..6 {
                    assert!(
                        (t[i] - m.q_deg[i]).abs() <= tol,
                        "{label}: move {} joint {}: read {} planned {}",
                        k + 1,
                        i + 1,
                        t[i],
                        m.q_deg[i]
                    );
                }
            }
            // Blends, exact stops, pauses and support marks in the same order.
            assert_eq!(read_events(&parsed), planned_events(program), "{label}");
            let blends: Vec<f64> = parsed
                .lines
                .iter()
                .filter_map(|l| match &l.step {
                    Step::Move { blend: Some(b), .. } => Some(*b),
                    _ => None,
                })
                .collect();
            assert!(
                blends
                    .iter()
                    .all(|b| (b - program.header.blend_mm).abs() < 1e-9),
                "{label}: blend distances {blends:?}"
            );
            // Each move takes at least its planned time, and no more than the language's
            // rounding adds (integer percentages: less than 1 % of the speed).
            let speeds = c.robot.max_speeds();
            let mut prev: Option<[f64; 6]> = None;
            let mut k = 0;
            for l in &parsed.lines {
                if let Step::Move { axes, .. } = &l.step {
                    if let (Some(p), true) = (prev, k > 0) {
                        let t = parsed.duration(&p, &l.step, &speeds).expect("a timed move");
                        let m = &program.moves[k];
                        let planned = m.time_s;
                        assert!(
                            t >= planned * (1.0 - 1e-9),
                            "{label}: move {} takes {t} s, less than the planned {planned} s",
                            k + 1
                        );
                        if matches!(*d, "krl" | "fanuc") {
                            // An integer percentage, rounded down, capped at 100 %.
                            let expect =
                                planned * m.speed_pct / edbbgen::emit::percent(m.speed_pct) as f64;
                            assert!(
                                (t - expect).abs() <= 1e-9 * expect,
                                "{label}: move {}: {t} s, expected {expect} s",
                                k + 1
                            );
                        } else {
                            // Rounded to the printed time (1 ms in RAPID) or feed (1e-4).
                            assert!(
                                t <= planned * (1.0 + 1e-5) + 1e-3,
                                "{label}: move {}: {t} s, planned {planned} s",
                                k + 1
                            );
                        }
                    }
                    prev = Some(*axes);
                    k += 1;
                }
            }
            // The header facts verify and simulate take from the text.
            let h = &program.header;
            let fixture = format!(
                "{:.3}, {:.3}, {:.3} mm in the robot base frame",
                h.fixture_mm[0], h.fixture_mm[1], h.fixture_mm[2]
            );
            assert_eq!(
                parsed.header_value("fixture"),
                Some(fixture.as_str()),
                "{label}"
            );
            assert_eq!(
                parsed.header_value("controller"),
                Some(map.describe().as_str()),
                "{label}"
            );
            assert_eq!(
                parsed.header_value("inputs sha256"),
                Some(h.inputs_sha256.as_str()),
                "{label}"
            );
            // The language's own rules, checked without edbbgen's reader.
            let stem = &program.header.program_name;
            structure::check(d, text, stem).unwrap_or_else(|e| panic!("{label}: {e}"));
        }
    }
}

/// `verify` ran on every program inside `retarget` (as in the compiler); the CLI reads the
/// written files too — the dialect from the extension, the mapping from the cell — for the
/// NJ-130's cell and the J2/J3-coupled FANUC cell.
#[test]
fn the_cli_verifies_the_written_programs() {
    for c in [cell("nj130_cell"), cell("fanuc_r2000ic_165f")] {
        let dir = tempdir();
        for (d, program, text) in &c.programs {
            let path = file_for(dir.path(), d, program);
            std::fs::write(&path, text).unwrap();
            let r = edbbgen([
                "verify",
                c.robot_path.to_str().unwrap(),
                path.to_str().unwrap(),
                "--cell",
                c.cell_path.to_str().unwrap(),
                "-q",
            ]);
            assert_eq!(r.code, 0, "{d}@{}: {}", c.case, r.stderr);
            assert!(r.stdout.contains(": ok: "), "{}", r.stdout);
        }
    }
}

#[test]
fn every_template_prints_every_header_field() {
    let h = &cell("nj130_cell").program("ngc").header;
    let fields: Vec<String> = match serde_json::to_value(h).unwrap() {
        serde_json::Value::Object(m) => m.keys().cloned().collect(),
        _ => unreachable!(),
    };
    assert!(fields.len() >= 24, "{fields:?}");
    for d in DIALECTS {
        let src = edbbgen::emit::dialect(d).unwrap();
        for f in &fields {
            assert!(
                src.contains(&format!("h.{f}")),
                "templates/{d}.j2 does not print the header field {f}"
            );
        }
    }
}

#[test]
fn rs274_accepts_every_ngc_program() {
    for c in cells() {
        crate::linuxcnc::check(&format!("ngc@{}", c.case), c.text("ngc"));
    }
}

/// `rapidchecker` (PyPI) under target/rapidchecker-venv, where `.ci/run` and `make
/// rapidchecker` install it. In CI (`CI` set) a missing checker fails the test; locally the test
/// says loudly that it checked nothing.
fn rapidchecker() -> Option<PathBuf> {
    let py = root().join("target/rapidchecker-venv/bin/python");
    if py.is_file() {
        return Some(py);
    }
    if std::env::var_os("CI").is_some() {
        panic!(
            "rapidchecker is not installed under target/rapidchecker-venv (.ci/run installs it: make rapidchecker)"
        );
    }
    eprintln!(
        "NOTE: rapidchecker is not installed (make rapidchecker): the RAPID modules were NOT checked by it"
    );
    None
}

fn run_rapidchecker(py: &Path, text: &str) -> (bool, String) {
    let dir = tempdir();
    let path = dir.path().join("EDBB.mod");
    std::fs::write(&path, text).unwrap();
    let out = std::process::Command::new(py)
        .args(["-m", "rapidchecker"])
        .arg(&path)
        .current_dir(dir.path())
        .output()
        .expect("run rapidchecker");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr),
    )
}

#[test]
fn rapidchecker_accepts_every_rapid_module_and_rejects_a_broken_one() {
    let Some(py) = rapidchecker() else { return };
    for c in cells() {
        let (ok, msg) = run_rapidchecker(&py, c.text("rapid"));
        assert!(ok, "rapid@{}: {msg}", c.case);
    }
    let good = cell("nj130_cell").text("rapid");
    for (from, to) in [
        ("  ENDPROC\n", ""),
        (", zEdbb, tEdbb;", ", zEdbb tEdbb;"),
        ("PROC main()", "proc main()"),
    ] {
        let bad = good.replacen(from, to, 1);
        assert_ne!(&bad, good);
        let (ok, msg) = run_rapidchecker(&py, &bad);
        assert!(
            !ok,
            "rapidchecker accepted a module with {from:?} -> {to:?}: {msg}"
        );
    }
}

#[test]
fn the_structural_checks_fail_on_hand_broken_programs() {
    let c = cell("nj130_cell");
    let broken: &[(&str, &str, &str, &str)] = &[
        ("krl", "\nEND", "\n", "END"),
        ("krl", "DECL INT edbbHandle\n", "", "not declared"),
        ("krl", "$VEL_AXIS[1] = 100", "$VEL_AXIS[1] = 130", "1..100"),
        ("krl", "PTP {A1", "PTP {{A1", "unbalanced"),
        ("urscript", "\nend", "\n", "end"),
        ("urscript", "blocking=True", "blocking=False", "blocking"),
        ("urscript", "movej([", "movej((", "unbalanced"),
        ("fanuc", "LINE_COUNT = ", "LINE_COUNT = 1", "LINE_COUNT"),
        (
            "fanuc",
            "MESSAGE[Mount the EDBB]",
            "MESSAGE[Mount the EDBB between the fixture]",
            "24",
        ),
        ("fanuc", "   2:  ", "   3:  ", "line number"),
        ("fanuc", "P[1]{", "P[9999]{", "P[1]"),
        ("sinumerik", "\nM30", "\n", "M30"),
        ("sinumerik", "ADIS=10.000", "ADIS=-10.000", "ADIS >= 0"),
        ("sinumerik", "FGROUP(X1, ", "FGROUP(", "FGROUP"),
        ("rapid", "ENDMODULE", "", "ENDMODULE"),
        (
            "rapid",
            "TPWrite \"Remove the EDBB.\"",
            &format!("TPWrite \"{}\"", "x".repeat(81)),
            "80",
        ),
        ("ngc", "\nM2", "\n", "M2"),
    ];
    for (d, from, to, needle) in broken {
        let good = c.text(d);
        let stem = &c.program(d).header.program_name;
        if let Err(e) = structure::check(d, good, stem) {
            panic!("{d}: the good program fails: {e}");
        }
        let bad = good.replacen(from, to, 1);
        assert_ne!(&bad, good, "{d}: {from:?} not found");
        let e =
            structure::check(d, &bad, stem).expect_err(&format!("{d}: {from:?} -> {to:?} passed"));
        assert!(e.contains(needle), "{d}: {from:?} -> {to:?}: {e}");
    }
    // Names the language cannot carry.
    assert!(structure::check("krl", c.text("krl"), "other").is_err());
    assert!(structure::check("fanuc", c.text("fanuc"), "OTHER").is_err());
}

//! Safe programs: every shipped cell compiles to a program that `verify` passes;
//! hand-made unsafe programs fail `verify` naming the violation; support poses are inserted
//! where a plain joint move fails; random cells never yield a panic or an unsafe file.

use crate::common::*;
use edbbgen::cell::CellSpec;
use edbbgen::ir::Reason;
use edbbgen::model::MeasurementModel;
use edbbgen::safety::{Checker, Extremes};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use std::path::{Path, PathBuf};

pub fn nj130_cell() -> PathBuf {
    root().join("robots/comau_nj130/cell.toml")
}

pub fn test_cell(robot: &str) -> PathBuf {
    root().join("tests/cells").join(format!("{robot}.toml"))
}

fn compile_and_verify(robot: &Path, cell: &Path, fast: &[&str]) -> String {
    let dir = tempdir();
    let out = dir.path().join("p.nc");
    let mut args = vec![
        robot.display().to_string(),
        "--cell".into(),
        cell.display().to_string(),
        "-o".into(),
        out.display().to_string(),
    ];
    args.extend(fast.iter().map(|s| s.to_string()));
    let r = edbbgen(&args);
    assert_eq!(r.code, 0, "{}: {}", robot.display(), r.stderr);
    let v = edbbgen([
        "verify".to_string(),
        robot.display().to_string(),
        out.display().to_string(),
        "--cell".into(),
        cell.display().to_string(),
    ]);
    assert_eq!(
        v.code,
        0,
        "verify {}: {}{}",
        robot.display(),
        v.stdout,
        v.stderr
    );
    assert!(v.stdout.contains(": ok: "), "{}", v.stdout);
    std::fs::read_to_string(out).unwrap()
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn every_shipped_cell_compiles_to_a_program_that_verifies() {
    let text = compile_and_verify(&nj130_dh(), &nj130_cell(), &["--step", "15"]);
    assert!(text.contains("safety margin: 10.0 mm; joint margin: 1.0 deg)"));
    for name in SHARED_ROBOTS {
        compile_and_verify(
            &shared_robot(name),
            &test_cell(name),
            &["--step", "20", "--max-candidates", "1500"],
        );
    }
}

/// Everything a library-level check needs for the NJ-130 cell.
struct Setup {
    robot: edbbgen::robot::Robot,
    model: MeasurementModel,
    cell: edbbgen::ir::Cell,
    scene: edbbgen::collision::Scene,
    spec: CellSpec,
}

fn nj130_setup() -> Setup {
    let spec = edbbgen::cell::load(&nj130_cell()).unwrap();
    let robot = load(&nj130_dh());
    let fixture = spec.fixture.unwrap();
    let map = spec.map.unwrap();
    let cell = edbbgen::pipeline::make_cell(&robot, fixture, map, &spec).unwrap();
    let model = MeasurementModel::new(&robot, fixture, map);
    let (scene, _) = edbbgen::pipeline::build_scene(&robot, &spec, &fixture, &map).unwrap();
    Setup {
        robot,
        model,
        cell,
        scene,
        spec,
    }
}

fn deg(q: &[f64; 6]) -> String {
    let w = ["X", "Y", "Z", "A", "B", "C"];
    (0..6)
        .map(|i| format!("{}{:.4}", w[i], q[i].to_degrees()))
        .collect::<Vec<_>>()
        .join(" ")
}

/// A program: approach q0 without the bar, mount, then each target as a slow G1 (bar mounted).
fn program(approach: &[f64; 6], moves: &[[f64; 6]], transits: &[[f64; 6]]) -> String {
    let mut s = String::from("(hand-made)\nG21 G90 G94\nG61\n");
    s += &format!("G0 {}\n", deg(approach));
    for t in transits {
        s += &format!("G0 {}\n", deg(t));
    }
    s += "M0\nG93\n";
    for m in moves {
        s += &format!("G1 {} F1.0\n", deg(m));
    }
    s += "G94\nM0\nM2\n";
    s
}

fn run_verify(text: &str) -> Run {
    let dir = tempdir();
    let p = dir.path().join("bad.nc");
    std::fs::write(&p, text).unwrap();
    edbbgen([
        "verify",
        nj130_dh().to_str().unwrap(),
        p.to_str().unwrap(),
        "--cell",
        nj130_cell().to_str().unwrap(),
    ])
}

/// Seeded search for a pose near `q0` such that the move q0 → pose first fails for `reason`
/// (the check reports the first failing constraint along the move).
fn find_pose(
    s: &Setup,
    q0: &[f64; 6],
    reason: Reason,
    f: impl Fn(&mut rand_chacha::ChaCha8Rng, &[f64; 6]) -> [f64; 6],
) -> [f64; 6] {
    find_pose_any(s, q0, &[reason], f)
}

fn find_pose_any(
    s: &Setup,
    q0: &[f64; 6],
    reasons: &[Reason],
    f: impl Fn(&mut rand_chacha::ChaCha8Rng, &[f64; 6]) -> [f64; 6],
) -> [f64; 6] {
    let ck = Checker::new(&s.robot, &s.model, &s.cell, &s.scene, s.spec.margin);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(42);
    for _ in 0..20_000 {
        let q = f(&mut rng, q0);
        let mut e = Extremes::default();
        if let Err((_, v)) = ck.line(q0, &q, &mut e) {
            if reasons.contains(&v.reason) {
                return q;
            }
        }
    }
    panic!("no pose found for {reasons:?}");
}

fn first_pose(text: &str) -> [f64; 6] {
    program_poses(text)[0].map(|d| d.to_radians())
}

#[test]
fn hand_made_unsafe_programs_fail_verify_naming_the_violation() {
    let s = nj130_setup();
    let good = compile_and_verify(
        &nj130_dh(),
        &nj130_cell(),
        &["--step", "20", "--max-candidates", "800"],
    );
    let q0 = first_pose(&good);
    let ck = Checker::new(&s.robot, &s.model, &s.cell, &s.scene, s.spec.margin);
    assert!(ck.pose(&q0).is_ok());

    // A bar stretched beyond its maximum: move the arm away from the fixture.
    let far = find_pose(&s, &q0, Reason::BarLength, |r, q| {
        let mut x = *q;
        for v in x.iter_mut().take(3) {
            *v += r.random_range(-0.25..0.25);
        }
        x
    });
    let v = run_verify(&program(&q0, &[far], &[]));
    assert_eq!(v.code, 1, "{}", v.stderr);
    assert!(
        v.stderr.contains("bar_length") && v.stderr.contains("outside 300.0..520.0 mm"),
        "{}",
        v.stderr
    );
    assert!(v.stderr.contains("line 7"), "{}", v.stderr);

    // A cone violation: turn the wrist until the cup faces away from the bar.
    // A cone violation: the same good program in a cell whose tool cup allows only 10°.
    let dir = tempdir();
    let narrow = dir.path().join("narrow.toml");
    let cell_text = std::fs::read_to_string(nj130_cell()).unwrap();
    let tool_cone =
        "axis = [0.0, 0.0, 1.0]      # cup opening along the flange z axis\ncone = 60.0";
    assert!(
        cell_text.contains(tool_cone),
        "the shipped cell's tool section"
    );
    std::fs::write(
        &narrow,
        cell_text.replace(tool_cone, "axis = [0.0, 0.0, 1.0]\ncone = 10.0"),
    )
    .unwrap();
    let good_path = dir.path().join("good.nc");
    std::fs::write(&good_path, &good).unwrap();
    let v = edbbgen([
        "verify",
        nj130_dh().to_str().unwrap(),
        good_path.to_str().unwrap(),
        "--cell",
        narrow.to_str().unwrap(),
    ]);
    assert_eq!(v.code, 1, "{}", v.stderr);
    assert!(
        v.stderr.contains("cup_cone") && v.stderr.contains("(cone 10.0 deg)"),
        "{}",
        v.stderr
    );

    // A cable-limit violation where the bar is mounted: q4 one turn further (same geometry).
    let mut wound = q0;
    // (the folded pose below only needs to fail the pose check)
    wound[3] += if q0[3] > 0.0 {
        -2.0 * std::f64::consts::PI
    } else {
        2.0 * std::f64::consts::PI
    };
    let v = run_verify(&program(&wound, &[], &[]));
    assert_eq!(v.code, 1, "{}", v.stderr);
    assert!(
        v.stderr.contains("cable_limit") && v.stderr.contains("harness range"),
        "{}",
        v.stderr
    );

    // A self-collision during the approach (no bar yet): the arm or the tool into the arm.
    let ckf = ck.unmounted();
    let self_hit = (0..2000)
        .map(|k| {
            let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(k);
            let (lo, hi) = s.robot.limits();
            // Within the harness (q4, q6 within one turn), so collisions are what fails.
            let q: [f64; 6] = std::array::from_fn(|i| r.random_range(lo[i].max(-3.0)..hi[i].min(3.0)));
            q
        })
        .find(|q| matches!(ckf.pose(q), Err(v) if v.detail.contains("link") && !["floor", "fixture", "stand"].iter().any(|w| v.detail.contains(w))))
        .expect("a self-colliding pose");
    let v = run_verify(&program(&q0, &[], &[self_hit]));
    assert_eq!(v.code, 1, "{}", v.stderr);
    assert!(
        v.stderr.contains("collision") && v.stderr.contains("link"),
        "{}",
        v.stderr
    );

    // A move through the floor (a transit without the bar whose straight move dips the wrist
    // through the floor): two poses that are fine on their own.
    let (lo, hi) = s.robot.limits();
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut found = None;
    for _ in 0..20_000 {
        let a: [f64; 6] = std::array::from_fn(|i| r.random_range(lo[i].max(-3.0)..hi[i].min(3.0)));
        let b: [f64; 6] = std::array::from_fn(|i| r.random_range(lo[i].max(-3.0)..hi[i].min(3.0)));
        if ckf.pose(&a).is_err() || ckf.pose(&b).is_err() {
            continue;
        }
        let mut e = Extremes::default();
        if let Err((_, v)) = ckf.line(&a, &b, &mut e) {
            if v.detail.contains("floor") {
                found = Some((a, b));
                break;
            }
        }
    }
    let (a, b) = found.expect("a move through the floor");
    let v = run_verify(&program(&a, &[], &[b]));
    assert_eq!(v.code, 1, "{}", v.stderr);
    assert!(
        v.stderr.contains("floor") && v.stderr.contains("line 5"),
        "{}",
        v.stderr
    );
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_move_that_leaves_the_shell_gets_support_poses_and_verifies() {
    let s = nj130_setup();
    let text = compile_and_verify(&nj130_dh(), &nj130_cell(), &["--step", "15"]);
    let parsed = edbbgen::verify::gcode::parse(&text).unwrap();
    let ck = Checker::new(&s.robot, &s.model, &s.cell, &s.scene, s.spec.margin);
    // For a support pose between two measurement poses, the plain move between those fails.
    let lines: Vec<(&str, [f64; 6])> = parsed
        .lines
        .iter()
        .filter_map(|l| match &l.step {
            edbbgen::verify::gcode::Step::Move { target, .. } => Some((
                l.comment.as_deref().unwrap_or(""),
                target.map(|d| d.to_radians()),
            )),
            _ => None,
        })
        .collect();
    let mut needed = 0;
    for w in lines.windows(3) {
        if w[1].0.starts_with("support") && w[0].0.starts_with("pose") && w[2].0.starts_with("pose")
        {
            let mut e = Extremes::default();
            if ck.line(&w[0].1, &w[2].1, &mut e).is_err() {
                needed += 1;
            }
        }
    }
    assert!(
        lines.iter().any(|l| l.0.starts_with("support")),
        "the NJ-130 cell needs support poses"
    );
    assert!(
        needed > 0,
        "a support pose that replaces a failing plain move"
    );
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_urdf_without_joint_speeds_asks_for_them_or_takes_them_from_the_cell() {
    let dir = tempdir();
    let text = std::fs::read_to_string(shared_robot("kuka_kr120_r2500pro")).unwrap();
    let no_speed = regex_free_strip_velocity(&text);
    let urdf = dir.path().join("robot.urdf");
    std::fs::write(&urdf, no_speed).unwrap();
    // Meshes are relative to the URDF: link them in.
    std::os::unix::fs::symlink(
        shared_robot("kuka_kr120_r2500pro")
            .parent()
            .unwrap()
            .join("meshes"),
        dir.path().join("meshes"),
    )
    .unwrap();
    let out = dir.path().join("p.nc");
    let r = edbbgen([
        urdf.to_str().unwrap(),
        "--fixture",
        "1400,400,700",
        "--tool",
        "60,30,120",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 2);
    assert!(
        r.stderr.contains("max speed missing or zero") && r.stderr.contains("speeds"),
        "{}",
        r.stderr
    );
    let cell = dir.path().join("cell.toml");
    let base = std::fs::read_to_string(test_cell("kuka_kr120_r2500pro")).unwrap();
    std::fs::write(
        &cell,
        base + "\n[robot]\nspeeds = [120, 115, 120, 190, 180, 260]\n",
    )
    .unwrap();
    let r = edbbgen([
        urdf.to_str().unwrap(),
        "--cell",
        cell.to_str().unwrap(),
        "--step",
        "20",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
}

fn regex_free_strip_velocity(text: &str) -> String {
    let mut out = String::new();
    for line in text.lines() {
        match line.find("velocity=\"") {
            Some(i) => {
                let rest = &line[i + 10..];
                let end = rest.find('"').unwrap_or(0);
                out += &line[..i];
                out += &rest[end + 1..];
            }
            None => out += line,
        }
        out.push('\n');
    }
    out
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn random_cells_verify_clean_or_fail_with_a_clear_reason() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2026);
    let robots: Vec<(PathBuf, f64)> = std::iter::once((nj130_dh(), 1.9))
        .chain(SHARED_ROBOTS.iter().map(|r| (shared_robot(r), 2.4)))
        .collect();
    let mut ok = 0;
    let mut refused = Vec::new();
    for (robot, reach) in &robots {
        for k in 0..CELLS_PER_ROBOT {
            let dir = tempdir();
            let out = dir.path().join("p.nc");
            let r = rng.random_range(0.5..0.85) * reach;
            let phi: f64 = rng.random_range(-2.5..2.5);
            let fixture =
                Vector3::new(r * phi.cos(), r * phi.sin(), rng.random_range(0.2..1.4)) * 1e3;
            let tool = Vector3::new(
                rng.random_range(-120.0..120.0),
                rng.random_range(-120.0..120.0),
                rng.random_range(60.0..220.0),
            );
            let args = [
                robot.display().to_string(),
                "--fixture".into(),
                format!("{:.1},{:.1},{:.1}", fixture.x, fixture.y, fixture.z),
                "--tool".into(),
                format!("{:.1},{:.1},{:.1}", tool.x, tool.y, tool.z),
                "--step".into(),
                "30".into(),
                "--max-candidates".into(),
                "300".into(),
                "-o".into(),
                out.display().to_string(),
            ];
            let c = edbbgen(&args);
            match c.code {
                0 => {
                    let v = edbbgen([
                        "verify".to_string(),
                        robot.display().to_string(),
                        out.display().to_string(),
                    ]);
                    assert_eq!(
                        v.code,
                        0,
                        "{} cell {k}: {args:?}: {}",
                        robot.display(),
                        v.stderr
                    );
                    ok += 1;
                }
                2 => {
                    assert_eq!(c.stderr.lines().count(), 1, "{}", c.stderr);
                    assert!(c.stderr.starts_with("edbbgen: error: "), "{}", c.stderr);
                    assert!(!out.exists(), "no file on refusal");
                    refused.push(c.stderr.trim().to_string());
                }
                code => panic!("{} cell {k}: exit {code}: {}", robot.display(), c.stderr),
            }
        }
    }
    eprintln!(
        "random cells: {ok} verified, {} refused: {refused:#?}",
        refused.len()
    );
    assert!(
        ok >= robots.len() * CELLS_PER_ROBOT / 2,
        "most random reachable cells give a program: {ok}"
    );
}

const CELLS_PER_ROBOT: usize = 30;

//! The planner never commands a zero-length move. At some fixtures a
//! deferred measurement pose was inserted next to a support pose equal to it (the roadmap's
//! support chains run through the pool, measurement poses included): a 0.000 s move that
//! `ngc`/`sinumerik` refused with a misleading "F0 must be positive" and `rapid`, `krl`,
//! `urscript`, `fanuc` wrote as a move without a time.
//!
//! The robots are test files made from the public ROS-Industrial descriptions with primitive
//! collision shapes (`tests/robots/*/robot.urdf`, sources in their headers). The Stäubli
//! TX2-90 reproduces the defect at the fixture itself; the IRB 2400 file does not at
//! the fixture (its collision shapes are primitives, not the meshes the report used),
//! so that fixture is compiled too, and the same root cause is exercised at a fixture where
//! this file does reproduce it (found by a seeded search with the old planner).

use crate::common::*;
use edbbgen::pipeline::{self, CompileOptions, PipelineError};
use nalgebra::Vector3;

fn robot_file(name: &str) -> std::path::PathBuf {
    root().join("tests/robots").join(name).join("robot.urdf")
}

/// The consecutive targets of a program that are equal, read back by the dialect's reader.
fn repeats(text: &str, dialect: &str, robot: &edbbgen::robot::Robot) -> Vec<usize> {
    let d = edbbgen::dialect::by_name(dialect).unwrap();
    let map = d.default_map(robot).unwrap();
    let parsed = d.read(text, &map).unwrap();
    let t: Vec<(usize, [f64; 6])> = parsed.targets().map(|(l, q)| (l, *q)).collect();
    t.windows(2)
        .filter(|w| w[0].1 == w[1].1)
        .map(|w| w[1].0)
        .collect()
}

struct Case {
    robot: &'static str,
    fixture: &'static str,
    tool: &'static str,
    stand: bool,
}

const CASES: &[Case] = &[
    // The fixture: the old planner failed here with "F0 must be positive".
    Case {
        robot: "staubli_tx2_90",
        fixture: "-550,183.3,540",
        tool: "0,0,150",
        stand: false,
    },
    // The IRB 2400 fixture with its 40 mm stand (no zero-length move with these
    // primitive shapes even before the fix, but it must compile clean).
    Case {
        robot: "abb_irb2400",
        fixture: "253.3,-760,1410",
        tool: "60,30,120",
        stand: true,
    },
    // The same root cause on the IRB 2400 file: the old planner wrote a zero-length move here.
    Case {
        robot: "abb_irb2400",
        fixture: "-557.6,332.2,1208.8",
        tool: "150,0,0",
        stand: false,
    },
];

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn no_dialect_writes_a_zero_length_move_at_the_reported_fixtures() {
    let dir = tempdir();
    let stand = dir.path().join("stand.toml");
    std::fs::write(&stand, "[fixture]\nstand_radius = 40.0\n").unwrap();
    for c in CASES {
        let path = robot_file(c.robot);
        let robot = load(&path);
        for dialect in ["ngc", "rapid"] {
            let out = dir.path().join(format!("{}.{dialect}", c.robot));
            let mut args = vec![
                path.display().to_string(),
                format!("--fixture={}", c.fixture),
                "--tool".into(),
                c.tool.into(),
                "--step".into(),
                "20".into(),
                "--max-candidates".into(),
                "600".into(),
                "--dialect".into(),
                dialect.into(),
                "-o".into(),
                out.display().to_string(),
            ];
            if c.stand {
                args.extend(["--cell".into(), stand.display().to_string()]);
            }
            let r = edbbgen(&args);
            assert_eq!(
                r.code, 0,
                "{} at {} ({dialect}): {}",
                c.robot, c.fixture, r.stderr
            );
            let text = std::fs::read_to_string(&out).unwrap();
            let rep = repeats(&text, dialect, &robot);
            assert!(
                rep.is_empty(),
                "{} at {} ({dialect}): zero-length moves at lines {rep:?}",
                c.robot,
                c.fixture
            );
            if dialect == "ngc" {
                // Independently of the readers: no motion line repeats the one before, and
                // every timed move has a positive inverse-time feed.
                let poses = program_poses(&text);
                assert!(poses.windows(2).all(|w| w[0] != w[1]), "{}", c.robot);
                for l in text.lines().filter(|l| l.starts_with("G1 ")) {
                    let f: f64 = l
                        .split_whitespace()
                        .find_map(|w| w.strip_prefix('F'))
                        .unwrap()
                        .parse()
                        .unwrap();
                    assert!(f > 0.0 && f.is_finite(), "{l}");
                }
            }
            let v = edbbgen([
                "verify".into(),
                path.display().to_string(),
                out.display().to_string(),
                "--dialect".into(),
                dialect.to_string(),
                "--tool".into(),
                c.tool.to_string(),
            ]);
            assert_eq!(v.code, 0, "{}: {}{}", c.robot, v.stdout, v.stderr);
        }
    }
}

#[test]
fn a_plan_that_repeats_a_pose_is_named_a_planner_bug_not_emitted() {
    // The invariant and the emit-time check: a program with a zero-length move is refused with
    // a message that names the planner, whatever the dialect (not "F0 must be positive").
    let robot = load(&nj130_dh());
    let mut opts = CompileOptions::new(Vector3::new(0.258, 1.468, 0.708));
    opts.step = [20f64.to_radians(); 6];
    opts.max_candidates = 600;
    let ngc = edbbgen::dialect::source("ngc").unwrap();
    let c = pipeline::compile(&robot, &opts, ngc, &edbbgen::sample::NoProgress).unwrap();
    assert_eq!(c.plan.repeated_pose(), None);
    let mut plan = c.plan.clone();
    let k = plan.waypoints.len() / 2;
    let twin = edbbgen::safety::path::Waypoint {
        support: true,
        ..plan.waypoints[k].clone()
    };
    plan.waypoints.insert(k + 1, twin);
    assert_eq!(plan.repeated_pose(), Some(k + 1));

    let mut bad = c.program.clone();
    let mut m = bad.moves[k].clone();
    m.support = true;
    m.pose = 0;
    m.time_s = 0.0;
    bad.moves.insert(k + 1, m);
    let (scene, _) = pipeline::build_scene(&robot, &opts.cell, &opts.fixture, &c.cell.map).unwrap();
    let ck = edbbgen::safety::Checker::new(&robot, &c.model, &c.cell, &scene, opts.cell.margin);
    for (name, source) in edbbgen::dialect::bundled() {
        let t = edbbgen::dialect::Template::from_source(source).unwrap();
        let map = pipeline::controller_map(&robot, &opts, &t).unwrap();
        let e = pipeline::finish(&ck, &robot, &opts, &bad, &t, &map).unwrap_err();
        assert!(matches!(e, PipelineError::Bug(_)), "{name}: {e}");
        assert_eq!(e.exit_code(), 1);
        let msg = e.to_string();
        assert!(
            msg.contains("a bug in edbbgen") && msg.contains("the same pose twice in a row"),
            "{name}: {msg}"
        );
    }
}

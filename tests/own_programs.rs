//! A user's own stop-and-measure program (no edbbgen header): the measurement poses are the
//! moves followed by a dwell, in every dialect. The programs here are written the way a person
//! writes them (a home move, an approach without a dwell, a short settling dwell, variables where
//! the language has them, comments of every kind), their bar logs made by the twin; each must
//! calibrate as the compiled `--dwell` program of the same poses does.

use crate::common::*;
use crate::logs::dwell_program;
use edbbgen::twin::{logsim, Trajectory};
use std::fmt::Write as _;
use std::path::Path;

const TRUTH: &str =
    "noise_um = 1.0\n[geometric]\na2 = 0.15\ntheta3 = 0.01\nd4 = -0.08\nalpha2 = 0.005\n";

/// Controller axis values of model joints (deg) in a dialect's default mapping.
fn axes(dialect: &str, q_deg: &[f64; 6]) -> [f64; 6] {
    let robot = load(&nj130_dh());
    edbbgen::dialect::by_name(dialect)
        .unwrap()
        .default_map(&robot)
        .unwrap()
        .apply(q_deg)
}

fn list(v: &[f64; 6], decimals: usize, sep: &str) -> String {
    v.iter()
        .map(|x| format!("{x:.decimals$}"))
        .collect::<Vec<_>>()
        .join(sep)
}

/// The program a person writes for `poses` (model joints, deg) in `dialect`: file name and text.
fn hand_written(dialect: &str, home: &[f64; 6], poses: &[[f64; 6]]) -> (String, String) {
    // The approach: half-way from home to the first pose, no dwell there.
    let approach: [f64; 6] = std::array::from_fn(|i| 0.5 * (home[i] + poses[0][i]));
    let ax = |q: &[f64; 6]| axes(dialect, q);
    let mut t = String::new();
    match dialect {
        "ngc" => {
            // No pause: the bar stays in its cups from start to end.
            t.push_str("%\n(ball bar check of the NJ-130, written by hand)\n");
            t.push_str("G21 G90 G94 G17 G40 G49 G80 ; safe start\nG61 (exact stop)\n");
            let c = ax(home);
            writeln!(
                t,
                "G0 X{:.3} Y{:.3} Z{:.3} A{:.3} B{:.3} C{:.3} (home)",
                c[0], c[1], c[2], c[3], c[4], c[5]
            )
            .unwrap();
            let c = ax(&approach);
            writeln!(
                t,
                "G1 F3000 X{:.3} Y{:.3} Z{:.3} A{:.3} B{:.3} C{:.3} ; approach",
                c[0], c[1], c[2], c[3], c[4], c[5]
            )
            .unwrap();
            for (k, q) in poses.iter().enumerate() {
                let c = ax(q);
                writeln!(
                    t,
                    "N{} G1 X{:.3} Y{:.3} Z{:.3} A{:.3} B{:.3} C{:.3} F2400",
                    100 + 10 * k,
                    c[0],
                    c[1],
                    c[2],
                    c[3],
                    c[4],
                    c[5]
                )
                .unwrap();
                t.push_str("G4 P2 (measure)\n");
            }
            let c = ax(home);
            writeln!(
                t,
                "G0 X{:.3} Y{:.3} Z{:.3} A{:.3} B{:.3} C{:.3}\nM2\n%",
                c[0], c[1], c[2], c[3], c[4], c[5]
            )
            .unwrap();
            ("check.ngc".into(), t)
        }
        "krl" => {
            // Axis variables, declared with and without DECL, a settling wait after the
            // approach, no pause.
            t.push_str(
                "&ACCESS RVP\n&REL 3\nDEF bb_check( )\n; ball bar: stand 2 s at each pose\n",
            );
            let c = ax(home);
            writeln!(t, "DECL E6AXIS xHome = {{A1 {:.2}, A2 {:.2}, A3 {:.2}, A4 {:.2}, A5 {:.2}, A6 {:.2}, E1 0.0, E2 0.0}}", c[0], c[1], c[2], c[3], c[4], c[5]).unwrap();
            for k in 0..poses.len() {
                writeln!(t, "E6AXIS xP{}", k + 1).unwrap();
            }
            t.push_str("DECL INT i\n\n");
            for i in 1..=6 {
                writeln!(t, "$VEL_AXIS[{i}] = 40").unwrap();
            }
            for (k, q) in poses.iter().enumerate() {
                let c = ax(q);
                writeln!(
                    t,
                    "xP{} = {{A1 {:.3}, A2 {:.3}, A3 {:.3}, A4 {:.3}, A5 {:.3}, A6 {:.3}}}",
                    k + 1,
                    c[0],
                    c[1],
                    c[2],
                    c[3],
                    c[4],
                    c[5]
                )
                .unwrap();
            }
            t.push_str("PTP xHome ; home\n");
            let c = ax(&approach);
            writeln!(
                t,
                "PTP {{A1 {:.3}, A2 {:.3}, A3 {:.3}, A4 {:.3}, A5 {:.3}, A6 {:.3}}}",
                c[0], c[1], c[2], c[3], c[4], c[5]
            )
            .unwrap();
            t.push_str("WAIT SEC 0.2 ; let it settle\n");
            for k in 0..poses.len() {
                writeln!(t, "PTP xP{}\nWAIT SEC 2.0", k + 1).unwrap();
            }
            t.push_str("PTP xHome\nEND\n");
            ("bb_check.src".into(), t)
        }
        "rapid" => {
            // CONST jointtargets, a mount pause after the approach, a removal pause before home.
            t.push_str("MODULE BallBar\n  ! ball bar check, written by hand\n");
            let c = ax(home);
            writeln!(
                t,
                "  CONST jointtarget jHome := [[{}], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]];",
                list(&c, 1, ", ")
            )
            .unwrap();
            for (k, q) in poses.iter().enumerate() {
                writeln!(
                    t,
                    "  CONST jointtarget jP{} := [[{}], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]];",
                    k + 1,
                    list(&ax(q), 3, ",")
                )
                .unwrap();
            }
            t.push_str("\n  PROC main()\n    ConfJ \\Off;\n    MoveAbsJ jHome\\NoEOffs, v500, z50, tool0;  ! home\n");
            writeln!(
                t,
                "    MoveAbsJ [[{}], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]]\\NoEOffs, v500, fine, tool0;",
                list(&ax(&approach), 3, ",")
            )
            .unwrap();
            t.push_str("    TPWrite \"Mount the ball bar\";\n    Stop;\n");
            for k in 0..poses.len() {
                writeln!(
                    t,
                    "    MoveAbsJ jP{}\\NoEOffs, v300, fine, tool0;\n    WaitTime \\InPos, 2;",
                    k + 1
                )
                .unwrap();
            }
            t.push_str("    TPWrite \"Remove the ball bar\";\n    Stop;\n    MoveAbsJ jHome\\NoEOffs, v500, fine, tool0;\n  ENDPROC\nENDMODULE\n");
            ("BallBar.mod".into(), t)
        }
        "fanuc" => {
            // LS text with named positions, a mount and a removal pause.
            let mut mn: Vec<String> = vec![
                "UFRAME_NUM=0".into(),
                "UTOOL_NUM=1".into(),
                "J P[1:HOME] 30% FINE".into(),
                "J P[2] 30% FINE".into(),
                "!mount the ball bar".into(),
                "PAUSE".into(),
            ];
            for k in 0..poses.len() {
                mn.push(format!("J P[{}] 25% FINE", k + 3));
                mn.push("WAIT   2.00(sec)".into());
            }
            mn.extend([
                "!remove the bar".into(),
                "PAUSE".into(),
                "J P[1:HOME] 30% FINE".into(),
            ]);
            t.push_str("/PROG  BBCHECK\n/ATTR\nOWNER\t\t= MNEDITOR;\nCOMMENT\t\t= \"ball bar\";\nPROG_SIZE\t= 0;\nFILE_NAME\t= ;\nVERSION\t\t= 0;\nLINE_COUNT\t= 0;\nPROTECT\t\t= READ_WRITE;\nTCD:  STACK_SIZE\t= 0,\n      TASK_PRIORITY\t= 50,\n      TIME_SLICE\t= 0,\n      BUSY_LAMP_OFF\t= 0,\n      ABORT_REQUEST\t= 0,\n      PAUSE_REQUEST\t= 0;\nDEFAULT_GROUP\t= 1,*,*,*,*;\n/MN\n");
            for (k, l) in mn.iter().enumerate() {
                if l.starts_with("J ") {
                    writeln!(t, "{:4}:{l}    ;", k + 1).unwrap();
                } else {
                    writeln!(t, "{:4}:  {l} ;", k + 1).unwrap();
                }
            }
            t.push_str("/POS\n");
            let mut pos = |n: usize, label: &str, q: &[f64; 6]| {
                let c = ax(q);
                writeln!(t, "P[{n}{label}]{{\n   GP1:\n\tUF : 0, UT : 1,\t\n\tJ1=  {:9.3} deg,\tJ2=  {:9.3} deg,\tJ3=  {:9.3} deg,\n\tJ4=  {:9.3} deg,\tJ5=  {:9.3} deg,\tJ6=  {:9.3} deg\n}};", c[0], c[1], c[2], c[3], c[4], c[5]).unwrap();
            };
            pos(1, ":\"HOME\"", home);
            pos(2, "", &approach);
            for (k, q) in poses.iter().enumerate() {
                pos(k + 3, "", q);
            }
            t.push_str("/END\n");
            ("BBCHECK.ls".into(), t)
        }
        "sinumerik" => {
            // Block numbers, G94 path feed, a mount and a removal pause.
            t.push_str("; BALL BAR CHECK\nN10 G71 G90 G60\nN20 FGROUP(X1, Y1, Z1, A1, B1, C1)\n");
            let c = ax(home);
            writeln!(
                t,
                "N30 G0 X1={:.3} Y1={:.3} Z1={:.3} A1={:.3} B1={:.3} C1={:.3} ; home",
                c[0], c[1], c[2], c[3], c[4], c[5]
            )
            .unwrap();
            let c = ax(&approach);
            writeln!(
                t,
                "N40 G94 G1 F3000 X1={:.3} Y1={:.3} Z1={:.3} A1={:.3} B1={:.3} C1={:.3}",
                c[0], c[1], c[2], c[3], c[4], c[5]
            )
            .unwrap();
            t.push_str("N50 MSG(\"MOUNT THE BAR\")\nN60 M0\n");
            for (k, q) in poses.iter().enumerate() {
                let c = ax(q);
                writeln!(
                    t,
                    "N{} X1={:.3} Y1={:.3} Z1={:.3} A1={:.3} B1={:.3} C1={:.3}\nN{} G4 F2.0",
                    100 + 20 * k,
                    c[0],
                    c[1],
                    c[2],
                    c[3],
                    c[4],
                    c[5],
                    110 + 20 * k
                )
                .unwrap();
            }
            let c = ax(home);
            writeln!(t, "M0 ; remove the bar\nG0 X1={:.3} Y1={:.3} Z1={:.3} A1={:.3} B1={:.3} C1={:.3}\nM30", c[0], c[1], c[2], c[3], c[4], c[5]).unwrap();
            ("BBCHECK.mpf".into(), t)
        }
        "urscript" => {
            // Named joint lists (radians, and the home in degrees through d2r), speeds in
            // variables, a settling sleep, no pause.
            t.push_str("def bb_check():\n  # ball bar check: 2 s at each pose\n");
            let h = home;
            writeln!(
                t,
                "  global home = [d2r({}), d2r({}), d2r({}), d2r({}), d2r({}), d2r({})]",
                h[0], h[1], h[2], h[3], h[4], h[5]
            )
            .unwrap();
            t.push_str("  acc = 1.2\n  vel = 0.6\n");
            for (k, q) in poses.iter().enumerate() {
                writeln!(t, "  p{} = [{}]", k + 1, list(&ax(q), 6, ", ")).unwrap();
            }
            t.push_str("  movej(home, a=acc, v=vel)\n");
            writeln!(
                t,
                "  movej([{}], a=acc, v=vel)  # approach",
                list(&ax(&approach), 6, ", ")
            )
            .unwrap();
            t.push_str("  sleep(0.3)  # settle\n");
            for k in 0..poses.len() {
                writeln!(t, "  movej(p{}, a=acc, v=0.5)\n  sleep(2.0)", k + 1).unwrap();
            }
            t.push_str("  movej(home, a=acc, v=vel)\nend\n");
            ("bb_check.script".into(), t)
        }
        other => panic!("no hand-written program for {other}"),
    }
}

/// Writes a bar log of `prog` (the twin, truth TRUTH) and calibrates from it: exit code,
/// stdout and the report.
fn measure_and_calibrate(
    dir: &Path,
    tag: &str,
    prog: &Path,
    fixture: bool,
    extra: &[&str],
) -> (i32, String, serde_json::Value) {
    let truth = dir.join("truth.toml");
    std::fs::write(&truth, TRUTH).unwrap();
    let (bar, sync) = (
        dir.join(format!("{tag}.bar.csv")),
        dir.join(format!("{tag}.sync.csv")),
    );
    let mut args: Vec<String> = [
        "simulate",
        nj130_dh().to_str().unwrap(),
        prog.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
        "-o",
        sync.to_str().unwrap(),
        "--bar-log",
        bar.to_str().unwrap(),
        "--clock-offset",
        "-9.5",
        "--clock-drift",
        "60",
    ]
    .map(String::from)
    .to_vec();
    if fixture {
        args.extend(["--fixture".into(), "258,1468,708".into()]);
    }
    args.extend(extra.iter().map(|s| s.to_string()));
    let r = edbbgen(&args);
    assert_eq!(r.code, 0, "{tag}: simulate: {}", r.stderr);
    let json = dir.join(format!("{tag}.json"));
    let mut args: Vec<String> = [
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--bar-log",
        bar.to_str().unwrap(),
        "--program",
        prog.to_str().unwrap(),
        "-o",
        dir.join(format!("{tag}.dh.toml")).to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]
    .map(String::from)
    .to_vec();
    if fixture {
        args.extend(["--fixture".into(), "258,1468,708".into()]);
    }
    let r = edbbgen(&args);
    let report = std::fs::read_to_string(&json)
        .ok()
        .and_then(|s| serde_json::from_str(&s).ok())
        .unwrap_or(serde_json::Value::Null);
    (r.code, format!("{}{}", r.stdout, r.stderr), report)
}

/// The acceptance test: the compiled NJ-130 `--dwell 2` program's poses, written by hand in
/// each of the six dialects without a header, measured by the twin (the same robot errors),
/// every pose matched to its plateau and the robot calibrated as from the compiled program:
/// the same parameters determined, the calibrated robots within the noise of each other over
/// the joint space.
#[test]
fn a_hand_written_dwell_program_in_every_dialect_calibrates_as_the_compiled_one() {
    let d = dwell_program();
    let dir = tempdir();
    let traj = Trajectory::from_program(&d.robot, &d.model, &d.parsed).unwrap();
    let tpl = logsim::template(&traj, &d.model);
    let poses: Vec<[f64; 6]> = tpl.slots.iter().map(|s| s.q.map(f64::to_degrees)).collect();
    let n = poses.len();
    // A home posture near the first pose (the upper arm raised, the forearm folded): a move
    // without a dwell, as is the approach half-way from it to the first pose.
    let mut home = poses[0].map(|v| v.round());
    home[1] -= 15.0;
    home[2] += 15.0;
    // The reference: the compiled program, its header's list checked.
    let prog = dir.path().join("compiled.nc");
    std::fs::write(&prog, &d.compiled.text).unwrap();
    let (code, out, reference) = measure_and_calibrate(dir.path(), "compiled", &prog, false, &[]);
    assert_eq!(code, 0, "compiled: {out}");
    assert!(!out.contains("taken from its dwells"), "{out}");
    let space = edbbgen::calibrate::predict::workspace(&d.robot, 2000, 5);
    let positions = |tag: &str| {
        let robot = load(&dir.path().join(format!("{tag}.dh.toml")));
        let model = edbbgen::model::MeasurementModel::new(
            &robot,
            nalgebra::Vector3::new(0.258, 1.468, 0.708),
            robot.tool.expect("calibrated tool"),
        );
        space
            .iter()
            .map(|q| model.map_position(&model.nominal, q))
            .collect::<Vec<_>>()
    };
    let ref_positions = positions("compiled");
    let predicted = reference["predicted_position_std_um"]["workspace_rms"]
        .as_f64()
        .unwrap();
    for dialect in ["ngc", "krl", "rapid", "fanuc", "sinumerik", "urscript"] {
        let (file, text) = hand_written(dialect, &home, &poses);
        assert!(!text.contains("measure "), "{dialect}: a header list");
        let prog = dir.path().join(&file);
        std::fs::write(&prog, &text).unwrap();
        // RAPID speed data without `\T` leaves a move's time to the controller: edbbgen times
        // it at the axes' maximum speeds, and this controller takes 2.5 times as long.
        let extra: &[&str] = if dialect == "rapid" {
            &["--move-scale", "2.5"]
        } else {
            &[]
        };
        let (code, out, report) = measure_and_calibrate(dir.path(), dialect, &prog, true, extra);
        assert_eq!(code, 0, "{dialect}: {out}\n{text}");
        assert!(
            out.contains(&format!(
                "{file}: {n} measurement poses taken from its dwells"
            )),
            "{dialect}: {out}"
        );
        let settles = matches!(dialect, "krl" | "urscript");
        assert_eq!(
            out.contains("1 shorter dwells"),
            settles,
            "{dialect}: the settling dwell: {out}"
        );
        let run = &report["runs"][0];
        assert_eq!(run["form"], "stop_and_measure", "{dialect}");
        assert_eq!(run["missing"], serde_json::json!([]), "{dialect}");
        let matched: Vec<u64> = run["plateaus"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|p| p["pose"].as_u64())
            .collect();
        assert_eq!(matched, (1..=n as u64).collect::<Vec<_>>(), "{dialect}");
        assert_eq!(
            report["determined"], reference["determined"],
            "{dialect}: other parameters determined"
        );
        // The two calibrations, each with its own noise, over the joint space.
        // After a best rigid registration, as the prediction states it.
        let rms =
            edbbgen::calibrate::predict::register(&positions(dialect), &ref_positions).0 * 1e6;
        let own = report["predicted_position_std_um"]["workspace_rms"]
            .as_f64()
            .unwrap();
        eprintln!(
            "{dialect}: {n} poses matched; {rms:.3} um RMS from the compiled program's calibration (predicted {own:.3} um, compiled {predicted:.3} um)"
        );
        assert!(
            rms <= 3.0 * own.hypot(predicted),
            "{dialect}: {rms} um from the compiled program's calibration, predicted {own} and {predicted} um"
        );
    }
}

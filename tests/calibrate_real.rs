//! Calibration that survives real data, tested on data from a simulator the
//! library did not write (`othersim`: its own kinematics, trajectories and physics of every
//! effect): the fixture off by 50-80 µm and the tool point off, every effect of the library,
//! a fixture slipping mid-run, outliers; and a static draw-wire campaign on an ABB IRB 120 with
//! an unknown anchor, tool point and zero, zero jumps and a drifting zero, outliers and joint
//! angles to 0.1°. The calibrated robot file is read back and compared with the true robot
//! over random joint poses after a best rigid registration.

use crate::calibrate::{file_points, registered_um};
use crate::common::*;
use crate::othersim::*;
use edbbgen::calibrate::{self, predict, CalibrateOptions};
use edbbgen::diagnose::Run as RunData;
use edbbgen::model::MeasurementModel;
use edbbgen::twin::measured::Form;
use edbbgen::twin::{self, Measured};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use std::path::{Path, PathBuf};

fn irb120() -> PathBuf {
    root().join("tests/data/abb_irb120.dh.toml")
}

/// Random joint poses within the limits, this module's own draw.
pub fn poses(arm: &Arm, n: usize, seed: u64) -> Vec<[f64; 6]> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x2222);
    (0..n)
        .map(|_| std::array::from_fn(|j| rng.random_range(arm.lo[j]..arm.hi[j])))
        .collect()
}

/// Every number of a report finite and of a sane size (no 8.4e145 deg).
pub fn sane(v: &Value, path: &str) {
    match v {
        Value::Number(n) => {
            let x = n.as_f64().unwrap();
            assert!(x.is_finite() && x.abs() < 1e7, "{path} = {x}");
        }
        Value::Array(a) => a
            .iter()
            .enumerate()
            .for_each(|(i, x)| sane(x, &format!("{path}[{i}]"))),
        Value::Object(o) => o.iter().for_each(|(k, x)| sane(x, &format!("{path}.{k}"))),
        _ => {}
    }
}

/// `edbbgen calibrate` on one CSV; the exit code, the report and the output path.
pub fn calibrate_cli(
    dir: &Path,
    robot: &Path,
    csv_text: &str,
    tag: &str,
    fixture_mm: Vector3<f64>,
    extra: &[&str],
) -> (i32, Value, PathBuf, crate::common::Run) {
    let csv = dir.join(format!("{tag}.csv"));
    std::fs::write(&csv, csv_text).unwrap();
    let out = dir.join(format!("{tag}.dh.toml"));
    let json = dir.join(format!("{tag}.json"));
    let mut args: Vec<String> = vec![
        "calibrate".into(),
        robot.display().to_string(),
        "--measured".into(),
        csv.display().to_string(),
        "--fixture".into(),
        format!("{},{},{}", fixture_mm.x, fixture_mm.y, fixture_mm.z),
        "-o".into(),
        out.display().to_string(),
        "--json".into(),
        json.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let r = edbbgen(&args);
    let report: Value = std::fs::read_to_string(&json)
        .ok()
        .and_then(|t| serde_json::from_str(&t).ok())
        .unwrap_or(Value::Null);
    (r.code, report, out, r)
}

/// One NJ-130 case of the other simulator: the truth (fixture 50-80 µm off the given one,
/// the tool 0.2 mm off, DH errors up to 0.2 mm / 0.02°) and a continuous recording at 50 Hz.
pub struct Case {
    pub truth: Truth,
    pub recording: Recording,
    pub given_fixture: Vector3<f64>,
    pub given_tool: Vector3<f64>,
}

/// The true NJ-130 of a case and the set-up it is given: the fixture 50-80 µm and the tool
/// 0.2 mm off the given ones, DH errors up to 0.2 mm / 0.02°, 1 µm bar noise.
pub fn nj130_truth(arm: &Arm, physics: Physics, seed: u64) -> (Truth, Vector3<f64>, Vector3<f64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let given_fixture = Vector3::new(0.258, 1.468, 0.708);
    let given_tool = Vector3::new(0.06, 0.03, 0.12);
    let fixture = given_fixture + direction(&mut rng) * rng.random_range(50e-6..80e-6);
    let tool = given_tool + direction(&mut rng) * 0.2e-3;
    let truth = Truth {
        arm: arm.perturbed(&dh_errors(&mut rng, 0.2, 0.02)),
        tool,
        fixture,
        physics,
        noise: 1e-6,
        resolution: 0.1e-6,
    };
    (truth, given_fixture, given_tool)
}

pub fn nj130_case(physics: Physics, minutes: f64, seed: u64) -> Case {
    let arm = Arm::from_file(&nj130_dh());
    let (truth, given_fixture, given_tool) = nj130_truth(&arm, physics, seed);
    let (fixture, tool) = (truth.fixture, truth.tool);
    let path = walk(
        &arm,
        &Walk {
            fixture,
            tool,
            len: (0.32, 0.48),
            duration: minutes * 60.0,
            speed: 0.25,
            seed,
        },
    );
    let recording = record(&truth, &path, 50.0, seed);
    Case {
        truth,
        recording,
        given_fixture,
        given_tool,
    }
}

/// The calibrated file (its effects applied, at rest: a backlash at the centre of its play, a
/// thermal drift at the start of the recording) against the true robot at rest, and the
/// nominal file against the same.
fn score(case: &Case, out: &Path, seed: u64) -> (f64, f64) {
    let arm = Arm::from_file(&nj130_dh());
    score_at(case, out, &arm, &poses(&arm, 2000, seed))
}

/// The same at given joint poses.
fn score_at(case: &Case, out: &Path, arm: &Arm, qs: &[[f64; 6]]) -> (f64, f64) {
    let want: Vec<Vector3<f64>> = qs
        .iter()
        .map(|q| case.truth.reached(q, None, 0.0))
        .collect();
    let nominal: Vec<Vector3<f64>> = qs.iter().map(|q| arm.point(q, &case.given_tool)).collect();
    (
        registered_um(&file_points(out, qs), &want),
        registered_um(&nominal, &want),
    )
}

/// The same where the data reached: at the recorded poses (every k-th, up to 2000).
fn score_measured(case: &Case, out: &Path) -> f64 {
    let arm = Arm::from_file(&nj130_dh());
    let q = &case.recording.q;
    let qs: Vec<[f64; 6]> = q
        .iter()
        .step_by(q.len().div_ceil(2000).max(1))
        .copied()
        .collect();
    score_at(case, out, &arm, &qs).0
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn every_effect_of_the_library_from_another_simulator_calibrates_within_10_um_as_predicted() {
    let dir = workdir_nj130();
    let masses = vec![
        (2, Vector3::new(-0.43, 0.0, 0.05), 120.0),
        (3, Vector3::new(0.0, 0.3, 0.0), 60.0),
        (6, Vector3::new(0.0, 0.0, 0.15), 40.0),
    ];
    let cases: Vec<(&str, Physics)> = vec![
        ("none", Physics::default()),
        (
            "joint compliance",
            Physics {
                compliance: Some((masses, [2e7, 6e6, 5e6, 2e6, 2e6, 1e6])),
                ..Physics::default()
            },
        ),
        (
            "thermal drift",
            Physics {
                thermal: Some((11.5e-6, 3.0, 0.5, 240.0)),
                ..Physics::default()
            },
        ),
        (
            "cyclic error, joint 1",
            Physics {
                cyclic: Some((0, vec![(1, 0.003 * DEG, 0.7), (2, 0.0015 * DEG, -0.3)])),
                ..Physics::default()
            },
        ),
        (
            "cyclic error, joint 2",
            Physics {
                cyclic: Some((1, vec![(1, 0.003 * DEG, 0.7), (3, 0.0015 * DEG, -0.3)])),
                ..Physics::default()
            },
        ),
        (
            "cyclic error, joint 5",
            Physics {
                cyclic: Some((4, vec![(2, 0.003 * DEG, 0.2), (4, 0.0015 * DEG, 1.3)])),
                ..Physics::default()
            },
        ),
        (
            "backlash, joint 3",
            Physics {
                backlash: Some((2, 0.0156 * DEG)),
                ..Physics::default()
            },
        ),
        (
            "servo lag (first-order loop)",
            Physics {
                servo: Some(0.006),
                ..Physics::default()
            },
        ),
    ];
    let mut lines = Vec::new();
    let mut failures = Vec::new();
    let (mut ms_real, mut ms_pred) = (0.0, 0.0);
    let (mut ms_real_measured, mut ms_pred_measured) = (0.0, 0.0);
    // To re-measure one case over more robots: ONLY_CASE=backlash REPS=6 cargo test --test main
    // every_effect_of_the_library -- --nocapture (each repeat a new robot and noise seed;
    // SEED_BASE sets the first seed, VERBOSE=1 prints each report's effects and predictions).
    let only = std::env::var("ONLY_CASE").ok();
    let reps: u64 = std::env::var("REPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1);
    let cases: Vec<(&str, Physics)> = cases
        .into_iter()
        .filter(|(n, _)| only.as_deref().is_none_or(|o| n.starts_with(o)))
        .flat_map(|c| (0..reps).map(move |_| c.clone()))
        .collect();
    for (k, (name, physics)) in cases.into_iter().enumerate() {
        let base: u64 = std::env::var("SEED_BASE")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(if reps > 1 { 1220 } else { 220 });
        let seed = base + k as u64;
        let case = nj130_case(physics, 10.0, seed);
        let (code, report, out, run) = calibrate_cli(
            dir.path(),
            &nj130_dh(),
            &case.recording.csv(),
            &format!("case{k}"),
            case.given_fixture * 1e3,
            &["--tool", "60,30,120"],
        );
        assert_eq!(code, 0, "{name}: {}", run.stderr);
        sane(&report, name);
        let (err, nominal) = score(&case, &out, seed);
        let err_measured = score_measured(&case, &out);
        let predicted = &report["predicted_position_std_um"];
        let pred = predicted["workspace_rms"].as_f64().unwrap();
        let pred_measured = predicted["measured_region_rms"].as_f64().unwrap();
        // An effect's form beyond the joint range measured is a bound the report states, not
        // an estimate: there the prediction is only required not to be optimistic.
        let extrapolated = report["warnings"].as_array().unwrap().iter().any(|w| {
            w.as_str()
                .unwrap()
                .contains("extrapolated beyond the range measured")
        });
        if !extrapolated {
            ms_real += err * err;
            ms_pred += pred * pred;
        }
        ms_real_measured += err_measured * err_measured;
        ms_pred_measured += pred_measured * pred_measured;
        let effects: Vec<String> = report["effects"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| format!("{} {}", e["effect"], e["joint"]))
            .collect();
        lines.push(format!(
            "{name}: {err:.2} um (nominal {nominal:.0} um), predicted {pred:.2} um{}; where measured {err_measured:.2} um, predicted {pred_measured:.2} um; effects {effects:?}, held out {} um",
            if extrapolated { " (extrapolated, stated)" } else { "" },
            report["validation"]["heldout_rms_um"]["calibrated"]
        ));
        if std::env::var("VERBOSE").is_ok() {
            eprintln!(
                "{name} seed {seed}: effects {}\npredicted {}\ncandidates {}",
                report["effects"], report["predicted_position_std_um"], report["candidates"]
            );
        }
        // Within 10 µm, better than nominal, and never worse than twice the prediction (a
        // single robot's error lies along a few directions: it may fall well below). Below
        // a micrometre, at the bar's 1 µm noise, the factor gets 0.5 µm of room, as in the
        // slip test (measured: the backlash case realises 0.94 µm against 0.44 µm predicted,
        // the one case past 2x; over six more robots, seeds 1220-1225, it realises 0.14-0.74
        // µm against 0.51-0.98 µm predicted, ratios 0.23-1.39, pooled 0.69: one robot's error
        // lies along a few directions, so a single ratio scatters; the pooled ratio below is
        // the factor-2 check).
        // Where the data reached, the same within 10 µm and the factor 2. Beyond it, over the
        // whole joint space, a cyclic error's harmonics are extrapolated (the walk measures
        // joint 2 over about 85 deg): more than 10 µm there is allowed only when the report
        // says so and predicts it.
        let honest = err <= 2.0 * pred + 0.5 && err < nominal;
        let within = err <= 10.0 || extrapolated;
        let measured_ok = err_measured <= 10.0 && err_measured <= 2.0 * pred_measured + 0.5;
        if !(honest && within && measured_ok) {
            failures.push(lines.last().unwrap().clone());
        }
        // The effect present is the one adopted, on held-out data; the others are listed.
        let adopted: Vec<&Value> = report["candidates"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| c["adopted"] == true && c["effect"] != "geometric")
            .collect();
        if name != "none" {
            assert_eq!(adopted.len(), 1, "{name}: {}", report["candidates"]);
            assert!(name.starts_with(&adopted[0]["effect"].as_str().unwrap().replace('_', " ")));
            let geometric = report["candidates"][0]["heldout_rms_um"].as_f64().unwrap();
            assert!(adopted[0]["heldout_rms_um"].as_f64().unwrap() < geometric);
        } else {
            assert!(
                adopted.is_empty(),
                "no effect is there: {}",
                report["candidates"]
            );
        }
        assert!(report["candidates"].as_array().unwrap().len() > 10);
    }
    let pooled = (ms_real / ms_pred).sqrt();
    let pooled_measured = (ms_real_measured / ms_pred_measured).sqrt();
    eprintln!(
        "{}\npooled realised/predicted {pooled:.2} over the joint space (cases not extrapolated), {pooled_measured:.2} where measured",
        lines.join("\n")
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    // Over the cases, realised and predicted agree within a factor 2.
    assert!((0.5..=2.0).contains(&pooled), "{pooled}");
    assert!((0.5..=2.0).contains(&pooled_measured), "{pooled_measured}");
}

/// A scratch folder beside which the NJ-130's files resolve.
pub fn workdir_nj130() -> tempfile::TempDir {
    crate::calibrate::workdir(&nj130_dh())
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_fixture_slipping_once_mid_run_and_spikes_are_found_and_reported() {
    let dir = workdir_nj130();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let shift = direction(&mut rng) * 40e-6;
    let spikes = vec![(4321, 60e-6), (17_000, -45e-6), (25_555, 80e-6)];
    let physics = Physics {
        slip: Some((270.0, shift)),
        spikes: spikes.clone(),
        ..Physics::default()
    };
    let case = nj130_case(physics, 10.0, 231);
    let (code, report, out, run) = calibrate_cli(
        dir.path(),
        &nj130_dh(),
        &case.recording.csv(),
        "slip",
        case.given_fixture * 1e3,
        &["--tool", "60,30,120"],
    );
    assert_eq!(code, 0, "{}", run.stderr);
    sane(&report, "slip");
    let (err, nominal) = score(&case, &out, 231);
    let pred = report["predicted_position_std_um"]["workspace_rms"]
        .as_f64()
        .unwrap();
    eprintln!(
        "slip: {err:.2} um (nominal {nominal:.0}), predicted {pred:.2} um; segments {}; outliers {}",
        report["segments"], report["outliers"]
    );
    assert!(
        err <= 20.0 && err <= 2.0 * pred + 0.5,
        "{err} um, predicted {pred}"
    );
    // The step: at the slip (0.2 s of sliding, 50 Hz), as a moved fixture.
    let segments = report["segments"].as_array().unwrap();
    assert_eq!(segments.len(), 2, "{}", report["segments"]);
    assert_eq!(segments[1]["cause"], "fixture moved");
    let t = segments[1]["t_from_s"].as_f64().unwrap();
    assert!((270.0..=270.4).contains(&t), "step at {t} s");
    assert_eq!(
        segments[1]["from_row"].as_u64().unwrap(),
        segments[0]["to_row"].as_u64().unwrap() + 1
    );
    // The segment's own fixture moved by the slip, registered in the robot's frame.
    let f0: Vec<f64> = (0..3)
        .map(|a| segments[0]["fixture_fitted_mm"][a].as_f64().unwrap())
        .collect();
    let f1: Vec<f64> = (0..3)
        .map(|a| segments[1]["fixture_fitted_mm"][a].as_f64().unwrap())
        .collect();
    let moved = Vector3::new(f1[0] - f0[0], f1[1] - f0[1], f1[2] - f0[2]) * 1e-3;
    assert!(
        (moved - shift).norm() < 5e-6,
        "moved {moved:?}, slipped {shift:?}"
    );
    // The spikes are dropped (rows are 1-based in the file), and otherwise only readings
    // taken while the fixture slid (between its two positions, neither segment's).
    let outliers: Vec<(u64, f64)> = report["outliers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| (o["row"].as_u64().unwrap(), o["t_s"].as_f64().unwrap()))
        .collect();
    for (i, _) in &spikes {
        assert!(
            outliers.iter().any(|o| o.0 == *i as u64 + 1),
            "{outliers:?}"
        );
    }
    assert!(
        outliers
            .iter()
            .all(|o| spikes.iter().any(|(i, _)| o.0 == *i as u64 + 1)
                || (270.0..=270.2).contains(&o.1)),
        "{outliers:?}"
    );
    assert!(run.stdout.contains("step in run 1") && run.stdout.contains("outliers dropped"));
}

/// The IRB 120 draw-wire campaign of the issue: 1,042 static poses, joints to 0.1°, the wire's
/// length to 0.01 mm; anchor, zero and attachment point unknown (the point 65 mm out along the
/// flange axis); two zero jumps in the first half, one of them drifting over 100 readings;
/// outliers.
struct Wire {
    truth: Truth,
    spec: Static,
    recording: StaticRecording,
    given_anchor: Vector3<f64>,
}

fn wire_campaign(seed: u64) -> Wire {
    let arm = Arm::from_file(&irb120());
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let anchor = Vector3::new(0.35, -0.25, 0.02);
    let truth = Truth {
        arm: arm.perturbed(&dh_errors(&mut rng, 0.5, 0.15)),
        tool: Vector3::new(0.002, -0.003, 0.065),
        fixture: anchor,
        physics: Physics::default(),
        noise: 5e-6,
        resolution: 1e-5,
    };
    let spec = Static {
        poses: 1042,
        joint_step: 0.1 * DEG,
        length_step: 1e-5,
        noise: 5e-6,
        zero: 0.1234,
        jumps: vec![(230, 1.5e-3)],
        drift: Some((380, 100, 5e-3)),
        outliers: vec![(57, 3e-3), (612, -8e-3), (800, 2.5e-3), (901, 10e-3)],
        min_z: 0.05,
        max_len: 1.2,
        seed,
    };
    let recording = static_readings(&truth, &spec);
    Wire {
        truth,
        spec,
        recording,
        // A tape measure's guess of the anchor: 70 mm off.
        given_anchor: anchor + Vector3::new(0.04, -0.03, 0.05),
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn static_draw_wire_data_reach_the_joint_resolution_floor_without_a_given_tool_or_zero() {
    let dir = tempdir();
    let w = wire_campaign(1);
    let floor = resolution_floor(&w.truth, &w.recording.q_true, &w.spec);
    // The robot file has no tool: the MAP starts at the flange centre, 65 mm from the truth.
    let (code, report, out, run) = calibrate_cli(
        dir.path(),
        &irb120(),
        &w.recording.csv(),
        "wire",
        w.given_anchor * 1e3,
        &["--length-offset", "free"],
    );
    assert_eq!(code, 0, "{}", run.stderr);
    sane(&report, "wire");
    let heldout = report["validation"]["heldout_rms_um"]["calibrated"]
        .as_f64()
        .unwrap()
        * 1e-6;
    let nominal = report["validation"]["heldout_rms_um"]["nominal"]
        .as_f64()
        .unwrap()
        * 1e-6;
    eprintln!(
        "{}\nwire: held out {:.3} mm against the 0.1 deg floor {:.3} mm (nominal {:.3} mm)",
        run.stdout,
        heldout * 1e3,
        floor * 1e3,
        nominal * 1e3
    );
    assert!(heldout <= 1.3 * floor, "{heldout} vs floor {floor}");
    assert!(nominal > 2.0 * heldout);
    assert_eq!(report["runs"][0]["form"], "static");
    // The tool point, the anchor and the zero found.
    let tool: Vec<f64> = (0..3)
        .map(|a| report["tool"]["fitted_mm"][a].as_f64().unwrap())
        .collect();
    let t = Vector3::new(tool[0], tool[1], tool[2]) * 1e-3;
    assert!((t - w.truth.tool).norm() < 0.5e-3, "tool {t:?}");
    let zero = report["runs"][0]["length_offset_mm"].as_f64().unwrap() * 1e-3;
    assert!((zero - w.spec.zero).abs() < 0.5e-3, "zero {zero}");
    assert!(report["warnings"].to_string().contains("check --tool"));
    // The 1.5 mm jump where it happened (row 231 of the file), the drift split along its 100
    // readings, every step a changed zero; the outliers exactly.
    let segments = report["segments"].as_array().unwrap();
    assert_eq!(segments[1]["from_row"], 231, "{}", report["segments"]);
    let drift: Vec<u64> = segments[2..]
        .iter()
        .map(|s| s["from_row"].as_u64().unwrap())
        .collect();
    assert!(
        !drift.is_empty() && drift.iter().all(|r| (381..=481).contains(r)),
        "{drift:?}"
    );
    assert!(segments[1..]
        .iter()
        .all(|s| s["cause"] == "length zero changed"));
    assert!(segments.iter().all(|s| s["t_from_s"].is_null()));
    let rows: Vec<u64> = report["outliers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["row"].as_u64().unwrap())
        .collect();
    assert_eq!(rows, vec![58, 613, 801, 902]);
    // No time effect on untimed data: none even considered.
    for c in report["candidates"].as_array().unwrap() {
        assert!(
            c["effect"] != "thermal_drift" && c["effect"] != "servo_lag",
            "{c}"
        );
    }
    // The calibrated robot, against the true one: as predicted.
    let arm = Arm::from_file(&irb120());
    let qs = poses(&arm, 2000, 3);
    let err = registered_um(
        &file_points(&out, &qs),
        &qs.iter().map(|q| w.truth.point(q)).collect::<Vec<_>>(),
    );
    let pred = report["predicted_position_std_um"]["workspace_rms"]
        .as_f64()
        .unwrap();
    eprintln!("wire: robot {err:.1} um, predicted {pred:.1} um");
    assert!(err < 2.0 * pred && pred < 2.5 * err, "{err} vs {pred}");
}

/// Draw-wire data as a real set-up gives them, made by this module's own generator: the anchor
/// 80 mm from where it is said to be, the wire attached 75 mm out from the flange centre along
/// one of the flange's axes (none given: `--tool 0,0,0`), the wire's zero unknown and jumping
/// twice, the joints logged to 0.1°, 0.2 mm reading noise. Default options otherwise.
fn wire_from_a_tape_measure(
    axis: usize,
    seed: u64,
) -> (Truth, Static, StaticRecording, Vector3<f64>) {
    let arm = Arm::from_file(&irb120());
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let anchor = Vector3::new(0.38, 0.22, 0.05);
    let mut tool = Vector3::zeros();
    tool[axis] = 0.075;
    let truth = Truth {
        arm: arm.perturbed(&dh_errors(&mut rng, 0.5, 0.15)),
        tool,
        fixture: anchor,
        physics: Physics::default(),
        noise: 0.2e-3,
        resolution: 1e-5,
    };
    let spec = Static {
        poses: 1042,
        joint_step: 0.1 * DEG,
        length_step: 1e-5,
        noise: 0.2e-3,
        zero: -0.0417,
        jumps: vec![(300, 2.0e-3), (700, -3.5e-3)],
        drift: None,
        outliers: vec![],
        min_z: 0.05,
        max_len: 1.2,
        seed,
    };
    let recording = static_readings(&truth, &spec);
    // 80 mm off, in a direction of its own.
    let given = anchor + direction(&mut rng) * 0.080;
    (truth, spec, recording, given)
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_draw_wire_known_to_a_tape_measure_calibrates_to_the_quantisation_floor_with_defaults() {
    let dir = tempdir();
    for axis in 0..3 {
        let (truth, spec, rec, given) = wire_from_a_tape_measure(axis, 31 + axis as u64);
        let floor = resolution_floor(&truth, &rec.q_true, &spec);
        let tag = format!("wire{axis}");
        let (code, report, out, run) = calibrate_cli(
            dir.path(),
            &irb120(),
            &rec.csv(),
            &tag,
            given * 1e3,
            &["--tool", "0,0,0", "--length-offset", "free"],
        );
        eprintln!("{}{}", run.stdout, run.stderr);
        // A calibrated robot (0), or the set-up with the geometry confirmed nominal (3): both
        // write the robot file with the tool point found.
        assert!(
            code == 0 || code == 3,
            "axis {axis}: exit {code}: {}",
            run.stderr
        );
        assert!(out.exists());
        sane(&report, &tag);
        let (heldout, tool, anchor) = if code == 0 {
            let t: Vec<f64> = (0..3)
                .map(|a| report["tool"]["fitted_mm"][a].as_f64().unwrap())
                .collect();
            let f: Vec<f64> = (0..3)
                .map(|a| report["runs"][0]["fixture_fitted_mm"][a].as_f64().unwrap())
                .collect();
            (
                report["validation"]["heldout_rms_um"]["calibrated"]
                    .as_f64()
                    .unwrap(),
                t,
                f,
            )
        } else {
            let set = &report["setup"];
            assert_eq!(set["delivered"], true);
            assert!(report["verdict"]
                .as_str()
                .unwrap()
                .starts_with("geometry confirmed within"));
            (
                set["heldout_rms_um"].as_f64().unwrap(),
                (0..3)
                    .map(|a| set["tool_mm"][a].as_f64().unwrap())
                    .collect(),
                (0..3)
                    .map(|a| set["fixtures_mm"][0][a].as_f64().unwrap())
                    .collect(),
            )
        };
        let t = Vector3::new(tool[0], tool[1], tool[2]) * 1e-3;
        let f = Vector3::new(anchor[0], anchor[1], anchor[2]) * 1e-3;
        eprintln!(
            "axis {axis}: exit {code}, held out {:.1} um against the floor {:.1} um; tool {:.2} mm, anchor {:.2} mm from the truth",
            heldout,
            floor * 1e6,
            (t - truth.tool).norm() * 1e3,
            (f - truth.fixture).norm() * 1e3
        );
        // The set-up found (the given one was 75 and 80 mm off): the attachment point within a
        // millimetre, the anchor within two. Both carry what they stand in for: link 6's
        // lengths the tool point, d1 and θ1 the anchor's height and azimuth (0.15° of θ1 is
        // 1.2 mm at the anchor), which the truth perturbs and no ball-bar datum separates.
        assert!((t - truth.tool).norm() < 1e-3, "axis {axis}: tool {t:?}");
        assert!(
            (f - truth.fixture).norm() < 2e-3,
            "axis {axis}: anchor {f:?}"
        );
        // The joints' 0.1° read from the log, and the wire's own 0.2 mm noise told from the
        // rounding in the residual: the readings weighted by their own uncertainty.
        let w = &report["reading_weights"];
        assert!(
            w["joint_resolution_deg"][0]
                .as_array()
                .unwrap()
                .iter()
                .all(|g| g.as_f64() == Some(0.1)),
            "{w}"
        );
        let noise = w["instrument_noise_um"].as_f64().unwrap();
        assert!((160.0..240.0).contains(&noise), "{w}");
        // The quantisation and noise floor, held out.
        assert!(
            heldout * 1e-6 <= 1.15 * floor,
            "axis {axis}: {heldout} um vs {floor}"
        );
        // Both jumps of the zero located (rows 301 and 701 of the file), nothing else split.
        let cuts: Vec<u64> = report["segments"]
            .as_array()
            .unwrap()
            .iter()
            .skip(1)
            .map(|s| s["from_row"].as_u64().unwrap())
            .collect();
        assert_eq!(cuts.len(), 2, "axis {axis}: {}", report["segments"]);
        assert!(
            (296..=306).contains(&cuts[0]) && (696..=706).contains(&cuts[1]),
            "{cuts:?}"
        );
    }
}

#[test]
fn nothing_determined_is_said_and_exits_1_writing_no_robot() {
    // The robot barely moves: 60 readings at one pose.
    let dir = tempdir();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut csv = String::from("q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm\n");
    for _ in 0..60 {
        csv += &format!("10,20,-10,5,40,30,{:.5}\n", 400.0 + 1e-3 * normal(&mut rng));
    }
    let (code, report, out, run) = calibrate_cli(
        dir.path(),
        &nj130_dh(),
        &csv,
        "still",
        Vector3::new(258.0, 1468.0, 708.0),
        &[],
    );
    assert_eq!(code, 1, "{}", run.stderr);
    assert_eq!(run.stderr.trim().lines().count(), 1, "{}", run.stderr);
    assert!(
        run.stderr.contains("not calibrated") && run.stderr.contains("measure"),
        "{}",
        run.stderr
    );
    assert!(!out.exists(), "no robot file");
    assert_eq!(report["calibrated"], false);
    assert!(report["verdict"]
        .as_str()
        .unwrap()
        .starts_with("not calibrated"));
    sane(&report, "still");
}

#[test]
fn a_robot_no_better_than_nominal_held_out_is_delivered_with_its_set_up_and_exit_3() {
    // The true robot is the nominal one: the data show no deviation the geometry explains. The
    // set-up is known to a tape measure: the fixture 15 mm and the tool point 5 mm off.
    let dir = workdir_nj130();
    let arm = Arm::from_file(&nj130_dh());
    let given = Vector3::new(0.258, 1.468, 0.708);
    let fixture = given + Vector3::new(0.009, -0.008, 0.009);
    let given_tool = Vector3::new(0.06, 0.03, 0.12);
    let tool = given_tool + Vector3::new(0.003, -0.002, 0.0035);
    let truth = Truth {
        arm: arm.clone(),
        tool,
        fixture,
        physics: Physics::default(),
        noise: 1e-6,
        resolution: 0.1e-6,
    };
    let path = walk(
        &arm,
        &Walk {
            fixture,
            tool,
            len: (0.32, 0.48),
            duration: 120.0,
            speed: 0.25,
            seed: 9,
        },
    );
    let rec = record(&truth, &path, 50.0, 9);
    let (code, report, out, run) = calibrate_cli(
        dir.path(),
        &nj130_dh(),
        &rec.csv(),
        "exact",
        given * 1e3,
        &["--tool", "60,30,120", "-q"],
    );
    eprintln!("{}{}", run.stdout, run.stderr);
    // Not calibrated, but a result: exit 3, the robot file written with the set-up found.
    assert_eq!(code, 3, "{}", run.stderr);
    assert_eq!(report["calibrated"], false);
    let verdict = report["verdict"].as_str().unwrap();
    assert!(
        verdict.starts_with("geometry confirmed within")
            && verdict.contains("set-up fitted")
            && verdict.contains("no better than the nominal"),
        "{verdict}"
    );
    // With -q, no summary; the exit code explains itself on stderr.
    assert!(
        !run.stdout.contains("geometry confirmed within"),
        "{}",
        run.stdout
    );
    assert!(
        run.stderr.contains("calibrate: geometry confirmed within"),
        "{}",
        run.stderr
    );
    let h = &report["validation"]["heldout_rms_um"];
    assert!(h["calibrated"].as_f64().unwrap() >= h["nominal"].as_f64().unwrap());
    let set = &report["setup"];
    assert_eq!(set["delivered"], true);
    let within = set["geometry_within_um"].as_f64().unwrap();
    assert!(within > 0.0 && within < 50.0, "{within}");
    let got = |v: &Value| {
        Vector3::new(
            v[0].as_f64().unwrap(),
            v[1].as_f64().unwrap(),
            v[2].as_f64().unwrap(),
        ) * 1e-3
    };
    assert!(
        (got(&set["tool_mm"]) - tool).norm() < 20e-6,
        "{}",
        set["tool_mm"]
    );
    assert!(
        (got(&set["fixtures_mm"][0]) - fixture).norm() < 20e-6,
        "{}",
        set["fixtures_mm"]
    );
    assert!(set["tool_std_mm"][0].as_f64().unwrap() < 0.01);
    // The written robot is the nominal geometry with the tool point found: its MAP is where
    // the true one is, everywhere in the joint space (not only where measured).
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(
        text.contains("set-up fitted (the geometry nominal)"),
        "{text}"
    );
    assert!(!text.contains("[effects]"));
    let qs = poses(&arm, 500, 4);
    let err = registered_um(
        &file_points(&out, &qs),
        &qs.iter().map(|q| truth.point(q)).collect::<Vec<_>>(),
    );
    assert!(err < 5.0, "{err} um");
}

/// A stop-and-measure campaign as a cell hands it over: one reading per pose with real times
/// (plateau midpoints), a standard error and a sample count each.
fn plateaus(case: &Case, every: usize) -> Measured {
    let r = &case.recording;
    let idx: Vec<usize> = (0..r.t.len()).step_by(every).collect();
    Measured {
        t: idx.iter().map(|&k| r.t[k]).collect(),
        q: idx.iter().map(|&k| r.q[k]).collect(),
        length: idx.iter().map(|&k| r.length[k]).collect(),
        temp: None,
        std: Some(vec![0.3e-6; idx.len()]),
        samples: Some(vec![25; idx.len()]),
        form: Form::Static { timed: true },
    }
}

#[test]
fn timed_static_readings_take_a_thermal_drift_but_no_servo_lag() {
    // Readings every 2 s of a warming robot (this truth has no servo lag: where the robot is
    // at a reading does not depend on how it moved there). A thermal drift is fitted on their
    // times; a servo lag is never considered.
    let arm = Arm::from_file(&nj130_dh());
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    let given_fixture = Vector3::new(0.258, 1.468, 0.708);
    let given_tool = Vector3::new(0.06, 0.03, 0.12);
    let fixture = given_fixture + direction(&mut rng) * 60e-6;
    let truth = Truth {
        arm: arm.perturbed(&dh_errors(&mut rng, 0.2, 0.02)),
        tool: given_tool,
        fixture,
        physics: Physics {
            thermal: Some((11.5e-6, 3.0, 0.2, 300.0)),
            ..Physics::default()
        },
        noise: 0.3e-6,
        resolution: 0.01e-6,
    };
    let path = walk(
        &arm,
        &Walk {
            fixture,
            tool: given_tool,
            len: (0.32, 0.48),
            duration: 900.0,
            speed: 0.25,
            seed: 77,
        },
    );
    let rec = record(&truth, &path, 50.0, 77);
    let case = Case {
        truth,
        recording: rec,
        given_fixture,
        given_tool,
    };
    let m = plateaus(&case, 100);
    let robot = load(&nj130_dh());
    let model = MeasurementModel::new(&robot, given_fixture, given_tool);
    let cal = calibrate::run(
        &model,
        &robot,
        &[RunData {
            measured: &m,
            fixture: given_fixture,
        }],
        &["plateaus".into()],
        &CalibrateOptions::default(),
    )
    .expect("calibrates");
    let r = &cal.report;
    eprintln!("{}", cal.summary);
    assert_eq!(r.runs[0].form, "static, timed");
    assert!(r.candidates.iter().all(|c| c.effect != "servo_lag"));
    assert!(
        r.effects.iter().any(|e| e.effect == "thermal_drift"),
        "{:?}",
        r.candidates
    );
    let qs = poses(&arm, 2000, 4);
    let p = cal.params();
    let got: Vec<Vector3<f64>> = qs.iter().map(|q| model.map_position(&p, q)).collect();
    let want: Vec<Vector3<f64>> = qs.iter().map(|q| case.truth.point_at(q, m.t[0])).collect();
    let err = predict::register(&got, &want).0 * 1e6;
    eprintln!(
        "timed static: {err:.2} um, predicted {:.2} um",
        r.predicted_position_std_um.workspace_rms
    );
    assert!(err < 10.0, "{err}");
}

#[test]
fn the_static_form_reads_std_n_and_temperature_and_time_effects_are_refused_without_times() {
    let dir = tempdir();
    let w = wire_campaign(2);
    let mut text =
        String::from("q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm,std_um,n,temp_c\n");
    for k in 0..w.recording.length.len() {
        for j in 0..6 {
            text += &format!("{:.4},", w.recording.q_logged[k][j] / DEG);
        }
        text += &format!(
            "{:.5},5.0,10,{:.2}\n",
            w.recording.length[k] * 1e3,
            20.0 + 0.001 * k as f64
        );
    }
    let m = twin::parse_csv(&text, 1).expect("parses");
    assert_eq!(m.form, Form::Static { timed: false });
    assert_eq!(m.t[..3], [0.0, 1.0, 2.0]);
    assert!((m.std.as_ref().unwrap()[0] - 5e-6).abs() < 1e-15);
    assert_eq!(m.samples.as_ref().unwrap()[0], 10);
    assert!(m.temp.is_some());
    // Written back in the static form.
    assert!(m
        .to_csv()
        .starts_with("q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm,std_um,n,temp_c\n"));
    assert_eq!(twin::parse_csv(&m.to_csv(), 1).unwrap().length, m.length);
    // A time effect on untimed readings is refused (exit 2, one line naming it); servo lag
    // needs motion. A drift with the logged temperature is allowed.
    let no_temp = w.recording.csv();
    for (effects, text, code) in [
        ("thermal_drift", &no_temp, 2),
        ("servo_lag", &text, 2),
        ("thermal_drift", &text, 0),
    ] {
        let (c, _, _, run) = calibrate_cli(
            dir.path(),
            &irb120(),
            text,
            "static",
            w.given_anchor * 1e3,
            &["--length-offset", "free", "--effects", effects],
        );
        assert_eq!(c, code, "{effects}: {}", run.stderr);
        if code == 2 {
            assert_eq!(run.stderr.trim().lines().count(), 1);
            assert!(run.stderr.contains(effects), "{}", run.stderr);
        }
    }
    // Bad static cells name their line and column.
    for (bad, want) in [
        (
            "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm,std_um\n1,2,3,4,5,6,400,-1\n",
            "column 8 (std_um)",
        ),
        (
            "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm,n\n1,2,3,4,5,6,400,2.5\n",
            "column 8 (n)",
        ),
    ] {
        let e = twin::parse_csv(bad, 1).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains(want), "{e}");
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_campaign_may_hold_a_short_run_and_a_known_zero_is_used() {
    // A long run and a 12-row run of the same robot at a second fixture; the bar's zero is
    // known to be 100 mm (the reading is 100 mm longer than the ball-centre distance).
    let dir = workdir_nj130();
    let long = nj130_case(Physics::default(), 3.0, 301);
    let arm = Arm::from_file(&nj130_dh());
    let second = Vector3::new(1.3, -0.6, 0.5);
    let short_path = walk(
        &arm,
        &Walk {
            fixture: second,
            tool: long.truth.tool,
            len: (0.32, 0.48),
            duration: 20.0,
            speed: 0.25,
            seed: 302,
        },
    );
    let short_truth = Truth {
        fixture: second,
        ..long.truth.clone()
    };
    let mut short = record(&short_truth, &short_path, 50.0, 302);
    short.t.truncate(12);
    short.q.truncate(12);
    short.length.truncate(12);
    let offset = |r: &Recording| Recording {
        length: r.length.iter().map(|l| l + 0.1).collect(),
        ..r.clone()
    };
    let a = dir.path().join("long.csv");
    let b = dir.path().join("short.csv");
    std::fs::write(&a, offset(&long.recording).csv()).unwrap();
    std::fs::write(&b, offset(&short).csv()).unwrap();
    let out = dir.path().join("camp.dh.toml");
    let json = dir.path().join("camp.json");
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--measured",
        a.to_str().unwrap(),
        "--fixture",
        "258,1468,708",
        "--measured",
        b.to_str().unwrap(),
        "--fixture",
        "1300,-600,500",
        "--tool",
        "60,30,120",
        "--length-offset",
        "100",
        "-o",
        out.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(report["runs"][1]["rows"], 12);
    assert_eq!(report["length_offset_mm"], 100.0);
    assert!(report["runs"][0]["length_offset_std_mm"].is_null());
    assert!(report["held"].to_string().contains("length_offset"));
    let (err, _) = score(&long, &out, 301);
    assert!(err < 5.0, "{err}");
    // A campaign too short in all is refused, naming the count.
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--measured",
        b.to_str().unwrap(),
        "--fixture",
        "1300,-600,500",
        "--measured",
        b.to_str().unwrap(),
        "--fixture",
        "1300,-600,500",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("24 rows in all"), "{}", r.stderr);
}

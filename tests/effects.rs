//! The model a calibration fits is the model its files deliver: every adopted effect is
//! written with the geometry (`[effects]` of a `.dh.toml`, a sidecar beside a `.urdf`), and
//! the loader, `compensate` and the twin evaluate it. Checked against the fit's own model
//! (`Problem::pose_model`, the code the calibration fits with) — the file's evaluation
//! (`robot::effects`) is separate code, and the two must agree to 0.01 µm.

use crate::calibrate::record;
use crate::common::*;
use crate::diagnose::{nj130_cell, truth_with, urdf_cell, Cell, Hidden};
use edbbgen::calibrate::{self, CalibrateOptions, Calibration};
use edbbgen::compensate::{Compensator, Target};
use edbbgen::diagnose::fit::ThermalAt;
use edbbgen::diagnose::{Problem, Run};
use edbbgen::model::MeasurementModel;
use edbbgen::robot::effects::{self, ThermalState};
use edbbgen::robot::{Frame, Robot};
use edbbgen::twin::{self, SimOptions, Truth};
use nalgebra::Vector3;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::Path;

/// The calibrated robot file as `calibrate -o` writes it, loaded back from `dir` by the
/// loader (a URDF with its sidecar).
fn written(dir: &Path, robot_file: &Path, cal: &Calibration, tag: &str) -> Robot {
    let text = std::fs::read_to_string(robot_file).unwrap();
    let p = cal.params();
    let fx = effects::to_toml(&cal.file.effects, &cal.file.reference);
    if robot_file.extension().unwrap() == "urdf" {
        let robot = load(robot_file);
        let side = format!("{tag}.effects.toml");
        let header = vec![format!("{} {side}", effects::SIDECAR_MARK)];
        let out = edbbgen::robot::urdf::calibrated(
            &text,
            robot_file,
            &Default::default(),
            &robot,
            &p.dh,
            &p.map,
            &header,
        )
        .unwrap();
        let (b, dh, f) = edbbgen::robot::urdf::dh_chain(&out, &Default::default()).unwrap();
        let moved = cal
            .file
            .effects
            .reframed((&robot.base, &p.dh, &robot.flange), (&b, &dh, &f));
        let fx = effects::to_toml(&moved, &cal.file.reference);
        std::fs::write(dir.join(format!("{tag}.urdf")), out).unwrap();
        std::fs::write(dir.join(&side), &fx).unwrap();
        load(&dir.join(format!("{tag}.urdf")))
    } else {
        let out =
            edbbgen::robot::dh::calibrated(&text, robot_file, &p.dh, &p.map, &["t".into()], &fx)
                .unwrap();
        let path = dir.join(format!("{tag}.dh.toml"));
        std::fs::write(&path, out).unwrap();
        load(&path)
    }
}

/// Equal values, numbers to a few ulps (degrees in the file, radians in memory).
fn same(a: &serde_json::Value, b: &serde_json::Value) -> bool {
    use serde_json::Value;
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            (x - y).abs() <= 1e-14 * x.abs().max(y.abs())
        }
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(p, q)| same(p, q))
        }
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len() && x.iter().all(|(k, v)| y.get(k).is_some_and(|w| same(v, w)))
        }
        _ => a == b,
    }
}

/// The fit's own model of a pose: the MAP for motor angles `q`, the backlash joints on the
/// flank of `approach`, at `since` seconds of a thermal lag.
fn fitted_point(
    problem: &Problem,
    cal: &Calibration,
    model: &MeasurementModel,
    q: &[f64; 6],
    approach: &[f64; 6],
    since: f64,
) -> Vector3<f64> {
    let play: [f64; 6] = std::array::from_fn(|j| {
        cal.file
            .effects
            .backlash
            .iter()
            .find(|b| b.joint == j)
            .map_or(0.0, |b| -0.5 * b.play * approach[j])
    });
    let (load, p) = problem.pose_model(&cal.estimate, 0, q, &play, ThermalAt { since, rise: 0.0 });
    model.map_position(&p, &load)
}

/// The file's model of the same pose.
fn file_point(robot: &Robot, q: &[f64; 6], approach: &[f64; 6], since: f64) -> Vector3<f64> {
    let e = &robot.effects;
    let load = e.load(&robot.base, &robot.dh, &robot.flange, q, approach);
    let dh = e.at_state(&robot.dh, ThermalState::Elapsed(since));
    let f = edbbgen::robot::kinematics::flange_pose(&robot.base, &dh, &robot.flange, &load);
    f.apply(&robot.tool.expect("a calibrated file carries the MAP"))
}

/// Round trip on one cell for every effect of the library: calibrate (library), write and
/// load the file, then (1) the file's model at 400 random poses, both flanks of a backlash
/// and a warm thermal state, (2) `compensate`'s joints on the fit's model, (3) the twin
/// running the written robot against the fit's model on the rows it records, all within
/// 0.01 µm.
fn round_trip(c: &Cell, robot_file: &Path, seed0: u64) -> Vec<String> {
    let dir = crate::calibrate::workdir(robot_file);
    let mut failures = Vec::new();
    let cases = [
        Hidden::Cyclic(1),
        Hidden::Compliance,
        Hidden::Thermal(false),
        Hidden::Backlash(2),
        Hidden::Servo,
    ];
    for (k, h) in cases.iter().enumerate() {
        let seed = seed0 + k as u64;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut truth = truth_with(*h, &mut rng);
        truth.noise = 1e-6;
        let m = record(c, &truth, seed);
        let fixture = c.model.nominal.fix;
        let runs = [Run {
            measured: &m,
            fixture,
        }];
        let cal = calibrate::run(
            &c.model,
            &c.robot,
            &runs,
            &["m.csv".into()],
            &CalibrateOptions::default(),
        )
        .expect("calibrates");
        assert!(
            !cal.file.effects.is_empty(),
            "{h:?}: an effect adopted: {:?}",
            cal.report.effects
        );
        let problem = Problem::new(&c.model, &runs).with_masses(&c.robot.masses);
        let robot = written(dir.path(), robot_file, &cal, &format!("trip{k}"));
        assert!(
            robot_file.extension().unwrap() == "urdf"
                || same(
                    &serde_json::to_value(&robot.effects).unwrap(),
                    &serde_json::to_value(&cal.file.effects).unwrap()
                ),
            "{h:?}: the file reads back: {:?} against {:?}",
            robot.effects,
            cal.file.effects
        );

        // (1) The file's model against the fit's.
        let mut worst: f64 = 0.0;
        let qs = crate::calibrate::joint_space(&c.robot, 400, seed);
        for (i, q) in qs.iter().enumerate() {
            let approach = if i % 2 == 0 { [1.0; 6] } else { [-1.0; 6] };
            let since = if i % 3 == 0 { 0.0 } else { 30.0 };
            let a = fitted_point(&problem, &cal, &c.model, q, &approach, since);
            let b = file_point(&robot, q, &approach, since);
            worst = worst.max((a - b).norm());
        }
        if worst > 1e-8 {
            failures.push(format!(
                "{h:?}: file model {:.4} um off the fit's",
                worst * 1e6
            ));
        }

        // (2) Compensation: the commanded joints put the fit's model on the nominal target.
        let nominal = c.robot.clone();
        let tcp_n = Frame::translation(c.model.nominal.map);
        let tcp_c = Frame::translation(robot.tool.unwrap());
        let comp = Compensator::new(&nominal, &robot, &tcp_n, &tcp_c);
        let mut worst: f64 = 0.0;
        let mut done = 0;
        for (i, q) in qs.iter().enumerate().take(100) {
            let approach = if i % 2 == 0 { [1.0; 6] } else { [-1.0; 6] };
            let r = comp.compensate(&Target::Joints(*q), &approach);
            let Some(qc) = r.q else { continue };
            done += 1;
            let want = nominal.point(q, &c.model.nominal.map);
            let got = fitted_point(&problem, &cal, &c.model, &qc, &approach, 0.0);
            worst = worst.max((got - want).norm());
        }
        if done < 50 || worst > 1e-8 {
            failures.push(format!(
                "{h:?}: compensated {done}/100, the fit's model {:.4} um off the target",
                worst * 1e6
            ));
        }

        // (3) The twin runs the written robot: its readings are the fit's model of its rows.
        let est = &cal.estimate;
        let map = Vector3::new(est.p[27], est.p[28], est.p[29]);
        let model2 = MeasurementModel::new(&robot, est.fixtures[0], map);
        let quiet = Truth {
            noise: 0.0,
            resolution: 0.0,
            ..Truth::default()
        };
        let m2 = twin::simulate(
            &robot,
            &model2,
            &c.program,
            &quiet,
            // At 250 Hz: the fit interpolates a servo lag's delayed setpoints between the
            // rows and follows a backlash's turns between them; at 50 Hz that alone is
            // 0.01-0.04 um of the comparison, which is about the files.
            &SimOptions {
                rate: 250.0,
                seed: 1,
            },
        )
        .unwrap();
        let p2 = Problem::new(
            &c.model,
            &[Run {
                measured: &m2,
                fixture: est.fixtures[0],
            }],
        )
        .with_masses(&c.robot.masses)
        .with_harmonic_means_of(&problem)
        .with_offset(est.offsets[0]);
        let r = p2.residual(est);
        let rms = (r.iter().map(|v| v * v).sum::<f64>() / r.len() as f64).sqrt();
        if rms > 1e-8 {
            failures.push(format!(
                "{h:?}: the twin on the written robot reads {:.4} um RMS off the fit's model",
                rms * 1e6
            ));
        }
        eprintln!(
            "{} {h:?}: effects {:?}; twin vs fit {:.5} um RMS",
            c.robot.name,
            cal.report
                .effects
                .iter()
                .map(|e| e.effect)
                .collect::<Vec<_>>(),
            rms * 1e6
        );
    }
    failures
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn calibrate_written_files_compensate_and_simulate_reproduce_the_fit_to_0_01_um() {
    let mut failures = round_trip(&nj130_cell(), &nj130_dh(), 300);
    failures.extend(round_trip(
        &urdf_cell(),
        &shared_robot("kuka_kr210_l150"),
        400,
    ));
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn a_urdf_whose_sidecar_is_missing_or_bad_is_refused_with_one_line() {
    let dir = crate::calibrate::workdir(&shared_robot("kuka_kr210_l150"));
    let text = std::fs::read_to_string(shared_robot("kuka_kr210_l150")).unwrap();
    let named = text.replacen(
        "<robot",
        "<!-- edbbgen effects: gone.effects.toml -->\n<robot",
        1,
    );
    let path = dir.path().join("r.urdf");
    std::fs::write(&path, named).unwrap();
    let r = edbbgen(["model", path.to_str().unwrap(), "--fixture", "1400,400,700"]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert_eq!(r.stderr.trim().lines().count(), 1, "{}", r.stderr);
    assert!(r.stderr.contains("gone.effects.toml"), "{}", r.stderr);
    std::fs::write(
        dir.path().join("gone.effects.toml"),
        "[effects]\nschema = \"edbbgen.effects/1\"\n[[effects.backlash]]\njoint = 9\nplay_deg = 0.01\n",
    )
    .unwrap();
    let r = edbbgen(["model", path.to_str().unwrap(), "--fixture", "1400,400,700"]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("joint 9"), "{}", r.stderr);
}

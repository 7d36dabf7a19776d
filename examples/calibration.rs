//! What a measurement program buys (`make calibration`): 20 simulated NJ-130s with random
//! geometric errors (±0.2 mm, ±0.02°) and 5 more with joint compliance as well, each measured
//! at 1 µm bar noise with three programs of about equal duration — the compiled
//! error-sensitive program, the ISO 230-4 circle test, and random poses in the bar shell —
//! then calibrated (`calibrate::run`, effects auto). Printed per robot and program: the true
//! MAP position error over 2,000 random joint poses after a best rigid registration (RMS and
//! max), before and after calibration, next to the predicted 1σ uncertainty.

use edbbgen::calibrate::{self, predict, CalibrateOptions};
use edbbgen::diagnose::Run;
use edbbgen::model::{MeasurementModel, Params, A, ALPHA, D, THETA};
use edbbgen::robot::Robot;
use edbbgen::twin::truth::Compliance;
use edbbgen::twin::{self, SimOptions, Truth};
use edbbgen::units::fmt_fixed;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

const DEG: f64 = std::f64::consts::PI / 180.0;
const RATE_HZ: f64 = 50.0;

/// Random poses of the compiled program's own pool (in the shell, collision-free), visited in
/// random order until the Eq. 7 time matches `duration`: an ngc program without optimisation.
fn random_program(robot: &Robot, pool: &[[f64; 6]], duration: f64, seed: u64) -> String {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let speeds = robot.max_speeds();
    let mut q = pool[rng.random_range(0..pool.len())];
    let deg = |q: &[f64; 6]| -> String {
        ["X", "Y", "Z", "A", "B", "C"]
            .iter()
            .zip(q)
            .map(|(l, v)| format!("{l}{}", fmt_fixed(v / DEG, 4)))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let mut text = format!("G21 G90 G94\nG61\nG0 {}\nM0\nG93\nG64 P10\n", deg(&q));
    let mut t = 0.0;
    while t < duration {
        let next = pool[rng.random_range(0..pool.len())];
        let dt = edbbgen::order::move_time(&q, &next, &speeds).max(0.05);
        text += &format!("G1 {} F{}\n", deg(&next), fmt_fixed(60.0 / dt, 4));
        t += dt;
        q = next;
    }
    text + "G61\nG94\nM0\nM2\n"
}

struct Row {
    before: f64,
    after: f64,
    max: f64,
    predicted: f64,
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let robot = edbbgen::robot::load(
        &root.join("robots/comau_nj130/robot.dh.toml"),
        &Default::default(),
    )
    .expect("robot");
    let fixture = Vector3::new(0.258, 1.468, 0.708);
    let opts = edbbgen::pipeline::CompileOptions::new(fixture);
    let template = edbbgen::emit::dialect("ngc").expect("ngc");
    let compiled =
        edbbgen::pipeline::compile(&robot, &opts, template, &edbbgen::sample::NoProgress)
            .expect("compile");
    let model = compiled.model.clone();
    let pool: Vec<[f64; 6]> = compiled.pool.candidates.iter().map(|c| c.q).collect();
    let circle_model = MeasurementModel::new(&robot, fixture, model.nominal.map);
    let circle_text =
        twin::circle::program(&robot, &circle_model, &Default::default()).expect("circle");
    let parse = |t: &str| edbbgen::verify::gcode::parse(t).expect("parse");
    let programs = [
        ("compiled", parse(&compiled.text)),
        ("ISO circle", parse(&circle_text)),
        (
            "random poses",
            parse(&random_program(
                &robot,
                &pool,
                compiled.path.time_sorted,
                99,
            )),
        ),
    ];
    println!(
        "compiled program: {} poses, {} s estimated; header predicts {} um RMS over the joint space",
        compiled.program.header.poses,
        fmt_fixed(compiled.program.header.time_s, 1),
        fmt_fixed(compiled.program.header.predicted_std_um, 2)
    );
    let space = predict::workspace(&robot, 2000, 4242);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2024);
    let mut rows: Vec<Vec<Row>> = programs.iter().map(|_| Vec::new()).collect();
    println!(
        "{:>5} {:>11}  {:>14} {:>14} {:>12} {:>14} {:>9}",
        "robot",
        "compliance",
        "program",
        "before [um]",
        "after [um]",
        "max after [um]",
        "pred [um]"
    );
    for r in 0..25u64 {
        let mut truth = Truth {
            noise: 1e-6,
            ..Truth::default()
        };
        for i in 0..6 {
            truth.geometric[A + i] = rng.random_range(-0.2..0.2) * 1e-3;
            truth.geometric[D + i] = rng.random_range(-0.2..0.2) * 1e-3;
            truth.geometric[ALPHA + i] = rng.random_range(-0.02..0.02) * DEG;
            truth.geometric[THETA + i] = rng.random_range(-0.02..0.02) * DEG;
        }
        if r >= 20 {
            let s = rng.random_range(0.5..2.0);
            truth.compliance = Some(Compliance {
                stiffness: [1e7, 4e6 * s, 4e6 * s, 1.5e6 * s, 1.5e6 * s, 1.5e6 * s],
                masses: Vec::new(),
            });
        }
        let mut tp = model.nominal.to_array();
        for (v, g) in tp.iter_mut().zip(&truth.geometric) {
            *v += g;
        }
        let tp = Params::from_array(&tp);
        let truep: Vec<_> = space.iter().map(|q| model.map_position(&tp, q)).collect();
        let nominal: Vec<_> = space
            .iter()
            .map(|q| model.map_position(&model.nominal, q))
            .collect();
        let before = predict::register(&nominal, &truep).0 * 1e6;
        for (k, (name, program)) in programs.iter().enumerate() {
            let m = twin::simulate(
                &robot,
                &model,
                program,
                &truth,
                &SimOptions {
                    rate: RATE_HZ,
                    seed: r,
                },
            )
            .expect("simulate");
            let cal = calibrate::run(
                &model,
                &robot,
                &[Run {
                    measured: &m,
                    fixture,
                }],
                &[name.to_string()],
                &CalibrateOptions::default(),
            )
            .expect("calibrate");
            // What the user gets: the calibrated robot when `calibrate` writes one, else (its
            // verdict: no better than nominal held out, or nothing determined) the nominal one.
            let written = cal.report.calibrated;
            let p = if written { cal.params() } else { model.nominal };
            let got: Vec<_> = space.iter().map(|q| model.map_position(&p, q)).collect();
            let (rms, max, _, _) = predict::register(&got, &truep);
            let row = Row {
                before,
                after: rms * 1e6,
                max: max * 1e6,
                predicted: cal.report.predicted_position_std_um.workspace_rms,
            };
            println!(
                "{:>5} {:>11}  {:>14} {:>14} {:>12} {:>14} {:>9}",
                r + 1,
                if r >= 20 { "yes" } else { "no" },
                name,
                fmt_fixed(row.before, 1),
                fmt_fixed(row.after, 2),
                fmt_fixed(row.max, 2),
                fmt_fixed(row.predicted, 2)
            );
            if !written {
                println!("      not written: {}", cal.report.verdict);
            }
            rows[k].push(row);
        }
    }
    let median = |mut v: Vec<f64>| -> f64 {
        v.sort_by(f64::total_cmp);
        let n = v.len();
        if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        }
    };
    println!("\nsummary over 25 robots (median; RMS over 2,000 random joint poses after rigid registration):");
    for (k, (name, _)) in programs.iter().enumerate() {
        let r = &rows[k];
        let ratio: Vec<f64> = r.iter().map(|x| x.predicted / x.after).collect();
        println!(
            "  {name:>14}: before {} um, after {} um (max over robots {} um), predicted {} um, predicted/realised median {} (range {}..{})",
            fmt_fixed(median(r.iter().map(|x| x.before).collect()), 1),
            fmt_fixed(median(r.iter().map(|x| x.after).collect()), 2),
            fmt_fixed(r.iter().map(|x| x.after).fold(0.0, f64::max), 2),
            fmt_fixed(median(r.iter().map(|x| x.predicted).collect()), 2),
            fmt_fixed(median(ratio.clone()), 2),
            fmt_fixed(ratio.iter().copied().fold(f64::MAX, f64::min), 2),
            fmt_fixed(ratio.iter().copied().fold(0.0, f64::max), 2)
        );
    }
}

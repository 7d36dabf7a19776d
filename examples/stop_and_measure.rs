//! Measuring without a synchronous joint log (`make stop-and-measure`): simulated
//! NJ-130s with random geometric errors (±0.2 mm, ±0.02°), 1 µm bar noise at 50 Hz, measured
//! two ways, each against its synchronous reference:
//!
//! 1. The stop-and-measure program (`--dwell 5`): the bar's own log (clock offset ±30 s, drift
//!    ±200 ppm, random pauses, a controller stop, the bar handled while unmounted) matched to
//!    the program's poses, calibrated from the plateau means — against the same run recorded
//!    synchronously (every bar sample with the joints at its instant).
//! 2. The continuous program: the bar's log and the controller's joint log at 10 ms, each on
//!    its clock, synchronised — against the same run recorded synchronously.
//!
//! Both calibrated with `calibrate`'s defaults (fixture and tool point estimated). Printed per
//! robot: the true MAP position error over 2,000 random joint poses after a best rigid
//! registration (RMS) before and after each calibration, the predicted 1σ, the ratio of the
//! plateaus' to the synchronous run's (realised and predicted), the clock recovered, and (2)
//! the difference between the two calibrated robots over the joint space.

use edbbgen::calibrate::{self, predict, CalibrateOptions};
use edbbgen::diagnose::Run;
use edbbgen::logs;
use edbbgen::model::{MeasurementModel, Params, A, ALPHA, D, THETA};
use edbbgen::twin::logsim::{self, LogOptions};
use edbbgen::twin::measured::Form;
use edbbgen::twin::{Measured, Trajectory, Truth};
use edbbgen::units::fmt_fixed;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

const DEG: f64 = std::f64::consts::PI / 180.0;
const ROBOTS: u64 = 10;
/// The dwell (s): long enough that the plateau means carry what the continuous recording of
/// the same run adds along its moves to within 2x (the compiler predicts both; the figures are
/// on docs/validation.md).
const DWELL: f64 = 5.0;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn calibrated(
    model: &MeasurementModel,
    robot: &edbbgen::robot::Robot,
    m: &Measured,
) -> (Params, f64) {
    let cal = calibrate::run(
        model,
        robot,
        &[Run {
            measured: m,
            fixture: model.nominal.fix,
        }],
        &["run".to_string()],
        &CalibrateOptions::default(),
    )
    .expect("calibrate");
    (
        cal.params(),
        cal.report.predicted_position_std_um.workspace_rms,
    )
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let robot = edbbgen::robot::load(
        &root.join("robots/comau_nj130/robot.dh.toml"),
        &Default::default(),
    )
    .expect("robot");
    let fixture = Vector3::new(0.258, 1.468, 0.708);
    let template = edbbgen::emit::dialect("ngc").expect("ngc");
    let compile = |dwell: Option<f64>| {
        let mut opts = edbbgen::pipeline::CompileOptions::new(fixture);
        opts.dwell = dwell;
        edbbgen::pipeline::compile(&robot, &opts, template, &edbbgen::sample::NoProgress)
            .expect("compile")
    };
    let stop = compile(Some(DWELL));
    let cont = compile(None);
    let model = stop.model.clone();
    let h = &stop.program.header;
    println!(
        "stop-and-measure program: {} poses, {} s estimated (dwells included); header predicts {} um RMS over the joint space from the plateaus, {} um from the same run recorded synchronously",
        h.poses,
        fmt_fixed(h.time_s, 1),
        fmt_fixed(h.predicted_std_um, 2),
        fmt_fixed(h.predicted_continuous_std_um, 2)
    );
    println!(
        "continuous program: {} poses, {} s estimated; header predicts {} um",
        cont.program.header.poses,
        fmt_fixed(cont.program.header.time_s, 1),
        fmt_fixed(cont.program.header.predicted_std_um, 2)
    );
    let read = |text: &str| edbbgen::verify::gcode::parse(text).expect("parse");
    let (stop_p, cont_p) = (read(&stop.text), read(&cont.text));
    let stop_traj = Trajectory::from_program(&robot, &model, &stop_p).expect("trajectory");
    let cont_traj = Trajectory::from_program(&robot, &model, &cont_p).expect("trajectory");
    let tpl = logsim::template(&stop_traj, &model);
    let space = predict::workspace(&robot, 2000, 4242);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2023);
    let mut rows: Vec<[f64; 10]> = Vec::new();
    println!(
        "{:>5} {:>9} | {:>9} {:>9} {:>9} {:>9} {:>6} {:>6} | {:>9} {:>9} {:>9} {:>9} {:>9}",
        "robot",
        "before",
        "plateaus",
        "pred",
        "sync",
        "pred",
        "ratio",
        "pred",
        "joint log",
        "sync",
        "diff",
        "offset",
        "drift"
    );
    println!(
        "{:>5} {:>9} | {:>9} {:>9} {:>9} {:>9} {:>6} {:>6} | {:>9} {:>9} {:>9} {:>9} {:>9}",
        "",
        "[um]",
        "[um]",
        "[um]",
        "[um]",
        "[um]",
        "",
        "",
        "[um]",
        "[um]",
        "[um]",
        "err [ms]",
        "err [ppm]"
    );
    for r in 0..ROBOTS {
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
        let mut tp = model.nominal.to_array();
        for (v, g) in tp.iter_mut().zip(&truth.geometric) {
            *v += g;
        }
        let tp = Params::from_array(&tp);
        let truep: Vec<_> = space.iter().map(|q| model.map_position(&tp, q)).collect();
        let err = |p: &Params| {
            let got: Vec<_> = space.iter().map(|q| model.map_position(p, q)).collect();
            predict::register(&got, &truep).0 * 1e6
        };
        let before = err(&model.nominal);
        let opts = LogOptions {
            offset: rng.random_range(-30.0..30.0),
            drift: rng.random_range(-200e-6..200e-6),
            holds: 1,
            seed: r,
            ..LogOptions::default()
        };
        // 1. Stop-and-measure: the plateaus, and the same run synchronously.
        let logs1 = logsim::simulate_logs(&robot, &model, &stop_traj, &truth, &opts).expect("logs");
        let sm = logs::stop_and_measure(&tpl, &logs1.bar).expect("matched");
        let mut m = Measured {
            form: Form::Static { timed: true },
            std: Some(Vec::new()),
            samples: Some(Vec::new()),
            ..Measured::default()
        };
        for &(k, j) in &sm.readings {
            let p = &sm.plateaus[j];
            m.t.push(p.t - sm.t0);
            m.q.push(tpl.slots[k].q);
            m.length.push(p.mean);
            m.std.as_mut().unwrap().push(p.std);
            m.samples.as_mut().unwrap().push(p.samples as u32);
        }
        let (pa, pred_a) = calibrated(&model, &robot, &m);
        let (pb, pred_b) = calibrated(&model, &robot, &logs1.synchronous);
        // 2. Continuous with a joint log at 10 ms: synchronised (twice: nominal, calibrated).
        let logs2 = logsim::simulate_logs(&robot, &model, &cont_traj, &truth, &opts).expect("logs");
        let spline = logs::sync::Spline::new(&logs2.joints.t, &logs2.joints.q);
        let to_measured = |s: &logs::sync::Synced| {
            let t0 = logs2.bar.t[0];
            Measured {
                t: s.rows.iter().map(|&k| logs2.bar.t[k] - t0).collect(),
                q: s.q.clone(),
                length: s.rows.iter().map(|&k| logs2.bar.length[k]).collect(),
                ..Measured::default()
            }
        };
        let nominal = |q: &[f64; 6]| model.length(&model.nominal, q);
        let s1 =
            logs::sync::sync(&logs2.bar.t, &logs2.bar.length, &spline, &nominal).expect("sync");
        let (p1, _) = calibrated(&model, &robot, &to_measured(&s1));
        let refined = |q: &[f64; 6]| model.length(&p1, q);
        let s2 =
            logs::sync::sync(&logs2.bar.t, &logs2.bar.length, &spline, &refined).expect("sync");
        let (pc, _) = calibrated(&model, &robot, &to_measured(&s2));
        let (pd, _) = calibrated(&model, &robot, &logs2.synchronous);
        let c: Vec<_> = space.iter().map(|q| model.map_position(&pc, q)).collect();
        let dd: Vec<_> = space.iter().map(|q| model.map_position(&pd, q)).collect();
        let diff = (c
            .iter()
            .zip(&dd)
            .map(|(a, b)| (a - b).norm_squared())
            .sum::<f64>()
            / c.len() as f64)
            .sqrt()
            * 1e6;
        let row = [
            before,
            err(&pa),
            pred_a,
            err(&pb),
            pred_b,
            err(&pc),
            err(&pd),
            diff,
            (s2.offset - opts.offset) * 1e3,
            (s2.drift - opts.drift) * 1e6,
        ];
        println!(
            "{:>5} {:>9} | {:>9} {:>9} {:>9} {:>9} {:>6} {:>6} | {:>9} {:>9} {:>9} {:>9} {:>9}",
            r + 1,
            fmt_fixed(row[0], 1),
            fmt_fixed(row[1], 3),
            fmt_fixed(row[2], 3),
            fmt_fixed(row[3], 3),
            fmt_fixed(row[4], 3),
            fmt_fixed(row[1] / row[3], 2),
            fmt_fixed(row[2] / row[4], 2),
            fmt_fixed(row[5], 3),
            fmt_fixed(row[6], 3),
            fmt_fixed(row[7], 3),
            fmt_fixed(row[8], 4),
            fmt_fixed(row[9], 2)
        );
        rows.push(row);
    }
    let col = |k: usize| median(rows.iter().map(|r| r[k]).collect());
    let ratio = |a: usize, b: usize| median(rows.iter().map(|r| r[a] / r[b]).collect());
    let worst = |a: usize, b: usize| rows.iter().map(|r| r[a] / r[b]).fold(0.0, f64::max);
    println!("\nmedians over {ROBOTS} robots (RMS over 2,000 random joint poses after rigid registration):");
    println!("  before calibration {} um", fmt_fixed(col(0), 1));
    println!(
        "  stop-and-measure from the bar log: {} um (predicted {} um); the same run synchronous: {} um (predicted {} um); ratio realised {} (largest {}), predicted {} (largest {}); the compiler predicted {} and {} um (ratio {})",
        fmt_fixed(col(1), 3),
        fmt_fixed(col(2), 3),
        fmt_fixed(col(3), 3),
        fmt_fixed(col(4), 3),
        fmt_fixed(ratio(1, 3), 2),
        fmt_fixed(worst(1, 3), 2),
        fmt_fixed(ratio(2, 4), 2),
        fmt_fixed(worst(2, 4), 2),
        fmt_fixed(h.predicted_std_um, 2),
        fmt_fixed(h.predicted_continuous_std_um, 2),
        fmt_fixed(h.predicted_std_um / h.predicted_continuous_std_um, 2)
    );
    println!(
        "  continuous with a 10 ms joint log: {} um; synchronous: {} um; the two calibrated robots differ by {} um RMS (largest {} um); clock offset error {} ms (largest {} ms), drift error {} ppm",
        fmt_fixed(col(5), 3),
        fmt_fixed(col(6), 3),
        fmt_fixed(col(7), 3),
        fmt_fixed(rows.iter().map(|r| r[7]).fold(0.0, f64::max), 3),
        fmt_fixed(median(rows.iter().map(|r| r[8].abs()).collect()), 4),
        fmt_fixed(rows.iter().map(|r| r[8].abs()).fold(0.0, f64::max), 4),
        fmt_fixed(median(rows.iter().map(|r| r[9].abs()).collect()), 2)
    );
}

//! What pose selection buys on static readings (`make pose-selection`): the paper's premise
//! at equal effort. Simulated NJ-130s with random geometric errors (±0.2 mm, ±0.02°), each
//! read once at the 35 measurement poses the compiler selects for the default cell's
//! `--dwell 5` program and once at 35 poses drawn at random from the same pool (inside the
//! bar's shell, free of collisions), every reading with the same noise (a 5 s plateau's mean:
//! 1 µm / √225). Both calibrated with `calibrate`'s defaults, and again with the fixture
//! known; each calibrated robot against the true one over 2,000 random joint poses after a
//! best rigid registration (RMS), with `calibrate`'s predicted 1σ.
//!
//! A continuous recording washes the selection out (`make calibration`: random pool poses
//! recorded along their moves calibrate about as well as the compiled program); one reading
//! per pose does not.

use edbbgen::calibrate::{self, predict, CalibrateOptions};
use edbbgen::diagnose::Run;
use edbbgen::model::{Params, A, ALPHA, D, THETA};
use edbbgen::twin::measured::Form;
use edbbgen::twin::Measured;
use edbbgen::units::fmt_fixed;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

const DEG: f64 = std::f64::consts::PI / 180.0;
const ROBOTS: usize = 12;
/// A 5 s plateau's core at 50 Hz averages about this many samples of 1 µm noise.
const SAMPLES: u32 = 225;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// A standard normal draw (Box–Muller).
fn gauss(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let robot = edbbgen::robot::load(
        &root.join("robots/comau_nj130/robot.dh.toml"),
        &Default::default(),
    )
    .expect("robot");
    let mut opts = edbbgen::pipeline::CompileOptions::new(Vector3::new(0.258, 1.468, 0.708));
    opts.dwell = Some(5.0);
    let compiled = edbbgen::pipeline::compile(
        &robot,
        &opts,
        edbbgen::emit::dialect("ngc").expect("ngc"),
        &edbbgen::sample::NoProgress,
    )
    .expect("compile");
    let model = compiled.model.clone();
    let selected: Vec<[f64; 6]> = compiled
        .path
        .poses
        .iter()
        .zip(&compiled.plan.waypoints)
        .filter(|(_, w)| !w.support)
        .map(|(q, _)| *q)
        .collect();
    let pool: Vec<[f64; 6]> = compiled.pool.candidates.iter().map(|c| c.q).collect();
    println!(
        "{} selected measurement poses of a pool of {}; each reading 1 um / sqrt({SAMPLES})",
        selected.len(),
        pool.len()
    );
    let space = predict::workspace(&robot, 2000, 4242);
    let sigma = 1e-6 / f64::from(SAMPLES).sqrt();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    for fixture_known in [false, true] {
        println!(
            "\n{}\n{:>5} {:>10} {:>10} {:>10} {:>10}",
            if fixture_known {
                "fixture known (--fixture-known)"
            } else {
                "calibrate's defaults (fixture and tool point estimated)"
            },
            "robot",
            "selected",
            "pred",
            "random",
            "pred"
        );
        let mut rows: Vec<[f64; 4]> = Vec::new();
        for r in 0..ROBOTS {
            let mut p = model.nominal.to_array();
            for i in 0..6 {
                p[A + i] += rng.random_range(-0.2..0.2) * 1e-3;
                p[D + i] += rng.random_range(-0.2..0.2) * 1e-3;
                p[ALPHA + i] += rng.random_range(-0.02..0.02) * DEG;
                p[THETA + i] += rng.random_range(-0.02..0.02) * DEG;
            }
            let truth = Params::from_array(&p);
            let true_map: Vec<_> = space
                .iter()
                .map(|q| model.map_position(&truth, q))
                .collect();
            let random: Vec<[f64; 6]> = (0..selected.len())
                .map(|_| pool[rng.random_range(0..pool.len())])
                .collect();
            let mut row = [0.0; 4];
            for (c, poses) in [&selected, &random].into_iter().enumerate() {
                let mut m = Measured {
                    form: Form::Static { timed: false },
                    std: Some(vec![sigma; poses.len()]),
                    samples: Some(vec![SAMPLES; poses.len()]),
                    ..Measured::default()
                };
                for q in poses {
                    m.t.push(m.q.len() as f64);
                    m.q.push(*q);
                    m.length
                        .push(model.length(&truth, q) + sigma * gauss(&mut rng));
                }
                let o = CalibrateOptions {
                    fixture_known,
                    ..CalibrateOptions::default()
                };
                let cal = calibrate::run(
                    &model,
                    &robot,
                    &[Run {
                        measured: &m,
                        fixture: model.nominal.fix,
                    }],
                    &["run".to_string()],
                    &o,
                )
                .expect("calibrate");
                let got: Vec<_> = space
                    .iter()
                    .map(|q| model.map_position(&cal.params(), q))
                    .collect();
                row[2 * c] = predict::register(&got, &true_map).0 * 1e6;
                row[2 * c + 1] = cal.report.predicted_position_std_um.workspace_rms;
            }
            println!(
                "{:>5} {:>10} {:>10} {:>10} {:>10}",
                r + 1,
                fmt_fixed(row[0], 3),
                fmt_fixed(row[1], 3),
                fmt_fixed(row[2], 3),
                fmt_fixed(row[3], 3)
            );
            rows.push(row);
        }
        let col = |k: usize| rows.iter().map(|r| r[k]).collect::<Vec<f64>>();
        let worst = |k: usize| col(k).into_iter().fold(0.0f64, f64::max);
        println!(
            "median (worst): selected {} um ({}), predicted {} um; random {} um ({}), predicted {} um",
            fmt_fixed(median(col(0)), 3),
            fmt_fixed(worst(0), 3),
            fmt_fixed(median(col(1)), 3),
            fmt_fixed(median(col(2)), 3),
            fmt_fixed(worst(2), 3),
            fmt_fixed(median(col(3)), 3)
        );
    }
}

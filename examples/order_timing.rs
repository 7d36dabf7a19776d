//! Times `order::solve`. Prints; asserts nothing (speed is measured, never asserted by tests).
//!
//! - `cargo run --release --example order_timing [n] [seed]`: n random poses (uniform in ±3 rad).
//! - `cargo run --release --example order_timing nj130 [n ...]`: the TSP instances of `make bench`
//!   (NJ-130 pools built exactly as `examples/bench.rs` builds them, pose 0 the fixed start; by
//!   default 35, 200, 1000 and 3400 poses), best of 3 like the bench, with the gap to the LKH-3
//!   cost of the same instance (the LKH-3 costs in BENCHMARKS.md). The pools are cached in
//!   `target/tsp-pools/` (exact f64 bits) because sampling them takes longer than the tours.
//!   `TSP_REPS=k` in the environment times k runs instead of 3.

use edbbgen::ir::Cell;
use edbbgen::model::MeasurementModel;
use edbbgen::sample::{self, NoProgress, SampleConfig};
use edbbgen::units::{DEG, MM};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::Path;
use std::time::Instant;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// LKH-3 (elkai 2.0.1, runs=1) tour costs of the bench instances, from the edbbgen costs and
/// ratios of a `make bench-peers` run (CHANGELOG.md, performance history: 12.8510 +0.000 %,
/// 52.2494 +0.146 %, 178.5687 +0.186 %, 466.3317 +0.344 %).
const LKH: [(usize, f64); 4] = [
    (35, 12.8510),
    (200, 52.2494 / 1.00146),
    (1000, 178.5687 / 1.00186),
    (3400, 466.3317 / 1.00344),
];

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("nj130") {
        let sizes: Vec<usize> = if args.len() > 1 {
            args[1..].iter().map(|s| s.parse().expect("n")).collect()
        } else {
            LKH.iter().map(|&(n, _)| n).collect()
        };
        return nj130(&sizes);
    }
    let n: usize = args.first().map_or(3400, |s| s.parse().expect("n"));
    let seed: u64 = args.get(1).map_or(1, |s| s.parse().expect("seed"));
    let speed = [2.0, 1.8, 2.2, 3.5, 3.5, 5.0];
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let poses: Vec<[f64; 6]> = (0..n)
        .map(|_| std::array::from_fn(|_| rng.random_range(-3.0..3.0)))
        .collect();
    let t0 = Instant::now();
    let tour = edbbgen::order::solve(&poses, 0, &speed).expect("valid input");
    let dt = t0.elapsed();
    println!(
        "n={n} seed={seed}: {:.1} ms, unsorted {:.3} s, sorted {:.3} s",
        dt.as_secs_f64() * 1e3,
        tour.time_unsorted,
        tour.time_sorted
    );
}

fn nj130(sizes: &[usize]) {
    let path = Path::new(ROOT).join("robots/comau_nj130/robot.dh.toml");
    let robot = edbbgen::robot::load(&path, &Default::default()).expect("NJ-130");
    let speed = robot.max_speeds();
    let dir = Path::new(ROOT).join("target/tsp-pools");
    std::fs::create_dir_all(&dir).expect("target/tsp-pools");
    for &k in sizes {
        let file = dir.join(format!("nj130_{k}.txt"));
        let poses: Vec<[f64; 6]> = match std::fs::read_to_string(&file) {
            Ok(s) => s
                .lines()
                .map(|l| {
                    let v: Vec<f64> = l
                        .split(' ')
                        .map(|x| f64::from_bits(u64::from_str_radix(x, 16).expect("hex")))
                        .collect();
                    std::array::from_fn(|i| v[i])
                })
                .collect(),
            Err(_) => {
                // As examples/bench.rs: the NJ-130 default cell, 10 deg grid, seed 1.
                let fixture = Vector3::new(258.0, 1468.0, 708.0) * MM;
                let map = Vector3::new(60.0, 30.0, 120.0) * MM;
                let model = MeasurementModel::new(&robot, fixture, map);
                let cell = Cell::shell_only(fixture, map, 0.30, 0.52, 0.0);
                let cfg = SampleConfig {
                    step: [10.0 * DEG; 6],
                    max_candidates: k,
                    seed: 1,
                    movable: [true; 6],
                };
                let (pool, _) = sample::run(&robot, &model, &cell, &cfg, &NoProgress);
                let poses: Vec<[f64; 6]> = pool.candidates.iter().map(|c| c.q).collect();
                let text: String = poses
                    .iter()
                    .map(|q| {
                        let v: Vec<String> =
                            q.iter().map(|x| format!("{:016x}", x.to_bits())).collect();
                        v.join(" ") + "\n"
                    })
                    .collect();
                std::fs::write(&file, text).expect("cache");
                poses
            }
        };
        let mut best = f64::INFINITY;
        let mut tour = None;
        for _ in 0..std::env::var("TSP_REPS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(3)
        {
            let t0 = Instant::now();
            let t = edbbgen::order::solve(&poses, 0, &speed).expect("tour");
            best = best.min(t0.elapsed().as_secs_f64());
            tour = Some(t);
        }
        let tour = tour.expect("ran");
        let lkh = LKH
            .iter()
            .find(|&&(n, _)| n == poses.len())
            .map(|&(_, c)| c);
        let gap = lkh.map_or(String::new(), |c| {
            format!(
                ", LKH-3 {c:.4} s, gap {:+.3} %",
                (tour.time_sorted / c - 1.0) * 100.0
            )
        });
        println!(
            "TSP {} poses: {:.4} s (best of 3), cost {:.4} s{gap}",
            poses.len(),
            best,
            tour.time_sorted
        );
    }
}

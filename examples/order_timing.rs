//! Times `order::solve` on random poses: `cargo run --release --example order_timing [n] [seed]`.
//! Prints; asserts nothing (speed is measured, never asserted by tests).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

fn main() {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().map_or(3400, |s| s.parse().expect("n"));
    let seed: u64 = args.next().map_or(1, |s| s.parse().expect("seed"));
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

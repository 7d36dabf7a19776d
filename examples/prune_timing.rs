//! Times only the pruning (`select::eliminate`) on the bench's NJ-130 pools:
//! `cargo run --release --example prune_timing [n ...] [--reps R] [--save DIR] [--check DIR]
//! [--reference]`.
//!
//! In: pool sizes (default 3400 20000), taken like `make bench` from `sample::run` on the 10° grid
//! and scaled on the 22 identifiable columns. Out (stdout): the wall time of `eliminate` per size
//! (best of R, default 1), and a hash of its removal order and curve bits. `--save DIR` writes the
//! removal order and curve (bits) to DIR/prune_N.txt, `--check DIR` compares against such a file
//! bit for bit, `--reference` also runs `eliminate_reference` and compares. Asserts nothing
//! else; speed is measured, never asserted by tests.

use edbbgen::ir::Cell;
use edbbgen::model::MeasurementModel;
use edbbgen::sample::{self, NoProgress, SampleConfig};
use edbbgen::units::{DEG, MM};
use nalgebra::Vector3;
use std::path::{Path, PathBuf};
use std::time::Instant;

fn text(removed: &[usize], curve: &[(usize, f64)]) -> String {
    let mut s = String::new();
    for r in removed {
        s.push_str(&format!("r {r}\n"));
    }
    for (n, c) in curve {
        s.push_str(&format!("c {n} {:016x}\n", c.to_bits()));
    }
    s
}

fn hash(s: &str) -> u64 {
    // FNV-1a: enough to tell runs apart at a glance.
    s.bytes().fold(0xcbf29ce484222325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100000001b3)
    })
}

fn main() {
    let mut sizes = Vec::new();
    let mut reps = 1;
    let mut save: Option<PathBuf> = None;
    let mut check: Option<PathBuf> = None;
    let mut reference = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--reps" => reps = args.next().expect("R").parse().expect("R"),
            "--save" => save = Some(args.next().expect("DIR").into()),
            "--check" => check = Some(args.next().expect("DIR").into()),
            "--reference" => reference = true,
            n => sizes.push(n.parse::<usize>().expect("pool size")),
        }
    }
    if sizes.is_empty() {
        sizes = vec![3400, 20_000];
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let robot = edbbgen::robot::load(
        &root.join("robots/comau_nj130/robot.dh.toml"),
        &Default::default(),
    )
    .expect("NJ-130");
    let fixture = Vector3::new(258.0, 1468.0, 708.0) * MM;
    let map = Vector3::new(60.0, 30.0, 120.0) * MM;
    let model = MeasurementModel::new(&robot, fixture, map);
    let cell = Cell::shell_only(fixture, map, 0.30, 0.52, 0.0);
    let pool = |cap: usize| {
        let cfg = SampleConfig {
            step: [10.0 * DEG; 6],
            max_candidates: cap,
            seed: 1,
            movable: [true; 6],
        };
        sample::run(&robot, &model, &cell, &cfg, &NoProgress).0
    };
    // The bench's columns: identifiable on the 3,400 pool.
    let ids = {
        let p = pool(3400);
        let qs: Vec<[f64; 6]> = p.candidates.iter().map(|c| c.q).collect();
        edbbgen::model::analyse(&model.rows(&qs), &Default::default()).identifiable
    };
    let m = ids.len();
    eprintln!("threads {}", rayon::current_num_threads());
    for n in sizes {
        let p = pool(n);
        let (j, _) = edbbgen::select::scaled_jacobian(&model, &p, &ids);
        let mut best = f64::INFINITY;
        let mut out = None;
        for _ in 0..reps.max(1) {
            let t = Instant::now();
            let r = edbbgen::select::eliminate(&j, m);
            best = best.min(t.elapsed().as_secs_f64());
            out = Some(r);
        }
        let (removed, curve) = out.expect("one run");
        let t = text(&removed, &curve);
        println!(
            "prune {} -> {m}: {best:.3} s (best of {reps}), hash {:016x}",
            p.candidates.len(),
            hash(&t)
        );
        if let Some(d) = &save {
            std::fs::create_dir_all(d).expect("dir");
            std::fs::write(d.join(format!("prune_{n}.txt")), &t).expect("write");
        }
        if let Some(d) = &check {
            let want = std::fs::read_to_string(d.join(format!("prune_{n}.txt"))).expect("read");
            println!(
                "  check vs saved: {}",
                if want == t { "IDENTICAL" } else { "DIFFERENT" }
            );
        }
        if reference {
            let t0 = Instant::now();
            let (rr, rc) = edbbgen::select::eliminate_reference(&j, m);
            let dt = t0.elapsed().as_secs_f64();
            let same = text(&rr, &rc) == t;
            println!(
                "  reference: {dt:.3} s, {}",
                if same { "IDENTICAL" } else { "DIFFERENT" }
            );
        }
    }
}

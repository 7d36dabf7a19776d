//! `make bench`: throughput of the hot stages on the bundled NJ-130 cell. Prints a table and
//! writes target/bench.json. Speed is measured here, never asserted by tests.

use edbbgen::ir::Cell;
use edbbgen::model::{MeasurementModel, N_PARAMS};
use edbbgen::sample::{self, NoProgress, SampleConfig};
use edbbgen::units::{DEG, MM};
use nalgebra::Vector3;
use std::time::Instant;

fn main() {
    let path = std::path::Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/robots/comau_nj130/robot.dh.toml"
    ));
    let robot = edbbgen::robot::load(path, &Default::default()).expect("NJ-130");
    let fixture = Vector3::new(258.0, 1468.0, 708.0) * MM;
    let map = Vector3::new(60.0, 30.0, 120.0) * MM;
    let model = MeasurementModel::new(&robot, fixture, map);
    let cell = Cell::shell_only(fixture, map, 0.30, 0.52, 0.0);
    let mut rows: Vec<(String, f64, String)> = Vec::new();

    // FK (map position) on a stream of configurations.
    let n = 2_000_000u64;
    let t = Instant::now();
    let mut acc = 0.0;
    for k in 0..n {
        let x = k as f64 * 1e-6;
        let q = [x, -x, 0.5 * x, x, -0.3 * x, 2.0 * x];
        acc += model.map_position(&model.nominal, &q).x;
    }
    let fk = n as f64 / t.elapsed().as_secs_f64();
    std::hint::black_box(acc);
    rows.push(("FK (MAP position), 1 thread".into(), fk, "poses/s".into()));

    let t = Instant::now();
    let mut row = [0.0; N_PARAMS];
    let m = 500_000u64;
    for k in 0..m {
        let x = k as f64 * 1e-6;
        let q = [x, -x, 0.5 * x, x, -0.3 * x, 2.0 * x];
        acc += model.jacobian_row(&model.nominal, &q, &mut row);
    }
    std::hint::black_box(acc);
    rows.push((
        "identification-Jacobian rows, 1 thread".into(),
        m as f64 / t.elapsed().as_secs_f64(),
        "rows/s".into(),
    ));

    let cfg = SampleConfig {
        step: [10.0 * DEG; 6],
        max_candidates: 3400,
        seed: 1,
        movable: [true; 6],
    };
    let t = Instant::now();
    let (pool, report) = sample::run(&robot, &model, &cell, &cfg, &NoProgress);
    let dt = t.elapsed().as_secs_f64();
    rows.push((
        "sampling 10 deg grid: grid poses covered".into(),
        report.grid_size as f64 / dt,
        "configs/s".into(),
    ));
    rows.push((
        "sampling 10 deg grid: poses evaluated".into(),
        report.evaluated as f64 / dt,
        "configs/s".into(),
    ));
    rows.push(("sampling 10 deg grid: wall time".into(), dt, "s".into()));

    let ids: Vec<usize> = {
        let r: Vec<[f64; N_PARAMS]> = pool
            .candidates
            .iter()
            .map(|c| {
                let mut r = [0.0; N_PARAMS];
                model.jacobian_row(&model.nominal, &c.q, &mut r);
                r
            })
            .collect();
        edbbgen::model::analyse(&r, &Default::default()).identifiable
    };
    let t = Instant::now();
    let sel = edbbgen::select::run(&model, &pool, &ids, &Default::default()).expect("selection");
    rows.push((
        format!(
            "pruning: full cond(n) curve {} -> {}",
            pool.candidates.len(),
            sel.m
        ),
        t.elapsed().as_secs_f64(),
        "s".into(),
    ));

    let poses: Vec<[f64; 6]> = pool.candidates.iter().map(|c| c.q).collect();
    let t = Instant::now();
    let tour = edbbgen::order::solve(&poses, 0, &robot.max_speeds()).expect("tour");
    rows.push((
        format!("TSP on {} poses", poses.len()),
        t.elapsed().as_secs_f64(),
        "s".into(),
    ));
    rows.push((
        format!("TSP tour cost on {} poses", poses.len()),
        tour.time_sorted,
        "s (Eq. 7)".into(),
    ));

    println!("{:<48} {:>16}  unit", "benchmark", "value");
    for (name, v, unit) in &rows {
        println!("{name:<48} {v:>16.4}  {unit}");
    }
    let json: Vec<serde_json::Value> = rows
        .iter()
        .map(|(n, v, u)| serde_json::json!({"name": n, "value": v, "unit": u}))
        .collect();
    let out = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/target/bench.json"));
    if let Err(e) = std::fs::write(out, serde_json::to_string_pretty(&json).unwrap_or_default()) {
        eprintln!("cannot write {}: {e}", out.display());
    }
}

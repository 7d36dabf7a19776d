//! How well `place`'s proxy ranks positions: Spearman's rank correlation between the proxy and
//! the full estimate (a compile there) over the fully estimated candidates of a `place --json`
//! report, for proxy settings STEP:POSES (joint grid step in degrees, admitted pool). Two proxy
//! predictions are compared: from the greedy selection (what `place` uses) and from the whole
//! admitted pool. Not part of `make test`; the figures are on docs/validation.md.
//!
//! ```sh
//! edbbgen place robots/comau_nj130/robot.dh.toml --cell robots/comau_nj130/cell.toml --top 40 --json top40.json -q
//! cargo run --release --example place_proxy -- top40.json robots/comau_nj130/robot.dh.toml \
//!     robots/comau_nj130/cell.toml 20:240 30:240 15:240 20:120 20:600
//! ```

use edbbgen::calibrate::predict;
use edbbgen::place::{self, proxy};
use nalgebra::Vector3;
use std::path::Path;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 5 {
        eprintln!("usage: place_proxy REPORT.json ROBOT CELL.toml STEP:POSES...");
        std::process::exit(2);
    }
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&args[1]).expect("report")).expect("json");
    let spec = edbbgen::cell::load(Path::new(&args[3])).expect("cell");
    let robot = edbbgen::robot::load(
        Path::new(&args[2]),
        &edbbgen::robot::LoadOptions {
            speeds: spec.speeds,
            ..Default::default()
        },
    )
    .expect("robot");
    let (pspec, _) = place::placement_spec(&spec, None);
    let (map, _) = edbbgen::pipeline::resolve_map(&robot, pspec.map);
    // The fully estimated candidates and their full estimates.
    let mut pts = Vec::new();
    for c in report["candidates"].as_array().expect("candidates") {
        if c["full"].is_object() {
            let f: Vec<f64> = c["fixture_mm"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            pts.push((
                Vector3::new(f[0], f[1], f[2]) * 1e-3,
                c["full"]["predicted_um"].as_f64().unwrap(),
            ));
        }
    }
    let full: Vec<f64> = pts.iter().map(|p| p.1).collect();
    let space = predict::workspace(&robot, 2000, 1);
    let search: Vec<[f64; 6]> = space
        .iter()
        .step_by(place::SEARCH_POSES_STRIDE)
        .copied()
        .collect();
    let positions: Vec<Vector3<f64>> = pts.iter().map(|p| p.0).collect();
    for setting in &args[4..] {
        let (step, poses) = setting.split_once(':').expect("STEP:POSES");
        let (step, poses): (f64, usize) = (step.parse().unwrap(), poses.parse().unwrap());
        let mut opts = place::PlaceOptions::new(
            pspec.clone(),
            place::Region {
                lo: Vector3::zeros(),
                hi: Vector3::zeros(),
            },
        );
        opts.proxy_step = [step.to_radians(); 6];
        opts.proxy_poses = poses;
        let t = std::time::Instant::now();
        let ctx = proxy::Context::new(&robot, &pspec, &map, &positions, &opts).expect("context");
        let (sel, pool): (Vec<f64>, Vec<f64>) =
            positions.iter().map(|p| both(&ctx, p, &search)).unzip();
        println!(
            "step {step} deg, {poses} poses: {:.2} s for {} positions; Spearman vs full: selection {:.3}, whole pool {:.3}",
            t.elapsed().as_secs_f64(),
            pts.len(),
            spearman(&sel, &full),
            spearman(&pool, &full)
        );
    }
}

/// The proxy's prediction from the greedy selection and from the whole admitted pool (µm).
fn both(ctx: &proxy::Context, fixture: &Vector3<f64>, search: &[[f64; 6]]) -> (f64, f64) {
    let Ok(f) = proxy::evaluate(ctx, fixture) else {
        return (f64::INFINITY, f64::INFINITY);
    };
    let prior = predict::Prior::default();
    let rms = |rows: &[[f64; 30]]| {
        let e = predict::expected(
            &f.model,
            &[&predict::readings_information(rows)],
            1e-6,
            &prior,
            search,
        );
        predict::spread(&e.combined).rms * 1e6
    };
    let chosen: Vec<[f64; 30]> = f.selected.iter().map(|&i| f.rows[i]).collect();
    (rms(&chosen), rms(&f.rows))
}

fn ranks(v: &[f64]) -> Vec<f64> {
    let mut idx: Vec<usize> = (0..v.len()).collect();
    idx.sort_by(|&a, &b| v[a].total_cmp(&v[b]).then(a.cmp(&b)));
    let mut r = vec![0.0; v.len()];
    for (k, &i) in idx.iter().enumerate() {
        r[i] = k as f64;
    }
    r
}

fn spearman(a: &[f64], b: &[f64]) -> f64 {
    let (ra, rb) = (ranks(a), ranks(b));
    let n = a.len() as f64;
    let d: f64 = ra.iter().zip(&rb).map(|(x, y)| (x - y).powi(2)).sum();
    1.0 - 6.0 * d / (n * (n * n - 1.0))
}

//! Fig. 12 of the paper: sensitivity of the error-sensitive program versus the ISO 230-4
//! circle test. On 20 simulated NJ-130s with random geometric errors (no other effect, no
//! noise), the deviation range max − min of (measured − nominal length) of each program; the
//! ratio says how much more the compiled program sees. `make paper`.

use edbbgen::model::{MeasurementModel, A, ALPHA, D, THETA};
use edbbgen::twin::{self, SimOptions, Truth};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};

fn range(model: &MeasurementModel, m: &twin::Measured) -> f64 {
    let (mut lo, mut hi) = (f64::MAX, f64::MIN);
    for k in 0..m.len() {
        let dev = m.length[k] - model.length(&model.nominal, &m.q[k]);
        lo = lo.min(dev);
        hi = hi.max(dev);
    }
    hi - lo
}

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let robot = edbbgen::robot::load(
        &root.join("robots/comau_nj130/robot.dh.toml"),
        &Default::default(),
    )
    .expect("robot");
    let fixture = Vector3::new(0.258, 1.468, 0.708);
    let opts = edbbgen::pipeline::CompileOptions {
        step: [10f64.to_radians(); 6],
        ..edbbgen::pipeline::CompileOptions::new(fixture)
    };
    let template = edbbgen::emit::dialect("ngc").expect("ngc");
    let compiled =
        edbbgen::pipeline::compile(&robot, &opts, template, &edbbgen::sample::NoProgress)
            .expect("compile");
    let model = compiled.model.clone();
    let sensitive = edbbgen::verify::gcode::parse(&compiled.text).expect("parse");
    let circle_model = MeasurementModel::new(&robot, fixture, model.nominal.map);
    let circle_text =
        twin::circle::program(&robot, &circle_model, &Default::default()).expect("circle");
    let circle = edbbgen::verify::gcode::parse(&circle_text).expect("parse");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
    println!("robot  range_sensitive_um  range_circle_um  ratio");
    let mut ratios = Vec::new();
    for r in 0..20 {
        let mut truth = Truth {
            noise: 0.0,
            resolution: 0.0,
            ..Truth::default()
        };
        for i in 0..6 {
            truth.geometric[A + i] = rng.random_range(-0.2..0.2) * 1e-3;
            truth.geometric[D + i] = rng.random_range(-0.2..0.2) * 1e-3;
            truth.geometric[ALPHA + i] = rng.random_range(-0.02..0.02f64).to_radians();
            truth.geometric[THETA + i] = rng.random_range(-0.02..0.02f64).to_radians();
        }
        let sim = SimOptions {
            rate: 50.0,
            seed: r,
        };
        let ms = twin::simulate(&robot, &model, &sensitive, &truth, &sim).expect("sim");
        let mc = twin::simulate(&robot, &circle_model, &circle, &truth, &sim).expect("sim");
        let (rs, rc) = (range(&model, &ms), range(&circle_model, &mc));
        ratios.push(rs / rc);
        println!(
            "{:>5}  {:>18.1}  {:>15.1}  {:>5.2}",
            r + 1,
            rs * 1e6,
            rc * 1e6,
            rs / rc
        );
    }
    ratios.sort_by(f64::total_cmp);
    let mean = ratios.iter().sum::<f64>() / ratios.len() as f64;
    println!(
        "ratio sensitive/circle over 20 robots: mean {mean:.2}, median {:.2}, min {:.2}, max {:.2} (paper: 3.5)",
        ratios[10], ratios[0], ratios[19]
    );
}

//! Benchmark: `diagnose` on a 10-minute, 50 Hz run (30,000 rows) of the NJ-130 with random
//! geometric errors and a hidden backlash of joint 1 (so the candidate rounds run too). `make bench-diagnose`.

use edbbgen::model::MeasurementModel;
use edbbgen::twin::truth::Backlash;
use edbbgen::twin::{self, SimOptions, Truth};
use nalgebra::Vector3;
use std::time::Instant;

fn main() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let robot = edbbgen::robot::load(
        &root.join("robots/comau_nj130/robot.dh.toml"),
        &Default::default(),
    )
    .expect("robot");
    let fixture = Vector3::new(0.258, 1.468, 0.708);
    let map = robot.tool.unwrap_or_else(Vector3::zeros);
    let model = MeasurementModel::new(&robot, fixture, map);
    let opts = twin::circle::CircleOptions {
        speed: 0.0115,
        ..Default::default()
    };
    // A slow circle test runs for about ten minutes.
    let text = twin::circle::program(&robot, &model, &opts).expect("circle");
    let program = edbbgen::verify::gcode::parse(&text).expect("parse");
    let mut truth = Truth::default();
    truth.geometric[10] = 0.15e-3;
    truth.geometric[23] = 0.01f64.to_radians();
    truth.backlash = Some(Backlash {
        joint: 0,
        play: 0.005f64.to_radians(),
    });
    let mut m =
        twin::simulate(&robot, &model, &program, &truth, &SimOptions::default()).expect("sim");
    let n = 30_000.min(m.len());
    m.t.truncate(n);
    m.q.truncate(n);
    m.length.truncate(n);
    let t = Instant::now();
    let d = edbbgen::diagnose::run(&model, &m, &Default::default()).expect("diagnose");
    let dt = t.elapsed().as_secs_f64();
    print!("{}", d.summary);
    println!(
        "diagnose: {} rows in {:.2} s ({} threads)",
        m.len(),
        dt,
        rayon::current_num_threads()
    );
}

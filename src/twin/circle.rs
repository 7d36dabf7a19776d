//! The extended circle test after ISO 230-4 (Section 3.1 of the paper): in = robot, fixture,
//! MAP, options; out = the program text (ngc, joint space), the baseline the error-sensitive
//! program is compared with (Fig. 12).
//!
//! The MAP runs on the sphere of radius D/2 around the fixture ball (constant bar length):
//! a full circle in the XY plane counter-clockwise and back, a half circle over the top in XZ
//! and back, a quarter of the XY circle to reach the YZ plane, a half circle in YZ and back.
//! Joint values come from a damped-least-squares position IK continued along the path from the
//! previous point (minimal joint motion; the tool orientation is free).

use crate::model::MeasurementModel;
use crate::robot::kinematics::chain_frames;
use crate::robot::Robot;
use crate::units::{fmt_fixed, to_deg, to_mm};
use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};

#[derive(Clone, Debug)]
pub struct CircleOptions {
    /// Circle diameter (m); the bar length is half of it.
    pub diameter: f64,
    /// MAP speed along the circle (m/s).
    pub speed: f64,
    /// Angular step between programmed points (rad).
    pub step: f64,
    pub seed: u64,
}

impl Default for CircleOptions {
    fn default() -> Self {
        CircleOptions {
            diameter: 0.7,
            speed: 0.05,
            step: 2f64.to_radians(),
            seed: 1,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CircleError {
    #[error("circle point {what} at ({x}, {y}, {z}) mm is out of reach within the joint limits")]
    Unreachable {
        what: String,
        x: String,
        y: String,
        z: String,
    },
}

/// The MAP positions of the test, with a label for each part: (label, direction on the sphere).
fn path(step: f64) -> Vec<(&'static str, Vector3<f64>)> {
    use std::f64::consts::{FRAC_PI_2, PI, TAU};
    let mut out = Vec::new();
    let mut arc = |label, a0: f64, a1: f64, f: &dyn Fn(f64) -> Vector3<f64>| {
        let n = ((a1 - a0).abs() / step).ceil().max(1.0) as usize;
        for k in 1..=n {
            out.push((label, f(a0 + (a1 - a0) * k as f64 / n as f64)));
        }
    };
    let xy = |a: f64| Vector3::new(a.cos(), a.sin(), 0.0);
    let xz = |a: f64| Vector3::new(a.cos(), 0.0, a.sin());
    let yz = |a: f64| Vector3::new(0.0, a.cos(), a.sin());
    arc("XY ccw", 0.0, TAU, &xy);
    arc("XY cw", TAU, 0.0, &xy);
    arc("XZ up", 0.0, PI, &xz);
    arc("XZ back", PI, 0.0, &xz);
    arc("to YZ", 0.0, FRAC_PI_2, &xy);
    arc("YZ up", 0.0, PI, &yz);
    arc("YZ back", PI, 0.0, &yz);
    out
}

/// Position IK by damped least squares from `seed`; None if it does not converge in limits.
fn ik(
    model: &MeasurementModel,
    robot: &Robot,
    target: &Vector3<f64>,
    seed: &[f64; 6],
) -> Option<[f64; 6]> {
    let (lo, hi) = robot.limits();
    let mut q = *seed;
    for _ in 0..200 {
        let f = chain_frames(&model.base, &model.nominal.dh, &model.flange, &q);
        let p = f[7].apply(&model.nominal.map);
        let e = target - p;
        if e.norm() < 1e-10 {
            return Some(q);
        }
        let cols: [Vector3<f64>; 6] =
            std::array::from_fn(|i| f[i].r.column(2).cross(&(p - f[i].t)));
        let mut jjt = Matrix3::zeros();
        for c in &cols {
            jjt += c * c.transpose();
        }
        let lambda2 = 1e-4;
        let y = (jjt + Matrix3::identity() * lambda2).try_inverse()? * e;
        let mut step = 0.0f64;
        for i in 0..6 {
            let dq = cols[i].dot(&y);
            q[i] = (q[i] + dq).clamp(lo[i], hi[i]);
            step = step.max(dq.abs());
        }
        if step < 1e-14 {
            break;
        }
    }
    let p = chain_frames(&model.base, &model.nominal.dh, &model.flange, &q)[7]
        .apply(&model.nominal.map);
    ((target - p).norm() < 1e-8).then_some(q)
}

/// The circle-test program text (ngc dialect).
pub fn program(
    robot: &Robot,
    model: &MeasurementModel,
    opts: &CircleOptions,
) -> Result<String, CircleError> {
    let r = 0.5 * opts.diameter;
    let fix = model.nominal.fix;
    let pts = path(opts.step);
    let start_dir = Vector3::new(1.0, 0.0, 0.0);
    let unreachable = |what: &str, p: &Vector3<f64>| CircleError::Unreachable {
        what: what.to_string(),
        x: fmt_fixed(to_mm(p.x), 1),
        y: fmt_fixed(to_mm(p.y), 1),
        z: fmt_fixed(to_mm(p.z), 1),
    };
    // Start: the seeded configuration whose whole path is reachable and that moves least.
    let (lo, hi) = robot.limits();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed);
    let p0 = fix + start_dir * r;
    let mut best: Option<(f64, Vec<[f64; 6]>)> = None;
    for attempt in 0..24 {
        let seed: [f64; 6] = if attempt == 0 {
            std::array::from_fn(|i| 0.0f64.clamp(lo[i], hi[i]))
        } else {
            std::array::from_fn(|i| {
                let (a, b) = (lo[i].max(-3.0), hi[i].min(3.0));
                rng.random_range(a..=b)
            })
        };
        let Some(q0) = ik(model, robot, &p0, &seed) else {
            continue;
        };
        let mut qs = vec![q0];
        let mut ok = true;
        let mut travel = 0.0;
        for (_, d) in &pts {
            let prev = *qs.last().unwrap_or(&q0);
            match ik(model, robot, &(fix + d * r), &prev) {
                Some(q) => {
                    travel += (0..6).map(|i| (q[i] - prev[i]).abs()).sum::<f64>();
                    qs.push(q);
                }
                None => {
                    ok = false;
                    break;
                }
            }
        }
        if ok && best.as_ref().is_none_or(|(t, _)| travel < *t) {
            best = Some((travel, qs));
        }
    }
    let (_, qs) = best.ok_or_else(|| unreachable("start of the XY circle", &p0))?;

    let vmax = robot.max_speeds();
    let mut s = String::new();
    let deg = |q: &[f64; 6]| {
        let names = ["X", "Y", "Z", "A", "B", "C"];
        (0..6)
            .map(|i| format!("{}{}", names[i], fmt_fixed(to_deg(q[i]), 4)))
            .collect::<Vec<_>>()
            .join(" ")
    };
    s += &format!(
        "(EDBB extended circle test after ISO 230-4 -- edbbgen {})\n",
        env!("CARGO_PKG_VERSION")
    );
    s += &format!("(robot: {} [{}])\n", robot.name, robot.source);
    s += "(axes: X Y Z A B C = joints 1-6, degrees; joint-space moves)\n";
    s += &format!(
        "(fixture: {}, {}, {} mm in the robot base frame)\n",
        fmt_fixed(to_mm(fix.x), 3),
        fmt_fixed(to_mm(fix.y), 3),
        fmt_fixed(to_mm(fix.z), 3)
    );
    let map = model.nominal.map;
    s += &format!(
        "(MAP: {}, {}, {} mm in the flange frame)\n",
        fmt_fixed(to_mm(map.x), 3),
        fmt_fixed(to_mm(map.y), 3),
        fmt_fixed(to_mm(map.z), 3)
    );
    s += &format!(
        "(circle: diameter {} mm, bar length {} mm; XY full circle, XZ and YZ half circles, each bidirectional)\n",
        fmt_fixed(to_mm(opts.diameter), 1),
        fmt_fixed(to_mm(r), 1)
    );
    s += "G21 G90 G94\nG64 P1.000 (blend corners within 1.0 mm)\n";
    s += &format!("G0 {} (start, approach without the bar)\n", deg(&qs[0]));
    s += "M0 (mount the EDBB between the fixture and the tool cup, then resume)\nG93\n";
    let mut label = "";
    for (k, (l, d)) in pts.iter().enumerate() {
        let (a, b) = (&qs[k], &qs[k + 1]);
        let arc = (d - pts.get(k.wrapping_sub(1)).map_or(start_dir, |p| p.1)).norm() * r;
        let eq7 = (0..6)
            .map(|i| (b[i] - a[i]).abs() / vmax[i])
            .fold(0.0, f64::max);
        let t = (arc / opts.speed).max(eq7).max(1e-3);
        let note = if *l != label {
            label = l;
            format!(" ({l})")
        } else {
            String::new()
        };
        s += &format!("G1 {} F{}{note}\n", deg(b), fmt_fixed(60.0 / t, 4));
    }
    s += "G94\nM0 (remove the EDBB)\nM2\n";
    Ok(s)
}

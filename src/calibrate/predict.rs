//! Position uncertainty of a calibrated robot: in = the measurement model, a parameter
//! covariance on some geometric parameters, joint poses; out = the 1σ MAP position uncertainty
//! per pose after a best rigid registration, and its RMS / 95th percentile. Also the
//! registration itself (for validating a calibration against a reference) and the workspace
//! sample the predictions are made over.
//!
//! Why registered: the bar never sees where the robot's base is relative to the world, and any
//! external check of a calibrated robot (a laser tracker, a second instrument) first registers
//! its frame to the robot's. A rigid motion of every MAP position is therefore not an error;
//! the prediction removes it exactly as the validation does, linearised: the stacked position
//! Jacobian J (3n × k) becomes (I − R(RᵀR)⁻¹Rᵀ) J, with R the six rigid displacements
//! t + ω × (p − c) of the n positions.

use crate::model::{MeasurementModel, Params, N_PARAMS};
use crate::robot::Robot;
use nalgebra::{DMatrix, Matrix3, Matrix6, Vector3};
use rand::{Rng, SeedableRng};
use serde::Serialize;

/// Summary of the per-pose position uncertainty (µm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Spread {
    pub rms: f64,
    pub p95: f64,
    pub max: f64,
}

/// RMS, 95th percentile and maximum of per-pose values.
pub fn spread(values: &[f64]) -> Spread {
    if values.is_empty() {
        return Spread {
            rms: 0.0,
            p95: 0.0,
            max: 0.0,
        };
    }
    let rms = (values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt();
    let mut s = values.to_vec();
    s.sort_by(f64::total_cmp);
    let k = ((0.95 * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1;
    Spread {
        rms,
        p95: s[k],
        max: s[s.len() - 1],
    }
}

/// `count` joint poses drawn uniformly within the joint limits (seeded, portable): the
/// "whole joint space" the predictions and validations are made over.
pub fn workspace(robot: &Robot, count: usize, seed: u64) -> Vec<[f64; 6]> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let (lo, hi) = robot.limits();
    (0..count)
        .map(|_| std::array::from_fn(|i| rng.random_range(lo[i]..=hi[i])))
        .collect()
}

/// The columns of the parameters `params` (Eq. 6 indices): the map W (30 × k) for
/// [`position_std`] when the covariance is of those parameters themselves.
pub fn selection(params: &[usize]) -> DMatrix<f64> {
    DMatrix::from_fn(N_PARAMS, params.len(), |i, c| {
        if params[c] == i {
            1.0
        } else {
            0.0
        }
    })
}

/// Per-pose 1σ MAP position uncertainty (m, the root of the trace of the 3 × 3 covariance)
/// after a best rigid registration, for a covariance `cov` (SI, k × k) of k quantities that
/// move the Eq. 6 parameters by `w` (30 × k; [`selection`] when they are parameters).
pub fn position_std(
    model: &MeasurementModel,
    p: &Params,
    poses: &[[f64; 6]],
    w: &DMatrix<f64>,
    cov: &DMatrix<f64>,
) -> Vec<f64> {
    let k = w.ncols();
    if poses.is_empty() || k == 0 {
        return vec![0.0; poses.len()];
    }
    // Positions and the Jacobian of every pose with respect to the k quantities.
    let mut pos = Vec::with_capacity(poses.len());
    let mut jac = DMatrix::zeros(3 * poses.len(), k);
    let mut cols = [Vector3::zeros(); N_PARAMS];
    for (n, q) in poses.iter().enumerate() {
        pos.push(model.position_jacobian(p, q, &mut cols));
        for i in 0..N_PARAMS {
            for c in 0..k {
                let wi = w[(i, c)];
                if wi != 0.0 {
                    for a in 0..3 {
                        jac[(3 * n + a, c)] += cols[i][a] * wi;
                    }
                }
            }
        }
    }
    // Project out the rigid displacements: R = [I, −[p − c]×] per pose.
    let centre = pos.iter().sum::<Vector3<f64>>() / pos.len() as f64;
    let rigid = |n: usize| -> nalgebra::Matrix3x6<f64> {
        let r = pos[n] - centre;
        let mut m = nalgebra::Matrix3x6::zeros();
        m.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&Matrix3::identity());
        m.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(-r.cross_matrix()));
        m
    };
    let mut rtr = Matrix6::zeros();
    let mut rtj = DMatrix::zeros(6, k);
    for n in 0..pos.len() {
        let r = rigid(n);
        rtr += r.transpose() * r;
        rtj += r.transpose() * jac.rows(3 * n, 3);
    }
    // Positions spanning a plane or less leave a rigid direction undefined: pseudo-inverse.
    let pinv = rtr
        .pseudo_inverse(1e-12 * rtr.norm())
        .unwrap_or_else(|_| Matrix6::zeros());
    let coef = pinv * rtj; // 6 × k
    (0..pos.len())
        .map(|n| {
            let jn = jac.rows(3 * n, 3) - rigid(n) * &coef; // 3 × k, registered
            let c = &jn * cov * jn.transpose();
            c.trace().max(0.0).sqrt()
        })
        .collect()
}

/// What a recording buys: the predicted MAP position uncertainty after calibrating from the
/// bar readings along `segments` (joint-linear moves: from, to, duration in s), sampled at
/// `rate` Hz with white noise `noise` (m per reading), with the parameters `params` (Eq. 6
/// indices) free. Type A only: σ²(JᵀJ)⁻¹ propagated to the MAP over `poses`, after a best
/// rigid registration; per-pose values (m).
pub fn after_recording(
    model: &MeasurementModel,
    segments: &[([f64; 6], [f64; 6], f64)],
    params: &[usize],
    noise: f64,
    rate: f64,
    poses: &[[f64; 6]],
) -> Vec<f64> {
    use rayon::prelude::*;
    let k = params.len();
    // JᵀJ over the readings, summed per segment in parallel and in order (deterministic).
    let parts: Vec<DMatrix<f64>> = segments
        .par_iter()
        .map(|(a, b, t)| {
            let n = ((t * rate).ceil() as usize).max(1);
            let mut nn = DMatrix::zeros(k, k);
            let mut row = [0.0; N_PARAMS];
            for s in 0..n {
                let f = (s as f64 + 0.5) / n as f64;
                let q: [f64; 6] = std::array::from_fn(|i| a[i] + f * (b[i] - a[i]));
                model.jacobian_row(&model.nominal, &q, &mut row);
                for x in 0..k {
                    let rx = row[params[x]];
                    for y in x..k {
                        nn[(x, y)] += rx * row[params[y]];
                    }
                }
            }
            nn
        })
        .collect();
    let mut nn = DMatrix::zeros(k, k);
    for p in parts {
        nn += p;
    }
    for x in 0..k {
        for y in 0..x {
            nn[(x, y)] = nn[(y, x)];
        }
    }
    from_normal(model, &nn, params, noise, poses)
}

/// As [`after_recording`] for one reading per pose: Jacobian rows (Eq. 5) given directly.
pub fn after_readings(
    model: &MeasurementModel,
    rows: &[[f64; N_PARAMS]],
    params: &[usize],
    noise: f64,
    poses: &[[f64; 6]],
) -> Vec<f64> {
    let nn = DMatrix::from_fn(params.len(), params.len(), |x, y| {
        rows.iter().map(|r| r[params[x]] * r[params[y]]).sum()
    });
    from_normal(model, &nn, params, noise, poses)
}

/// σ² N⁻¹ of the normal matrix `nn` on `params`, propagated to the MAP over `poses`.
fn from_normal(
    model: &MeasurementModel,
    nn: &DMatrix<f64>,
    params: &[usize],
    noise: f64,
    poses: &[[f64; 6]],
) -> Vec<f64> {
    let cov = crate::diagnose::fit::inverse(nn) * (noise * noise);
    position_std(model, &model.nominal, poses, &selection(params), &cov)
}

/// The best rigid registration of `a` onto `b` (Kabsch, no scale): the RMS and the maximum
/// distance between R·a + t and b, and (R, t).
pub fn register(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> (f64, f64, Matrix3<f64>, Vector3<f64>) {
    let n = a.len().max(1) as f64;
    let ca = a.iter().sum::<Vector3<f64>>() / n;
    let cb = b.iter().sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    for (x, y) in a.iter().zip(b) {
        h += (x - ca) * (y - cb).transpose();
    }
    let svd = h.svd(true, true);
    let (u, vt) = match (svd.u, svd.v_t) {
        (Some(u), Some(vt)) => (u, vt),
        _ => (Matrix3::identity(), Matrix3::identity()),
    };
    let mut d = Matrix3::identity();
    if (vt.transpose() * u.transpose()).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = vt.transpose() * d * u.transpose();
    let t = cb - r * ca;
    let (mut ss, mut max) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        let e = (r * x + t - y).norm();
        ss += e * e;
        max = max.max(e);
    }
    ((ss / n).sqrt(), max, r, t)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{A, THETA};

    fn nj130() -> Robot {
        crate::robot::load(
            std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/robots/comau_nj130/robot.dh.toml"
            )),
            &Default::default(),
        )
        .expect("bundled NJ-130")
    }

    #[test]
    fn registration_recovers_a_known_rigid_motion() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let a: Vec<Vector3<f64>> = (0..50)
            .map(|_| Vector3::new(rng.random(), rng.random(), rng.random()))
            .collect();
        let r = nalgebra::Rotation3::from_euler_angles(0.1, -0.2, 0.3).into_inner();
        let t = Vector3::new(0.5, -1.0, 2.0);
        let b: Vec<Vector3<f64>> = a.iter().map(|x| r * x + t).collect();
        let (rms, max, rr, tt) = register(&a, &b);
        assert!(rms < 1e-12 && max < 1e-12, "{rms} {max}");
        assert!((rr - r).norm() < 1e-12 && (tt - t).norm() < 1e-12);
        // A non-rigid change is not registered away.
        let mut c = b.clone();
        c[0].x += 1e-3;
        assert!(register(&a, &c).0 > 1e-4);
    }

    /// The linearised prediction against Monte Carlo: parameter errors drawn from the
    /// covariance, positions compared after an exact (Kabsch) registration.
    #[test]
    fn prediction_matches_monte_carlo_with_registration() {
        let robot = nj130();
        let model = MeasurementModel::new(
            &robot,
            Vector3::new(0.258, 1.468, 0.708),
            Vector3::new(0.06, 0.03, 0.12),
        );
        let poses = workspace(&robot, 300, 5);
        // Independent errors on a few parameters, 10 µm and 10 µrad: small enough to be linear.
        let params = [A + 1, A + 2, THETA, THETA + 1, THETA + 4];
        let sd = [10e-6, 10e-6, 10e-6, 10e-6, 10e-6];
        let cov = DMatrix::from_fn(5, 5, |a, b| if a == b { sd[a] * sd[a] } else { 0.0 });
        let predicted = spread(&position_std(
            &model,
            &model.nominal,
            &poses,
            &selection(&params),
            &cov,
        ))
        .rms;
        let nominal: Vec<Vector3<f64>> = poses
            .iter()
            .map(|q| model.map_position(&model.nominal, q))
            .collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let trials = 400;
        let mut ms = 0.0;
        for _ in 0..trials {
            let mut p = model.nominal.to_array();
            for (k, &i) in params.iter().enumerate() {
                p[i] += sd[k] * crate::twin::gauss(&mut rng);
            }
            let moved: Vec<Vector3<f64>> = poses
                .iter()
                .map(|q| model.map_position(&Params::from_array(&p), q))
                .collect();
            let (rms, _, _, _) = register(&moved, &nominal);
            ms += rms * rms;
        }
        let realised = (ms / trials as f64).sqrt();
        assert!(
            (predicted / realised - 1.0).abs() < 0.1,
            "predicted {predicted:e} realised {realised:e}"
        );
        // theta1 alone is a rotation about z0: registered away entirely.
        let one = position_std(
            &model,
            &model.nominal,
            &poses,
            &selection(&[THETA]),
            &DMatrix::from_element(1, 1, 1e-6),
        );
        assert!(spread(&one).max < 1e-9, "{:?}", spread(&one));
    }
}

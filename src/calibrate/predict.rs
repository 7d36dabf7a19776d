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
use nalgebra::{DMatrix, Matrix3, Matrix3xX, Matrix6, Vector3};
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
    position_std_with(model, p, poses, w, &NoJointTerms, cov)
}

/// Quantities that move joint angles by a pose-dependent amount (an effect's coefficients: a
/// harmonic of a joint's angle, a compliance's gravity torque): per pose, each quantity's
/// joint and the angle (rad) it moves that joint by per unit.
pub trait JointTerms: Sync {
    fn count(&self) -> usize;
    fn at(&self, q: &[f64; 6], out: &mut Vec<(usize, f64)>);
}

struct NoJointTerms;

impl JointTerms for NoJointTerms {
    fn count(&self) -> usize {
        0
    }
    fn at(&self, _: &[f64; 6], _: &mut Vec<(usize, f64)>) {}
}

/// [`position_std`] with more quantities after the k of `w`: `terms`, which move joint
/// angles pose by pose; `cov` covers all k + terms.count() of them.
pub fn position_std_with(
    model: &MeasurementModel,
    p: &Params,
    poses: &[[f64; 6]],
    w: &DMatrix<f64>,
    terms: &dyn JointTerms,
    cov: &DMatrix<f64>,
) -> Vec<f64> {
    registered(model, p, poses, w, terms)
        .iter()
        .map(|jn| {
            let c = jn * cov * jn.transpose();
            c.trace().max(0.0).sqrt()
        })
        .collect()
}

/// For independent quantities with standard deviations `sd` moving the parameters by `w`
/// (30 × k): each one's own contribution to the MAP position uncertainty after registration,
/// as an RMS over `poses` (m). Which held parameter costs how much.
pub fn column_rms(
    model: &MeasurementModel,
    p: &Params,
    poses: &[[f64; 6]],
    w: &DMatrix<f64>,
    sd: &[f64],
) -> Vec<f64> {
    let reg = registered(model, p, poses, w, &NoJointTerms);
    (0..w.ncols())
        .map(|c| {
            let ms = reg
                .iter()
                .map(|jn| jn.column(c).norm_squared())
                .sum::<f64>()
                / reg.len().max(1) as f64;
            ms.sqrt() * sd[c]
        })
        .collect()
}

/// The registered position Jacobian of every pose (3 × k each): ∂P/∂(k quantities) with the
/// six rigid displacements t + ω × (p − c) of all the positions projected out.
fn registered(
    model: &MeasurementModel,
    p: &Params,
    poses: &[[f64; 6]],
    w: &DMatrix<f64>,
    terms: &dyn JointTerms,
) -> Vec<Matrix3xX<f64>> {
    let kw = w.ncols();
    let k = kw + terms.count();
    if poses.is_empty() || k == 0 {
        return vec![Matrix3xX::zeros(k); poses.len()];
    }
    // Positions and the Jacobian of every pose with respect to the k quantities.
    let mut pos = Vec::with_capacity(poses.len());
    let mut jac = DMatrix::zeros(3 * poses.len(), k);
    let mut cols = [Vector3::zeros(); N_PARAMS];
    let mut joint = Vec::with_capacity(terms.count());
    for (n, q) in poses.iter().enumerate() {
        pos.push(model.position_jacobian(p, q, &mut cols));
        for i in 0..N_PARAMS {
            for c in 0..kw {
                let wi = w[(i, c)];
                if wi != 0.0 {
                    for a in 0..3 {
                        jac[(3 * n + a, c)] += cols[i][a] * wi;
                    }
                }
            }
        }
        joint.clear();
        terms.at(q, &mut joint);
        for (c, &(j, f)) in joint.iter().enumerate() {
            for a in 0..3 {
                jac[(3 * n + a, kw + c)] = cols[crate::model::THETA + j][a] * f;
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
        .map(|n| jac.rows(3 * n, 3) - rigid(n) * &coef)
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
    let full = recording_information(model, segments, rate).normal;
    let nn = DMatrix::from_fn(params.len(), params.len(), |x, y| {
        full[(params[x], params[y])]
    });
    from_normal(model, &nn, params, noise, poses)
}

/// At most this many Jacobian rows of a run are kept for the structure question (which
/// parameters are separable at all): the rank does not need every reading.
pub const STRUCTURE_ROWS: usize = 1500;

/// What one run's readings tell about the 30 Eq. 6 parameters: the normal matrix JᵀJ of every
/// reading (30 × 30, not yet divided by the noise variance), the number of readings, and an
/// evenly spaced subset of the rows (at most [`STRUCTURE_ROWS`]) for the structure.
#[derive(Clone, Debug, PartialEq)]
pub struct RunInformation {
    pub normal: DMatrix<f64>,
    pub readings: usize,
    pub rows: Vec<[f64; N_PARAMS]>,
}

/// The readings a recording takes: along every segment (from, to, duration in s) at `rate` Hz,
/// at the middle of each sample interval; per segment, in order.
fn readings_of(segment: &([f64; 6], [f64; 6], f64), rate: f64) -> impl Iterator<Item = [f64; 6]> {
    let (a, b, t) = *segment;
    let n = ((t * rate).ceil() as usize).max(1);
    (0..n).map(move |s| {
        let f = (s as f64 + 0.5) / n as f64;
        std::array::from_fn(|i| a[i] + f * (b[i] - a[i]))
    })
}

/// The information of a recording along `segments` at `rate` Hz (see [`after_recording`]),
/// at the model's nominal parameters (its fixture included).
pub fn recording_information(
    model: &MeasurementModel,
    segments: &[([f64; 6], [f64; 6], f64)],
    rate: f64,
) -> RunInformation {
    use rayon::prelude::*;
    // JᵀJ over the readings, summed per segment in parallel and in order (deterministic).
    let parts: Vec<(DMatrix<f64>, usize)> = segments
        .par_iter()
        .map(|seg| {
            let mut nn = DMatrix::zeros(N_PARAMS, N_PARAMS);
            let mut row = [0.0; N_PARAMS];
            let mut n = 0;
            for q in readings_of(seg, rate) {
                model.jacobian_row(&model.nominal, &q, &mut row);
                accumulate_row(&mut nn, &row);
                n += 1;
            }
            (nn, n)
        })
        .collect();
    let mut nn = DMatrix::zeros(N_PARAMS, N_PARAMS);
    let mut readings = 0;
    for (p, n) in parts {
        nn += p;
        readings += n;
    }
    symmetrise(&mut nn);
    let stride = readings.div_ceil(STRUCTURE_ROWS).max(1);
    let rows = segments
        .iter()
        .flat_map(|seg| readings_of(seg, rate))
        .step_by(stride)
        .map(|q| {
            let mut row = [0.0; N_PARAMS];
            model.jacobian_row(&model.nominal, &q, &mut row);
            row
        })
        .collect();
    RunInformation {
        normal: nn,
        readings,
        rows,
    }
}

/// The information of one reading per row (Jacobian rows, Eq. 5, given directly).
pub fn readings_information(rows: &[[f64; N_PARAMS]]) -> RunInformation {
    let mut nn = DMatrix::zeros(N_PARAMS, N_PARAMS);
    for r in rows {
        accumulate_row(&mut nn, r);
    }
    symmetrise(&mut nn);
    let stride = rows.len().div_ceil(STRUCTURE_ROWS).max(1);
    RunInformation {
        normal: nn,
        readings: rows.len(),
        rows: rows.iter().step_by(stride).copied().collect(),
    }
}

/// Adds row·rowᵀ to the upper triangle.
#[inline]
fn accumulate_row(nn: &mut DMatrix<f64>, row: &[f64; N_PARAMS]) {
    for x in 0..N_PARAMS {
        let rx = row[x];
        for y in x..N_PARAMS {
            nn[(x, y)] += rx * row[y];
        }
    }
}

fn symmetrise(nn: &mut DMatrix<f64>) {
    for x in 0..nn.nrows() {
        for y in 0..x {
            nn[(x, y)] = nn[(y, x)];
        }
    }
}

/// The prior knowledge a prediction assumes, as `calibrate` uses it: the standard uncertainty
/// of a length (m) and an angle (rad) before calibration, and κ (a parameter is determined
/// when the data bring its uncertainty to prior/κ or less).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Prior {
    pub length: f64,
    pub angle: f64,
    pub kappa: f64,
}

impl Default for Prior {
    fn default() -> Self {
        Prior {
            length: super::DEFAULT_PRIOR_MM * crate::units::MM,
            angle: super::DEFAULT_PRIOR_DEG * crate::units::DEG,
            kappa: super::DEFAULT_KAPPA,
        }
    }
}

impl Prior {
    fn of(&self, param: usize) -> f64 {
        if crate::model::is_angle(param) {
            self.angle
        } else {
            self.length
        }
    }
}

/// What a calibration from planned runs would state, before any data exist: per-pose 1σ MAP
/// position uncertainty (m) after a best rigid registration, in total and by its two GUM
/// components, and which parameters it would determine.
#[derive(Clone, Debug, PartialEq)]
pub struct Expected {
    /// Shared Eq. 6 parameters the runs can separate at all (structure).
    pub identifiable: Vec<usize>,
    /// Of those, the ones the information determines to prior/κ.
    pub determined: Vec<usize>,
    /// The shared parameters held at nominal: dependent, negligible or not determined.
    pub held: Vec<usize>,
    /// Type A: σ²N⁻¹ of the determined parameters.
    pub from_noise: Vec<f64>,
    /// Type B: the held parameters' priors, with what the determined ones absorb of them.
    pub from_held: Vec<f64>,
    pub combined: Vec<f64>,
    /// What each held parameter costs on its own (RMS over the poses, m), in `held` order: 0
    /// (to rounding) for an exact dependency such as d3 on d2.
    pub held_cost: Vec<f64>,
}

/// The prediction of a calibration over a campaign of runs, as [`super::run`] would make it
/// from their data with the fixtures held at their given positions (its default): the robot's
/// parameters are shared by every run, each run has its own (known) fixture, so the
/// information adds up, N = Σ N_k over the shared parameters (the fixture columns of each run
/// drop out). Then, like `calibrate`: the structure from the runs' rows (Gram–Schmidt in Eq. 6
/// order, the MAP free: it is dependent on link 6), the determined parameters by the same rule
/// ([`super::determined_columns`]) for white noise `noise` per reading, Type A over the
/// determined ones and Type B for every other shared parameter at its prior; both propagated
/// to the MAP over `poses` after a rigid registration. One run is a campaign of one.
pub fn expected(
    model: &MeasurementModel,
    runs: &[&RunInformation],
    noise: f64,
    prior: &Prior,
    poses: &[[f64; 6]],
) -> Expected {
    let shared: Vec<usize> = (crate::model::ALPHA..N_PARAMS).collect();
    // Structure: every run's rows on the shared columns (Eq. 6 order is the preference order).
    let n_rows: usize = runs.iter().map(|r| r.rows.len()).sum();
    let mut cols = DMatrix::zeros(n_rows, shared.len());
    let mut i = 0;
    for r in runs {
        for row in &r.rows {
            for (c, &p) in shared.iter().enumerate() {
                cols[(i, c)] = row[p];
            }
            i += 1;
        }
    }
    let names: Vec<String> = shared
        .iter()
        .map(|&p| crate::model::PARAM_NAMES[p].to_string())
        .collect();
    let order: Vec<usize> = (0..shared.len()).collect();
    let known = vec![false; shared.len()];
    let (_, ident) = crate::model::identify::classify(&cols, &names, &order, &known);
    let identifiable: Vec<usize> = ident.iter().map(|&c| shared[c]).collect();

    let mut total = DMatrix::zeros(N_PARAMS, N_PARAMS);
    for r in runs {
        total += &r.normal;
    }
    finish(
        model,
        &total,
        identifiable,
        &shared,
        noise,
        &|p| prior.of(p),
        prior.kappa,
        poses,
    )
}

/// The prediction of a calibration from one run as [`super::run`] makes it by default: the
/// fixture and the tool point (MAP) estimated where the data determine them, each with the
/// set-up prior `setup` (m) as its yardstick, the length zero given. The structure in
/// `calibrate`'s preference order (the MAP, the fixture, then the DH in Eq. 6 order: the MAP
/// takes link 6's place and the fixture d1's and θ1's), then as [`expected`]: the determined
/// parameters by the same rule, Type A over them, Type B for every other parameter at its
/// prior, propagated to the MAP over `poses` after a rigid registration.
pub fn expected_setup_free(
    model: &MeasurementModel,
    run: &RunInformation,
    noise: f64,
    prior: &Prior,
    setup: f64,
    poses: &[[f64; 6]],
) -> Expected {
    let all: Vec<usize> = (0..N_PARAMS).collect();
    let order: Vec<usize> = (crate::model::MAP..N_PARAMS)
        .chain(crate::model::FIX..crate::model::ALPHA)
        .chain(crate::model::ALPHA..crate::model::MAP)
        .collect();
    let cols = DMatrix::from_fn(run.rows.len(), N_PARAMS, |i, c| run.rows[i][c]);
    let names: Vec<String> = crate::model::PARAM_NAMES
        .iter()
        .map(|s| s.to_string())
        .collect();
    let (_, identifiable) =
        crate::model::identify::classify(&cols, &names, &order, &[false; N_PARAMS]);
    let prior_of = |p: usize| {
        if crate::model::is_fixture(p) || crate::model::is_map(p) {
            setup
        } else {
            prior.of(p)
        }
    };
    finish(
        model,
        &run.normal,
        identifiable,
        &all,
        noise,
        &prior_of,
        prior.kappa,
        poses,
    )
}

/// The common end of [`expected`] and [`expected_setup_free`]: from the summed information
/// `total` (30 × 30) and the `identifiable` parameters among `shared`, the determined ones
/// and the two components over `poses`.
#[allow(clippy::too_many_arguments)]
fn finish(
    model: &MeasurementModel,
    total: &DMatrix<f64>,
    identifiable: Vec<usize>,
    shared: &[usize],
    noise: f64,
    prior_of: &dyn Fn(usize) -> f64,
    kappa: f64,
    poses: &[[f64; 6]],
) -> Expected {
    let sub =
        |a: &[usize], b: &[usize]| DMatrix::from_fn(a.len(), b.len(), |x, y| total[(a[x], b[y])]);
    // Determined: the prior-scaled information, as calibrate judges it.
    let scale: Vec<f64> = identifiable.iter().map(|&p| prior_of(p)).collect();
    let ni = sub(&identifiable, &identifiable);
    let ss = DMatrix::from_fn(ni.nrows(), ni.ncols(), |a, b| {
        ni[(a, b)] * scale[a] * scale[b]
    });
    let (chosen, _) = super::determined_columns(&ss, noise, kappa);
    let determined: Vec<usize> = chosen.iter().map(|&k| identifiable[k]).collect();
    let held: Vec<usize> = shared
        .iter()
        .copied()
        .filter(|p| !determined.contains(p))
        .collect();

    let nd = sub(&determined, &determined);
    let cov_a = crate::diagnose::fit::inverse(&nd) * (noise * noise);
    let from_noise = position_std(
        model,
        &model.nominal,
        poses,
        &selection(&determined),
        &cov_a,
    );
    let (from_held, held_cost) = if held.is_empty() {
        (vec![0.0; poses.len()], Vec::new())
    } else {
        let both: Vec<usize> = determined.iter().chain(&held).copied().collect();
        let fitted: Vec<Option<usize>> = determined.iter().map(|&p| Some(p)).collect();
        let held_idx: Vec<Option<usize>> = held.iter().map(|&p| Some(p)).collect();
        let w = held_weights(&sub(&both, &both), &fitted, &held_idx);
        let sd: Vec<f64> = held.iter().map(|&p| prior_of(p)).collect();
        let cov_b = DMatrix::from_fn(held.len(), held.len(), |a, b| {
            if a == b {
                sd[a] * sd[a]
            } else {
                0.0
            }
        });
        (
            position_std(model, &model.nominal, poses, &w, &cov_b),
            column_rms(model, &model.nominal, poses, &w, &sd),
        )
    };
    let combined = from_noise
        .iter()
        .zip(&from_held)
        .map(|(a, b)| a.hypot(*b))
        .collect();
    Expected {
        identifiable,
        determined,
        held,
        from_noise,
        from_held,
        combined,
        held_cost,
    }
}

/// Type B (GUM) of parameters held at nominal: how their true deviations move the MAP. A held
/// parameter's deviation δ moves the MAP by J_h δ directly and by −J_f K δ through the fitted
/// columns that absorb it (K = N_ff⁻¹ N_fh); for an exact dependency (d3 on d2) the two cancel.
/// `n` is the normal matrix over the fitted columns followed by the held ones; `fitted[a]` and
/// `held[b]` name each column's Eq. 6 parameter, None for a column that does not move the MAP
/// (an effect's coefficient, a fixture coordinate). Returns W (30 × held), for
/// [`position_std`] with the held parameters' prior covariance.
pub fn held_weights(
    n: &DMatrix<f64>,
    fitted: &[Option<usize>],
    held: &[Option<usize>],
) -> DMatrix<f64> {
    let (c, h) = (fitted.len(), held.len());
    let nff = n.view((0, 0), (c, c)).into_owned();
    let nfh = n.view((0, c), (c, h)).into_owned();
    let k = crate::diagnose::fit::inverse(&nff) * nfh; // c × h
    let mut w = DMatrix::zeros(N_PARAMS, h);
    for (b, q) in held.iter().enumerate() {
        if let Some(i) = q {
            w[(*i, b)] += 1.0;
        }
        for (a, d) in fitted.iter().enumerate() {
            if let Some(i) = d {
                w[(*i, b)] -= k[(a, b)];
            }
        }
    }
    w
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
    use crate::model::tests::nj130;
    use crate::model::{A, THETA};

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

    /// Jacobian rows of random poses with the MAP in the default shell around `fixture`.
    fn shell_rows(
        robot: &Robot,
        model: &MeasurementModel,
        n: usize,
        seed: u64,
    ) -> Vec<[f64; N_PARAMS]> {
        let cell = crate::pipeline::make_cell(
            robot,
            model.nominal.fix,
            model.nominal.map,
            &crate::cell::CellSpec::default(),
        )
        .unwrap();
        crate::pipeline::rich_rows(robot, model, &cell, n, seed).expect("reachable")
    }

    #[test]
    fn expected_of_a_rich_run_is_the_type_a_prediction_and_adds_up_over_runs() {
        let robot = nj130();
        let model = MeasurementModel::new(
            &robot,
            Vector3::new(0.258, 1.468, 0.708),
            Vector3::new(0.06, 0.03, 0.12),
        );
        let rows = shell_rows(&robot, &model, 300, 2);
        let poses = workspace(&robot, 400, 8);
        let info = readings_information(&rows);
        let e = expected(&model, &[&info], 1e-6, &Prior::default(), &poses);
        // Everything the structure allows is determined (the paper's 22), and only exact
        // dependencies are held (d3 on d2, theta6 and the MAP on link 6): they cost nothing.
        let id = crate::model::analyse(&rows, &Default::default());
        assert_eq!(e.identifiable, id.identifiable);
        assert_eq!(e.determined, id.identifiable);
        let a = spread(&after_readings(
            &model,
            &rows,
            &id.identifiable,
            1e-6,
            &poses,
        ))
        .rms;
        let got = spread(&e.from_noise).rms;
        assert!((got / a - 1.0).abs() < 1e-9, "{got:e} vs {a:e}");
        assert!(
            spread(&e.from_held).max < 1e-3 * got,
            "{:?}",
            spread(&e.from_held)
        );
        // Three runs with the same information: the uncertainty falls by √3 exactly.
        let three = expected(
            &model,
            &[&info, &info, &info],
            1e-6,
            &Prior::default(),
            &poses,
        );
        let ratio = spread(&e.combined).rms / spread(&three.combined).rms;
        assert!((ratio - 3f64.sqrt()).abs() < 1e-6, "{ratio}");
    }

    /// The Type B part against its definition, computed another way: parameters held at
    /// nominal deviate by draws from their prior, the determined ones are fitted to the
    /// readings those deviations cause (least squares on the rows themselves), and the fitted
    /// robot's MAP positions are compared with the true ones after an exact registration.
    #[test]
    fn held_parameters_cost_what_the_fit_cannot_absorb() {
        let robot = nj130();
        // On the joint-1 axis: q1 cannot change the bar length, and several parameters go
        // unseen.
        let model = MeasurementModel::new(
            &robot,
            Vector3::new(0.0, 0.0, 1.8),
            Vector3::new(0.06, 0.03, 0.12),
        );
        let rows = shell_rows(&robot, &model, 300, 4);
        let poses = workspace(&robot, 300, 6);
        let prior = Prior::default();
        let e = expected(
            &model,
            &[&readings_information(&rows)],
            1e-6,
            &prior,
            &poses,
        );
        assert!(e.determined.len() < 22, "{:?}", e.determined);
        let predicted = spread(&e.from_held).rms;
        assert!(predicted > 10.0 * spread(&e.from_noise).rms);

        let d = &e.determined;
        let jd = DMatrix::from_fn(rows.len(), d.len(), |i, k| rows[i][d[k]]);
        let jd_pinv = jd.clone().pseudo_inverse(1e-14).unwrap();
        let nominal: Vec<Vector3<f64>> = poses
            .iter()
            .map(|q| model.map_position(&model.nominal, q))
            .collect();
        let mut cols = [Vector3::zeros(); N_PARAMS];
        let pj: Vec<[Vector3<f64>; N_PARAMS]> = poses
            .iter()
            .map(|q| {
                model.position_jacobian(&model.nominal, q, &mut cols);
                cols
            })
            .collect();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(12);
        let trials = 300;
        let mut ms = 0.0;
        for _ in 0..trials {
            let mut delta = [0.0; N_PARAMS];
            for &h in &e.held {
                delta[h] = prior.of(h) * crate::twin::gauss(&mut rng) * 1e-3;
            }
            // The readings the held deviations cause, and the determined parameters' fit.
            let m = nalgebra::DVector::from_fn(rows.len(), |i, _| {
                (0..N_PARAMS).map(|k| rows[i][k] * delta[k]).sum::<f64>()
            });
            let fit = &jd_pinv * m;
            let (truth, fitted): (Vec<_>, Vec<_>) = (0..poses.len())
                .map(|n| {
                    let t: Vector3<f64> = nominal[n]
                        + (0..N_PARAMS)
                            .map(|k| pj[n][k] * delta[k])
                            .sum::<Vector3<f64>>();
                    let f: Vector3<f64> = nominal[n]
                        + (0..d.len())
                            .map(|k| pj[n][d[k]] * fit[k])
                            .sum::<Vector3<f64>>();
                    (t, f)
                })
                .unzip();
            let (rms, _, _, _) = register(&fitted, &truth);
            ms += rms * rms;
        }
        // Deviations a thousandth of the prior keep the registration linear; scale back.
        let realised = (ms / trials as f64).sqrt() * 1e3;
        assert!(
            (predicted / realised - 1.0).abs() < 0.15,
            "predicted {predicted:e} realised {realised:e}"
        );
    }
}

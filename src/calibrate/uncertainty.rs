//! Step 6 of a calibration, the uncertainty (GUM): in = the converged fit and its held-out
//! score; out = the parameters' covariance and the predicted MAP position uncertainty after a
//! best rigid registration, where measured and over the whole joint space, by component.

use super::steps::{Fit, HeldOutScore};
use super::REGION_POSES;
use super::{predict, prior, round, shared_columns, CalibrateOptions, Component, Predicted};
use crate::diagnose::fit::{self, accumulate, model_cols, structural, Known};
use crate::diagnose::{Estimate, Fitted, Param, Problem};
use crate::model::{MeasurementModel, Params, Status, N_PARAMS};
use crate::robot::kinematics::chain_frames;
use crate::robot::Robot;
use crate::twin::effects::gravity_torques;
use crate::twin::effects::Effect;
use crate::units::length_um;
use nalgebra::{DMatrix, DVector};
use predict::JointTerms;

/// What step 6 leaves for the report.
pub(super) struct Uncertainty {
    pub predicted: Predicted,
    /// The variances of the fit's coefficients (the free parameters, then the effects'), and
    /// their whole covariance (SI).
    pub var: Vec<f64>,
    pub cov: DMatrix<f64>,
    /// The residual's σ with the model-error factor (m).
    pub sigma_eff: f64,
    /// The calibrated parameters (run 1's fixture).
    pub calibrated: Params,
    /// Poses of the measured region and of the whole joint space the prediction is made over.
    pub region: Vec<[f64; 6]>,
    pub space: Vec<[f64; 6]>,
    /// Per pose of `space`, the combined 1σ position uncertainty (µm).
    pub space_std: Vec<f64>,
    /// Its RMS (µm).
    pub space_rms: f64,
    /// What the priors say of the nominal robot over the joint space (m).
    pub nominal_prior_rms: f64,
    /// Every parameter's structural status at the estimate.
    pub status: Vec<(Param, Status)>,
}

/// The effects' coefficients of an estimate as quantities that move joints, in the fit's
/// column order: a harmonic by its (range-centred) value, a compliance term by its gravity
/// torque, a backlash by half its play (one flank). A thermal drift moves nothing at the
/// reference state the robot is delivered at, a servo lag nothing at a pose.
pub(super) struct EffectTerms<'a> {
    problem: &'a Problem,
    est: &'a Estimate,
    cols: Vec<fit::Col>,
}

impl<'a> EffectTerms<'a> {
    pub(super) fn new(problem: &'a Problem, est: &'a Estimate) -> Self {
        let cols = est
            .effects
            .iter()
            .flat_map(|t| fit::effect_cols(t.effect, t.basis))
            .collect();
        EffectTerms { problem, est, cols }
    }

    /// Terms for explicit effect columns (a richer model's).
    fn of(problem: &'a Problem, est: &'a Estimate, cols: Vec<fit::Col>) -> Self {
        EffectTerms { problem, est, cols }
    }
}

impl predict::JointTerms for EffectTerms<'_> {
    fn count(&self) -> usize {
        self.cols.len()
    }

    fn at(&self, q: &[f64; 6], out: &mut Vec<(usize, f64)>) {
        use fit::Col;
        let p = Params::from_array(&self.est.p);
        let m = &self.problem.model;
        let needs_frames = self.cols.iter().any(|c| matches!(c, Col::Comp(..)));
        let fr = needs_frames.then(|| chain_frames(&m.base, &p.dh, &m.flange, q));
        let needs_torques = self.cols.iter().any(|c| matches!(c, Col::CompKnown(..)));
        let tau = needs_torques.then(|| gravity_torques(m, &p, q, &self.problem.masses));
        for c in &self.cols {
            out.push(match *c {
                Col::Cyc(j, h, sine) => {
                    let (sn, cs) = self.problem.harmonic(j, h, q[j]);
                    (j, if sine { sn } else { cs })
                }
                Col::Back(j) => (j, -0.5),
                Col::Comp(j, i, comp) => (
                    j,
                    fr.as_ref()
                        .map_or(0.0, |fr| fit::gravity_basis(fr, j, i, comp)),
                ),
                Col::CompKnown(j) => (j, tau.as_ref().map_or(0.0, |t| t[j])),
                _ => (0, 0.0),
            });
        }
    }
}

pub(super) fn estimate(
    model: &MeasurementModel,
    robot: &Robot,
    problem: &Problem,
    known: &Known,
    f: &Fit,
    held_out: &HeldOutScore,
    opts: &CalibrateOptions,
) -> Uncertainty {
    let (est, free, fitted) = (&f.est, &f.free, &f.fitted);
    // Type A from the residual, with what the held-out residual says about model error.
    let factor = held_out.factor;
    let sigma_eff = f.sigma * factor.sqrt();
    let cov = fit::inverse(&fitted.normal) * (sigma_eff * sigma_eff);
    let var: Vec<f64> = (0..cov.nrows()).map(|k| cov[(k, k)]).collect();
    let calibrated = est.params(0);
    let region: Vec<[f64; 6]> = {
        let rows: Vec<usize> = (0..problem.rows())
            .filter(|&k| problem.weight[k] > 0.0)
            .collect();
        let stride = rows.len().div_ceil(REGION_POSES).max(1);
        rows.iter()
            .step_by(stride)
            .map(|&k| problem.m.q[k])
            .collect()
    };
    let space = predict::workspace(robot, opts.workspace_poses, opts.seed);
    let shared = shared_columns(free);
    let idx: Vec<usize> = shared.iter().map(|s| s.1).collect();
    // Type A covers the effects' coefficients too: the robot delivered applies them, and a
    // harmonic or a compliance fitted over part of the joint space is only as good elsewhere
    // as the data make it (its covariance with the joint zero it trades against included).
    let terms = EffectTerms::new(problem, est);
    let g = free.len();
    let rows: Vec<usize> = shared
        .iter()
        .map(|s| s.0)
        .chain(g..g + terms.count())
        .collect();
    let cov_a = DMatrix::from_fn(rows.len(), rows.len(), |a, b| cov[(rows[a], rows[b])]);
    let w_a = predict::selection(&idx);
    // Type B: every parameter held at nominal (not by assumption) keeps its prior; through
    // the fit the determined ones absorb K = N_aa⁻¹ N_ah of it, so the MAP moves by
    // (e_h − Σ_d e_d K_dh) per unit of held deviation.
    let (status, _) = structural(problem, known, est);
    let held_params: Vec<Param> = status
        .iter()
        .filter(|(q, st)| !free.contains(q) && *st != Status::Known)
        .map(|(q, _)| *q)
        .collect();
    let (w_b, cov_b) = held_map(problem, est, free, &held_params, opts);
    let a_region = predict::position_std_with(model, &calibrated, &region, &w_a, &terms, &cov_a);
    let a_space = predict::position_std_with(model, &calibrated, &space, &w_a, &terms, &cov_a);
    let b_region = predict::position_std(model, &calibrated, &region, &w_b, &cov_b);
    let b_space = predict::position_std(model, &calibrated, &space, &w_b, &cov_b);
    let [m_region, m_space] =
        effect_model_spread(problem, est, fitted, sigma_eff, &[&region, &space]);
    // The model's error as data it was not fitted to show it: the held-out residual (blocks
    // of every run's rows in the order taken, the same stretch of each run held out together)
    // beyond the reading noise is what the model misses on new poses, however many readings
    // are taken ([`HeldOutScore::model_error`]). A reading sees one component of the MAP's
    // error, along the bar; an error with no preferred direction has √3 times that RMS in 3D.
    // Added to every pose.
    let model_error = 3f64.sqrt() * held_out.model_error;
    let combine = |a: &[f64], b: &[f64], m: &[f64]| -> Vec<f64> {
        a.iter()
            .zip(b)
            .zip(m)
            .map(|((x, y), z)| x.hypot(*y).hypot(*z).hypot(model_error) * 1e6)
            .collect()
    };
    let um = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| x * 1e6).collect() };
    let region_std = predict::spread(&combine(&a_region, &b_region, &m_region));
    let space_std = combine(&a_space, &b_space, &m_space);
    let space_spread = predict::spread(&space_std);
    // The nominal robot as the priors see it: every robot parameter off by its prior.
    let nominal_prior_rms = {
        let all: Vec<usize> = (crate::model::ALPHA..N_PARAMS).collect();
        let cov = DMatrix::from_fn(all.len(), all.len(), |a, b| {
            if a == b {
                prior(opts, Param::Shared(all[a])).powi(2)
            } else {
                0.0
            }
        });
        predict::spread(&predict::position_std(
            model,
            &model.nominal,
            &space,
            &predict::selection(&all),
            &cov,
        ))
        .rms
    };
    let predicted = Predicted {
        measured_region_rms: round(region_std.rms, 3),
        workspace_rms: round(space_spread.rms, 3),
        workspace_p95: round(space_spread.p95, 3),
        from_noise: Component {
            measured_region_rms: round(predict::spread(&um(&a_region)).rms, 3),
            workspace_rms: round(predict::spread(&um(&a_space)).rms, 3),
        },
        from_held: Component {
            measured_region_rms: round(predict::spread(&um(&b_region)).rms, 3),
            workspace_rms: round(predict::spread(&um(&b_space)).rms, 3),
        },
        from_effect_model: Component {
            measured_region_rms: round(predict::spread(&um(&m_region)).rms, 3),
            workspace_rms: round(predict::spread(&um(&m_space)).rms, 3),
        },
        from_model_error: Component {
            measured_region_rms: round(model_error * 1e6, 3),
            workspace_rms: round(model_error * 1e6, 3),
        },
        nominal_workspace_rms: round(nominal_prior_rms * 1e6, 3),
        model_error_factor: round(factor, 3),
        model_workspace_rms: round(space_spread.rms, 3),
    };
    Uncertainty {
        predicted,
        var,
        cov,
        sigma_eff,
        calibrated,
        region,
        space,
        space_std,
        space_rms: space_spread.rms,
        nominal_prior_rms,
        status,
    }
}

/// What the data cannot say about the effects' form: for every cyclic error fitted with
/// harmonic orders 1..H, the geometry's covariance with orders up to H + 1 and H + 2 as well
/// (whatever H: up to [`fit::BOUND_HARMONIC`], past the orders the fit may select),
/// less the fitted model's. For nested least-squares models the two estimates differ by a
/// vector whose covariance is that difference (Hausman), so while the data do not reject the
/// smaller model its error is bounded by the larger model's covariance: this is the extra
/// variance, propagated to the MAP after registration. Beside it, the larger model's estimate
/// itself: the MAP shift between the two fits. Per pose of each set, the largest over the
/// alternatives and the two measures, root-sum-squared over the cyclic errors (m).
fn effect_model_spread<const N: usize>(
    problem: &Problem,
    est: &Estimate,
    fitted: &Fitted,
    sigma: f64,
    poses: &[&[[f64; 6]]; N],
) -> [Vec<f64>; N] {
    let mut out: [Vec<f64>; N] = std::array::from_fn(|i| vec![0.0; poses[i].len()]);
    let free = &fitted.free;
    let base = model_cols(est, free);
    let shared = shared_columns(free);
    let idx: Vec<usize> = shared.iter().map(|s| s.1).collect();
    let w = predict::selection(&idx);
    let p = est.params(0);
    let small = fit::inverse(&fitted.normal);
    for t in &est.effects {
        let Effect::CyclicError(j) = t.effect else {
            continue;
        };
        // The contiguous orders 1..H: screened single orders past them are stationary, their
        // form over the whole turn bounded by their own amplitude (in the covariance already).
        let h = t.basis.low_orders();
        let mut worst: [Vec<f64>; N] = std::array::from_fn(|i| vec![0.0; poses[i].len()]);
        // Orders past the fit's own limit included (the problem's harmonics are defined up to
        // BOUND_HARMONIC): a cyclic error fitted with every order the fit allows has its form
        // bounded like any other, not left out of the prediction.
        for extra in 1..=2 {
            debug_assert!(h + extra <= fit::BOUND_HARMONIC);
            let mut cols = base.clone();
            for o in (h + 1..=h + extra).filter(|o| !t.basis.orders().contains(o)) {
                cols.push(fit::Col::Cyc(j, o, false));
                cols.push(fit::Col::Cyc(j, o, true));
            }
            let (mut n, b, _, _) = accumulate(problem, est, &cols, 1).total();
            // An order the data do not determine (a joint measured over part of its range) is
            // bounded by what a gearbox does, not by the data: its amplitude is taken as at most
            // the largest the fit found on that joint (a prior of that size on each richer
            // order), so that where the data did not reach the bound is physical, not infinite.
            let amplitude = t.coef.iter().fold(0.0f64, |m, c| m.max(c.abs()));
            let prior = amplitude.max(1e-12);
            for k in base.len()..cols.len() {
                n[(k, k)] += (sigma / prior).powi(2);
            }
            let big = fit::inverse(&n);
            // The geometry and every effect coefficient, the richer orders' included: the
            // robot delivered applies the harmonics, and where the data did not reach, an order
            // they cannot reject moves the MAP through them (the joint's zero it trades with
            // included).
            let g = free.len();
            let rows: Vec<usize> = shared.iter().map(|s| s.0).chain(g..cols.len()).collect();
            let small_at = |x: usize, y: usize| {
                if x < small.nrows() && y < small.ncols() {
                    small[(x, y)]
                } else {
                    0.0
                }
            };
            let diff = DMatrix::from_fn(rows.len(), rows.len(), |a, b| {
                let (x, y) = (rows[a], rows[b]);
                (big[(x, y)] - small_at(x, y)) * sigma * sigma
            });
            let terms = EffectTerms::of(problem, est, cols[g..].to_vec());
            // The larger model's own estimate, one Gauss-Newton step from the fitted one (at
            // which the smaller model's step is nil): how far the MAP moves were the form one
            // order richer. Without model error its square is the variance above on average; a
            // higher order the data hold but the selection left out (a joint's third harmonic
            // mimicked by the second over a short range) shows in it alone.
            let all: Vec<usize> = (0..cols.len()).collect();
            let (step, _, _) = fit::solve(&n, &b, &all);
            let shift =
                DMatrix::from_fn(rows.len(), rows.len(), |a, b| step[rows[a]] * step[rows[b]]);
            for (i, set) in poses.iter().enumerate() {
                let v = predict::position_std_with(&problem.model, &p, set, &w, &terms, &diff);
                let d = predict::position_std_with(&problem.model, &p, set, &w, &terms, &shift);
                for ((m, x), y) in worst[i].iter_mut().zip(v).zip(d) {
                    *m = m.max(x).max(y);
                }
            }
        }
        // Where the data did not reach, the form's error is bounded by the effect's own size
        // (a smooth error whose variance is what the fit found, not more): the largest of the
        // effect's contributions over the poses, per pose at most that.
        let own_cols = fit::effect_cols(t.effect, t.basis);
        let coef = DVector::from_column_slice(&t.coef);
        let own = EffectTerms::of(problem, est, own_cols);
        let none = predict::selection(&[]);
        let size = poses
            .iter()
            .map(|set| {
                let v = predict::position_std_with(
                    &problem.model,
                    &p,
                    set,
                    &none,
                    &own,
                    &(&coef * coef.transpose()),
                );
                predict::spread(&v).rms
            })
            .fold(0.0f64, f64::max);
        for i in 0..N {
            for (o, x) in out[i].iter_mut().zip(&worst[i]) {
                *o = o.hypot(x.min(size));
            }
        }
    }
    out
}

/// Type B of the held parameters: W (30 × h) and their prior covariance (h × h). A held
/// parameter's true deviation δ moves the MAP by J_h δ directly, and by −J_d K δ through the
/// determined parameters that absorb it in the fit (K = N_aa⁻¹ N_ah, the effects included in
/// a). For an exact dependency (d3 on d2) the two cancel: no uncertainty.
fn held_map(
    problem: &Problem,
    est: &Estimate,
    free: &[Param],
    held: &[Param],
    opts: &CalibrateOptions,
) -> (DMatrix<f64>, DMatrix<f64>) {
    let h = held.len();
    if h == 0 {
        return (DMatrix::zeros(N_PARAMS, 0), DMatrix::zeros(0, 0));
    }
    let mut cols = model_cols(est, free);
    let c = cols.len();
    cols.extend(held.iter().map(|&q| fit::Col::Geo(q)));
    let (n, _, _, _) = accumulate(problem, est, &cols, 1).total();
    let shared = |q: &Param| match q {
        Param::Shared(i) => Some(*i),
        _ => None,
    };
    // Fitted columns: the free parameters, then the effects' coefficients (no MAP motion).
    let fitted: Vec<Option<usize>> = (0..c).map(|a| free.get(a).and_then(shared)).collect();
    let held_idx: Vec<Option<usize>> = held.iter().map(shared).collect();
    let w = predict::held_weights(&n, &fitted, &held_idx);
    let cov = DMatrix::from_fn(h, h, |a, b| {
        if a == b {
            prior(opts, held[a]).powi(2)
        } else {
            0.0
        }
    });
    (w, cov)
}

/// The effect whose coefficients, were they known, would shrink the geometry's predicted
/// workspace uncertainty most — when that is more than threefold: the data cannot tell it
/// from the geometry (e.g. a once-per-turn cyclic error of a joint that moves far less than a
/// turn looks like its zero offset).
pub(super) fn confounding(
    fitted: &Fitted,
    free: &[Param],
    est: &Estimate,
    sigma: f64,
    model: &MeasurementModel,
    p: &Params,
    space: &[[f64; 6]],
) -> Option<String> {
    let g = free.len();
    if est.effects.is_empty() || g == 0 {
        return None;
    }
    let poses: Vec<[f64; 6]> = space.iter().step_by(4).copied().collect();
    let shared = shared_columns(free);
    let idx: Vec<usize> = shared.iter().map(|s| s.1).collect();
    let w = predict::selection(&idx);
    // Type A workspace RMS from the normal matrix on the columns `keep`.
    let rms_with = |keep: &[usize]| -> f64 {
        let n = DMatrix::from_fn(keep.len(), keep.len(), |a, b| {
            fitted.normal[(keep[a], keep[b])]
        });
        let cov = fit::inverse(&n) * (sigma * sigma);
        let c = DMatrix::from_fn(shared.len(), shared.len(), |a, b| {
            cov[(shared[a].0, shared[b].0)]
        });
        predict::spread(&predict::position_std(model, p, &poses, &w, &c)).rms
    };
    let all: Vec<usize> = (0..fitted.coefficients()).collect();
    let full = rms_with(&all);
    let mut start = g;
    let mut best: Option<(Effect, f64)> = None;
    for t in &est.effects {
        let (e, c) = (&t.effect, &t.coef);
        let range = start..start + c.len();
        start += c.len();
        let keep: Vec<usize> = all.iter().copied().filter(|k| !range.contains(k)).collect();
        let without = rms_with(&keep);
        if best.is_none_or(|b| without < b.1) {
            best = Some((*e, without));
        }
    }
    let (e, without) = best?;
    (full > 3.0 * without && full > 2e-6).then(|| {
        let name = match e.joint() {
            Some(j) => format!("{} of joint {j}", e.name()),
            None => e.name().to_string(),
        };
        format!(
            "the data barely tell the {name} from the geometry: fitted together, the geometry's predicted uncertainty is {} RMS over the joint space; were the effect known, it would be {}. Measuring over a wider range of the joint separates them",
            length_um(full * 1e6),
            length_um(without * 1e6)
        )
    })
}

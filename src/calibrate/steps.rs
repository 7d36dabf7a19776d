//! Steps 1-5 of a calibration: in = the problem (the campaign's rows), the options; out = the
//! converged fit ([`Fit`]: the estimate, the parameters the data determine, the effects
//! adopted on held-out data, the noise) and its held-out validation ([`HeldOutScore`]).

use super::{prior, CalibrateOptions, Effects, FOLDS, LOO_ROWS, OUTLIER_SIGMAS};
use crate::diagnose::fit::{self, accumulate, model_cols, score, structural, Known};
use crate::diagnose::{self, noise_variance, start, Basis, DiagnoseOptions, Estimate, Fitted};
use crate::diagnose::{Param, Problem};
use crate::robot::Robot;
use crate::twin::effects::Effect;
use nalgebra::DMatrix;

/// Joint-space poses a compliance's general basis is tidied over.
const TIDY_POSES: usize = 500;

/// A converged fit: what steps 1-4 leave for the validation, the uncertainty and the report.
pub(super) struct Fit {
    pub est: Estimate,
    /// The determined parameters (the ones that moved).
    pub free: Vec<Param>,
    pub fitted: Fitted,
    /// Parameters ruled out in step 4, with the standard uncertainty they would have (SI).
    pub weak: Vec<(Param, f64)>,
    /// Every effect the selection considered.
    pub candidates: Vec<diagnose::Candidate>,
    /// The nominal robot with the runs' given set-up, after the selection opened segments.
    pub nominal: Estimate,
    /// The residual's σ per row, lag-1 autocorrelation and variance inflation.
    pub sigma: f64,
    pub rho: f64,
    pub inflate: f64,
    pub effects_mode: &'static str,
    pub warnings: Vec<String>,
}

/// Steps 1-4: the set-up from a start that needs none, the robust geometric fit, effects and
/// steps adopted on held-out data, then only what the data determine moves.
pub(super) fn fit(
    problem: &mut Problem,
    robot: &Robot,
    known: &Known,
    opts: &CalibrateOptions,
) -> Fit {
    let nominal = Estimate::nominal(problem);
    let nruns = problem.runs();
    let mut warnings = Vec::new();

    // Step 1: the set-up from a start that needs none, the robot held nominal.
    let mut est = nominal.clone();
    let (_, at_given) = structural(problem, known, &est);
    let setup: Vec<Param> = at_given.iter().copied().filter(Param::is_setup).collect();
    start::setup(problem, &mut est, &setup);
    // The set-up the data found with the nominal robot: where a set-up parameter the fit
    // cannot determine is held (never at the tape-measure value it was given).
    let started = est.clone();
    // Which parameters the poses separate, judged where the set-up really is.
    let (_, structural_free) = structural(problem, known, &est);

    // Steps 2-3: the robust geometric fit, then effects and steps on held-out data.
    let mut free = structural_free.clone();
    let mut fitted = fit::refit(problem, &mut est, &free);
    for _ in 0..3 {
        if !reweight(problem, &fitted.residual) {
            break;
        }
        fitted = fit::refit(problem, &mut est, &free);
    }
    let (effects_mode, max_effects) = match &opts.effects {
        Effects::Auto => ("auto", 3),
        Effects::None => ("none", 0),
        Effects::List(v) => {
            for e in v {
                est.add_effect(*e, list_basis(*e, problem), 0.5 * problem.span());
            }
            fit::refit(problem, &mut est, &free);
            ("list", 0)
        }
    };
    let sel_opts = DiagnoseOptions {
        folds: FOLDS,
        max_effects,
        masses: robot.masses.clone(),
        max_steps: opts.max_steps * nruns,
        min_explained: 0.3,
        // A calibration keeps what predicts better (the held-out gain and the BIC judge
        // that); naming the cause is the diagnosis's business.
        min_explained_heldout: 0.0,
        // The problem's harmonic caps already hold the robot's limits (`run`).
        joint_ranges: None,
        noise: opts.noise,
    };
    let sel = diagnose::select(problem, &free, est, &sel_opts);
    if max_effects > 0 && sel.diagnosis.report.unexplained {
        warnings.push(
            "structure remains that no effect of the library explains; the geometry may absorb part of it (see `edbbgen diagnose`)".to_string(),
        );
    }
    let mut est = sel.estimate.clone();
    free = sel.free.clone();
    // The segments opened at steps start from their run's given set-up.
    let nominal = Estimate::nominal(problem);
    fitted = sel.fitted;
    if reweight(problem, &fitted.residual) {
        fitted = fit::refit(problem, &mut est, &free);
    }

    // Step 4: only what the data determine moves.
    let mut weak: Vec<(Param, f64)> = Vec::new();
    let mut noise;
    loop {
        noise = noise_variance(&fitted, &problem.weight);
        let sigma_eff = noise.0 * noise.2.sqrt();
        let (kept, dropped) = determine(&fitted, sigma_eff, opts);
        if dropped.is_empty() {
            break;
        }
        for (q, _) in &dropped {
            let v = held_value(problem, &nominal, &started, &est, *q);
            est.set(*q, v);
        }
        weak.extend(dropped);
        free = kept;
        fitted = fit::refit(problem, &mut est, &free);
    }
    let (sigma, rho, inflate) = noise;
    // A compliance's general basis without the coefficients its dependencies leave free.
    est.tidy_compliance(
        problem,
        &super::predict::workspace(robot, TIDY_POSES, opts.seed),
    );
    Fit {
        est,
        free,
        fitted,
        weak,
        candidates: sel.candidates,
        nominal,
        sigma,
        rho,
        inflate,
        effects_mode,
        warnings,
    }
}

/// Step 5: held out, block by block, the calibrated model against the nominal robot with the
/// same set-up fitted; and what the held-out residual says about model error.
pub(super) struct HeldOutScore {
    /// Held-out residual RMS (m) of the calibrated and of the nominal robot.
    pub calibrated: f64,
    pub nominal: f64,
    pub folds: usize,
    /// Rows scored (outliers excluded).
    pub rows: usize,
    /// The variance factor Type A carries: the larger of the residual's integrated
    /// autocorrelation time and the held-out residual's mean square over the noise's.
    pub factor: f64,
    /// The RMS (m, along the bar) of what the model misses on held-out rows beyond the noise.
    pub model_error: f64,
    /// The nominal geometry with the set-up fitted alone (the determined set-up parameters
    /// of the calibration), and that fit: what is delivered when the geometry is not improved.
    pub setup: (Estimate, Fitted),
}

pub(super) fn held_out(problem: &Problem, f: &Fit, given_noise: Option<f64>) -> HeldOutScore {
    let (est, free, sigma) = (&f.est, &f.free, f.sigma);
    let kept_rows = problem.kept().max(1);
    let folds = FOLDS.min(kept_rows / 8).max(2);
    let cols = model_cols(est, free);
    let all: Vec<usize> = (0..cols.len()).collect();
    let st = accumulate(problem, est, &cols, folds);
    let cv_cal = score(&st, &all).3;
    let heldout_cal = (cv_cal / kept_rows as f64).sqrt();
    let (heldout_nom, setup) = {
        let mut e = est.clone();
        e.p[crate::model::ALPHA..crate::model::MAP]
            .copy_from_slice(&f.nominal.p[crate::model::ALPHA..crate::model::MAP]);
        e.effects.clear();
        let setup: Vec<Param> = free.iter().copied().filter(Param::is_setup).collect();
        let fitted = fit::refit(problem, &mut e, &setup);
        let c = model_cols(&e, &setup);
        let s = accumulate(problem, &e, &c, folds);
        let sel: Vec<usize> = (0..c.len()).collect();
        ((score(&s, &sel).3 / kept_rows as f64).sqrt(), (e, fitted))
    };
    // Type A's model-error factor: the held-out mean square over what the noise alone gives
    // held out (the noise plus the variance of predicting a block from the others, which on a
    // few static readings is no model error). Only folds whose complement determines the whole
    // fit count: on a few dozen readings with nearly as many unknowns (a stop-and-measure
    // run's plateau means) blocks of an eighth leave directions undetermined, so those are
    // held out one reading at a time.
    let model_factor = {
        let loo;
        let st_m = if kept_rows <= LOO_ROWS {
            loo = accumulate(problem, est, &cols, problem.rows());
            &loo
        } else {
            &st
        };
        match fit::heldout_determined(st_m, &all) {
            Some((cv, noise, _)) if sigma > 0.0 && noise > 0.0 => {
                (cv / (sigma * sigma * noise)).max(1.0)
            }
            _ => 1.0,
        }
    };
    // What the model misses on rows it was not fitted to, beyond the reading noise (its
    // high-frequency estimate) and what predicting from fewer rows costs a right model; only
    // an excess the noise estimate's own uncertainty (three standard errors of a variance from
    // n rows) cannot explain counts.
    let model_error = {
        // Weighted as the held-out sums are.
        let neighbours = diagnose::noise::Neighbours::new(problem);
        let noise = diagnose::noise::reading_noise(
            problem,
            &neighbours,
            &f.fitted.residual,
            given_noise,
            true,
        )
        .or(0.0);
        match fit::heldout_determined(&st, &all) {
            Some((cv, units, rows)) if rows > 0 => {
                let slack = 1.0 + 3.0 * (2.0 / rows as f64).sqrt();
                ((cv - noise * noise * units * slack) / rows as f64)
                    .max(0.0)
                    .sqrt()
            }
            _ => 0.0,
        }
    };
    HeldOutScore {
        calibrated: heldout_cal,
        nominal: heldout_nom,
        folds,
        rows: kept_rows,
        factor: f.inflate.max(model_factor),
        model_error,
        setup,
    }
}

/// Step 4: of the free parameters of a converged fit, the ones the data determine, and the
/// others with the standard uncertainty they would have (SI).
fn determine(
    fitted: &Fitted,
    sigma: f64,
    opts: &CalibrateOptions,
) -> (Vec<Param>, Vec<(Param, f64)>) {
    let free = &fitted.free;
    let g = free.len();
    let c = fitted.coefficients();
    let n = &fitted.normal;
    // The geometry's information once the effects' coefficients are eliminated.
    let mut s = n.view((0, 0), (g, g)).into_owned();
    if c > g {
        let nge = n.view((0, g), (g, c - g)).into_owned();
        let nee = n.view((g, g), (c - g, c - g)).into_owned();
        s -= &nge * fit::inverse(&nee) * nge.transpose();
    }
    let scale: Vec<f64> = free.iter().map(|&q| prior(opts, q)).collect();
    let ss = DMatrix::from_fn(g, g, |a, b| s[(a, b)] * scale[a] * scale[b]);
    let (chosen, weak) = determined_columns(&ss, sigma, opts.kappa);
    (
        chosen.into_iter().map(|k| free[k]).collect(),
        weak.into_iter()
            .map(|(k, ratio)| (free[k], ratio * scale[k]))
            .collect(),
    )
}

/// Step 3 on a normal matrix `ss` (g × g) whose columns are scaled by their parameters' prior
/// uncertainty, for a noise σ per reading: the columns the data determine (ascending), and the
/// others with the standard uncertainty each would have, in units of its prior (in the order
/// they were ruled out). Pivoted Cholesky takes the best-seen column next while its conditional
/// uncertainty stays below prior/κ; then any column whose marginal uncertainty exceeds prior/κ
/// is dropped, worst first. Shared by [`super::run`] (on fitted data) and
/// [`super::predict::expected`] (on the information a planned campaign would collect).
pub fn determined_columns(
    ss: &DMatrix<f64>,
    sigma: f64,
    kappa: f64,
) -> (Vec<usize>, Vec<(usize, f64)>) {
    let g = ss.nrows();
    // Pivoted Cholesky: the best-seen parameter next, while it is seen well enough.
    let floor = (kappa * sigma).powi(2);
    let mut d: Vec<f64> = (0..g).map(|k| ss[(k, k)]).collect();
    let mut chosen: Vec<usize> = Vec::new();
    let mut l = DMatrix::<f64>::zeros(g, g);
    loop {
        let best = (0..g)
            .filter(|k| !chosen.contains(k))
            .max_by(|&a, &b| d[a].total_cmp(&d[b]).then(b.cmp(&a)));
        let Some(k) = best else { break };
        if !(d[k] >= floor && d[k] > 0.0) {
            break;
        }
        let col = chosen.len();
        let piv = d[k].sqrt();
        for i in 0..g {
            let mut v = ss[(i, k)];
            for j in 0..col {
                v -= l[(i, j)] * l[(k, j)];
            }
            l[(i, col)] = v / piv;
        }
        for i in 0..g {
            d[i] -= l[(i, col)] * l[(i, col)];
        }
        chosen.push(k);
    }
    let mut weak: Vec<(usize, f64)> = (0..g)
        .filter(|k| !chosen.contains(k))
        .map(|k| (k, sigma / d[k].max(1e-300).sqrt()))
        .collect();
    // Every kept parameter's marginal uncertainty within prior / κ, worst dropped first.
    chosen.sort_unstable();
    loop {
        if chosen.is_empty() {
            break;
        }
        let sub = DMatrix::from_fn(chosen.len(), chosen.len(), |a, b| {
            ss[(chosen[a], chosen[b])]
        });
        let cov = fit::inverse(&sub);
        let (worst, ratio) = (0..chosen.len())
            .map(|a| (a, cov[(a, a)].max(0.0).sqrt() * sigma))
            .max_by(|x, y| x.1.total_cmp(&y.1).then(y.0.cmp(&x.0)))
            .unwrap_or((0, 0.0));
        if ratio <= 1.0 / kappa {
            break;
        }
        let k = chosen.remove(worst);
        weak.push((k, ratio));
    }
    (chosen, weak)
}

/// The form an effect named in `--effects` takes: cyclic errors with harmonic orders 1-3, a
/// thermal drift linear in a logged temperature or a first-order lag, a servo delay.
fn list_basis(e: Effect, problem: &Problem) -> Basis {
    match e {
        Effect::CyclicError(_) => Basis::Harmonics(0b111),
        Effect::ThermalDrift if problem.has_temperature() => Basis::Temperature,
        Effect::ThermalDrift => Basis::Lag,
        _ => Basis::Standard,
    }
}

/// Robust weights: rows whose residual leaves the median of its neighbours (7 rows, in the
/// order taken) by more than [`OUTLIER_SIGMAS`] robust standard deviations are dropped (weight
/// 0: a redescending loss), and in a campaign each run's rows are scaled by its own noise so
/// that a noisy run does not outweigh a quiet one. Returns true when the set of dropped rows
/// changed.
fn reweight(problem: &mut Problem, residual: &[f64]) -> bool {
    let n = problem.rows();
    let mut dropped = vec![false; n];
    let mut noise = vec![0.0; problem.runs()];
    let median = |v: &mut Vec<f64>| -> f64 {
        if v.is_empty() {
            return 0.0;
        }
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    for (r, range) in problem.ranges.iter().enumerate() {
        let idx: Vec<usize> = range
            .clone()
            .filter(|&k| problem.base_weight[k] > 0.0)
            .collect();
        if idx.len() < 8 {
            continue;
        }
        let e: Vec<f64> = (0..idx.len())
            .map(|i| {
                let (lo, hi) = (i.saturating_sub(3), (i + 4).min(idx.len()));
                let mut w: Vec<f64> = idx[lo..hi].iter().map(|&k| residual[k]).collect();
                residual[idx[i]] - median(&mut w)
            })
            .collect();
        let mut a: Vec<f64> = e.iter().map(|v| v.abs()).collect();
        let sigma = 1.4826 * median(&mut a);
        noise[r] = sigma;
        if sigma <= 0.0 {
            continue;
        }
        for (i, &k) in idx.iter().enumerate() {
            dropped[k] = e[i].abs() > OUTLIER_SIGMAS * sigma;
        }
    }
    // One yardstick for the runs: the median of their noise levels.
    let mut levels: Vec<f64> = noise.iter().copied().filter(|v| *v > 0.0).collect();
    let reference = median(&mut levels);
    let mut changed = false;
    for (r, range) in problem.ranges.iter().enumerate() {
        let scale = if problem.runs() > 1 && noise[r] > 0.0 && reference > 0.0 {
            (reference / noise[r]).clamp(0.01, 100.0)
        } else {
            1.0
        };
        for k in range.clone() {
            let was = problem.weight[k] <= 0.0 && problem.base_weight[k] > 0.0;
            changed |= was != dropped[k];
            problem.weight[k] = if dropped[k] {
                0.0
            } else {
                problem.base_weight[k] * scale
            };
        }
    }
    changed
}

/// The value a parameter the data do not determine is held at: nominal for the robot; a
/// run's own set-up where the start found it (`started`: fitted to the nominal robot, from
/// a start that needs none); a segment's fixture or zero keeps its run's first one.
fn held_value(
    problem: &Problem,
    nominal: &Estimate,
    started: &Estimate,
    est: &Estimate,
    q: Param,
) -> f64 {
    match q {
        Param::Fixture { group, axis } if !problem.fix_groups[group].given => {
            est.fixtures[problem.fix_groups[group].run][axis]
        }
        Param::Offset { group } if !problem.off_groups[group].given => {
            est.offsets[problem.off_groups[group].run]
        }
        q if q.is_setup() => started.get(q),
        _ => nominal.get(q),
    }
}

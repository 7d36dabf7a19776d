//! Calibration: in = the measurement model, a campaign of recorded runs (each with its own
//! fixture) and options; out = the calibrated geometry (only what the data determine moves,
//! the rest stays nominal), its covariance, the predicted MAP position uncertainty and the
//! `edbbgen.calibrate/1` report (DESIGN.md). No file I/O.
//!
//! Method, in four steps, on the diagnosis's own machinery ([`crate::diagnose::fit`]):
//! 1. **Structure.** Which parameters the recorded poses can separate at all (Section 2.1.2:
//!    Gram–Schmidt in Eq. 6's preference order): d3 against d2, θ6 against α6, a6, d6, the MAP
//!    against link 6, a free fixture against d1 and θ1.
//! 2. **Effects.** `auto` runs the diagnosis and takes the effects it names; the geometry and
//!    the effects are then fitted jointly (Levenberg-Marquardt), so an effect does not bias
//!    the geometry.
//! 3. **Determined or not.** Columns scaled by a tolerance (the deviation a parameter could
//!    plausibly have: 1 mm, 0.05°) are taken by pivoted Cholesky on the normal matrix (the
//!    effects' columns eliminated first) while the next one's conditional standard uncertainty
//!    stays below tolerance/κ; then any parameter whose marginal uncertainty exceeds
//!    tolerance/κ is dropped, worst first. The noise is the residual's, inflated by
//!    (1 + ρ)/(1 − ρ) for a lag-1 correlation ρ. Only determined parameters move; the rest are
//!    held at nominal and the geometry refitted, until the set is stable. A weakly seen
//!    parameter is thus never "fitted" to a value its uncertainty makes meaningless.
//! 4. **Uncertainty** (GUM, Type A): the covariance σ²_eff (JᵀJ)⁻¹ of the determined
//!    parameters and the effects, propagated to the MAP position after a best rigid
//!    registration ([`predict`]) over the recorded poses and over the whole joint space.
//!
//! The fit starts at nominal and takes only descending steps, so the calibrated model never
//! explains the recorded data worse than the nominal one.

pub mod plot;
pub mod predict;

use crate::diagnose::fit::{self, accumulate, model_cols, score, structural};
use crate::diagnose::{
    self, effects_report, geometry_report, noise_variance, Basis, DiagnoseOptions, EffectReport,
    Estimate, Fitted, Param, Problem, Run,
};
use crate::model::{MeasurementModel, Params, Status, N_PARAMS};
use crate::robot::Robot;
use crate::twin::effects::Effect;
use crate::units::{fmt_fixed, DEG, MM};
use nalgebra::DMatrix;
use serde::Serialize;

/// Which effects the calibration fits together with the geometry.
#[derive(Clone, Debug, PartialEq)]
pub enum Effects {
    /// Those the diagnosis names on the same data.
    Auto,
    /// None: geometry only.
    None,
    /// Exactly these.
    List(Vec<Effect>),
}

#[derive(Clone, Debug)]
pub struct CalibrateOptions {
    pub effects: Effects,
    /// Estimate each run's fixture where the campaign determines it (else held as given).
    pub fixture_free: bool,
    /// The standard uncertainty of a length (m) and an angle (rad) before calibration: the
    /// scale that makes parameters comparable, the yardstick of "determined", and the Type B
    /// uncertainty a parameter held at nominal keeps.
    pub prior_length: f64,
    pub prior_angle: f64,
    /// A parameter is determined when the data bring its standard uncertainty to at most
    /// prior / κ.
    pub kappa: f64,
    /// Random joint poses of the workspace prediction, and their seed.
    pub workspace_poses: usize,
    pub seed: u64,
}

pub const DEFAULT_PRIOR_MM: f64 = 1.0;
pub const DEFAULT_PRIOR_DEG: f64 = 0.05;
pub const DEFAULT_KAPPA: f64 = 3.0;
pub const WORKSPACE_POSES: usize = 2000;
/// Poses of the measured region the prediction is evaluated on (evenly spaced rows).
const REGION_POSES: usize = 2000;
/// Fewest rows a run must have.
pub const MIN_ROWS: usize = N_PARAMS + 2;

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            effects: Effects::Auto,
            fixture_free: false,
            prior_length: DEFAULT_PRIOR_MM * MM,
            prior_angle: DEFAULT_PRIOR_DEG * DEG,
            kappa: DEFAULT_KAPPA,
            workspace_poses: WORKSPACE_POSES,
            seed: 1,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    #[error("{0}")]
    Data(String),
}

#[derive(Clone, Debug, Serialize)]
pub struct RunReport {
    pub measured: String,
    /// The fixture position given for the run (mm).
    pub fixture_mm: [f64; 3],
    pub rows: usize,
    pub rms_before_um: f64,
    pub rms_after_um: f64,
    /// The estimated fixture position (mm), with `--fixture-free`.
    pub fixture_fitted_mm: Option<[f64; 3]>,
    /// Its standard uncertainty per coordinate (mm); null for a coordinate not determined.
    pub fixture_std_mm: Option<[Option<f64>; 3]>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Undetermined {
    pub param: String,
    pub why: String,
}

/// Predicted 1σ MAP position uncertainty after rigid registration (µm): combined, and its two
/// components.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Predicted {
    /// RMS over the recorded poses.
    pub measured_region_rms: f64,
    /// RMS and 95th percentile over random poses of the whole joint space.
    pub workspace_rms: f64,
    pub workspace_p95: f64,
    /// Type A: the determined parameters' covariance from the residual noise.
    pub from_noise: Component,
    /// Type B: the parameters held at nominal, each with its prior uncertainty, including
    /// how much of them the determined ones absorb.
    pub from_held: Component,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub struct Component {
    pub measured_region_rms: f64,
    pub workspace_rms: f64,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub struct Prior {
    pub length_mm: f64,
    pub angle_deg: f64,
    pub kappa: f64,
}

/// The `edbbgen.calibrate/1` report (DESIGN.md); keys after `predicted_position_std_um` are
/// additions.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub runs: Vec<RunReport>,
    pub determined: Vec<String>,
    pub undetermined: Vec<Undetermined>,
    /// Deviations from nominal of the determined parameters: {"a2": {"value", "std"}}, mm/deg.
    pub params: serde_json::Map<String, serde_json::Value>,
    pub effects: Vec<EffectReport>,
    /// The bar noise: the high-frequency part of the final residual (its second differences).
    pub noise_um: f64,
    pub rms_before_um: f64,
    pub rms_after_um: f64,
    pub predicted_position_std_um: Predicted,
    /// How the effects were chosen: "auto", "none" or "list".
    pub effects_mode: &'static str,
    /// Parameters held at their given values by assumption (the fixture without
    /// `--fixture-free`).
    pub held: Vec<String>,
    /// The residual's standard deviation per row (rᵀr / (n − p)), which the uncertainties
    /// use, its lag-1 autocorrelation, and the variance inflation that implies.
    pub residual_sigma_um: f64,
    pub residual_lag1: f64,
    pub noise_inflation: f64,
    /// Structure clearly above the noise is left in the residual: a missing effect.
    pub residual_structure: bool,
    pub prior: Prior,
    pub rows: usize,
    pub warnings: Vec<String>,
}

/// A calibration: the report, the calibrated estimate and what the plots need.
#[derive(Clone, Debug)]
pub struct Calibration {
    pub report: Report,
    pub estimate: Estimate,
    /// The determined parameters (the ones that moved).
    pub determined: Vec<Param>,
    /// Rows of each run in the residuals below.
    pub ranges: Vec<std::ops::Range<usize>>,
    /// Time of every row (each run from its own 0).
    pub t: Vec<f64>,
    pub residual_nominal: Vec<f64>,
    pub residual: Vec<f64>,
    /// Per-pose predicted position uncertainty over the workspace (µm), for plots.
    pub workspace_std_um: Vec<f64>,
    pub summary: String,
}

impl Calibration {
    /// The calibrated parameters (run 1's fixture).
    pub fn params(&self) -> Params {
        self.estimate.params(0)
    }
}

/// The robot's own parameters among the free ones: (column in the fit, Eq. 6 index). Fixtures
/// do not move the MAP.
fn shared_columns(free: &[Param]) -> Vec<(usize, usize)> {
    free.iter()
        .enumerate()
        .filter_map(|(a, q)| match q {
            Param::Shared(i) => Some((a, *i)),
            Param::Fixture { .. } => None,
        })
        .collect()
}

fn round(v: f64, d: i32) -> f64 {
    let s = 10f64.powi(d);
    let r = (v * s).round() / s;
    if r == 0.0 {
        0.0
    } else {
        r
    }
}

fn prior(opts: &CalibrateOptions, q: Param) -> f64 {
    if q.is_angle() {
        opts.prior_angle
    } else {
        opts.prior_length
    }
}

/// Step 3: of the free geometry of a converged fit, the parameters the data determine, and
/// the others with the standard uncertainty they would have (SI).
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
/// is dropped, worst first. Shared by [`run`] (on fitted data) and
/// [`predict::expected`] (on the information a planned campaign would collect).
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

/// Calibrates the robot of `model` on a campaign of runs (`labels` name them in the report).
pub fn run(
    model: &MeasurementModel,
    robot: &Robot,
    runs: &[Run],
    labels: &[String],
    opts: &CalibrateOptions,
) -> Result<Calibration, CalibrateError> {
    if runs.is_empty() {
        return Err(CalibrateError::Data("no run to calibrate from".into()));
    }
    for (k, r) in runs.iter().enumerate() {
        if r.measured.len() < MIN_ROWS {
            return Err(CalibrateError::Data(format!(
                "run {} ({}): {} rows, at least {MIN_ROWS} are needed",
                k + 1,
                labels.get(k).map_or("", |s| s.as_str()),
                r.measured.len()
            )));
        }
    }
    let problem = Problem::new(model, runs).with_masses(&robot.masses);
    let nruns = problem.runs();
    let (status, structural_free) = structural(&problem, opts.fixture_free, true);
    let mut warnings = Vec::new();

    // Step 2: the effects, then the joint fit.
    let (effects, effects_mode, diagnosis, diagnosis_estimate) = match &opts.effects {
        Effects::Auto => {
            let sel = diagnose::select(&problem, &structural_free, &DiagnoseOptions::default());
            let e: Vec<(Effect, Basis)> = sel
                .estimate
                .effects
                .iter()
                .map(|t| (t.effect, t.basis))
                .collect();
            (e, "auto", Some(sel.diagnosis), Some(sel.estimate))
        }
        Effects::None => (Vec::new(), "none", None, None),
        Effects::List(v) => (
            v.iter().map(|e| (*e, Basis::Standard)).collect(),
            "list",
            None,
            None,
        ),
    };
    if let Some(d) = &diagnosis {
        if d.report.unexplained {
            warnings.push(
                "the diagnosis found structure that no effect of the library explains; the geometry may absorb part of it (see `edbbgen diagnose`)".to_string(),
            );
        }
    }
    let nominal = Estimate::nominal(&problem);
    let mut free = structural_free.clone();
    // The joint fit, from where the diagnosis left it (auto), or like the diagnosis: the
    // geometry first, then the effects added and everything refitted together (a large
    // effect basis started at a geometry millimetres off converges badly).
    let mut est = match diagnosis_estimate {
        Some(e) => e,
        None => {
            let mut est = nominal.clone();
            if !effects.is_empty() {
                fit::refit(&problem, &mut est, &free);
            }
            for (e, basis) in &effects {
                est.add_effect(*e, *basis, problem.thermal_terms);
            }
            est
        }
    };
    let mut fitted = fit::refit(&problem, &mut est, &free);

    // Step 3: only what the data determine moves.
    let mut weak: Vec<(Param, f64)> = Vec::new();
    let mut sigma_eff;
    let mut noise;
    loop {
        noise = noise_variance(&fitted.residual, fitted.coefficients());
        sigma_eff = noise.0 * noise.2.sqrt();
        let (kept, dropped) = determine(&fitted, sigma_eff, opts);
        if dropped.is_empty() {
            break;
        }
        for (q, _) in &dropped {
            match *q {
                Param::Shared(i) => est.p[i] = nominal.p[i],
                Param::Fixture { run, axis } => {
                    est.fixtures[run][axis] = nominal.fixtures[run][axis]
                }
            }
        }
        weak.extend(dropped);
        free = kept;
        fitted = fit::refit(&problem, &mut est, &free);
    }
    let (sigma, rho, inflate) = noise;

    // Step 4: uncertainty.
    let cov = fit::inverse(&fitted.normal) * (sigma_eff * sigma_eff);
    let g = free.len();
    let var: Vec<f64> = (0..cov.nrows()).map(|k| cov[(k, k)]).collect();
    let (values, stds) = geometry_report(&problem, &est, &free, &var[..g]);
    let mut params = serde_json::Map::new();
    for (name, v) in &values {
        let mut e = serde_json::Map::new();
        e.insert("value".into(), v.clone());
        e.insert("std".into(), stds[name].clone());
        params.insert(name.clone(), e.into());
    }
    let effect_reports = effects_report(&problem, &est, &var[g..]);
    // Type A: the determined parameters (fixtures do not move the MAP), from the noise.
    let calibrated = est.params(0);
    let stride = problem.rows().div_ceil(REGION_POSES).max(1);
    let region: Vec<[f64; 6]> = problem.m.q.iter().step_by(stride).copied().collect();
    let space = predict::workspace(robot, opts.workspace_poses, opts.seed);
    let shared = shared_columns(&free);
    let idx: Vec<usize> = shared.iter().map(|s| s.1).collect();
    let cov_a = DMatrix::from_fn(shared.len(), shared.len(), |a, b| {
        cov[(shared[a].0, shared[b].0)]
    });
    let w_a = predict::selection(&idx);
    // Type B: every parameter held at nominal (not by assumption) keeps its prior; through
    // the fit the determined ones absorb K = N_aa⁻¹ N_ah of it, so the MAP moves by
    // (e_h − Σ_d e_d K_dh) per unit of held deviation.
    let held_params: Vec<Param> = status
        .iter()
        .filter(|(q, st)| !free.contains(q) && *st != Status::Known)
        .map(|(q, _)| *q)
        .collect();
    let (w_b, cov_b) = held_map(&problem, &est, &free, &held_params, opts);
    let a_region = predict::position_std(model, &calibrated, &region, &w_a, &cov_a);
    let b_region = predict::position_std(model, &calibrated, &region, &w_b, &cov_b);
    let a_space = predict::position_std(model, &calibrated, &space, &w_a, &cov_a);
    let b_space = predict::position_std(model, &calibrated, &space, &w_b, &cov_b);
    let combine = |a: &[f64], b: &[f64]| -> Vec<f64> {
        a.iter().zip(b).map(|(x, y)| x.hypot(*y) * 1e6).collect()
    };
    let um = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| x * 1e6).collect() };
    let region_std = predict::spread(&combine(&a_region, &b_region));
    let space_std = combine(&a_space, &b_space);
    let space_spread = predict::spread(&space_std);
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
    };

    // An effect the data cannot tell from the geometry makes the geometry uncertain: say which.
    if let Some(w) = confounding(&fitted, &free, &est, sigma_eff, model, &calibrated, &space) {
        warnings.push(w);
    }

    // Residuals, per run.
    let residual_nominal = accumulate(&problem, &nominal, &[], 1).residual;
    let residual = fitted.residual.clone();
    let noise_hf = fit::noise_estimate(&residual);
    let rms_after = fit::rms(&residual);
    // Structure above the noise: the residual clearly larger than its high-frequency part, or
    // a lag-1 correlation white noise of this length would not show (5 standard errors).
    let rho_limit = (5.0 / (problem.rows() as f64).sqrt()).max(0.1);
    let residual_structure = rms_after > 1.25 * noise_hf || rho > rho_limit;
    if residual_structure {
        let hint = match opts.effects {
            Effects::None => "; fit the effects with --effects auto",
            _ => "",
        };
        warnings.push(format!(
            "structure above the noise is left in the residual (RMS {} um against {} um of bar noise, lag-1 autocorrelation {}): the model misses an effect, and the geometry absorbs part of it{hint}",
            fmt_fixed(rms_after * 1e6, 3),
            fmt_fixed(noise_hf * 1e6, 3),
            fmt_fixed(rho, 2)
        ));
    }
    if !opts.fixture_free {
        if let Some(w) = fixture_check(&problem, &est, &free, &structural_free) {
            warnings.push(w);
        }
    }

    let mut run_reports = Vec::with_capacity(nruns);
    for (r, range) in problem.ranges.iter().enumerate() {
        let fixture_fitted = free
            .iter()
            .any(|q| matches!(q, Param::Fixture { run, .. } if *run == r));
        let std_of = |axis: usize| {
            free.iter()
                .position(|q| *q == Param::Fixture { run: r, axis })
                .map(|a| round(var[a].max(0.0).sqrt() / MM, 6))
        };
        run_reports.push(RunReport {
            measured: labels.get(r).cloned().unwrap_or_default(),
            fixture_mm: problem.fixtures[r].map(|v| round(v / MM, 6)).into(),
            rows: range.len(),
            rms_before_um: round(fit::rms(&residual_nominal[range.clone()]) * 1e6, 3),
            rms_after_um: round(fit::rms(&residual[range.clone()]) * 1e6, 3),
            fixture_fitted_mm: fixture_fitted
                .then(|| est.fixtures[r].map(|v| round(v / MM, 6)).into()),
            fixture_std_mm: fixture_fitted.then(|| [std_of(0), std_of(1), std_of(2)]),
        });
    }

    let mut undetermined = Vec::new();
    let mut held = Vec::new();
    for (q, st) in &status {
        if free.contains(q) {
            continue;
        }
        let name = q.name(nruns);
        let unit = |q: &Param| {
            if q.is_angle() {
                (DEG, "deg")
            } else {
                (MM, "mm")
            }
        };
        let why = match st {
            Status::Known => {
                held.push(name);
                continue;
            }
            Status::Dependent { on } => format!("dependent on {}", on.join(", ")),
            Status::Negligible => {
                "no influence on the bar length at the recorded poses".to_string()
            }
            Status::Identifiable => match weak.iter().find(|(w, _)| w == q) {
                Some((_, sd)) => {
                    let (u, name) = unit(q);
                    format!(
                        "not determined by these data: its standard uncertainty would be {} {name}, more than the prior {} {name} / {}",
                        fmt_fixed(sd / u, 4),
                        fmt_fixed(prior(opts, *q) / u, 4),
                        fmt_fixed(opts.kappa, 1)
                    )
                }
                None => "not determined by these data".to_string(),
            },
        };
        undetermined.push(Undetermined { param: name, why });
    }

    let report = Report {
        schema: "edbbgen.calibrate/1",
        runs: run_reports,
        determined: free.iter().map(|q| q.name(nruns)).collect(),
        undetermined,
        params,
        effects: effect_reports,
        noise_um: round(noise_hf * 1e6, 3),
        rms_before_um: round(fit::rms(&residual_nominal) * 1e6, 3),
        rms_after_um: round(rms_after * 1e6, 3),
        predicted_position_std_um: predicted,
        effects_mode,
        held,
        residual_sigma_um: round(sigma * 1e6, 3),
        residual_lag1: round(rho, 4),
        noise_inflation: round(inflate, 4),
        residual_structure,
        prior: Prior {
            length_mm: opts.prior_length / MM,
            angle_deg: opts.prior_angle / DEG,
            kappa: opts.kappa,
        },
        rows: problem.rows(),
        warnings,
    };
    let summary = summary(&report);
    Ok(Calibration {
        report,
        estimate: est,
        determined: free,
        ranges: problem.ranges.clone(),
        t: problem.m.t.clone(),
        residual_nominal,
        residual,
        workspace_std_um: space_std,
        summary,
    })
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
    let mut cols = model_cols(problem, est, free);
    let c = cols.len();
    cols.extend(held.iter().map(|&q| fit::Col::Geo(q)));
    let (n, _, _, _) = accumulate(problem, est, &cols, 1).total();
    let shared = |q: &Param| match q {
        Param::Shared(i) => Some(*i),
        Param::Fixture { .. } => None,
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
fn confounding(
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
            "the data barely tell the {name} from the geometry: fitted together, the geometry's predicted uncertainty is {} um RMS over the joint space; were the effect known, it would be {} um. Measuring over a wider range of the joint separates them",
            fmt_fixed(full * 1e6, 2),
            fmt_fixed(without * 1e6, 2)
        )
    })
}

/// With the fixture held: does freeing it explain clearly more (BIC, and a tenth of the
/// residual)? Then the given position is probably off, and the geometry absorbs it.
fn fixture_check(
    problem: &Problem,
    est: &Estimate,
    free: &[Param],
    structural_free: &[Param],
) -> Option<String> {
    let (_, with_fixture) = structural(problem, true, true);
    let extra: Vec<Param> = with_fixture
        .iter()
        .filter(|q| matches!(q, Param::Fixture { .. }) && !structural_free.contains(q))
        .copied()
        .collect();
    if extra.is_empty() {
        return None;
    }
    let mut cols = model_cols(problem, est, free);
    let base = cols.len();
    cols.extend(extra.iter().map(|&q| fit::Col::Geo(q)));
    let st = accumulate(problem, est, &cols, 1);
    let sel0: Vec<usize> = (0..base).collect();
    let sel1: Vec<usize> = (0..cols.len()).collect();
    let (rss0, _, bic0, _) = score(&st, &sel0);
    let (rss1, _, bic1, _) = score(&st, &sel1);
    let n = problem.rows() as f64;
    (bic1 < bic0 - 10.0 && rss1 < 0.9 * rss0).then(|| {
        format!(
            "the fixture position looks off: estimating it lowers the residual from {} um to {} um RMS; check --fixture, or estimate it with --fixture-free",
            fmt_fixed((rss0 / n).sqrt() * 1e6, 3),
            fmt_fixed((rss1 / n).sqrt() * 1e6, 3)
        )
    })
}

/// The printed summary of a report (also rebuilt when a report is restated, see
/// `compensate::drift`).
pub fn summary(r: &Report) -> String {
    let mut s = format!(
        "{} run{}, {} rows; bar noise {} um (lag-1 autocorrelation {})\n",
        r.runs.len(),
        if r.runs.len() == 1 { "" } else { "s" },
        r.rows,
        fmt_fixed(r.noise_um, 3),
        fmt_fixed(r.residual_lag1, 2)
    );
    s += &format!(
        "nominal model: RMS {} um; calibrated: RMS {} um\n",
        fmt_fixed(r.rms_before_um, 3),
        fmt_fixed(r.rms_after_um, 3)
    );
    let effects: Vec<String> = r
        .effects
        .iter()
        .map(|e| match e.joint {
            Some(j) => format!("{} (joint {j})", e.effect),
            None => e.effect.to_string(),
        })
        .collect();
    s += &format!(
        "effects fitted with the geometry ({}): {}\n",
        r.effects_mode,
        if effects.is_empty() {
            "none".to_string()
        } else {
            effects.join(", ")
        }
    );
    s += &format!(
        "determined: {} parameters; held at nominal: {}\n",
        r.determined.len(),
        if r.undetermined.is_empty() {
            "none".to_string()
        } else {
            r.undetermined
                .iter()
                .map(|u| u.param.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        }
    );
    for run in &r.runs {
        if let Some(f) = run.fixture_fitted_mm {
            s += &format!(
                "fixture of {}: {}, {}, {} mm (given {}, {}, {})\n",
                run.measured,
                fmt_fixed(f[0], 3),
                fmt_fixed(f[1], 3),
                fmt_fixed(f[2], 3),
                fmt_fixed(run.fixture_mm[0], 3),
                fmt_fixed(run.fixture_mm[1], 3),
                fmt_fixed(run.fixture_mm[2], 3)
            );
        }
    }
    let p = &r.predicted_position_std_um;
    s += &format!(
        "predicted MAP position uncertainty (1 sigma, after rigid registration): {} um RMS where measured; {} um RMS, {} um p95 over the joint space\n",
        fmt_fixed(p.measured_region_rms, 2),
        fmt_fixed(p.workspace_rms, 2),
        fmt_fixed(p.workspace_p95, 2)
    );
    for w in &r.warnings {
        s += &format!("warning: {w}\n");
    }
    s
}

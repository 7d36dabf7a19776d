//! Calibration: in = the measurement model, a campaign of recorded runs (each with its own
//! fixture) and options; out = the calibrated geometry (only what the data determine moves,
//! the rest stays nominal), its covariance, the predicted MAP position uncertainty, a held-out
//! validation, the verdict (calibrated or not, and why) and the `edbbgen.calibrate/1` report
//! (DESIGN.md). No file I/O.
//!
//! Method, on the diagnosis's own machinery ([`crate::diagnose::fit`]):
//! 1. **Set-up.** The tool point (MAP), each run's fixture and, with `--length-offset free`,
//!    its length zero are estimated wherever the data determine them; the given values are a
//!    prior (they keep what the data do not determine, and the report says how far the
//!    estimate moved). They start from the better of the given values and an algebraic
//!    solution that needs no start ([`crate::diagnose::start`]): a tool point tens of
//!    millimetres off is found, not linearised around.
//! 2. **Structure.** Which parameters the recorded poses can separate at all (Section 2.1.2:
//!    Gram–Schmidt, the least known first): the MAP takes link 6's place, the first fixture's
//!    height and azimuth d1's and θ1's (the base frame's), d3 goes with d2.
//! 3. **Robust fit, faults and effects.** Levenberg-Marquardt on the geometry and the set-up;
//!    rows that leave their neighbours' level by far (outliers) are dropped (a redescending
//!    loss) and reported. Then one move at a time, each adopted only when it lowers the
//!    residual on held-out blocks of rows (blocked cross-validation over time, or over the
//!    order the poses were taken): an effect of the library (`auto`), or a step — a fixture
//!    that moved, a length zero that changed — which splits the run into segments with their
//!    own fixture or zero ([`crate::diagnose::steps`]). Every candidate is listed with its
//!    held-out score.
//! 4. **Determined or not.** Columns scaled by their prior (1 mm, 0.05°; the set-up's 1 mm
//!    unless given) are taken by pivoted Cholesky on the normal matrix (the effects' columns
//!    eliminated first) while the next one's conditional standard uncertainty stays below
//!    prior/κ; then any parameter whose marginal uncertainty exceeds prior/κ is dropped, worst
//!    first. Only determined parameters move; the rest are held and the fit repeated.
//! 5. **Validation and verdict.** Held out block by block, the calibrated model must predict
//!    the readings better than the nominal robot with the same set-up fitted; otherwise, or
//!    when no robot parameter is determined, the calibration says so and is not to be written.
//! 6. **Uncertainty** (GUM). Type A: the covariance of the determined parameters and the
//!    effects from the residual, inflated by its integrated autocorrelation time and by the
//!    held-out residual's excess over the in-sample one (what the held-out data say about
//!    model error); Type B: the parameters held at nominal at their prior; the ambiguity of
//!    an effect's form (a cyclic error's harmonic orders the data cannot reject); all propagated to the MAP position after a best rigid
//!    registration ([`predict`]) over the recorded poses and over the whole joint space.
//!
//! The fit starts at the given values and takes only descending steps, so the calibrated model
//! never explains the recorded data worse than the nominal one.

pub mod plot;
pub mod predict;

use crate::diagnose::fit::{self, accumulate, model_cols, score, structural, Known};
use crate::diagnose::{
    self, effects_report, geometry_report, noise_variance, start, Basis, DiagnoseOptions,
    EffectReport, Estimate, Fitted, Param, Problem, Run,
};
use crate::model::{MeasurementModel, Params, Status, MAP, N_PARAMS};
use crate::robot::Robot;
use crate::twin::effects::Effect;
use crate::units::{fmt_fixed, DEG, MM};
use nalgebra::{DMatrix, Vector3};
use serde::Serialize;

/// Which effects the calibration fits together with the geometry.
#[derive(Clone, Debug, PartialEq)]
pub enum Effects {
    /// Those that lower the residual on held-out data.
    Auto,
    /// None: geometry only.
    None,
    /// Exactly these.
    List(Vec<Effect>),
}

/// A robot is written only when its predicted uncertainty over the joint space is under this
/// share of what the priors say of the nominal robot. Near the prior the data have told little,
/// and the fitted robot is as likely as not to be further from the truth than the nominal one
/// (an ISO 230-4 circle on the twin: predicted 2.3-3.8 mm against the priors' 3.9 mm, and 5 of
/// 25 robots written worse than nominal, up to 4.2 mm against 0.43 mm); at half the prior
/// uncertainty the variance is cut four-fold.
const WRITE_SHARE: f64 = 0.5;

/// Linear thermal expansion of structural steel (1/K), for sizing a logged temperature change.
const STEEL_EXPANSION: f64 = 11.5e-6;

/// The bar's zero: the reading minus the ball-centre distance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LengthOffset {
    /// Known (m): 0 for a bar that reads the ball-centre distance.
    Known(f64),
    /// Unknown: estimated per run (a draw-wire, a bar zeroed anywhere).
    Free,
}

#[derive(Clone, Debug)]
pub struct CalibrateOptions {
    pub effects: Effects,
    /// Hold each run's fixture at its given position (else it is estimated where the data
    /// determine it, the given position a prior).
    pub fixture_known: bool,
    /// Hold the tool point (MAP) at its given position (else estimated likewise).
    pub tool_known: bool,
    pub length_offset: LengthOffset,
    /// The standard uncertainty of a length (m) and an angle (rad) of the robot before
    /// calibration: the scale that makes parameters comparable, the yardstick of
    /// "determined", and the Type B uncertainty a parameter held at nominal keeps.
    pub prior_length: f64,
    pub prior_angle: f64,
    /// The standard uncertainty of the given set-up (m): the fixture, the tool point (MAP)
    /// and a given length zero.
    pub prior_setup: f64,
    /// A parameter is determined when the data bring its standard uncertainty to at most
    /// prior / κ.
    pub kappa: f64,
    /// Steps (a moved fixture, a changed length zero) split off at most, per run.
    pub max_steps: usize,
    /// Random joint poses of the workspace prediction, and their seed.
    pub workspace_poses: usize,
    pub seed: u64,
}

pub const DEFAULT_PRIOR_MM: f64 = 1.0;
pub const DEFAULT_PRIOR_DEG: f64 = 0.05;
/// The given fixture, tool point and length zero: like the robot's lengths unless told (a
/// draw-wire's anchor and attachment point may be tens of millimetres off: `--prior 1,0.05,100`).
/// It is also the yardstick of "determined": a tool point known to a millimetre only is not.
pub const DEFAULT_PRIOR_SETUP_MM: f64 = 1.0;
pub const DEFAULT_KAPPA: f64 = 3.0;
pub const WORKSPACE_POSES: usize = 2000;
/// Poses of the measured region the prediction is evaluated on (evenly spaced rows).
const REGION_POSES: usize = 2000;
/// Fewest rows a campaign must have in all (one run may have fewer when the others carry the
/// robot).
pub const MIN_ROWS: usize = N_PARAMS + 2;
/// Held-out blocks of the validation.
const FOLDS: usize = 8;
/// Up to this many readings, the model-error factor holds out one reading at a time.
const LOO_ROWS: usize = 200;
/// A row is an outlier when it leaves the median of its neighbours by more than this many
/// robust standard deviations.
const OUTLIER_SIGMAS: f64 = 8.0;
/// A determined parameter that moved by more than this many prior sigmas is flagged.
const FLAG_SIGMAS: f64 = 3.0;

impl Default for CalibrateOptions {
    fn default() -> Self {
        CalibrateOptions {
            effects: Effects::Auto,
            fixture_known: false,
            tool_known: false,
            length_offset: LengthOffset::Known(0.0),
            prior_length: DEFAULT_PRIOR_MM * MM,
            prior_angle: DEFAULT_PRIOR_DEG * DEG,
            prior_setup: DEFAULT_PRIOR_SETUP_MM * MM,
            kappa: DEFAULT_KAPPA,
            max_steps: 12,
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
    /// The estimated fixture position (mm; the run's first segment), in the calibrated
    /// robot's base frame; a coordinate the data do not determine keeps the given value.
    pub fixture_fitted_mm: Option<[f64; 3]>,
    /// Its standard uncertainty per coordinate (mm); null for a coordinate not determined.
    pub fixture_std_mm: Option<[Option<f64>; 3]>,
    /// How far the estimated fixture is from the given one (mm).
    pub fixture_moved_mm: Option<f64>,
    /// The run's length zero (mm): the reading minus the ball-centre distance (first
    /// segment); the given value unless `--length-offset free`.
    pub length_offset_mm: f64,
    /// Its standard uncertainty (mm); null when given.
    pub length_offset_std_mm: Option<f64>,
    /// `continuous`, `static` (one reading per pose, no times) or `static, timed`.
    pub form: &'static str,
    /// Rows used (outliers dropped).
    pub rows_used: usize,
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
    /// Type A: the determined parameters' covariance from the residual (model error
    /// included, see `model_error_factor`).
    pub from_noise: Component,
    /// Type B: the parameters held at nominal, each with its prior uncertainty, including
    /// how much of them the determined ones absorb.
    pub from_held: Component,
    /// What the data cannot say about an effect's form: the geometry's extra variance were a
    /// cyclic error fitted with harmonic orders 1..H to take one or two orders more (which
    /// the data do not reject): a bound on the error of the fitted form.
    pub from_effect_model: Component,
    /// What the priors say of the nominal robot: every parameter of the robot (and the tool
    /// point) off by its prior, after registration, RMS over the joint space. The calibrated
    /// robot must predict better than this to be written.
    pub nominal_workspace_rms: f64,
    /// The variance factor Type A carries beyond the white-noise one: the larger of the
    /// residual's integrated autocorrelation time and the held-out residual's mean square
    /// over the one noise alone gives held out (what the held-out data say about model
    /// error; only blocks whose complement determines the fit count, and up to 200 readings
    /// they are single readings).
    pub model_error_factor: f64,
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
    pub setup_mm: f64,
    pub kappa: f64,
}

/// The tool point (MAP, flange frame): given, estimated, its uncertainty, how far it moved.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct ToolReport {
    pub given_mm: [f64; 3],
    pub fitted_mm: [f64; 3],
    /// Null per coordinate not determined (held at the given value).
    pub std_mm: [Option<f64>; 3],
    pub moved_mm: f64,
}

/// A run split at a detected step: one entry per segment of a split run.
#[derive(Clone, Debug, Serialize)]
pub struct SegmentReport {
    /// 1-based.
    pub run: usize,
    /// The run file's data rows, 1-based, inclusive.
    pub from_row: usize,
    pub to_row: usize,
    /// Times of those rows (null for a run without times).
    pub t_from_s: Option<f64>,
    pub t_to_s: Option<f64>,
    /// What starts the segment: `run start`, `fixture moved`, `length zero changed`.
    pub cause: &'static str,
    pub fixture_fitted_mm: [f64; 3],
    pub length_offset_mm: f64,
}

/// A row dropped as an outlier.
#[derive(Clone, Debug, Serialize)]
pub struct OutlierReport {
    pub run: usize,
    /// The run file's data row, 1-based.
    pub row: usize,
    pub t_s: Option<f64>,
    /// Measured − model at the calibrated estimate (µm).
    pub residual_um: f64,
}

/// An effect considered, with the held-out RMS of the model with it.
#[derive(Clone, Debug, Serialize)]
pub struct CandidateReport {
    pub effect: &'static str,
    pub joint: Option<usize>,
    pub heldout_rms_um: f64,
    pub adopted: bool,
    pub form: String,
}

/// Held-out residual RMS (µm) of the nominal robot and of the calibrated one.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct HeldOut {
    pub nominal: f64,
    pub calibrated: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct Validation {
    pub heldout_rms_um: HeldOut,
    /// How the data were split.
    pub split: String,
    /// Rows scored (outliers excluded).
    pub rows: usize,
}

/// The `edbbgen.calibrate/1` report (DESIGN.md); keys after `predicted_position_std_um` are
/// additions.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub runs: Vec<RunReport>,
    pub determined: Vec<String>,
    pub undetermined: Vec<Undetermined>,
    /// Deviations from nominal (the set-up: from the given values) of the determined
    /// parameters: {"a2": {"value", "std"}}, mm/deg.
    pub params: serde_json::Map<String, serde_json::Value>,
    pub effects: Vec<EffectReport>,
    /// The bar noise: the high-frequency part of the final residual (its second differences).
    pub noise_um: f64,
    pub rms_before_um: f64,
    pub rms_after_um: f64,
    pub predicted_position_std_um: Predicted,
    /// True when the calibrated robot may be written: some robot parameter is determined and
    /// the held-out validation is better than nominal.
    pub calibrated: bool,
    /// Why (not), in one line, with what to try.
    pub verdict: String,
    /// How the effects were chosen: "auto", "none" or "list".
    pub effects_mode: &'static str,
    /// Parameters held at their given values by assumption (`--fixture-known`, a given
    /// length zero).
    pub held: Vec<String>,
    /// The residual's standard deviation per row (rᵀWr / (n − p)), which the uncertainties
    /// use, its lag-1 autocorrelation, and the variance inflation for its correlation (the
    /// integrated autocorrelation time).
    pub residual_sigma_um: f64,
    pub residual_lag1: f64,
    pub noise_inflation: f64,
    /// Structure clearly above the noise is left in the residual: a missing effect.
    pub residual_structure: bool,
    pub prior: Prior,
    pub rows: usize,
    pub warnings: Vec<String>,
    pub tool: ToolReport,
    /// The length zero (mm) when every run shares one (a given value, or one run's estimate);
    /// null otherwise (see `runs`).
    pub length_offset_mm: Option<f64>,
    pub segments: Vec<SegmentReport>,
    pub outliers: Vec<OutlierReport>,
    pub candidates: Vec<CandidateReport>,
    pub validation: Validation,
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
    /// Time of every row (each run from its own start; the row order for untimed runs).
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
/// and length zeros do not move the MAP.
fn shared_columns(free: &[Param]) -> Vec<(usize, usize)> {
    free.iter()
        .enumerate()
        .filter_map(|(a, q)| match q {
            Param::Shared(i) => Some((a, *i)),
            _ => None,
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
    if q.is_setup() {
        opts.prior_setup
    } else if q.is_angle() {
        opts.prior_angle
    } else {
        opts.prior_length
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

/// The value a parameter the data do not determine is held at: nominal (the given value) for
/// the robot and a run's own set-up; a segment's fixture or zero keeps its run's first one.
fn held_value(problem: &Problem, nominal: &Estimate, est: &Estimate, q: Param) -> f64 {
    match q {
        Param::Fixture { group, axis } if !problem.fix_groups[group].given => {
            est.fixtures[problem.fix_groups[group].run][axis]
        }
        Param::Offset { group } if !problem.off_groups[group].given => {
            est.offsets[problem.off_groups[group].run]
        }
        _ => nominal.get(q),
    }
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
    let total: usize = runs.iter().map(|r| r.measured.len()).sum();
    if total < MIN_ROWS {
        return Err(CalibrateError::Data(if runs.len() == 1 {
            format!(
                "run 1 ({}): {total} rows, at least {MIN_ROWS} are needed",
                labels.first().map_or("", |s| s.as_str())
            )
        } else {
            format!(
                "the campaign has {total} rows in all, at least {MIN_ROWS} are needed (one run may be short when the others carry the robot)"
            )
        }));
    }
    let given_offset = match opts.length_offset {
        LengthOffset::Known(v) => v,
        LengthOffset::Free => 0.0,
    };
    let mut problem = Problem::new(model, runs)
        .with_masses(&robot.masses)
        .with_offset(given_offset);

    if let Effects::List(v) = &opts.effects {
        for e in v {
            if *e == Effect::ThermalDrift && !problem.timed() && !problem.has_temperature() {
                return Err(CalibrateError::Data(
                    "--effects thermal_drift: a run has no times (the static form, one reading per pose) and no temp_c column: no time-dependent effect can be fitted to it".into(),
                ));
            }
            if *e == Effect::ServoLag && !problem.moving() {
                return Err(CalibrateError::Data(
                    "--effects servo_lag: no run was recorded in motion (static readings have no velocities)".into(),
                ));
            }
        }
    }
    let known = Known {
        fixture: opts.fixture_known,
        map: opts.tool_known,
        offset: matches!(opts.length_offset, LengthOffset::Known(_)),
    };
    let nominal = Estimate::nominal(&problem);
    let nruns = problem.runs();
    let mut warnings = Vec::new();

    // Step 1: the set-up from a start that needs none, the robot held nominal.
    let mut est = nominal.clone();
    let (_, at_given) = structural(&problem, &known, &est);
    let setup: Vec<Param> = at_given.iter().copied().filter(Param::is_setup).collect();
    start::setup(&problem, &mut est, &setup);
    // Which parameters the poses separate, judged where the set-up really is.
    let (_, structural_free) = structural(&problem, &known, &est);

    // Steps 2-3: the robust geometric fit, then effects and steps on held-out data.
    let mut free = structural_free.clone();
    let mut fitted = fit::refit(&problem, &mut est, &free);
    for _ in 0..3 {
        if !reweight(&mut problem, &fitted.residual) {
            break;
        }
        fitted = fit::refit(&problem, &mut est, &free);
    }
    let (effects_mode, max_effects) = match &opts.effects {
        Effects::Auto => ("auto", 3),
        Effects::None => ("none", 0),
        Effects::List(v) => {
            for e in v {
                est.add_effect(*e, list_basis(*e, &problem), 0.5 * problem.span());
            }
            fit::refit(&problem, &mut est, &free);
            ("list", 0)
        }
    };
    let sel_opts = DiagnoseOptions {
        folds: FOLDS,
        max_effects,
        masses: robot.masses.clone(),
        max_steps: opts.max_steps * nruns,
        min_explained: 0.3,
    };
    let sel = diagnose::select(&mut problem, &free, est, &sel_opts);
    if max_effects > 0 && sel.diagnosis.report.unexplained {
        warnings.push(
            "structure remains that no effect of the library explains; the geometry may absorb part of it (see `edbbgen diagnose`)".to_string(),
        );
    }
    let mut est = sel.estimate.clone();
    free = sel.free.clone();
    // The segments opened at steps start from their run's given set-up.
    let nominal = Estimate::nominal(&problem);
    fitted = sel.fitted;
    if reweight(&mut problem, &fitted.residual) {
        fitted = fit::refit(&problem, &mut est, &free);
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
            let v = held_value(&problem, &nominal, &est, *q);
            est.set(*q, v);
        }
        weak.extend(dropped);
        free = kept;
        fitted = fit::refit(&problem, &mut est, &free);
    }
    let (sigma, rho, inflate) = noise;
    let kept_rows = problem.kept().max(1);

    // Step 5: held out, block by block: the calibrated model against the nominal robot with
    // the same set-up fitted.
    let folds = FOLDS.min(kept_rows / 8).max(2);
    let cols = model_cols(&est, &free);
    let all: Vec<usize> = (0..cols.len()).collect();
    let st = accumulate(&problem, &est, &cols, folds);
    let cv_cal = score(&st, &all).3;
    let heldout_cal = (cv_cal / kept_rows as f64).sqrt();
    let heldout_nom = {
        let mut e = est.clone();
        e.p[crate::model::ALPHA..MAP].copy_from_slice(&nominal.p[crate::model::ALPHA..MAP]);
        e.effects.clear();
        let f: Vec<Param> = free.iter().copied().filter(Param::is_setup).collect();
        fit::refit(&problem, &mut e, &f);
        let c = model_cols(&e, &f);
        let s = accumulate(&problem, &e, &c, folds);
        let sel: Vec<usize> = (0..c.len()).collect();
        (score(&s, &sel).3 / kept_rows as f64).sqrt()
    };

    // Step 6: uncertainty. Type A from the residual, with what the held-out residual says
    // about model error: its mean square over what the noise alone gives held out (the
    // noise plus the variance of predicting a block from the others, which on a few static
    // readings is no model error).
    // Only folds whose complement determines the whole fit count: on a few dozen readings
    // with nearly as many unknowns (a stop-and-measure run's plateau means) blocks of an
    // eighth leave directions undetermined, so those are held out one reading at a time.
    let model_factor = {
        let loo;
        let st_m = if kept_rows <= LOO_ROWS {
            loo = accumulate(&problem, &est, &cols, problem.rows());
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
    let factor = inflate.max(model_factor);
    let sigma_eff = sigma * factor.sqrt();
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
    let effect_reports = effects_report(&est, &var[g..]);
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
    let shared = shared_columns(&free);
    let idx: Vec<usize> = shared.iter().map(|s| s.1).collect();
    let cov_a = DMatrix::from_fn(shared.len(), shared.len(), |a, b| {
        cov[(shared[a].0, shared[b].0)]
    });
    let w_a = predict::selection(&idx);
    // Type B: every parameter held at nominal (not by assumption) keeps its prior; through
    // the fit the determined ones absorb K = N_aa⁻¹ N_ah of it, so the MAP moves by
    // (e_h − Σ_d e_d K_dh) per unit of held deviation.
    let (status, _) = structural(&problem, &known, &est);
    let held_params: Vec<Param> = status
        .iter()
        .filter(|(q, st)| !free.contains(q) && *st != Status::Known)
        .map(|(q, _)| *q)
        .collect();
    let (w_b, cov_b) = held_map(&problem, &est, &free, &held_params, opts);
    let a_region = predict::position_std(model, &calibrated, &region, &w_a, &cov_a);
    let a_space = predict::position_std(model, &calibrated, &space, &w_a, &cov_a);
    let b_region = predict::position_std(model, &calibrated, &region, &w_b, &cov_b);
    let b_space = predict::position_std(model, &calibrated, &space, &w_b, &cov_b);
    let [m_region, m_space] =
        effect_model_spread(&problem, &est, &fitted, sigma_eff, &[&region, &space]);
    let combine = |a: &[f64], b: &[f64], m: &[f64]| -> Vec<f64> {
        a.iter()
            .zip(b)
            .zip(m)
            .map(|((x, y), z)| x.hypot(*y).hypot(*z) * 1e6)
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
        nominal_workspace_rms: round(nominal_prior_rms * 1e6, 3),
        model_error_factor: round(factor, 3),
    };

    // An effect the data cannot tell from the geometry makes the geometry uncertain: say which.
    if let Some(w) = confounding(&fitted, &free, &est, sigma_eff, model, &calibrated, &space) {
        warnings.push(w);
    }

    // Residuals, per run.
    let residual_nominal = problem.residual(&nominal);
    let residual = fitted.residual.clone();
    let live: Vec<f64> = residual
        .iter()
        .zip(&problem.weight)
        .filter(|(_, w)| **w > 0.0)
        .map(|(r, _)| *r)
        .collect();
    let noise_hf = fit::noise_estimate(&live);
    let rms_after = fit::rms(&live);
    // Structure above the noise: the residual clearly larger than its high-frequency part, or
    // a lag-1 correlation white noise of this length would not show (5 standard errors).
    let rho_limit = (5.0 / (kept_rows as f64).sqrt()).max(0.1);
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
    // A uniform expansion is a scale the geometry absorbs: a thermal drift the model leaves
    // out need not show in the residual. The temperature log says it is there all the same.
    let thermal_fitted = est.effects.iter().any(|t| t.effect == Effect::ThermalDrift);
    if let (false, Some(dt)) = (thermal_fitted, problem.temperature_change()) {
        let reach = region
            .iter()
            .map(|q| model.map_position(&calibrated, q).norm())
            .fold(0.0f64, f64::max);
        let growth = STEEL_EXPANSION * dt * reach;
        if growth > noise_hf {
            let hint = match opts.effects {
                Effects::Auto => "",
                _ => "; fit the effects with --effects auto",
            };
            warnings.push(format!(
                "the logged temperature changed by {} K during the runs: about {} um of thermal growth at the MAP's {} mm reach (steel, {} per K), which the model leaves to the geometry{hint}",
                fmt_fixed(dt, 2),
                fmt_fixed(growth * 1e6, 1),
                fmt_fixed(reach * 1e3, 0),
                STEEL_EXPANSION
            ));
        }
    }
    if opts.fixture_known {
        if let Some(w) = fixture_check(&problem, &est, &free) {
            warnings.push(w);
        }
    }
    // A parameter that moved by several prior sigmas: the prior (or the given value) was off.
    // A segment's own fixture or zero is a step (reported as one); a free length zero has no
    // given value.
    for q in &free {
        let flagged = match *q {
            Param::Fixture { group, .. } => problem.fix_groups[group].given,
            Param::Offset { group } => problem.off_groups[group].given && known.offset,
            Param::Shared(_) => true,
        };
        let dev = est.get(*q) - nominal.get(*q);
        let p = prior(opts, *q);
        if flagged && dev.abs() > FLAG_SIGMAS * p {
            let (u, unit) = if q.is_angle() {
                (DEG, "deg")
            } else {
                (MM, "mm")
            };
            let check = match q {
                Param::Shared(i) if crate::model::is_map(*i) => "check --tool",
                Param::Fixture { .. } => "check --fixture",
                Param::Offset { .. } => "check the bar's zero (--length-offset)",
                _ => "check the robot file, or widen --prior if such deviations are expected",
            };
            warnings.push(format!(
                "{} moved by {} {unit} from its {} value, more than {} prior sigmas ({} {unit}): {check}",
                problem.param_name(*q),
                fmt_fixed(dev / u, 4),
                if q.is_setup() { "given" } else { "nominal" },
                fmt_fixed(FLAG_SIGMAS, 0),
                fmt_fixed(p / u, 4)
            ));
        }
    }

    let std_of = |q: Param| -> Option<f64> {
        free.iter()
            .position(|x| *x == q)
            .map(|a| round(var[a].max(0.0).sqrt() / MM, 6))
    };
    let mut run_reports = Vec::with_capacity(nruns);
    for (r, range) in problem.ranges.iter().enumerate() {
        let fixture_fitted = free
            .iter()
            .any(|q| matches!(q, Param::Fixture { group, .. } if *group == r));
        let kept_r: Vec<usize> = range.clone().filter(|&k| problem.weight[k] > 0.0).collect();
        let rms_kept = |v: &[f64]| -> f64 {
            (kept_r.iter().map(|&k| v[k] * v[k]).sum::<f64>() / kept_r.len().max(1) as f64).sqrt()
        };
        let fixture_mm: [f64; 3] = problem.fixtures[r].map(|v| round(v / MM, 6)).into();
        run_reports.push(RunReport {
            measured: labels.get(r).cloned().unwrap_or_default(),
            fixture_mm,
            rows: range.len(),
            rms_before_um: round(rms_kept(&residual_nominal) * 1e6, 3),
            rms_after_um: round(rms_kept(&residual) * 1e6, 3),
            fixture_fitted_mm: fixture_fitted
                .then(|| est.fixtures[r].map(|v| round(v / MM, 6)).into()),
            fixture_std_mm: fixture_fitted
                .then(|| [0, 1, 2].map(|axis| std_of(Param::Fixture { group: r, axis }))),
            fixture_moved_mm: fixture_fitted
                .then(|| round((est.fixtures[r] - problem.fixtures[r]).norm() / MM, 6)),
            length_offset_mm: round(est.offsets[r] / MM, 6),
            length_offset_std_mm: std_of(Param::Offset { group: r }),
            form: problem.forms[r].name(),
            rows_used: kept_r.len(),
        });
    }

    let mut undetermined = Vec::new();
    let mut held = Vec::new();
    for (q, st) in &status {
        if free.contains(q) {
            continue;
        }
        let name = problem.param_name(*q);
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
                Some((_, sd)) if *sd < 1e3 * prior(opts, *q) => {
                    let (u, name) = unit(q);
                    format!(
                        "not determined by these data: its standard uncertainty would be {} {name}, more than the prior {} {name} / {}",
                        fmt_fixed(sd / u, 4),
                        fmt_fixed(prior(opts, *q) / u, 4),
                        fmt_fixed(opts.kappa, 1)
                    )
                }
                Some(_) => {
                    "not determined by these data: they do not constrain it (its uncertainty would exceed a thousand priors)".to_string()
                }
                None => "not determined by these data".to_string(),
            },
        };
        undetermined.push(Undetermined { param: name, why });
    }

    // The segments of every split run.
    let mut segments = Vec::new();
    for (r, range) in problem.ranges.iter().enumerate() {
        let mut cuts: Vec<usize> = problem
            .fix_groups
            .iter()
            .chain(&problem.off_groups)
            .filter(|g| g.run == r && !g.given && !g.rows.is_empty())
            .map(|g| g.rows.start)
            .collect();
        if cuts.is_empty() {
            continue;
        }
        cuts.push(range.start);
        cuts.push(range.end);
        cuts.sort_unstable();
        cuts.dedup();
        let timed = problem.forms[r].timed();
        for w in cuts.windows(2) {
            let (a, b) = (w[0], w[1]);
            if a >= b {
                continue;
            }
            let starts =
                |groups: &[fit::Group]| groups.iter().any(|g| g.rows.start == a && !g.given);
            let cause = match (
                a == range.start,
                starts(&problem.fix_groups),
                starts(&problem.off_groups),
            ) {
                (true, _, _) => "run start",
                (false, true, true) => "fixture moved and length zero changed",
                (false, true, false) => "fixture moved",
                _ => "length zero changed",
            };
            segments.push(SegmentReport {
                run: r + 1,
                from_row: a - range.start + 1,
                to_row: b - range.start,
                t_from_s: timed.then(|| round(problem.m.t[a], 3)),
                t_to_s: timed.then(|| round(problem.m.t[b - 1], 3)),
                cause,
                fixture_fitted_mm: est.fixtures[problem.fixture_group_of(a)]
                    .map(|v| round(v / MM, 6))
                    .into(),
                length_offset_mm: round(est.offsets[problem.offset_group_of(a)] / MM, 6),
            });
        }
    }
    let outliers: Vec<OutlierReport> = (0..problem.rows())
        .filter(|&k| problem.weight[k] <= 0.0 && problem.base_weight[k] > 0.0)
        .map(|k| {
            let r = problem.run_of(k);
            OutlierReport {
                run: r + 1,
                row: k - problem.ranges[r].start + 1,
                t_s: problem.forms[r].timed().then(|| round(problem.m.t[k], 3)),
                residual_um: round(residual[k] * 1e6, 3),
            }
        })
        .collect();
    let mut candidates: Vec<CandidateReport> = sel
        .candidates
        .iter()
        .map(|c| CandidateReport {
            effect: c.effect.name(),
            joint: c.effect.joint(),
            heldout_rms_um: round(c.heldout_rms * 1e6, 3),
            adopted: c.adopted && est.effects.iter().any(|t| t.effect == c.effect)
                || c.effect == Effect::Geometric,
            form: if c.effect == Effect::Geometric {
                "geometry".into()
            } else {
                diagnose::form_name(c.effect, c.basis)
            },
        })
        .collect();
    if let Effects::List(v) = &opts.effects {
        for e in v {
            let b = est
                .effects
                .iter()
                .find(|t| t.effect == *e)
                .map_or(Basis::Standard, |t| t.basis);
            candidates.push(CandidateReport {
                effect: e.name(),
                joint: e.joint(),
                heldout_rms_um: round(heldout_cal * 1e6, 3),
                adopted: true,
                form: diagnose::form_name(*e, b),
            });
        }
    }

    // The verdict: something of the robot determined, and better than nominal held out.
    let robot_determined = free.iter().any(|q| !q.is_setup());
    let (is_calibrated, verdict) = if !robot_determined {
        let closest = weak
            .iter()
            .filter(|(q, _)| !q.is_setup())
            .min_by(|a, b| (a.1 / prior(opts, a.0)).total_cmp(&(b.1 / prior(opts, b.0))));
        let detail = match closest {
            Some((q, sd)) if sd.is_finite() && *sd < 1e3 * prior(opts, *q) => format!(
                " (the best seen, {}, would have {} prior sigmas of uncertainty)",
                problem.param_name(*q),
                fmt_fixed(sd / prior(opts, *q), 2)
            ),
            _ => String::new(),
        };
        (
            false,
            format!(
                "not calibrated: no parameter of the robot is determined by these data{detail}; measure more poses over a wider range of every joint, or check the set-up (--tool, --fixture, --length-offset)"
            ),
        )
    } else if heldout_cal >= heldout_nom {
        let effects_hint = match (&opts.effects, residual_structure) {
            (Effects::Auto, _) | (_, false) => "",
            _ => ", fit the effects (--effects auto)",
        };
        (
            false,
            format!(
                "not calibrated: held out, the calibrated robot predicts the readings no better than the nominal one ({} um against {} um RMS); the data show no deviation the geometry explains: check the set-up (--tool, --fixture, --length-offset){effects_hint} or measure over a wider range",
                fmt_fixed(heldout_cal * 1e6, 3),
                fmt_fixed(heldout_nom * 1e6, 3)
            ),
        )
    } else if space_spread.rms >= WRITE_SHARE * nominal_prior_rms * 1e6 {
        (
            false,
            format!(
                "not calibrated: its predicted position uncertainty over the joint space ({} um RMS, mostly from the parameters these data cannot determine) is not under half of what the priors say of the nominal robot ({} um); measure over a wider range of every joint",
                fmt_fixed(space_spread.rms, 2),
                fmt_fixed(nominal_prior_rms * 1e6, 2)
            ),
        )
    } else {
        (
            true,
            format!(
                "calibrated: held out, the calibrated robot predicts the readings to {} um RMS against {} um for the nominal one",
                fmt_fixed(heldout_cal * 1e6, 3),
                fmt_fixed(heldout_nom * 1e6, 3)
            ),
        )
    };
    let tool_std = [0, 1, 2].map(|a| std_of(Param::Shared(MAP + a)));
    let map_given = Vector3::new(nominal.p[MAP], nominal.p[MAP + 1], nominal.p[MAP + 2]);
    let map_fitted = Vector3::new(est.p[MAP], est.p[MAP + 1], est.p[MAP + 2]);
    let tool = ToolReport {
        given_mm: map_given.map(|v| round(v / MM, 6)).into(),
        fitted_mm: map_fitted.map(|v| round(v / MM, 6)).into(),
        std_mm: tool_std,
        moved_mm: round((map_fitted - map_given).norm() / MM, 6),
    };
    let shared_offset = (nruns == 1 || matches!(opts.length_offset, LengthOffset::Known(_)))
        .then(|| round(est.offsets[0] / MM, 6));

    let report = Report {
        schema: "edbbgen.calibrate/1",
        runs: run_reports,
        determined: free.iter().map(|q| problem.param_name(*q)).collect(),
        undetermined,
        params,
        effects: effect_reports,
        noise_um: round(noise_hf * 1e6, 3),
        rms_before_um: round(fit::kept_rms(&residual_nominal, &problem.weight) * 1e6, 3),
        rms_after_um: round(rms_after * 1e6, 3),
        predicted_position_std_um: predicted,
        calibrated: is_calibrated,
        verdict,
        effects_mode,
        held,
        residual_sigma_um: round(sigma * 1e6, 3),
        residual_lag1: round(rho, 4),
        noise_inflation: round(inflate, 4),
        residual_structure,
        prior: Prior {
            length_mm: opts.prior_length / MM,
            angle_deg: opts.prior_angle / DEG,
            setup_mm: opts.prior_setup / MM,
            kappa: opts.kappa,
        },
        rows: problem.rows(),
        warnings,
        tool,
        length_offset_mm: shared_offset,
        segments,
        outliers,
        candidates,
        validation: Validation {
            heldout_rms_um: HeldOut {
                nominal: round(heldout_nom * 1e6, 3),
                calibrated: round(heldout_cal * 1e6, 3),
            },
            split: format!(
                "{folds} contiguous blocks of the rows in the order taken (time order; the campaign's runs one after the other), each predicted by the model fitted to the others (linearised at the fit to all rows); nominal: the nominal robot with the set-up (tool point, fixtures, length zeros) fitted"
            ),
            rows: kept_rows,
        },
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

/// What the data cannot say about the effects' form: for every cyclic error fitted with
/// harmonic orders 1..H, the geometry's covariance with orders up to H + 1 and H + 2 as well,
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
        let h = t.basis.orders().into_iter().max().unwrap_or(0);
        let mut worst: [Vec<f64>; N] = std::array::from_fn(|i| vec![0.0; poses[i].len()]);
        for extra in 1..=2 {
            if h + extra > fit::MAX_HARMONIC {
                break;
            }
            let mut cols = base.clone();
            for o in h + 1..=h + extra {
                cols.push(fit::Col::Cyc(j, o, false));
                cols.push(fit::Col::Cyc(j, o, true));
            }
            let (n, b, _, _) = accumulate(problem, est, &cols, 1).total();
            let big = fit::inverse(&n);
            let diff = DMatrix::from_fn(shared.len(), shared.len(), |a, b| {
                let (x, y) = (shared[a].0, shared[b].0);
                (big[(x, y)] - small[(x, y)]) * sigma * sigma
            });
            // The larger model's own estimate, one Gauss-Newton step from the fitted one (at
            // which the smaller model's step is nil): how far the geometry moves were the
            // form one order richer. Without model error its square is the variance above on
            // average; a higher order the data hold but the selection left out (a joint's
            // third harmonic mimicked by the second over a short range) shows in it alone.
            let all: Vec<usize> = (0..cols.len()).collect();
            let (step, _, _) = fit::solve(&n, &b, &all);
            let shift = DMatrix::from_fn(shared.len(), shared.len(), |a, b| {
                step[shared[a].0] * step[shared[b].0]
            });
            for (i, set) in poses.iter().enumerate() {
                let v = predict::position_std(&problem.model, &p, set, &w, &diff);
                let d = predict::position_std(&problem.model, &p, set, &w, &shift);
                for ((m, x), y) in worst[i].iter_mut().zip(v).zip(d) {
                    *m = m.max(x).max(y);
                }
            }
        }
        for i in 0..N {
            for (o, x) in out[i].iter_mut().zip(&worst[i]) {
                *o = o.hypot(*x);
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

/// With the fixture held (`--fixture-known`): does estimating it explain clearly more (BIC,
/// and a tenth of the residual)? Then the given position is probably off, and the geometry
/// absorbs it.
fn fixture_check(problem: &Problem, est: &Estimate, free: &[Param]) -> Option<String> {
    let (_, with_fixture) = structural(problem, &Known::default(), est);
    let extra: Vec<Param> = with_fixture
        .iter()
        .filter(|q| matches!(q, Param::Fixture { .. }) && !free.contains(q))
        .copied()
        .collect();
    if extra.is_empty() {
        return None;
    }
    let mut cols = model_cols(est, free);
    let base = cols.len();
    cols.extend(extra.iter().map(|&q| fit::Col::Geo(q)));
    let st = accumulate(problem, est, &cols, 1);
    let sel0: Vec<usize> = (0..base).collect();
    let sel1: Vec<usize> = (0..cols.len()).collect();
    let (rss0, _, bic0, _) = score(&st, &sel0);
    let (rss1, _, bic1, _) = score(&st, &sel1);
    let n = problem.kept().max(1) as f64;
    (bic1 < bic0 - 10.0 && rss1 < 0.9 * rss0).then(|| {
        format!(
            "the fixture position looks off: estimating it lowers the residual from {} um to {} um RMS; check --fixture, or leave out --fixture-known",
            fmt_fixed((rss0 / n).sqrt() * 1e6, 3),
            fmt_fixed((rss1 / n).sqrt() * 1e6, 3)
        )
    })
}

/// The printed summary of a report (also rebuilt when a report is restated, see
/// `compensate::drift`).
pub fn summary(r: &Report) -> String {
    let forms: Vec<&str> = r.runs.iter().map(|x| x.form).collect();
    let static_only = forms.iter().all(|f| *f != "continuous");
    let mut s = format!(
        "{} run{}, {} rows{}; {} noise {} um (lag-1 autocorrelation {})\n",
        r.runs.len(),
        if r.runs.len() == 1 { "" } else { "s" },
        r.rows,
        if static_only {
            " (static readings)"
        } else {
            ""
        },
        if static_only { "reading" } else { "bar" },
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
    let t = &r.tool;
    if t.moved_mm > 0.0 {
        s += &format!(
            "tool point (MAP): {}, {}, {} mm (given {}, {}, {}; moved {} mm)\n",
            fmt_fixed(t.fitted_mm[0], 3),
            fmt_fixed(t.fitted_mm[1], 3),
            fmt_fixed(t.fitted_mm[2], 3),
            fmt_fixed(t.given_mm[0], 3),
            fmt_fixed(t.given_mm[1], 3),
            fmt_fixed(t.given_mm[2], 3),
            fmt_fixed(t.moved_mm, 3)
        );
    }
    for run in &r.runs {
        if let Some(f) = run.fixture_fitted_mm {
            s += &format!(
                "fixture of {}: {}, {}, {} mm (given {}, {}, {}; moved {} mm)\n",
                run.measured,
                fmt_fixed(f[0], 3),
                fmt_fixed(f[1], 3),
                fmt_fixed(f[2], 3),
                fmt_fixed(run.fixture_mm[0], 3),
                fmt_fixed(run.fixture_mm[1], 3),
                fmt_fixed(run.fixture_mm[2], 3),
                fmt_fixed(run.fixture_moved_mm.unwrap_or(0.0), 4)
            );
        }
        if run.length_offset_std_mm.is_some() {
            s += &format!(
                "length zero of {}: {} mm (reading minus ball-centre distance)\n",
                run.measured,
                fmt_fixed(run.length_offset_mm, 4)
            );
        }
    }
    for g in r.segments.iter().filter(|g| g.cause != "run start") {
        let when = match g.t_from_s {
            Some(t) => format!("row {} (t {} s)", g.from_row, fmt_fixed(t, 2)),
            None => format!("row {}", g.from_row),
        };
        s += &format!("step in run {} at {when}: {}\n", g.run, g.cause);
    }
    if !r.outliers.is_empty() {
        s += &format!(
            "outliers dropped: {} row{}\n",
            r.outliers.len(),
            if r.outliers.len() == 1 { "" } else { "s" }
        );
    }
    let p = &r.predicted_position_std_um;
    s += &format!(
        "predicted MAP position uncertainty (1 sigma, after rigid registration): {} um RMS where measured; {} um RMS, {} um p95 over the joint space\n",
        fmt_fixed(p.measured_region_rms, 2),
        fmt_fixed(p.workspace_rms, 2),
        fmt_fixed(p.workspace_p95, 2)
    );
    s += &format!(
        "validation (held out): {} um RMS nominal, {} um RMS calibrated\n",
        fmt_fixed(r.validation.heldout_rms_um.nominal, 3),
        fmt_fixed(r.validation.heldout_rms_um.calibrated, 3)
    );
    for w in &r.warnings {
        s += &format!("warning: {w}\n");
    }
    s += &r.verdict;
    s.push('\n');
    s
}

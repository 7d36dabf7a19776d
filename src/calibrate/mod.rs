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
//! 4. **Determined or not.** Columns scaled by their prior (1 mm, 0.05°; the set-up's 10 mm
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

pub mod delivered;
pub mod files;
pub mod header;
mod parts;
pub mod plot;
pub mod predict;
pub mod resolution;
pub mod resync;
mod steps;
mod uncertainty;

pub use steps::determined_columns;

use crate::diagnose::fit::{self, Known};
use crate::diagnose::{
    effects_report, geometry_report, EffectReport, Estimate, Param, Problem, Run,
};
use crate::model::{MeasurementModel, Params, N_PARAMS};
use crate::robot::Robot;
use crate::twin::effects::Effect;
use crate::units::{fmt_fixed, length_mm, length_um, DEG, MM};
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

impl Effects {
    /// `auto`, `none`, or a comma-separated list of library effects, `NAME[:JOINT]` (joints
    /// 1-6); the message names the item at fault.
    pub fn parse(s: &str) -> Result<Effects, String> {
        match s.trim() {
            "auto" => return Ok(Effects::Auto),
            "none" => return Ok(Effects::None),
            _ => {}
        }
        let mut list = Vec::new();
        for item in s.split(',') {
            let item = item.trim();
            let (name, joint) = match item.split_once(':') {
                Some((n, j)) => (n, Some(j)),
                None => (item, None),
            };
            let joint = |what: &str| -> Result<usize, String> {
                let j = joint
                    .ok_or_else(|| format!("{what} needs its joint, e.g. {what}:2 (joints 1-6)"))?;
                match j.trim().parse::<usize>() {
                    Ok(n @ 1..=6) => Ok(n - 1),
                    _ => Err(format!("'{item}': the joint must be a number 1-6")),
                }
            };
            let no_joint = |e: Effect| -> Result<Effect, String> {
                match item.contains(':') {
                    true => Err(format!("'{item}': {} belongs to no single joint", e.name())),
                    false => Ok(e),
                }
            };
            let e = match name {
                "cyclic_error" => Effect::CyclicError(joint("cyclic_error")?),
                "backlash" => Effect::Backlash(joint("backlash")?),
                "joint_compliance" => no_joint(Effect::JointCompliance)?,
                "thermal_drift" => no_joint(Effect::ThermalDrift)?,
                "servo_lag" => no_joint(Effect::ServoLag)?,
                _ => {
                    return Err(format!(
                        "'{item}' is not auto, none, or a list of joint_compliance, thermal_drift, cyclic_error:J, backlash:J, servo_lag"
                    ))
                }
            };
            if list.contains(&e) {
                return Err(format!("'{item}' is given twice"));
            }
            list.push(e);
        }
        Ok(Effects::List(list))
    }
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

impl LengthOffset {
    /// A length in mm (the reading minus the ball-centre distance), `free`, or nothing (0).
    pub fn parse(s: Option<&str>) -> Result<LengthOffset, String> {
        match s.map(str::trim) {
            None => Ok(LengthOffset::Known(0.0)),
            Some("free") => Ok(LengthOffset::Free),
            Some(v) => match v.parse::<f64>() {
                Ok(x) if x.is_finite() => Ok(LengthOffset::Known(x * MM)),
                _ => Err(format!("'{v}' is neither a length in mm nor 'free'")),
            },
        }
    }
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
    /// Write the adopted effects into the robot file (else the geometry only, and the
    /// prediction includes what the effects left out do over the joint space).
    pub write_effects: bool,
    /// The step the joints were logged to (rad; `Some(0.0)`: exact), for every joint; `None`:
    /// read from each run's logged values ([`resolution::detect`]).
    pub joint_resolution: Option<f64>,
    /// Random joint poses of the workspace prediction, and their seed.
    pub workspace_poses: usize,
    pub seed: u64,
    /// One reading's noise as the instrument states it (m); `None`: estimated from the data
    /// ([`crate::diagnose::noise::reading_noise`]).
    pub noise: Option<f64>,
}

pub const DEFAULT_PRIOR_MM: f64 = 1.0;
pub const DEFAULT_PRIOR_DEG: f64 = 0.05;
/// The given fixture, tool point and length zero: what a tape measure tells of a fixture's
/// place in the robot's base frame (a point inside the robot's base) and of a tool point
/// (`--prior 1,0.05,S` when the set-up is known better, e.g. measured by a tracker). The fit
/// does not depend on it (it starts from the data, [`crate::diagnose::start`]); it is the
/// yardstick of "determined" for the set-up, the Type B uncertainty of a set-up parameter the
/// data do not determine, and the scale of the "moved by more than 3 prior sigmas" warning.
pub const DEFAULT_PRIOR_SETUP_MM: f64 = 10.0;
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
            write_effects: true,
            joint_resolution: None,
            workspace_poses: WORKSPACE_POSES,
            seed: 1,
            noise: None,
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

/// Predicted 1σ MAP position uncertainty after rigid registration (µm) of the robot the written
/// files deliver: combined, and its components. With every effect in the file it is the
/// calibrated model's own; an effect left out adds what it does over the joint space.
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
    /// What the model misses on poses it was not fitted to: the held-out residual (blocks of
    /// every run in the order taken) beyond the reading noise, times √3 (a reading sees the
    /// MAP's error along the bar only); the same at every pose.
    pub from_model_error: Component,
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
    /// The calibrated model's own workspace RMS (µm), every adopted effect applied: the figure
    /// above when every effect is delivered.
    pub model_workspace_rms: f64,
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

/// The set-up fitted with the nominal geometry (a report of a robot not calibrated). When
/// `delivered`, the robot file written holds the nominal geometry with this tool point, and
/// `calibrate` exits 3 (DESIGN.md, exit codes).
#[derive(Clone, Debug, Serialize)]
pub struct SetupReport {
    pub delivered: bool,
    pub tool_mm: [f64; 3],
    /// Standard uncertainties (mm; Type A of the set-up-only fit, its residual's correlation
    /// counted); null for a coordinate not determined (held at the given value).
    pub tool_std_mm: [Option<f64>; 3],
    /// Per run, its first segment's fixture.
    pub fixtures_mm: Vec<[f64; 3]>,
    pub fixtures_std_mm: Vec<[Option<f64>; 3]>,
    pub length_offsets_mm: Vec<f64>,
    pub length_offsets_std_mm: Vec<Option<f64>>,
    /// Held out, the nominal geometry with this set-up predicts the readings to this RMS.
    pub heldout_rms_um: f64,
    /// How close the data put the true geometry to the nominal one (RMS over the joint space:
    /// the fitted deviation plus twice its predicted uncertainty); null when the data
    /// determine no parameter of the robot.
    pub geometry_within_um: Option<f64>,
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
    /// Each adopted effect's size over the joint space, whether the written files carry it,
    /// and the prediction without it.
    pub effect_sizes: Vec<delivered::EffectSize>,
    /// What the written robot files carry: `geometry and effects` or `geometry only`, and
    /// the effects they leave out (with why).
    pub delivered: Delivered,
    /// Each joint's range over the rows the fit kept, [min, max] (deg): where the data reached;
    /// beyond it an effect's form is extrapolated.
    pub measured_joint_ranges_deg: [[f64; 2]; 6],
    /// A robot not calibrated: the set-up fitted with the nominal geometry.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub setup: Option<SetupReport>,
    /// Readings weighted by their own uncertainty (joints logged coarsely).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reading_weights: Option<ReadingWeights>,
    /// Where `noise_um` comes from (0 there when unknown).
    pub noise_source: crate::diagnose::noise::NoiseSource,
    /// For a noise from neighbouring or repeated poses: how close they were (deg).
    pub noise_within_deg: f64,
}

/// How the readings were weighted: the joints' logged resolution and the reading
/// uncertainties it makes with the instrument's noise.
#[derive(Clone, Debug, Serialize)]
pub struct ReadingWeights {
    /// Per run, per joint (deg; 0: none found or given).
    pub joint_resolution_deg: Vec<[f64; 6]>,
    /// The instrument's noise estimated for runs that state none (µm).
    pub instrument_noise_um: Option<f64>,
    /// The rounding's share of a reading, RMS and largest over the readings (µm).
    pub rounding_rms_um: f64,
    pub rounding_max_um: f64,
}

/// What the written files deliver.
#[derive(Clone, Debug, Serialize)]
pub struct Delivered {
    pub content: &'static str,
    pub not_delivered: Vec<String>,
    /// What a thermal drift in the file is referred to.
    pub thermal_reference: String,
    /// Joint zeros the file holds differently from `params`: a cyclic error's harmonics are
    /// fitted about their mean over the joint's measured range and written about zero (their
    /// mean over a turn), so the file's θ holds that constant (deg; the same robot).
    pub zero_shifts: Vec<ZeroShift>,
}

/// A joint zero the file holds with a cyclic error's constant part.
#[derive(Clone, Debug, Serialize)]
pub struct ZeroShift {
    pub param: String,
    /// The file's θ less the fit's (deg).
    pub shift_deg: f64,
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
    /// Per run: true when its `t` holds real times.
    pub timed: Vec<bool>,
    pub residual_nominal: Vec<f64>,
    pub residual: Vec<f64>,
    /// Per-pose predicted position uncertainty over the workspace (µm), for plots.
    pub workspace_std_um: Vec<f64>,
    /// The model the robot file holds: the physical geometry and the effects.
    pub file: delivered::FileModel,
    pub summary: String,
}

impl Calibration {
    /// The calibrated parameters (run 1's fixture) as the robot file holds them: the physical
    /// geometry (a cyclic error's mean over a turn is zero, its constant part in θ).
    pub fn params(&self) -> Params {
        self.file.params
    }

    /// A robot file is to be written: calibrated, or the set-up fitted with the nominal
    /// geometry.
    pub fn writes_robot(&self) -> bool {
        self.report.calibrated || self.setup_only()
    }

    /// Not calibrated, but the set-up found is delivered with the nominal geometry.
    pub fn setup_only(&self) -> bool {
        !self.report.calibrated && self.report.setup.as_ref().is_some_and(|s| s.delivered)
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

/// Calibrates the robot of `model` on a campaign of runs (`labels` name them in the report).
///
/// Where the joints were logged coarsely enough that rounding them makes some readings worth
/// less than others, the campaign is fitted again with each reading weighted by its own
/// uncertainty: the instrument's noise (a run's stated `std`, or what the first fit's residual
/// leaves beyond the rounding) combined with the rounding's share at its pose
/// ([`resolution`]).
pub fn run(
    model: &MeasurementModel,
    robot: &Robot,
    runs: &[Run],
    labels: &[String],
    opts: &CalibrateOptions,
) -> Result<Calibration, CalibrateError> {
    let first = run_once(model, robot, runs, labels, opts)?;
    let Some((weighted, how)) = resolution::reweighted(model, runs, &first, opts.joint_resolution)
    else {
        return Ok(first);
    };
    let again: Vec<Run> = weighted
        .iter()
        .zip(runs)
        .map(|(m, r)| Run {
            measured: m,
            fixture: r.fixture,
        })
        .collect();
    let mut cal = run_once(model, robot, &again, labels, opts)?;
    cal.report.reading_weights = Some(how);
    cal.summary = summary(&cal.report);
    Ok(cal)
}

fn run_once(
    model: &MeasurementModel,
    robot: &Robot,
    runs: &[Run],
    labels: &[String],
    opts: &CalibrateOptions,
) -> Result<Calibration, CalibrateError> {
    check_rows(runs, labels)?;
    let given_offset = match opts.length_offset {
        LengthOffset::Known(v) => v,
        LengthOffset::Free => 0.0,
    };
    let (lower, upper) = robot.limits();
    let mut problem = Problem::new(model, runs)
        .with_masses(&robot.masses)
        .with_joint_ranges(&std::array::from_fn(|j| (lower[j], upper[j])))
        .with_offset(given_offset);
    check_effects(&problem, opts)?;
    let known = Known {
        fixture: opts.fixture_known,
        map: opts.tool_known,
        offset: matches!(opts.length_offset, LengthOffset::Known(_)),
    };
    let fitted = steps::fit(&mut problem, robot, &known, opts);
    let held_out = steps::held_out(&problem, &fitted, opts.noise);
    let u = uncertainty::estimate(model, robot, &problem, &known, &fitted, &held_out, opts);
    Ok(assemble(
        model, robot, &problem, &known, fitted, &held_out, u, labels, opts,
    ))
}

/// The report's joint zeros as the robot file holds them: a joint with a cyclic error has its
/// harmonics' mean over the measured range moved into its zero (θ_file = θ_fit − Σ aₖ·cₖ, aₖ
/// the harmonics' means); its standard uncertainty through the covariance of θ and the
/// harmonics' coefficients.
fn physical_zeros(
    problem: &Problem,
    f: &steps::Fit,
    cov: &nalgebra::DMatrix<f64>,
    values: &mut serde_json::Map<String, serde_json::Value>,
    stds: &mut serde_json::Map<String, serde_json::Value>,
) {
    let g = f.free.len();
    let mut col = g;
    for t in &f.est.effects {
        let n = t.coef.len();
        if let Effect::CyclicError(j) = t.effect {
            let theta = Param::Shared(crate::model::THETA + j);
            if let Some(a) = f.free.iter().position(|q| *q == theta) {
                // θ_file = θ_fit − Σ_k w_k·coef_k.
                let mut w = vec![(a, 1.0)];
                let mut shift = 0.0;
                for (m, h) in t.basis.orders().into_iter().enumerate() {
                    let (ms, mc) = problem.harmonic_mean(j, h);
                    w.push((col + 2 * m, -mc));
                    w.push((col + 2 * m + 1, -ms));
                    shift += t.coef[2 * m] * mc + t.coef[2 * m + 1] * ms;
                }
                let var: f64 = w
                    .iter()
                    .flat_map(|&(x, wx)| w.iter().map(move |&(y, wy)| wx * wy * cov[(x, y)]))
                    .sum();
                let name = problem.param_name(theta);
                if let Some(v) = values.get(&name).and_then(|v| v.as_f64()) {
                    values.insert(name.clone(), round(v - shift / DEG, 6).into());
                    stds.insert(name, diagnose_sane(var.max(0.0).sqrt() / DEG));
                }
            }
        }
        col += n;
    }
}

fn diagnose_sane(v: f64) -> serde_json::Value {
    crate::diagnose::sane(crate::diagnose::round_std(v, 6))
}

/// A campaign too short to calibrate from is refused before any work.
fn check_rows(runs: &[Run], labels: &[String]) -> Result<(), CalibrateError> {
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
    Ok(())
}

/// An effect the user listed that the data cannot carry is refused.
fn check_effects(problem: &Problem, opts: &CalibrateOptions) -> Result<(), CalibrateError> {
    let Effects::List(v) = &opts.effects else {
        return Ok(());
    };
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
    Ok(())
}

/// The report and the calibration from the fit, its validation and its uncertainty.
#[allow(clippy::too_many_arguments)]
fn assemble(
    model: &MeasurementModel,
    robot: &Robot,
    problem: &Problem,
    known: &Known,
    f: steps::Fit,
    held_out: &steps::HeldOutScore,
    u: uncertainty::Uncertainty,
    labels: &[String],
    opts: &CalibrateOptions,
) -> Calibration {
    let g = f.free.len();
    let (mut values, mut stds) = geometry_report(problem, &f.est, &f.free, &u.var[..g]);
    if opts.write_effects {
        physical_zeros(problem, &f, &u.cov, &mut values, &mut stds);
    }
    let mut params = serde_json::Map::new();
    for (name, v) in &values {
        let mut e = serde_json::Map::new();
        e.insert("value".into(), v.clone());
        e.insert("std".into(), stds[name].clone());
        params.insert(name.clone(), e.into());
    }
    let effect_reports = effects_report(&f.est, &u.var[g..]);
    let mut file = delivered::file_model(problem, &f.est, &u.var[g..]);
    let (effect_sizes, predicted, space_std, delivered) =
        parts::delivered(model, robot, problem, &f, &u, &file, opts);
    if !opts.write_effects {
        // The geometry alone: with a cyclic error's constant over the measured range in the
        // joint zero, the best a table without the harmonics can hold there.
        file = delivered::FileModel {
            params: f.est.params(0),
            effects: Default::default(),
            reference: file.reference,
        };
    }
    let diag = parts::diagnostics(model, problem, known, &f, &u, opts);
    let residual_nominal = problem.residual(&f.nominal);
    let residual = f.fitted.residual.clone();
    let run_reports = parts::runs(problem, &f, &u.var, labels, &residual_nominal);
    let (undetermined, held) = parts::undetermined(problem, &f, &u.status, opts);
    let (is_calibrated, mut verdict) =
        parts::verdict(problem, &f, held_out, &u, opts, diag.structure);
    // Not calibrated: the set-up found is the result, with the nominal geometry.
    let setup = (!is_calibrated).then(|| {
        let robot_determined = f.free.iter().any(|q| !q.is_setup());
        parts::setup(model, problem, &f, held_out, &u, robot_determined)
    });
    if let Some(s) = setup.as_ref().filter(|s| s.delivered) {
        let reason = verdict.trim_start_matches("not calibrated: ");
        verdict = match s.geometry_within_um {
            Some(x) => format!(
                "geometry confirmed within {} of nominal; set-up fitted (written with the nominal geometry): {reason}",
                length_um(x)
            ),
            None => format!(
                "geometry not determined (nominal kept); set-up fitted (written with the nominal geometry): {reason}"
            ),
        };
        file = delivered::FileModel {
            params: held_out.setup.0.params(0),
            effects: Default::default(),
            reference: file.reference,
        };
    }
    let nruns = problem.runs();
    let shared_offset = (nruns == 1 || matches!(opts.length_offset, LengthOffset::Known(_)))
        .then(|| round(f.est.offsets[0] / MM, 6));
    let report = Report {
        schema: "edbbgen.calibrate/1",
        runs: run_reports,
        determined: f.free.iter().map(|q| problem.param_name(*q)).collect(),
        undetermined,
        params,
        effects: effect_reports,
        noise_um: round(diag.noise_hf * 1e6, 3),
        noise_source: diag.noise.source,
        noise_within_deg: diag.noise.within_deg,
        rms_before_um: round(fit::kept_rms(&residual_nominal, &problem.weight) * 1e6, 3),
        rms_after_um: round(diag.rms_after * 1e6, 3),
        predicted_position_std_um: predicted,
        calibrated: is_calibrated,
        verdict,
        effects_mode: f.effects_mode,
        held,
        residual_sigma_um: round(f.sigma * 1e6, 3),
        residual_lag1: round(f.rho, 4),
        noise_inflation: round(f.inflate, 4),
        residual_structure: diag.structure,
        prior: Prior {
            length_mm: opts.prior_length / MM,
            angle_deg: opts.prior_angle / DEG,
            setup_mm: opts.prior_setup / MM,
            kappa: opts.kappa,
        },
        rows: problem.rows(),
        warnings: diag.warnings,
        tool: parts::tool(&f, &u.var),
        length_offset_mm: shared_offset,
        segments: parts::segments(problem, &f.est),
        outliers: parts::outliers(problem, &residual),
        candidates: parts::candidates(&f, opts, held_out.calibrated),
        validation: Validation {
            heldout_rms_um: HeldOut {
                nominal: round(held_out.nominal * 1e6, 3),
                calibrated: round(held_out.calibrated * 1e6, 3),
            },
            split: format!(
                "{} contiguous blocks of each run's rows in the order taken, the same block of every run held out together and predicted by the model fitted to the others (linearised at the fit to all rows); nominal: the nominal robot with the set-up (MAP, fixtures, length zeros) fitted",
                held_out.folds
            ),
            rows: held_out.rows,
        },
        effect_sizes,
        delivered,
        measured_joint_ranges_deg: parts::joint_ranges(problem).map(|r| r.map(|x| round(x / DEG, 3))),
        setup,
        reading_weights: None,
    };
    let summary = summary(&report);
    Calibration {
        report,
        estimate: f.est,
        determined: f.free,
        ranges: problem.ranges.clone(),
        t: problem.m.t.clone(),
        timed: problem.forms.iter().map(|f| f.timed()).collect(),
        residual_nominal,
        residual,
        workspace_std_um: space_std,
        file,
        summary,
    }
}

/// "x, y, z" (mm), each with "± u" where determined: the uncertainty to two significant
/// digits and the value to the same place (at most 0.1 µm), else to 0.01 mm.
fn xyz_with_std(v: &[f64; 3], sd: &[Option<f64>; 3]) -> String {
    v.iter()
        .zip(sd)
        .map(|(x, u)| match u {
            Some(u) if *u > 0.0 => {
                let d = (1 - u.log10().floor() as i32).clamp(0, 4) as usize;
                format!("{} ± {}", fmt_fixed(*x, d), fmt_fixed(*u, d))
            }
            _ => fmt_fixed(*x, 2),
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// The printed summary of a report (also rebuilt when a report is restated, see
/// `compensate::drift`).
pub fn summary(r: &Report) -> String {
    let mut s = data_lines(r);
    model_lines(r, &mut s);
    setup_lines(r, &mut s);
    prediction_lines(r, &mut s);
    for w in &r.warnings {
        s += &format!("warning: {w}\n");
    }
    s += &r.verdict;
    s.push('\n');
    s
}

/// The summary's data: the runs, their rows and noise, and the RMS before and after.
fn data_lines(r: &Report) -> String {
    let forms: Vec<&str> = r.runs.iter().map(|x| x.form).collect();
    let static_only = forms.iter().all(|f| *f != "continuous");
    use crate::diagnose::noise::NoiseSource as N;
    let noise = match r.noise_source {
        N::Unknown => "unknown".to_string(),
        N::Neighbours => format!("≤ {}", length_um(r.noise_um)),
        _ => length_um(r.noise_um),
    };
    let how = match r.noise_source {
        N::Sequence | N::Unknown => String::new(),
        s => format!(", {}", s.describe(r.noise_within_deg)),
    };
    let mut s = format!(
        "{} run{}, {} rows{}; {} noise {noise} (lag-1 autocorrelation {}{how})\n",
        r.runs.len(),
        if r.runs.len() == 1 { "" } else { "s" },
        r.rows,
        if static_only {
            " (static readings)"
        } else {
            ""
        },
        if static_only { "reading" } else { "bar" },
        fmt_fixed(r.residual_lag1, 2)
    );
    s += &format!(
        "nominal model: RMS {}; calibrated: RMS {}\n",
        length_um(r.rms_before_um),
        length_um(r.rms_after_um)
    );
    s
}

/// The model fitted: the effects with their sizes, the parameters determined and held.
fn model_lines(r: &Report, s: &mut String) {
    let effects: Vec<String> = r
        .effects
        .iter()
        .map(|e| match e.joint {
            Some(j) => format!("{} (joint {j})", e.effect),
            None => e.effect.to_string(),
        })
        .collect();
    *s += &format!(
        "effects fitted with the geometry ({}): {}\n",
        r.effects_mode,
        if effects.is_empty() {
            "none".to_string()
        } else {
            effects.join(", ")
        }
    );
    for e in &r.effect_sizes {
        let name = match e.joint {
            Some(j) => format!("{} (joint {j})", e.effect),
            None => e.effect.to_string(),
        };
        let carried = match (e.delivered, e.acts_on) {
            (true, "motion") => "in the robot file; it moves no pose",
            (true, _) => "in the robot file",
            (false, _) => "NOT in the robot file",
        };
        *s += &format!(
            "  {name}: {} RMS, {} p95 over the joint space ({}); {carried}\n",
            length_um(e.workspace_rms_um),
            length_um(e.workspace_p95_um),
            e.at
        );
    }
    *s += &format!(
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
}

/// The set-up fitted with the robot: tool point, fixtures and length zeros; the steps in the
/// runs and the outliers dropped.
fn setup_lines(r: &Report, s: &mut String) {
    let t = &r.tool;
    if t.moved_mm > 0.0 {
        *s += &format!(
            "MAP: {}, {}, {} mm (given {}, {}, {}; moved {})\n",
            fmt_fixed(t.fitted_mm[0], 3),
            fmt_fixed(t.fitted_mm[1], 3),
            fmt_fixed(t.fitted_mm[2], 3),
            fmt_fixed(t.given_mm[0], 3),
            fmt_fixed(t.given_mm[1], 3),
            fmt_fixed(t.given_mm[2], 3),
            length_mm(t.moved_mm)
        );
    }
    for run in &r.runs {
        if let Some(f) = run.fixture_fitted_mm {
            *s += &format!(
                "fixture of {}: {}, {}, {} mm (given {}, {}, {}; moved {})\n",
                run.measured,
                fmt_fixed(f[0], 3),
                fmt_fixed(f[1], 3),
                fmt_fixed(f[2], 3),
                fmt_fixed(run.fixture_mm[0], 3),
                fmt_fixed(run.fixture_mm[1], 3),
                fmt_fixed(run.fixture_mm[2], 3),
                length_mm(run.fixture_moved_mm.unwrap_or(0.0))
            );
        }
        if run.length_offset_std_mm.is_some() {
            *s += &format!(
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
        *s += &format!("step in run {} at {when}: {}\n", g.run, g.cause);
    }
    if !r.outliers.is_empty() {
        *s += &format!(
            "outliers dropped: {} row{}\n",
            r.outliers.len(),
            if r.outliers.len() == 1 { "" } else { "s" }
        );
    }
}

/// What the calibration predicts and how it validated; the reading weights and the set-up
/// with the nominal geometry.
fn prediction_lines(r: &Report, s: &mut String) {
    let p = &r.predicted_position_std_um;
    *s += &format!(
        "predicted MAP position uncertainty (1 sigma, after rigid registration): {} RMS where measured; {} RMS, {} p95 over the joint space\n",
        length_um(p.measured_region_rms),
        length_um(p.workspace_rms),
        length_um(p.workspace_p95)
    );
    if r.delivered.content == "geometry only" {
        *s += &format!(
            "the robot file carries the geometry only: the prediction includes the effects left out (the model with them: {} RMS over the joint space)\n",
            length_um(p.model_workspace_rms)
        );
    }
    *s += &format!(
        "validation (held out): {} RMS nominal, {} RMS calibrated\n",
        length_um(r.validation.heldout_rms_um.nominal),
        length_um(r.validation.heldout_rms_um.calibrated)
    );
    if let Some(w) = &r.reading_weights {
        *s += &format!(
            "readings weighted by their own uncertainty: joints logged to {} deg; rounding {} RMS, up to {} per reading{}\n",
            w.joint_resolution_deg
                .first()
                .map(|g| {
                    let mut v: Vec<String> = g.iter().map(|x| format!("{x}")).collect();
                    v.dedup();
                    v.join("/")
                })
                .unwrap_or_default(),
            length_um(w.rounding_rms_um),
            length_um(w.rounding_max_um),
            match w.instrument_noise_um {
                Some(n) => format!(", instrument noise {}", length_um(n)),
                None => String::new(),
            }
        );
    }
    if let Some(set) = r.setup.as_ref().filter(|s| s.delivered) {
        *s += &format!(
            "set-up with the nominal geometry: MAP {} mm{}; held out {} RMS\n",
            xyz_with_std(&set.tool_mm, &set.tool_std_mm),
            set.fixtures_mm
                .iter()
                .zip(&set.fixtures_std_mm)
                .enumerate()
                .map(|(k, (f, sd))| format!(", fixture {} {} mm", k + 1, xyz_with_std(f, sd)))
                .collect::<String>(),
            length_um(set.heldout_rms_um)
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn effect_lists_parse_and_bad_ones_are_refused() {
        assert_eq!(Effects::parse("auto").unwrap(), Effects::Auto);
        assert_eq!(Effects::parse("none").unwrap(), Effects::None);
        assert_eq!(
            Effects::parse("cyclic_error:2, servo_lag").unwrap(),
            Effects::List(vec![Effect::CyclicError(1), Effect::ServoLag])
        );
        for bad in [
            "cyclic_error",
            "backlash:7",
            "servo_lag:2",
            "gravity",
            "servo_lag,servo_lag",
        ] {
            assert!(Effects::parse(bad).is_err(), "{bad}");
        }
    }
}

//! The fit under the diagnosis and the calibration: in = the measurement model, one or more
//! recorded runs (each with its own fixture), the free parameters and the effects of the
//! model; out = the estimate, its normal equations, residuals and covariance. No file I/O.
//!
//! Every effect of the library enters as regressors that are linear in its few parameters
//! around the current estimate (joint effects: ∂L/∂θ_j · basis; thermal drift:
//! Σ(a ∂L/∂a + d ∂L/∂d) · f(t); servo lag: −Σ ∂L/∂θ_j q̇_j). One parallel pass over the rows
//! (chunks of at most 256 rows inside contiguous blocks, summed in order: deterministic) builds
//! the normal equations of any set of columns per block, so candidate models and their blocked
//! cross-validation are solved from those sums without touching the rows again. [`refit`] is
//! Levenberg-Marquardt with the effects applied exactly: the recorded angles re-interpolated at
//! t − τ for a servo lag, a play (hysteresis) operator run along the rows for backlash, a
//! first-order lag 1 − exp(−t/τ) with its own time constant for a thermal drift.
//!
//! A campaign of runs shares the robot (DH, MAP, effects). Each run has its own fixture and
//! length zero (the bar's reading minus the ball-centre distance), and a run split at a
//! detected step has one per segment ([`Group`]): those are parameters per group
//! ([`Param::Fixture`], [`Param::Offset`]). Rows carry a weight: the reading's stated
//! uncertainty (`std_um`, a plateau's standard error) relative to the run's, times the robust
//! loss's (0 drops an outlier).

use crate::model::{self, MeasurementModel, Params, A, D, FIX, MAP, N_PARAMS, THETA};
use crate::robot::kinematics::chain_frames;
use crate::robot::PointMass;
use crate::twin::effects::{gravity_torques, play, Effect, G, MOTION_DEADBAND};
use crate::twin::measured::Form;
use crate::twin::Measured;
use nalgebra::{DMatrix, DVector, SymmetricEigen, Vector3};
use rayon::prelude::*;
use std::ops::Range;

/// One recorded run and the fixture position it was measured against (base frame, m).
#[derive(Clone, Copy, Debug)]
pub struct Run<'a> {
    pub measured: &'a Measured,
    pub fixture: Vector3<f64>,
}

/// A parameter a fit can move.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Param {
    /// A parameter of the robot shared by every run: Eq. 6 index ≥ 3 (DH, MAP).
    Shared(usize),
    /// Coordinate `axis` (0 = x) of fixture group `group` (a run, or a segment of one).
    Fixture { group: usize, axis: usize },
    /// The length zero of offset group `group`: the bar's reading minus the ball-centre
    /// distance.
    Offset { group: usize },
}

impl Param {
    /// True for angles (rad), false for lengths (m).
    pub fn is_angle(&self) -> bool {
        match *self {
            Param::Shared(i) => model::is_angle(i),
            _ => false,
        }
    }

    /// True for the parameters of the set-up rather than the robot: the fixture, the MAP (the
    /// tool ball), the length zero.
    pub fn is_setup(&self) -> bool {
        match *self {
            Param::Shared(i) => model::is_map(i),
            _ => true,
        }
    }
}

/// How an effect enters the fit.
///
/// Joint compliance has two forms: with the link masses known (the robot file's inertials) the
/// gravity torque of each joint is known and one compliance per joint remains; without, a
/// general basis (mass and first moments of every link after the joint) times each joint's
/// compliance. A cyclic error takes the harmonic orders the data support (bit h − 1 of the mask
/// for order h). A thermal drift is a first-order lag with its own time constant, or linear in
/// a logged temperature; either one scale for every link, or one per link (bit i of the mask
/// for DH row i: a link of no length has nothing to grow). A servo lag is a delay, or a delay
/// with a second-order term (a first-order servo loop lags by τ·q̇ − τ²·q̈, a pure delay by
/// τ·q̇ − τ²/2·q̈).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Basis {
    Standard,
    KnownMasses,
    Harmonics(u64),
    Lag,
    Temperature,
    LagLinks(u8),
    TemperatureLinks(u8),
    SecondOrder,
}

/// Highest harmonic order of a cyclic error the fit considers (over the joint's whole range
/// measured; over part of it [`harmonic_cap`] allows fewer).
pub const MAX_HARMONIC: usize = 6;

/// Highest harmonic order of the contiguous orders 1..H and the two richer ones the
/// prediction bounds the form's error with (`calibrate`'s effect-model spread).
pub const BOUND_HARMONIC: usize = MAX_HARMONIC + 2;

/// Highest harmonic order a cyclic error can take as a single stationary order (a gear mesh
/// or a tooth-count harmonic of a transmission: `diagnose`'s order screen), and the highest a
/// problem's harmonics are defined for.
pub const MAX_ORDER: usize = 40;

/// The highest harmonic order of a cyclic error that joint j's measured angles determine over
/// the range it can turn through (`range`, its limits in rad; `None`: the whole turn): the
/// largest H whose period 2π/H is at least the unmeasured gap G, at most [`MAX_HARMONIC`]. G is
/// the largest stretch of the range without a measured angle; a stretch at an end of a range
/// short of a turn counts twice (data on one side only).
///
/// Why: a cyclic error of orders 1..H is a trigonometric polynomial of degree H, and the
/// robot file applies it at every angle the joint takes. Between measured angles its form is
/// fixed by the data only where no oscillation can hide: a bump that is nil with its slope at
/// both edges of a gap needs a whole period of its order (1 − cos over 2π/h), one at an open
/// end half a period, hence the doubled ends. So an order whose whole period fits in the gap
/// can hold a swing there that no reading sees, and the fit, whose held-out blocks lie inside
/// the measured range too, cannot reject it. Counted in degrees of freedom (Landau–Slepian):
/// of the 2H + 1 coefficients about (2H + 1)·G/2π are concentrated in the gap, invisible to the
/// data; H·G ≤ 2π leaves at most about two there, one order's sine and cosine, the size of the
/// richer order the prediction bounds the form's error with (`calibrate`'s effect-model spread).
/// Past the rule the fitted form's growth over the gap is unbounded by the data: by Remez's
/// inequality for trigonometric polynomials (Erdélyi 1992) it is up to T₂ₕ(1/cos(G/4)),
/// about exp(H·G/2): 12-17 at H·G = 2π, but for joint 1 of the NJ-130 quick start (measured
/// over -110..100° of its ±180°, G = 150°) 2.2, 8.3, 34, 140, 560 and 2,300 for H = 1..6.
/// The stricter Nyquist spacing (G at most half the period, H·G ≤ π, Gröchenig's sufficient
/// condition for stable sampling) would keep only the first order there; on that recording
/// it left the true second and third orders to a joint compliance and two invented set-up
/// steps (held out 8.5 um against 3.1 um with two orders), so the bound on what the data can
/// hide, not on stable sampling, is the rule. The first order is always allowed: the gap never
/// holds its whole period, and a joint short of a turn confuses it with its zero, which the
/// fit's mean removal handles. Orders past the cap are not excluded outright: Remez's growth
/// multiplies what the data leave uncertain, and very precise data can carry an order across
/// the gap; the selection admits one only when the fitted form's standard uncertainty over the
/// whole range is at most half its size (`diagnose::form_determined`).
pub fn harmonic_cap(q: &[[f64; 6]], j: usize, range: Option<(f64, f64)>) -> usize {
    let gap = unmeasured_gap(q.iter().map(|x| x[j]), range);
    if gap <= 0.0 {
        return MAX_HARMONIC;
    }
    ((std::f64::consts::TAU / gap + 1e-9).floor() as usize).clamp(1, MAX_HARMONIC)
}

/// The largest stretch (rad) of a joint's range without a measured angle: on the turn (a
/// range of a turn or more, or none given) the largest arc between angles; on a shorter range
/// [lo, hi] the largest gap between angles or twice the stretch from the nearest angle to an
/// end. 2π without an angle.
fn unmeasured_gap(angles: impl Iterator<Item = f64>, range: Option<(f64, f64)>) -> f64 {
    use std::f64::consts::TAU;
    let mut a: Vec<f64> = angles.filter(|x| x.is_finite()).collect();
    if a.is_empty() {
        return TAU;
    }
    match range {
        Some((lo, hi)) if hi - lo < TAU => {
            a.sort_by(f64::total_cmp);
            let ends = (a[0] - lo).max(hi - a[a.len() - 1]).max(0.0);
            a.windows(2)
                .map(|w| w[1] - w[0])
                .fold(2.0 * ends, f64::max)
                .min(TAU)
        }
        _ => {
            for x in &mut a {
                *x = x.rem_euclid(TAU);
            }
            a.sort_by(f64::total_cmp);
            let wrap = a[0] + TAU - a[a.len() - 1];
            a.windows(2).map(|w| w[1] - w[0]).fold(wrap, f64::max)
        }
    }
}

impl Basis {
    /// The harmonic orders of a cyclic error's mask, ascending.
    pub fn orders(&self) -> Vec<usize> {
        match *self {
            Basis::Harmonics(mask) => (1..=MAX_ORDER)
                .filter(|h| mask & (1 << (h - 1)) != 0)
                .collect(),
            _ => Vec::new(),
        }
    }

    /// The highest of a cyclic error's contiguous low orders 1..H (0 without order 1): the
    /// orders the gap rule and the richer-order bound speak of; orders past
    /// [`MAX_HARMONIC`] are single stationary orders, bounded by their own amplitude.
    pub fn low_orders(&self) -> usize {
        match *self {
            Basis::Harmonics(mask) => (mask.trailing_ones() as usize).min(MAX_HARMONIC),
            _ => 0,
        }
    }

    /// The links (DH rows, 0-based) a per-link thermal drift grows.
    pub fn links(&self) -> Vec<usize> {
        match *self {
            Basis::LagLinks(mask) | Basis::TemperatureLinks(mask) => {
                (0..6).filter(|i| mask & (1 << i) != 0).collect()
            }
            _ => Vec::new(),
        }
    }

    /// A thermal drift in the form of a first-order lag (one scale or one per link).
    pub fn is_lag(&self) -> bool {
        matches!(self, Basis::Lag | Basis::LagLinks(_))
    }
}

/// The DH rows a per-link thermal drift can grow: those with a length (a or d) over 1 mm.
pub fn grown_links(p: &Params) -> u8 {
    (0..6)
        .filter(|&i| p.dh[i].a.abs() + p.dh[i].d.abs() > 1e-3)
        .fold(0u8, |m, i| m | (1 << i))
}

/// One effect of the model and its coefficients.
#[derive(Clone, Debug, PartialEq)]
pub struct Term {
    pub effect: Effect,
    pub basis: Basis,
    pub coef: Vec<f64>,
}

/// A stretch of one run's rows that shares a fixture position (or a length zero): the whole
/// run, or a segment of it after a detected step.
#[derive(Clone, Debug, PartialEq)]
pub struct Group {
    pub run: usize,
    /// Rows (of the concatenated problem), contiguous.
    pub rows: Range<usize>,
    /// True for a run's own group (its given fixture / length zero), false for a segment
    /// opened at a step.
    pub given: bool,
}

/// The current estimate: shared geometry, one fixture and one length zero per group, and the
/// coefficients of the effects in the model.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    /// Eq. 6 vector; its fixture entries are run 1's (see `fixtures`).
    pub p: [f64; N_PARAMS],
    /// Per fixture group.
    pub fixtures: Vec<Vector3<f64>>,
    /// Per offset group (m).
    pub offsets: Vec<f64>,
    pub effects: Vec<Term>,
}

/// Thermal time constants are kept within these bounds (s): a lag faster than 10 ms or slower
/// than a year is no thermal drift.
const TAU_RANGE: (f64, f64) = (1e-2, 3e7);

impl Estimate {
    /// Nominal geometry, the runs' given fixtures and length zeros, no effects.
    pub fn nominal(problem: &Problem) -> Self {
        Estimate {
            p: problem.model.nominal.to_array(),
            fixtures: problem
                .fix_groups
                .iter()
                .map(|g| problem.fixtures[g.run])
                .collect(),
            offsets: problem
                .off_groups
                .iter()
                .map(|g| problem.offsets_given[g.run])
                .collect(),
            effects: Vec::new(),
        }
    }

    /// The parameters of run `run` (its first fixture group).
    pub fn params(&self, run: usize) -> Params {
        self.params_group(run)
    }

    fn params_group(&self, group: usize) -> Params {
        let mut p = self.p;
        for a in 0..3 {
            p[FIX + a] = self.fixtures[group][a];
        }
        Params::from_array(&p)
    }

    pub fn get(&self, q: Param) -> f64 {
        match q {
            Param::Shared(i) => self.p[i],
            Param::Fixture { group, axis } => self.fixtures[group][axis],
            Param::Offset { group } => self.offsets[group],
        }
    }

    pub fn set(&mut self, q: Param, v: f64) {
        match q {
            Param::Shared(i) => self.p[i] = v,
            Param::Fixture { group, axis } => self.fixtures[group][axis] = v,
            Param::Offset { group } => self.offsets[group] = v,
        }
    }

    /// Adds an effect with zero coefficients (a lag starts at time constant `tau0`). A cyclic
    /// error of a joint that has one already gains the new orders: one term per joint, its
    /// orders' coefficients kept, the new ones zero, the term moved last (the effect added).
    pub fn add_effect(&mut self, effect: Effect, basis: Basis, tau0: f64) {
        if let (Effect::CyclicError(_), Basis::Harmonics(new)) = (effect, basis) {
            if let Some(i) = self.effects.iter().position(|t| t.effect == effect) {
                let old = self.effects.remove(i);
                let Basis::Harmonics(had) = old.basis else {
                    unreachable!("a cyclic error's basis is its harmonics")
                };
                let merged = Basis::Harmonics(had | new);
                let was = old.basis.orders();
                let coef = merged
                    .orders()
                    .into_iter()
                    .flat_map(|h| {
                        let k = was.iter().position(|&o| o == h);
                        [0, 1].map(|c| k.map_or(0.0, |k| old.coef[2 * k + c]))
                    })
                    .collect();
                self.effects.push(Term {
                    effect,
                    basis: merged,
                    coef,
                });
                return;
            }
        }
        let n = effect_cols(effect, basis).len();
        let mut coef = vec![0.0; n];
        if effect == Effect::ThermalDrift && basis.is_lag() {
            coef[n - 1] = tau0.clamp(TAU_RANGE.0, TAU_RANGE.1);
        }
        self.effects.push(Term {
            effect,
            basis,
            coef,
        });
    }

    /// The servo lag's delay τ (s) and second-order term (s²).
    fn servo(&self) -> (f64, f64) {
        self.effects
            .iter()
            .find(|t| t.effect == Effect::ServoLag)
            .map_or((0.0, 0.0), |t| {
                (t.coef[0], t.coef.get(1).copied().unwrap_or(0.0))
            })
    }

    /// The thermal lag's amplitude per link and time constant, when the model has one.
    fn lag(&self) -> Option<([f64; 6], f64)> {
        let t = self
            .effects
            .iter()
            .find(|t| t.effect == Effect::ThermalDrift && t.basis.is_lag())?;
        let tau = *t.coef.last()?;
        Some((growth_per_link(t.basis, &t.coef), tau))
    }
}

impl Estimate {
    /// The general gravity basis of a joint compliance (mass and first moments of every link
    /// after the joint) holds exact dependencies: links whose frames share an origin give one
    /// mass column twice. Along such a dependency the fit may leave coefficients of any size
    /// that cancel (10⁹ seen), which no file can carry: rounding the geometry to a nanometre
    /// then moves the deflection by micrometres. This replaces them by the smallest
    /// coefficients that give the same deflections over `poses` (the whole joint space): per
    /// joint, the columns scaled to unit norm, the coefficients projected on the right
    /// singular vectors above 1e-10 of the largest singular value.
    pub fn tidy_compliance(&mut self, problem: &Problem, poses: &[[f64; 6]]) {
        let p = Params::from_array(&self.p);
        let Some(t) = self
            .effects
            .iter_mut()
            .find(|t| t.effect == Effect::JointCompliance && t.basis == Basis::Standard)
        else {
            return;
        };
        let frames: Vec<[crate::robot::Frame; 8]> = poses
            .iter()
            .map(|q| chain_frames(&problem.model.base, &p.dh, &problem.model.flange, q))
            .collect();
        let cols = effect_cols(Effect::JointCompliance, Basis::Standard);
        for j in 0..6 {
            let idx: Vec<usize> = (0..cols.len())
                .filter(|&n| matches!(cols[n], Col::Comp(jj, ..) if jj == j))
                .collect();
            if idx.is_empty() {
                continue;
            }
            let mut a = DMatrix::from_fn(frames.len(), idx.len(), |r, c| match cols[idx[c]] {
                Col::Comp(jj, i, comp) => gravity_basis(&frames[r], jj, i, comp),
                _ => 0.0,
            });
            // A column that is rounding noise (a mass on the joint's own axis has no torque
            // about it) carries nothing: its coefficient is zero.
            let norms: Vec<f64> = (0..idx.len()).map(|c| a.column(c).norm()).collect();
            let largest = norms.iter().copied().fold(0.0, f64::max);
            let scale: Vec<f64> = norms
                .iter()
                .map(|&n| if n > 1e-9 * largest { n } else { 0.0 })
                .collect();
            for (c, sc) in scale.iter().enumerate() {
                let f = if *sc > 0.0 { 1.0 / sc } else { 0.0 };
                a.column_mut(c).scale_mut(f);
            }
            let svd = a.svd(false, true);
            let Some(vt) = svd.v_t else { continue };
            let top = svd.singular_values.iter().copied().fold(0.0, f64::max);
            let x = DVector::from_fn(idx.len(), |c, _| t.coef[idx[c]] * scale[c]);
            let mut y = DVector::zeros(idx.len());
            for (k, sv) in svd.singular_values.iter().enumerate() {
                if *sv > 1e-10 * top {
                    let v = vt.row(k).transpose();
                    y += &v * v.dot(&x);
                }
            }
            for (c, &n) in idx.iter().enumerate() {
                t.coef[n] = if scale[c] > 0.0 { y[c] / scale[c] } else { 0.0 };
            }
        }
    }
}

/// A thermal drift's coefficients as each link's growth per unit of its time function (the lag
/// 1 − exp(−t/τ), or the temperature rise): one for every link, or one per link of the mask.
pub fn growth_per_link(basis: Basis, coef: &[f64]) -> [f64; 6] {
    match basis {
        Basis::LagLinks(_) | Basis::TemperatureLinks(_) => {
            let mut g = [0.0; 6];
            for (n, i) in basis.links().into_iter().enumerate() {
                g[i] = coef[n];
            }
            g
        }
        _ => [coef.first().copied().unwrap_or(0.0); 6],
    }
}

/// The first-order thermal lag at time t since the start of the run: 1 − exp(−t/τ), and its
/// derivative with respect to τ.
fn lag(t: f64, tau: f64) -> (f64, f64) {
    let e = (-t.max(0.0) / tau).exp();
    (1.0 - e, -(t.max(0.0) / (tau * tau)) * e)
}

// ---- regressors ---------------------------------------------------------------------------

#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Col {
    Geo(Param),
    /// joint, harmonic order, sine?
    Cyc(usize, usize, bool),
    Back(usize),
    /// Servo lag: the delay, and the second-order term.
    Servo,
    Servo2,
    /// A thermal lag's amplitude at a fixed time constant (screening candidates).
    ThermAt(f64),
    /// The estimate's thermal lag: amplitude, time constant.
    ThermAmp,
    ThermTau,
    /// Linear in the logged temperature rise.
    ThermTemp,
    /// Link i's own lag amplitude, and its own coefficient of the temperature rise.
    ThermAmpLink(usize),
    ThermTempLink(usize),
    /// joint j, frame i, component 0 = mass at the origin, 1..3 = first moment along x, y, z.
    Comp(usize, usize, usize),
    /// joint j's compliance times its gravity torque from the known masses.
    CompKnown(usize),
    /// A step candidate: a new fixture coordinate for rows `from..to`.
    StepFix {
        from: usize,
        to: usize,
        axis: usize,
    },
    /// A step candidate: a new length zero for rows `from..to`.
    StepOff {
        from: usize,
        to: usize,
    },
}

pub(crate) fn effect_cols(e: Effect, basis: Basis) -> Vec<Col> {
    match e {
        Effect::JointCompliance if basis == Basis::KnownMasses => {
            (0..6).map(Col::CompKnown).collect()
        }
        Effect::Geometric => Vec::new(),
        Effect::CyclicError(j) => basis
            .orders()
            .into_iter()
            .flat_map(|h| [Col::Cyc(j, h, false), Col::Cyc(j, h, true)])
            .collect(),
        Effect::Backlash(j) => vec![Col::Back(j)],
        Effect::ServoLag if basis == Basis::SecondOrder => vec![Col::Servo, Col::Servo2],
        Effect::ServoLag => vec![Col::Servo],
        Effect::ThermalDrift if basis == Basis::Temperature => vec![Col::ThermTemp],
        Effect::ThermalDrift if matches!(basis, Basis::TemperatureLinks(_)) => {
            basis.links().into_iter().map(Col::ThermTempLink).collect()
        }
        Effect::ThermalDrift if matches!(basis, Basis::LagLinks(_)) => basis
            .links()
            .into_iter()
            .map(Col::ThermAmpLink)
            .chain([Col::ThermTau])
            .collect(),
        Effect::ThermalDrift => vec![Col::ThermAmp, Col::ThermTau],
        Effect::JointCompliance => (0..6)
            .flat_map(|j| (j + 1..=6).flat_map(move |i| (0..4).map(move |c| Col::Comp(j, i, c))))
            .collect(),
    }
}

/// The columns of a model: the free geometry, then every effect's coefficients in order.
pub(crate) fn model_cols(est: &Estimate, free: &[Param]) -> Vec<Col> {
    let mut cols: Vec<Col> = free.iter().map(|&q| Col::Geo(q)).collect();
    for t in &est.effects {
        cols.extend(effect_cols(t.effect, t.basis));
    }
    cols
}

/// The data of a fit: every run's rows one after the other, and what does not depend on the
/// estimate.
pub struct Problem {
    pub model: MeasurementModel,
    /// The runs' rows, concatenated.
    pub m: Measured,
    /// Rows of each run.
    pub ranges: Vec<Range<usize>>,
    /// The run of each row.
    run: Vec<usize>,
    /// The fixtures the runs were given.
    pub fixtures: Vec<Vector3<f64>>,
    /// The length zero each run was given (m; 0 unless `--length-offset` says otherwise).
    pub offsets_given: Vec<f64>,
    /// How each run's readings were taken.
    pub forms: Vec<Form>,
    /// Time since the run's first row (s), or the row's order in an untimed run.
    since: Vec<f64>,
    qdot: Vec<[f64; 6]>,
    qddot: Vec<[f64; 6]>,
    dir: Vec<[f64; 6]>,
    /// True for a row after a gap in a continuous recording (more than three sample periods,
    /// e.g. between the sections of a program): the robot moved unrecorded.
    gap: Vec<bool>,
    /// At a run's first row (and after a gap): the direction of each joint's next motion (the
    /// flank a backlash's load is taken to rest on at the start).
    next_dir: Vec<[f64; 6]>,
    /// Temperature above the run's first reading, when every run logs it.
    temp_rise: Option<Vec<f64>>,
    /// The robot's link masses (its file's inertials), when it has them.
    pub masses: Vec<PointMass>,
    /// Per joint and harmonic order h: the means of sin(h·q) and cos(h·q) over the range the
    /// joint was measured in (uniformly). A cyclic error's harmonics are taken free of them,
    /// so that the joint's zero offset holds the error's constant part: over a joint that
    /// turns far less than a turn, the data tell a zero offset from a harmonic's constant part
    /// only by the harmonic's form, while the zero plus the error's mean over the measured
    /// range is what they determine (and the best constant a DH table can hold there).
    harmonic_means: [[(f64, f64); MAX_ORDER]; 6],
    /// Per joint, the highest harmonic order its measured range determines ([`harmonic_cap`]).
    harmonic_caps: [usize; 6],
    /// Per joint, the range it can turn through (rad; at most one turn): where the robot file
    /// applies a cyclic error.
    joint_ranges: [(f64, f64); 6],
    /// √weight of each row from its stated uncertainty (1 without one).
    pub base_weight: Vec<f64>,
    /// Each row's stated standard uncertainty (m; 0: none stated).
    pub stated_std: Vec<f64>,
    /// √weight in use: the stated one times the robust loss's; 0 drops the row.
    pub weight: Vec<f64>,
    /// Fixture groups and the group of each row.
    pub fix_groups: Vec<Group>,
    fix_of: Vec<u32>,
    /// Length-zero groups and the group of each row.
    pub off_groups: Vec<Group>,
    off_of: Vec<u32>,
}

/// Quintic (6-point) Lagrange interpolation of the recorded angles at time t: servo lags are
/// a fraction of the sample period, and the interpolation error must stay below the bar noise.
fn interp(t: &[f64], q: &[[f64; 6]], at: f64) -> [f64; 6] {
    let n = t.len();
    let k = t.partition_point(|&x| x <= at);
    let lo = k.saturating_sub(3).min(n.saturating_sub(6));
    let hi = (lo + 6).min(n);
    let mut out = [0.0; 6];
    for a in lo..hi {
        let mut w = 1.0;
        for b in lo..hi {
            if a != b {
                w *= (at - t[b]) / (t[a] - t[b]);
            }
        }
        for j in 0..6 {
            out[j] += w * q[a][j];
        }
    }
    out
}

/// Joint velocities and accelerations of one continuous run (5-point stencils inside,
/// shorter ones at the ends).
fn derivatives(t: &[f64], q: &[[f64; 6]]) -> (Vec<[f64; 6]>, Vec<[f64; 6]>) {
    let n = t.len();
    let mut qdot = vec![[0.0; 6]; n];
    let mut qdd = vec![[0.0; 6]; n];
    for k in 0..n {
        for j in 0..6 {
            if k >= 2 && k + 2 < n {
                let h = (t[k + 2] - t[k - 2]) / 4.0;
                qdot[k][j] = (-q[k + 2][j] + 8.0 * q[k + 1][j] - 8.0 * q[k - 1][j] + q[k - 2][j])
                    / (12.0 * h);
                qdd[k][j] = (-q[k + 2][j] + 16.0 * q[k + 1][j] - 30.0 * q[k][j]
                    + 16.0 * q[k - 1][j]
                    - q[k - 2][j])
                    / (12.0 * h * h);
            } else {
                let (a, b) = (k.saturating_sub(1), (k + 1).min(n - 1));
                if b > a {
                    qdot[k][j] = (q[b][j] - q[a][j]) / (t[b] - t[a]);
                }
                if k >= 1 && k + 1 < n {
                    let h = (t[k + 1] - t[k - 1]) / 2.0;
                    qdd[k][j] = (q[k + 1][j] - 2.0 * q[k][j] + q[k - 1][j]) / (h * h);
                }
            }
        }
    }
    (qdot, qdd)
}

/// The means of sin(h·q) and cos(h·q), h = 1..MAX_ORDER, over each joint's measured range
/// [min q, max q], uniformly (closed form).
fn harmonic_means(q: &[[f64; 6]]) -> [[(f64, f64); MAX_ORDER]; 6] {
    std::array::from_fn(|j| {
        let (lo, hi) = q
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                (a.min(x[j]), b.max(x[j]))
            });
        let span = hi - lo;
        std::array::from_fn(|k| {
            let h = (k + 1) as f64;
            if span.is_nan() || span <= 1e-9 {
                let (s, c) = (h * lo).sin_cos();
                return if lo.is_finite() { (s, c) } else { (0.0, 0.0) };
            }
            (
                ((h * lo).cos() - (h * hi).cos()) / (h * span),
                ((h * hi).sin() - (h * lo).sin()) / (h * span),
            )
        })
    })
}

/// Direction of the last motion between rows (a continuous run's samples, or a static run's
/// poses: the approach to each pose); before the first motion, that of the first.
fn directions(q: &[[f64; 6]]) -> Vec<[f64; 6]> {
    let n = q.len();
    let mut dir = vec![[0.0; 6]; n];
    for j in 0..6 {
        let step = |k: usize| q[k][j] - q[k - 1][j];
        let first = (1..n)
            .map(step)
            .find(|v| v.abs() > MOTION_DEADBAND)
            .map_or(1.0, f64::signum);
        let mut d = first;
        for k in 0..n {
            if k > 0 && step(k).abs() > MOTION_DEADBAND {
                d = step(k).signum();
            }
            dir[k][j] = d;
        }
    }
    dir
}

/// A run's restarts: true after a gap (a continuous recording's time step more than three
/// times its median: the robot moved unrecorded), and at the first row and each gap the
/// direction of every joint's next motion.
fn restarts(t: &[f64], q: &[[f64; 6]], form: Form) -> (Vec<bool>, Vec<[f64; 6]>) {
    let n = t.len();
    let mut gap = vec![false; n];
    if form == Form::Continuous && n > 2 {
        let mut dt: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
        dt.sort_by(f64::total_cmp);
        let median = dt[dt.len() / 2];
        for k in 1..n {
            gap[k] = t[k] - t[k - 1] > 3.0 * median;
        }
    }
    let mut next = vec![[0.0; 6]; n];
    for k in (0..n).filter(|&k| k == 0 || gap[k]) {
        for j in 0..6 {
            next[k][j] = (k + 1..n)
                .take_while(|&i| !gap[i])
                .map(|i| q[i][j] - q[i - 1][j])
                .find(|d| d.abs() > MOTION_DEADBAND)
                .map_or(1.0, f64::signum);
        }
    }
    (gap, next)
}

impl Problem {
    /// The rows of every run, in order. Temperatures are used for thermal drift only when
    /// every run has them; stated uncertainties weight the rows of their run.
    pub fn new(model: &MeasurementModel, runs: &[Run]) -> Problem {
        let with_temp = !runs.is_empty() && runs.iter().all(|r| r.measured.temp.is_some());
        let n: usize = runs.iter().map(|r| r.measured.len()).sum();
        let mut m = Measured {
            t: Vec::with_capacity(n),
            q: Vec::with_capacity(n),
            length: Vec::with_capacity(n),
            temp: with_temp.then(|| Vec::with_capacity(n)),
            ..Measured::default()
        };
        let mut ranges = Vec::with_capacity(runs.len());
        let mut run = Vec::with_capacity(n);
        let mut since = Vec::with_capacity(n);
        let (mut qdot, mut qddot, mut dir) = (
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        );
        let mut temp_rise = with_temp.then(|| Vec::with_capacity(n));
        let (mut gap, mut next_dir) = (Vec::with_capacity(n), Vec::with_capacity(n));
        let mut base_weight = Vec::with_capacity(n);
        let mut stated_std = Vec::with_capacity(n);
        // One yardstick for the stated uncertainties of the whole campaign: their RMS.
        let stated: Vec<f64> = runs
            .iter()
            .filter_map(|r| r.measured.std.as_ref())
            .flatten()
            .copied()
            .collect();
        let s_ref = (stated.iter().map(|s| s * s).sum::<f64>() / stated.len().max(1) as f64).sqrt();
        for (r, x) in runs.iter().enumerate() {
            let rm = x.measured;
            let start = m.len();
            m.t.extend_from_slice(&rm.t);
            m.q.extend_from_slice(&rm.q);
            m.length.extend_from_slice(&rm.length);
            ranges.push(start..m.len());
            run.extend(std::iter::repeat_n(r, rm.len()));
            if rm.is_empty() {
                continue;
            }
            since.extend(rm.t.iter().map(|t| t - rm.t[0]));
            let (g, nd) = restarts(&rm.t, &rm.q, rm.form);
            match rm.form {
                Form::Continuous => {
                    // Rates of each stretch between gaps on its own: across a gap the robot
                    // moved unrecorded, and a stencil spanning it would see a jump.
                    let mut a = 0;
                    while a < rm.len() {
                        let b = (a + 1..rm.len()).find(|&i| g[i]).unwrap_or(rm.len());
                        let (v, acc) = derivatives(&rm.t[a..b], &rm.q[a..b]);
                        qdot.extend(v);
                        qddot.extend(acc);
                        a = b;
                    }
                }
                Form::Static { .. } => {
                    qdot.extend(std::iter::repeat_n([0.0; 6], rm.len()));
                    qddot.extend(std::iter::repeat_n([0.0; 6], rm.len()));
                }
            }
            dir.extend(directions(&rm.q));
            gap.extend(g);
            next_dir.extend(nd);
            if let (Some(all), Some(t), Some(rise)) = (&mut m.temp, &rm.temp, &mut temp_rise) {
                all.extend_from_slice(t);
                rise.extend(t.iter().map(|c| c - t[0]));
            }
            match &rm.std {
                Some(s) if s_ref > 0.0 => {
                    base_weight.extend(s.iter().map(|v| s_ref / v.max(1e-3 * s_ref)))
                }
                _ => base_weight.extend(std::iter::repeat_n(1.0, rm.len())),
            }
            match &rm.std {
                Some(s) => stated_std.extend_from_slice(s),
                None => stated_std.extend(std::iter::repeat_n(0.0, rm.len())),
            }
        }
        let groups: Vec<Group> = ranges
            .iter()
            .enumerate()
            .map(|(r, rows)| Group {
                run: r,
                rows: rows.clone(),
                given: true,
            })
            .collect();
        let means = harmonic_means(&m.q);
        let caps = std::array::from_fn(|j| harmonic_cap(&m.q, j, None));
        Problem {
            model: model.clone(),
            fix_of: run.iter().map(|&r| r as u32).collect(),
            off_of: run.iter().map(|&r| r as u32).collect(),
            m,
            ranges,
            run,
            fixtures: runs.iter().map(|r| r.fixture).collect(),
            offsets_given: vec![0.0; runs.len()],
            forms: runs.iter().map(|r| r.measured.form).collect(),
            since,
            qdot,
            qddot,
            dir,
            gap,
            next_dir,
            temp_rise,
            masses: Vec::new(),
            harmonic_means: means,
            harmonic_caps: caps,
            joint_ranges: [(-std::f64::consts::PI, std::f64::consts::PI); 6],
            weight: base_weight.clone(),
            base_weight,
            stated_std,
            fix_groups: groups.clone(),
            off_groups: groups,
        }
    }

    /// The ranges the joints can turn through (their limits, rad): a cyclic error's harmonic
    /// orders are capped by how much of its joint's range was measured ([`harmonic_cap`];
    /// without them, of the whole turn).
    pub fn with_joint_ranges(mut self, ranges: &[(f64, f64); 6]) -> Self {
        self.harmonic_caps = std::array::from_fn(|j| harmonic_cap(&self.m.q, j, Some(ranges[j])));
        self.joint_ranges = std::array::from_fn(|j| {
            let (lo, hi) = ranges[j];
            if hi - lo < std::f64::consts::TAU {
                (lo, hi)
            } else {
                (-std::f64::consts::PI, std::f64::consts::PI)
            }
        });
        self
    }

    /// The range joint j can turn through (rad, at most one turn; the turn without limits).
    pub fn joint_range(&self, j: usize) -> (f64, f64) {
        self.joint_ranges[j]
    }

    /// The robot's link masses, for the known-mass form of joint compliance.
    pub fn with_masses(mut self, masses: &[PointMass]) -> Self {
        self.masses = masses.to_vec();
        self
    }

    /// sin(h·q) and cos(h·q) less their means over joint j's measured range.
    pub(crate) fn harmonic(&self, j: usize, h: usize, q: f64) -> (f64, f64) {
        let (sn, cs) = (h as f64 * q).sin_cos();
        let (ms, mc) = self.harmonic_means[j][h - 1];
        (sn - ms, cs - mc)
    }

    /// The highest harmonic order of a cyclic error of joint j that its measured range
    /// determines over the joint's range ([`harmonic_cap`]).
    pub fn harmonic_cap(&self, j: usize) -> usize {
        self.harmonic_caps[j]
    }

    /// The means of (sin(h·q), cos(h·q)) over joint j's measured range: what the fit's
    /// harmonics are taken about (the constant part goes to the joint's zero).
    pub fn harmonic_mean(&self, j: usize, h: usize) -> (f64, f64) {
        self.harmonic_means[j][h - 1]
    }

    /// This problem with another's harmonic means: to evaluate an estimate fitted to `other`
    /// on rows it was not fitted to (its cyclic errors' harmonics are taken about `other`'s).
    pub fn with_harmonic_means_of(mut self, other: &Problem) -> Self {
        self.harmonic_means = other.harmonic_means;
        self.harmonic_caps = other.harmonic_caps;
        self.joint_ranges = other.joint_ranges;
        self
    }

    /// The joint velocities (rad/s) of row k (zero for a static row).
    pub fn velocity(&self, k: usize) -> [f64; 6] {
        self.qdot[k]
    }

    /// The temperature (°C) of run `r`'s first row, when the runs log one.
    pub fn first_temperature(&self, r: usize) -> Option<f64> {
        let t = self.m.temp.as_ref()?;
        let range = self.ranges.get(r)?;
        t.get(range.start).copied()
    }

    /// The length zero every run was given (m).
    pub fn with_offset(mut self, offset: f64) -> Self {
        self.offsets_given = vec![offset; self.runs()];
        self
    }

    pub fn rows(&self) -> usize {
        self.m.len()
    }

    pub fn runs(&self) -> usize {
        self.ranges.len()
    }

    /// The run row k belongs to.
    pub fn run_of(&self, k: usize) -> usize {
        self.run[k]
    }

    /// The fixture group of row k.
    pub fn fixture_group_of(&self, k: usize) -> usize {
        self.fix_of[k] as usize
    }

    /// The length-zero group of row k.
    pub fn offset_group_of(&self, k: usize) -> usize {
        self.off_of[k] as usize
    }

    /// Rows that count (weight above zero).
    pub fn kept(&self) -> usize {
        self.weight.iter().filter(|w| **w > 0.0).count()
    }

    /// True when every run has real times: a time-dependent effect may be fitted.
    pub fn timed(&self) -> bool {
        !self.forms.is_empty() && self.forms.iter().all(Form::timed)
    }

    /// True when some run was recorded while the robot moved (velocities exist).
    pub fn moving(&self) -> bool {
        self.forms.contains(&Form::Continuous)
    }

    /// True when every run logs a temperature.
    pub fn has_temperature(&self) -> bool {
        self.temp_rise.is_some()
    }

    /// How far the logged temperature moved within the runs (K): the largest rise or fall
    /// from a run's first reading; None without a `temp_c` column.
    pub fn temperature_change(&self) -> Option<f64> {
        self.temp_rise
            .as_ref()
            .map(|r| r.iter().fold(0.0f64, |m, x| m.max(x.abs())))
    }

    /// The longest run's span (s, or rows for untimed runs).
    pub fn span(&self) -> f64 {
        self.ranges
            .iter()
            .filter(|r| !r.is_empty())
            .map(|r| self.since[r.end - 1])
            .fold(0.0, f64::max)
    }

    /// A thinned copy for fits that need fewer rows (the set-up's start): every s-th row of
    /// each run, s such that at most about `max` rows remain; groups keep their rows.
    pub fn thinned(&self, max: usize) -> Problem {
        let n = self.rows();
        let stride = n.div_ceil(max.max(1)).max(1);
        let keep: Vec<usize> = self
            .ranges
            .iter()
            .flat_map(|r| r.clone().step_by(stride))
            .collect();
        // New index of the first kept row at or after each old row.
        let mut before = vec![0usize; n + 1];
        let mut j = 0;
        for k in 0..=n {
            while j < keep.len() && keep[j] < k {
                j += 1;
            }
            before[k] = j;
        }
        let remap = |g: &Group| Group {
            run: g.run,
            rows: before[g.rows.start]..before[g.rows.end],
            given: g.given,
        };
        let pick = |v: &[[f64; 6]]| keep.iter().map(|&k| v[k]).collect::<Vec<_>>();
        let m = Measured {
            t: keep.iter().map(|&k| self.m.t[k]).collect(),
            q: pick(&self.m.q),
            length: keep.iter().map(|&k| self.m.length[k]).collect(),
            temp: self
                .m
                .temp
                .as_ref()
                .map(|t| keep.iter().map(|&k| t[k]).collect()),
            ..Measured::default()
        };
        Problem {
            model: self.model.clone(),
            m,
            ranges: self
                .ranges
                .iter()
                .map(|r| before[r.start]..before[r.end])
                .collect(),
            run: keep.iter().map(|&k| self.run[k]).collect(),
            fixtures: self.fixtures.clone(),
            offsets_given: self.offsets_given.clone(),
            forms: self.forms.clone(),
            since: keep.iter().map(|&k| self.since[k]).collect(),
            qdot: pick(&self.qdot),
            qddot: pick(&self.qddot),
            dir: pick(&self.dir),
            gap: keep.iter().map(|&k| self.gap[k]).collect(),
            next_dir: pick(&self.next_dir),
            temp_rise: self
                .temp_rise
                .as_ref()
                .map(|t| keep.iter().map(|&k| t[k]).collect()),
            masses: self.masses.clone(),
            harmonic_means: self.harmonic_means,
            harmonic_caps: self.harmonic_caps,
            joint_ranges: self.joint_ranges,
            base_weight: keep.iter().map(|&k| self.base_weight[k]).collect(),
            stated_std: keep.iter().map(|&k| self.stated_std[k]).collect(),
            weight: keep.iter().map(|&k| self.weight[k]).collect(),
            fix_groups: self.fix_groups.iter().map(remap).collect(),
            fix_of: keep.iter().map(|&k| self.fix_of[k]).collect(),
            off_groups: self.off_groups.iter().map(remap).collect(),
            off_of: keep.iter().map(|&k| self.off_of[k]).collect(),
        }
    }

    /// Splits the fixture group (or, `fixture` false, the length-zero group) that holds row
    /// `at` there: rows from `at` to the end of that group get a new group, which starts at
    /// the old one's estimate. Returns the new group's index.
    pub fn split(&mut self, est: &mut Estimate, fixture: bool, at: usize) -> usize {
        let (groups, of) = if fixture {
            (&mut self.fix_groups, &mut self.fix_of)
        } else {
            (&mut self.off_groups, &mut self.off_of)
        };
        let old = of[at] as usize;
        let end = groups[old].rows.end;
        let new = groups.len();
        groups[old].rows.end = at;
        groups.push(Group {
            run: groups[old].run,
            rows: at..end,
            given: false,
        });
        for g in &mut of[at..end] {
            *g = new as u32;
        }
        if fixture {
            let f = est.fixtures[old];
            est.fixtures.push(f);
        } else {
            let o = est.offsets[old];
            est.offsets.push(o);
        }
        new
    }

    /// Undoes the last [`Problem::split`] (`group` is what it returned); an estimate from
    /// before the split fits the problem again.
    pub fn unsplit(&mut self, fixture: bool, group: usize) {
        let (groups, of) = if fixture {
            (&mut self.fix_groups, &mut self.fix_of)
        } else {
            (&mut self.off_groups, &mut self.off_of)
        };
        debug_assert_eq!(group + 1, groups.len(), "only the last split is undone");
        let g = groups.pop().expect("a split group");
        let old = groups
            .iter()
            .position(|h| h.run == g.run && h.rows.end == g.rows.start)
            .expect("the group the split cut");
        groups[old].rows.end = g.rows.end;
        for o in &mut of[g.rows.clone()] {
            *o = old as u32;
        }
    }

    /// 1-based segment number of a group within its run (by its first row) and the number of
    /// groups of that kind in the run.
    pub fn segment_of(&self, fixture: bool, group: usize) -> (usize, usize) {
        let groups = if fixture {
            &self.fix_groups
        } else {
            &self.off_groups
        };
        let g = &groups[group];
        let same: Vec<&Group> = groups.iter().filter(|h| h.run == g.run).collect();
        let before = same.iter().filter(|h| h.rows.start < g.rows.start).count();
        (before + 1, same.len())
    }

    /// The report name of a parameter: Eq. 6's (`a2`, `x_map`); a fixture coordinate is
    /// `x_fix`, or `x_fix[k]` (run k, 1-based) in a campaign of several runs, `x_fix[k.s]` for
    /// segment s of a run split at a step; a length zero likewise `length_offset[...]`.
    pub fn param_name(&self, q: Param) -> String {
        let suffix = |fixture: bool, group: usize| -> String {
            let groups = if fixture {
                &self.fix_groups
            } else {
                &self.off_groups
            };
            let run = groups[group].run;
            let (s, of) = self.segment_of(fixture, group);
            match (self.runs() > 1, of > 1) {
                (_, true) => format!("[{}.{s}]", run + 1),
                (true, false) => format!("[{}]", run + 1),
                (false, false) => String::new(),
            }
        };
        match q {
            Param::Shared(i) => model::PARAM_NAMES[i].to_string(),
            Param::Fixture { group, axis } => {
                format!("{}{}", model::PARAM_NAMES[FIX + axis], suffix(true, group))
            }
            Param::Offset { group } => format!("length_offset{}", suffix(false, group)),
        }
    }

    /// Recorded values of row k's run, re-interpolated at that run's time `at` (near row k)
    /// from the rows of k's stretch between gaps only: across a gap the robot moved
    /// unrecorded, and a polynomial through samples on both sides of it is no estimate of
    /// where it was (before a stretch's first row it is extrapolated from the stretch).
    fn interp_run(&self, k: usize, values: &[[f64; 6]], at: f64) -> [f64; 6] {
        let r = self.ranges[self.run[k]].clone();
        let mut lo = k;
        while lo > r.start && !self.gap[lo] && k - lo < 6 {
            lo -= 1;
        }
        let mut hi = k + 1;
        while hi < r.end && !self.gap[hi] && hi - k < 6 {
            hi += 1;
        }
        interp(&self.m.t[lo..hi], &values[lo..hi], at)
    }

    /// Effective (load-side) configuration, parameters and length zero of row k under the
    /// estimate.
    fn apply(&self, est: &Estimate, prep: &Prep, k: usize) -> ([f64; 6], Params, f64) {
        let q0 = prep.motor.as_ref().map_or(self.m.q[k], |m| m[k]);
        let backlash: [f64; 6] =
            std::array::from_fn(|j| prep.back[j].as_ref().map_or(0.0, |b| b.offset[k]));
        let thermal = ThermalAt {
            since: self.since[k],
            rise: self.temp_rise.as_ref().map_or(0.0, |r| r[k]),
        };
        let (q, p) = self.pose_model(est, self.fix_of[k] as usize, &q0, &backlash, thermal);
        (q, p, est.offsets[self.off_of[k] as usize])
    }

    /// The model of one pose: the load-side joints and the parameters (fixture group `group`)
    /// the estimate gives for the motor-side angles `q0`, each backlash joint's load offset
    /// from its motor (`backlash`, rad) and the thermal state. `Problem::apply` evaluates the
    /// rows with it; a pose that was not recorded can be evaluated with it too.
    pub fn pose_model(
        &self,
        est: &Estimate,
        group: usize,
        q0: &[f64; 6],
        backlash: &[f64; 6],
        thermal: ThermalAt,
    ) -> ([f64; 6], Params) {
        let mut p = est.params_group(group).to_array();
        let mut q = *q0;
        let mut frames = None;
        for t in &est.effects {
            let c = &t.coef;
            match t.effect {
                Effect::CyclicError(j) => {
                    for (n, h) in t.basis.orders().into_iter().enumerate() {
                        let (sn, cs) = self.harmonic(j, h, q0[j]);
                        q[j] += c[2 * n] * cs + c[2 * n + 1] * sn;
                    }
                }
                Effect::Backlash(j) => q[j] += backlash[j],
                Effect::ThermalDrift => {
                    let g = growth_per_link(t.basis, c);
                    let f = if t.basis.is_lag() {
                        lag(thermal.since, c[c.len() - 1]).0
                    } else {
                        thermal.rise
                    };
                    for i in 0..6 {
                        p[A + i] *= 1.0 + g[i] * f;
                        p[D + i] *= 1.0 + g[i] * f;
                    }
                }
                Effect::JointCompliance if t.basis == Basis::KnownMasses => {
                    let tau =
                        gravity_torques(&self.model, &Params::from_array(&est.p), q0, &self.masses);
                    for j in 0..6 {
                        q[j] += c[j] * tau[j];
                    }
                }
                Effect::JointCompliance => {
                    let fr = frames.get_or_insert_with(|| {
                        chain_frames(
                            &self.model.base,
                            &Params::from_array(&est.p).dh,
                            &self.model.flange,
                            q0,
                        )
                    });
                    let cols = effect_cols(Effect::JointCompliance, Basis::Standard);
                    for (n, col) in cols.iter().enumerate() {
                        if let Col::Comp(j, i, comp) = col {
                            q[*j] += c[n] * gravity_basis(fr, *j, *i, *comp);
                        }
                    }
                }
                Effect::Geometric | Effect::ServoLag => {}
            }
        }
        (q, Params::from_array(&p))
    }

    /// Fills the regressor values of row k for `cols`; returns the residual measured − model
    /// (unweighted).
    fn row_values(
        &self,
        est: &Estimate,
        prep: &Prep,
        k: usize,
        cols: &[Col],
        out: &mut [f64],
    ) -> f64 {
        let (q, p, offset) = self.apply(est, prep, k);
        let q0 = prep.motor.as_ref().map_or(self.m.q[k], |m| m[k]);
        let mut j = [0.0; N_PARAMS];
        let len = self.model.jacobian_row(&p, &q, &mut j);
        // The compliance regressors exactly as `apply` deflects: at the motor-side angles and
        // the estimate's own geometry (a consistent derivative: Levenberg-Marquardt stalls on
        // an inconsistent one once the cost is small).
        let needs_frames = cols.iter().any(|c| matches!(c, Col::Comp(..)));
        let geometry = || Params::from_array(&est.p);
        let fr = needs_frames
            .then(|| chain_frames(&self.model.base, &geometry().dh, &self.model.flange, &q0));
        let needs_torques = cols.iter().any(|c| matches!(c, Col::CompKnown(..)));
        let torques =
            needs_torques.then(|| gravity_torques(&self.model, &geometry(), &q0, &self.masses));
        let (qd, qdd) = match &prep.rates {
            Some((v, a)) => (v[k], a[k]),
            None => (self.qdot[k], self.qddot[k]),
        };
        let sens_link = |i: usize| -> f64 { est.p[A + i] * j[A + i] + est.p[D + i] * j[D + i] };
        let sens = || -> f64 { (0..6).map(sens_link).sum() };
        let (fg, og) = (self.fix_of[k] as usize, self.off_of[k] as usize);
        for (o, c) in out.iter_mut().zip(cols) {
            *o = match *c {
                Col::Geo(Param::Shared(i)) => j[i],
                Col::Geo(Param::Fixture { group, axis }) => {
                    if group == fg {
                        j[FIX + axis]
                    } else {
                        0.0
                    }
                }
                Col::Geo(Param::Offset { group }) => {
                    if group == og {
                        1.0
                    } else {
                        0.0
                    }
                }
                Col::Cyc(jj, h, sine) => {
                    let (sn, cs) = self.harmonic(jj, h, q0[jj]);
                    j[THETA + jj] * if sine { sn } else { cs }
                }
                Col::Back(jj) => {
                    let side = prep.back[jj]
                        .as_ref()
                        .map_or(self.dir[k][jj], |b| b.side[k]);
                    -0.5 * j[THETA + jj] * side
                }
                Col::Servo => -(0..6).map(|i| j[THETA + i] * qd[i]).sum::<f64>(),
                Col::Servo2 => (0..6).map(|i| j[THETA + i] * qdd[i]).sum::<f64>(),
                Col::ThermAt(tau) => sens() * lag(self.since[k], tau).0,
                Col::ThermAmp => match est.lag() {
                    Some((_, tau)) => sens() * lag(self.since[k], tau).0,
                    None => 0.0,
                },
                Col::ThermAmpLink(i) => match est.lag() {
                    Some((_, tau)) => sens_link(i) * lag(self.since[k], tau).0,
                    None => 0.0,
                },
                Col::ThermTau => match est.lag() {
                    Some((amp, tau)) => {
                        (0..6).map(|i| amp[i] * sens_link(i)).sum::<f64>()
                            * lag(self.since[k], tau).1
                    }
                    None => 0.0,
                },
                Col::ThermTemp => sens() * self.temp_rise.as_ref().map_or(0.0, |r| r[k]),
                Col::ThermTempLink(i) => {
                    sens_link(i) * self.temp_rise.as_ref().map_or(0.0, |r| r[k])
                }
                Col::Comp(jj, i, comp) => match &fr {
                    Some(fr) => j[THETA + jj] * gravity_basis(fr, jj, i, comp),
                    None => 0.0,
                },
                Col::CompKnown(jj) => match &torques {
                    Some(tau) => j[THETA + jj] * tau[jj],
                    None => 0.0,
                },
                Col::StepFix { from, to, axis } => {
                    if (from..to).contains(&k) {
                        j[FIX + axis]
                    } else {
                        0.0
                    }
                }
                Col::StepOff { from, to } => {
                    if (from..to).contains(&k) {
                        1.0
                    } else {
                        0.0
                    }
                }
            };
        }
        self.m.length[k] - len - offset
    }

    /// Residual (measured − model, unweighted) of every row under the estimate.
    pub fn residual(&self, est: &Estimate) -> Vec<f64> {
        accumulate(self, est, &[], 1).residual
    }

    /// The MAP's position (in the base frame of the estimate) and the load-side joints of row
    /// k: for figures and the robust start.
    pub fn loaded(&self, est: &Estimate, k: usize) -> ([f64; 6], Params) {
        let prep = prepare(self, est);
        let (q, p, _) = self.apply(est, &prep, k);
        (q, p)
    }
}

/// The thermal state of a pose: the time since its run's start (s) and the logged
/// temperature's rise since then (K).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ThermalAt {
    pub since: f64,
    pub rise: f64,
}

/// Per-row joint velocities and accelerations.
type Rates = (Vec<[f64; 6]>, Vec<[f64; 6]>);

/// What the rows need from the estimate before they can be evaluated one by one: the motor
/// angles under a servo lag and the backlash play operator, which runs along each run.
pub(crate) struct Prep {
    /// Motor-side joint angles (the logged setpoints delayed), when a servo lag is fitted.
    motor: Option<Vec<[f64; 6]>>,
    /// Joint rates at the delayed time (velocity, acceleration), with a servo lag.
    rates: Option<Rates>,
    /// Per joint with a backlash term: the load's offset from the motor and the flank it
    /// rests on (+1: it was last pushed in the positive direction).
    back: [Option<Play>; 6],
}

pub(crate) struct Play {
    offset: Vec<f64>,
    side: Vec<f64>,
}

pub(crate) fn prepare(problem: &Problem, est: &Estimate) -> Prep {
    let (tau, c2) = est.servo();
    let n = problem.rows();
    let (motor, rates) = if tau != 0.0 || c2 != 0.0 {
        let rows: Vec<([f64; 6], [f64; 6], [f64; 6])> = (0..n)
            .into_par_iter()
            .map(|k| {
                if problem.forms[problem.run[k]] != Form::Continuous {
                    return (problem.m.q[k], [0.0; 6], [0.0; 6]);
                }
                let at = problem.m.t[k] - tau;
                let q = problem.interp_run(k, &problem.m.q, at);
                let v = problem.interp_run(k, &problem.qdot, at);
                let a = problem.interp_run(k, &problem.qddot, at);
                (std::array::from_fn(|j| q[j] + c2 * a[j]), v, a)
            })
            .collect();
        let mut motor = Vec::with_capacity(n);
        let mut v = Vec::with_capacity(n);
        let mut a = Vec::with_capacity(n);
        for (q, qd, qdd) in rows {
            motor.push(q);
            v.push(qd);
            a.push(qdd);
        }
        (Some(motor), Some((v, a)))
    } else {
        (None, None)
    };
    let mut back: [Option<Play>; 6] = Default::default();
    for t in &est.effects {
        if let Effect::Backlash(j) = t.effect {
            let b = t.coef[0].max(0.0);
            let x = |k: usize| motor.as_ref().map_or(problem.m.q[k][j], |m| m[k][j]);
            let mut offset = vec![0.0; n];
            let mut side = vec![0.0; n];
            for (r, range) in problem.ranges.iter().enumerate() {
                if range.is_empty() {
                    continue;
                }
                let moving = problem.forms[r] == Form::Continuous;
                // The load rests against the flank of the run's first motion, then follows the
                // motor only where the motor pushes it (a play operator of width b). Across a
                // gap (the robot moved unrecorded, e.g. between a program's sections) it is
                // pushed by the net motion: exact for one monotonic move.
                let mut s = problem.next_dir[range.start][j];
                let mut y = x(range.start) - 0.5 * b * s;
                for k in range.clone() {
                    let xk = x(k);
                    let mut steps = Vec::new();
                    // Where the motor turns between samples (the differences change sign at
                    // the previous sample), its extreme lies past the samples: take it from
                    // the parabola through the three samples around the turn, before this one.
                    if moving && k >= range.start + 2 && !problem.gap[k] && !problem.gap[k - 1] {
                        let (x0, x1) = (x(k - 2), x(k - 1));
                        let (d1, d2) = (x1 - x0, xk - x1);
                        if d1 * d2 < 0.0 && d1.abs() > MOTION_DEADBAND && d2.abs() > MOTION_DEADBAND
                        {
                            let curv = x0 - 2.0 * x1 + xk;
                            steps.push(x1 - (xk - x0).powi(2) / (8.0 * curv));
                        }
                    }
                    steps.push(xk);
                    for xi in steps {
                        let pushed = play(y, xi, b);
                        if pushed != y {
                            s = (pushed - y).signum();
                            y = pushed;
                        }
                    }
                    offset[k] = y - xk;
                    side[k] = s;
                }
            }
            back[j] = Some(Play { offset, side });
        }
    }
    Prep { motor, rates, back }
}

/// Torque about joint j per unit mass (comp 0, mass at frame i's origin) or per unit first
/// moment along frame i's axis comp (1..3), gravity −z of the base.
pub(crate) fn gravity_basis(fr: &[crate::robot::Frame; 8], j: usize, i: usize, comp: usize) -> f64 {
    let z = fr[j].r.column(2);
    let f = Vector3::new(0.0, 0.0, -G);
    let arm = if comp == 0 {
        fr[i].t - fr[j].t
    } else {
        fr[i].r.column(comp - 1).into_owned()
    };
    z.dot(&arm.cross(&f))
}

/// Normal equations per fold (contiguous blocks of rows), weighted.
pub(crate) struct Stats {
    pub c: usize,
    /// Per fold: N (c×c, full), b, rᵀr, rows that count.
    pub n: Vec<DMatrix<f64>>,
    pub b: Vec<DVector<f64>>,
    pub rr: Vec<f64>,
    pub rows: Vec<usize>,
    /// Measured − model of every row, unweighted.
    pub residual: Vec<f64>,
}

impl Stats {
    /// The sums over every fold: (N, b, rᵀr, rows).
    pub fn total(&self) -> (DMatrix<f64>, DVector<f64>, f64, usize) {
        let mut nt = DMatrix::zeros(self.c, self.c);
        let mut bt = DVector::zeros(self.c);
        for f in 0..self.n.len() {
            nt += &self.n[f];
            bt += &self.b[f];
        }
        (nt, bt, self.rr.iter().sum(), self.rows.iter().sum())
    }
}

pub(crate) const CHUNK: usize = 256;

/// The rows in chunks of at most [`CHUNK`], in order, each with its fold: fold f is the f-th of
/// `folds` contiguous blocks of every run's rows, so that a fold holds out the same stretch of
/// each run (runs over the same poses to other fixtures are held out together: the held-out
/// poses are new to the fit) and leaves every run's set-up determined by the others.
fn chunks(ranges: &[Range<usize>], folds: usize) -> Vec<(Range<usize>, usize)> {
    let mut out = Vec::new();
    for run in ranges {
        let n = run.len();
        for f in 0..folds {
            let (a, b) = (run.start + f * n / folds, run.start + (f + 1) * n / folds);
            let mut s = a;
            while s < b {
                let e = (s + CHUNK).min(b);
                out.push((s..e, f));
                s = e;
            }
        }
    }
    out
}

/// One chunk's partial sums: N (row-major upper triangle), b, rᵀr, rows, residuals.
type Partial = (Vec<f64>, Vec<f64>, f64, usize, Vec<f64>);

pub(crate) fn accumulate(problem: &Problem, est: &Estimate, cols: &[Col], folds: usize) -> Stats {
    let prep = prepare(problem, est);
    accumulate_with(problem, est, &prep, cols, folds)
}

fn accumulate_with(
    problem: &Problem,
    est: &Estimate,
    prep: &Prep,
    cols: &[Col],
    folds: usize,
) -> Stats {
    let n = problem.rows();
    let c = cols.len();
    let folds = folds.max(1);
    let parts: Vec<(Partial, usize)> = chunks(&problem.ranges, folds)
        .into_par_iter()
        .map(|(rows, f)| {
            let mut nn = vec![0.0; c * c];
            let mut b = vec![0.0; c];
            let mut rr = 0.0;
            let mut kept = 0;
            let mut res = Vec::with_capacity(rows.len());
            let mut x = vec![0.0; c];
            for k in rows {
                let r = problem.row_values(est, prep, k, cols, &mut x);
                res.push(r);
                let w = problem.weight[k];
                if w <= 0.0 {
                    continue;
                }
                kept += 1;
                let rw = r * w;
                rr += rw * rw;
                for a in 0..c {
                    let xa = x[a] * w;
                    if xa == 0.0 {
                        continue;
                    }
                    b[a] += xa * rw;
                    let row = &mut nn[a * c..a * c + c];
                    for bb in a..c {
                        row[bb] += xa * x[bb] * w;
                    }
                }
            }
            ((nn, b, rr, kept, res), f)
        })
        .collect();
    let mut st = Stats {
        c,
        n: vec![DMatrix::zeros(c, c); folds],
        b: vec![DVector::zeros(c); folds],
        rr: vec![0.0; folds],
        rows: vec![0; folds],
        residual: Vec::with_capacity(n),
    };
    for ((nn, b, rr, kept, res), f) in parts {
        for a in 0..c {
            st.b[f][a] += b[a];
            for bb in a..c {
                st.n[f][(a, bb)] += nn[a * c + bb];
            }
        }
        st.rr[f] += rr;
        st.rows[f] += kept;
        st.residual.extend(res);
    }
    for f in 0..folds {
        for a in 0..c {
            for bb in 0..a {
                st.n[f][(a, bb)] = st.n[f][(bb, a)];
            }
        }
    }
    st
}

/// The sums an order screen needs: for each candidate (joint j, harmonic order h) the normal
/// equations per fold of the model's columns `base` and that order's two columns
/// (`Col::Cyc(j, h, ..)`), as [`accumulate`] would give them for `base` plus those two, from
/// one pass that forms only the products a single added order needs (base × base, base ×
/// candidate, each candidate's own 2 × 2 and right-hand side): six joints of 34 orders cost
/// about as much as the model's own columns, not 400 columns more.
pub(crate) fn screen_orders(
    problem: &Problem,
    est: &Estimate,
    base: &[Col],
    cand: &[(usize, usize)],
    folds: usize,
) -> Vec<Stats> {
    let prep = prepare(problem, est);
    let cb = base.len();
    let m = 2 * cand.len();
    let cols: Vec<Col> = base
        .iter()
        .copied()
        .chain(
            cand.iter()
                .flat_map(|&(j, h)| [Col::Cyc(j, h, false), Col::Cyc(j, h, true)]),
        )
        .collect();
    let folds = folds.max(1);
    // Per chunk: base × base (upper, row-major), base × candidate (cb × m), each candidate
    // column pair's own products (3 per pair), the right-hand sides, rᵀr, rows.
    type Sums = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, f64, usize);
    let parts: Vec<(Sums, usize)> = chunks(&problem.ranges, folds)
        .into_par_iter()
        .map(|(rows, f)| {
            let mut nbb = vec![0.0; cb * cb];
            let mut cross = vec![0.0; cb * m];
            let mut own = vec![0.0; 3 * cand.len()];
            let mut b = vec![0.0; cb + m];
            let (mut rr, mut kept) = (0.0, 0);
            let mut x = vec![0.0; cb + m];
            for k in rows {
                let w = problem.weight[k];
                if w <= 0.0 {
                    continue;
                }
                let r = problem.row_values(est, &prep, k, &cols, &mut x) * w;
                for v in x.iter_mut() {
                    *v *= w;
                }
                kept += 1;
                rr += r * r;
                for (bv, xv) in b.iter_mut().zip(&x) {
                    *bv += xv * r;
                }
                let (xb, xc) = x.split_at(cb);
                for a in 0..cb {
                    let xa = xb[a];
                    if xa == 0.0 {
                        continue;
                    }
                    for (n, xv) in nbb[a * cb + a..a * cb + cb].iter_mut().zip(&xb[a..]) {
                        *n += xa * xv;
                    }
                    for (n, xv) in cross[a * m..a * m + m].iter_mut().zip(xc) {
                        *n += xa * xv;
                    }
                }
                for (p, o) in own.chunks_exact_mut(3).enumerate() {
                    let (c, s) = (xc[2 * p], xc[2 * p + 1]);
                    o[0] += c * c;
                    o[1] += c * s;
                    o[2] += s * s;
                }
            }
            ((nbb, cross, own, b, rr, kept), f)
        })
        .collect();
    let mut per_fold: Vec<Sums> = (0..folds)
        .map(|_| {
            (
                vec![0.0; cb * cb],
                vec![0.0; cb * m],
                vec![0.0; 3 * cand.len()],
                vec![0.0; cb + m],
                0.0,
                0,
            )
        })
        .collect();
    // Summed in the chunks' order: the same sums on any thread count.
    for ((nbb, cross, own, b, rr, kept), f) in parts {
        let t = &mut per_fold[f];
        for (a, v) in t.0.iter_mut().zip(&nbb) {
            *a += v;
        }
        for (a, v) in t.1.iter_mut().zip(&cross) {
            *a += v;
        }
        for (a, v) in t.2.iter_mut().zip(&own) {
            *a += v;
        }
        for (a, v) in t.3.iter_mut().zip(&b) {
            *a += v;
        }
        t.4 += rr;
        t.5 += kept;
    }
    (0..cand.len())
        .map(|p| {
            let c = cb + 2;
            let mut st = Stats {
                c,
                n: Vec::with_capacity(folds),
                b: Vec::with_capacity(folds),
                rr: Vec::with_capacity(folds),
                rows: Vec::with_capacity(folds),
                residual: Vec::new(),
            };
            for (nbb, cross, own, b, rr, kept) in &per_fold {
                let n = DMatrix::from_fn(c, c, |r, q| {
                    let (lo, hi) = (r.min(q), r.max(q));
                    match (lo < cb, hi < cb) {
                        (true, true) => nbb[lo * cb + hi],
                        (true, false) => cross[lo * m + 2 * p + (hi - cb)],
                        _ => own[3 * p + (lo - cb) + (hi - cb)],
                    }
                });
                let bv = DVector::from_fn(c, |r, _| {
                    if r < cb {
                        b[r]
                    } else {
                        b[cb + 2 * p + (r - cb)]
                    }
                });
                st.n.push(n);
                st.b.push(bv);
                st.rr.push(*rr);
                st.rows.push(*kept);
            }
            st
        })
        .collect()
}

/// Every row's regressors (weighted), weighted residual and weight, for the step scan: the
/// rows in order, `cols.len()` values each.
pub(crate) fn rows_of(
    problem: &Problem,
    est: &Estimate,
    cols: &[Col],
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let prep = prepare(problem, est);
    let c = cols.len();
    let n = problem.rows();
    let parts: Vec<(Vec<f64>, Vec<f64>)> = chunks(&problem.ranges, 1)
        .into_par_iter()
        .map(|(rows, _)| {
            let mut xs = Vec::with_capacity(rows.len() * c);
            let mut rs = Vec::with_capacity(rows.len());
            let mut x = vec![0.0; c];
            for k in rows {
                let r = problem.row_values(est, &prep, k, cols, &mut x);
                let w = problem.weight[k];
                xs.extend(x.iter().map(|v| v * w));
                rs.push(r * w);
            }
            (xs, rs)
        })
        .collect();
    let mut xs = Vec::with_capacity(n * c);
    let mut rs = Vec::with_capacity(n);
    for (x, r) in parts {
        xs.extend(x);
        rs.extend(r);
    }
    (xs, rs, problem.weight.clone())
}

/// Least squares from normal equations on the columns `sel`: (x, N⁺ diagonal, rank).
pub(crate) fn solve(
    n: &DMatrix<f64>,
    b: &DVector<f64>,
    sel: &[usize],
) -> (DVector<f64>, DVector<f64>, usize) {
    solve_damped(n, b, sel, 0.0)
}

/// [`solve`] with Levenberg-Marquardt damping `lambda` on the column-scaled normal equations
/// (every eigenvalue l becomes l + lambda): 0 is the Gauss-Newton step.
fn solve_damped(
    n: &DMatrix<f64>,
    b: &DVector<f64>,
    sel: &[usize],
    lambda: f64,
) -> (DVector<f64>, DVector<f64>, usize) {
    let k = sel.len();
    if k == 0 {
        return (DVector::zeros(0), DVector::zeros(0), 0);
    }
    let scale: Vec<f64> = sel
        .iter()
        .map(|&i| {
            let v = n[(i, i)];
            if v > 0.0 {
                1.0 / v.sqrt()
            } else {
                0.0
            }
        })
        .collect();
    let ns = DMatrix::from_fn(k, k, |a, c| n[(sel[a], sel[c])] * scale[a] * scale[c]);
    let bs = DVector::from_fn(k, |a, _| b[sel[a]] * scale[a]);
    let eig = SymmetricEigen::new(ns);
    let max = eig.eigenvalues.iter().fold(0.0f64, |m, v| m.max(*v));
    let tol = max * 1e-11;
    let mut x = DVector::zeros(k);
    let mut var = DVector::zeros(k);
    let mut rank = 0;
    for e in 0..k {
        let l = eig.eigenvalues[e];
        if l > tol {
            rank += 1;
            let v = eig.eigenvectors.column(e);
            x += v * (v.dot(&bs) / (l + lambda));
            for a in 0..k {
                var[a] += v[a] * v[a] / l;
            }
        }
    }
    for a in 0..k {
        x[a] *= scale[a];
        var[a] *= scale[a] * scale[a];
    }
    (x, var, rank)
}

/// The pseudo-inverse of the normal matrix on all its columns (column-scaled eigensolve,
/// directions below 1e-11 of the largest dropped): the covariance per unit noise variance.
pub fn inverse(n: &DMatrix<f64>) -> DMatrix<f64> {
    let k = n.nrows();
    if k == 0 {
        return DMatrix::zeros(0, 0);
    }
    let scale: Vec<f64> = (0..k)
        .map(|i| {
            let v = n[(i, i)];
            if v > 0.0 {
                1.0 / v.sqrt()
            } else {
                0.0
            }
        })
        .collect();
    let ns = DMatrix::from_fn(k, k, |a, c| n[(a, c)] * scale[a] * scale[c]);
    let eig = SymmetricEigen::new(ns);
    let max = eig.eigenvalues.iter().fold(0.0f64, |m, v| m.max(*v));
    let mut out = DMatrix::zeros(k, k);
    for e in 0..k {
        let l = eig.eigenvalues[e];
        if l > max * 1e-11 {
            let v = eig.eigenvectors.column(e);
            out += (v * v.transpose()) / l;
        }
    }
    DMatrix::from_fn(k, k, |a, c| out[(a, c)] * scale[a] * scale[c])
}

/// Score of the model on columns `sel`: (RSS, rank, BIC, held-out sum of squares). The
/// held-out sum: each block's rows predicted by the model fitted to the other blocks.
pub(crate) fn score(st: &Stats, sel: &[usize]) -> (f64, usize, f64, f64) {
    let folds = st.n.len();
    let (nt, bt, rr, rows) = st.total();
    let (x, _, rank) = solve(&nt, &bt, sel);
    let bsel = DVector::from_fn(sel.len(), |a, _| bt[sel[a]]);
    let rss = (rr - x.dot(&bsel)).max(rr * 1e-15);
    let nf = (rows as f64).max(1.0);
    let bic = nf * (rss / nf).max(1e-300).ln() + rank as f64 * nf.ln();
    let mut cv = 0.0;
    for f in 0..folds {
        if st.rows[f] == 0 {
            continue;
        }
        let (xf, _, _) = solve(&(&nt - &st.n[f]), &(&bt - &st.b[f]), sel);
        let nsel = DMatrix::from_fn(sel.len(), sel.len(), |a, c| st.n[f][(sel[a], sel[c])]);
        let bsel = DVector::from_fn(sel.len(), |a, _| st.b[f][sel[a]]);
        cv += (st.rr[f] - 2.0 * xf.dot(&bsel) + xf.dot(&(nsel * &xf))).max(0.0);
    }
    (rss, rank, bic, cv)
}

/// The held-out sum of squares (as [`score`]'s) and what white noise of unit variance gives
/// a right model there (per fold, its rows plus the variance of its prediction by the model
/// fitted to the others, tr(N_f · (N − N_f)⁺): by little on a long recording, by a large
/// factor on a few dozen static readings with nearly as many parameters), over the folds
/// whose complement determines every direction the whole data do (same rank), and the rows
/// of those folds; None when no fold does. A fold whose complement leaves a direction undetermined predicts its rows from the
/// minimum-norm solution there: its held-out error then grows with the robot's true error
/// along that direction, which is neither noise nor a model error.
pub(crate) fn heldout_determined(st: &Stats, sel: &[usize]) -> Option<(f64, f64, usize)> {
    let (nt, bt, _, _) = st.total();
    let k = sel.len();
    let (_, _, full) = solve(&nt, &bt, sel);
    let (mut cv, mut noise, mut rows) = (0.0, 0.0, 0);
    for f in 0..st.n.len() {
        if st.rows[f] == 0 {
            continue;
        }
        let (xf, _, rank) = solve(&(&nt - &st.n[f]), &(&bt - &st.b[f]), sel);
        if rank < full {
            continue;
        }
        let nsel = DMatrix::from_fn(k, k, |a, c| st.n[f][(sel[a], sel[c])]);
        let bsel = DVector::from_fn(k, |a, _| st.b[f][sel[a]]);
        cv += (st.rr[f] - 2.0 * xf.dot(&bsel) + xf.dot(&(&nsel * &xf))).max(0.0);
        let rest = DMatrix::from_fn(k, k, |a, c| nt[(sel[a], sel[c])]) - &nsel;
        noise += st.rows[f] as f64 + (nsel * inverse(&rest)).trace().max(0.0);
        rows += st.rows[f];
    }
    (rows > 0).then_some((cv, noise, rows))
}

/// A converged fit: the model's columns (free geometry, then the effects' coefficients), its
/// normal matrix N = JᵀWJ at the estimate, and the residual measured − model per row.
pub struct Fitted {
    pub free: Vec<Param>,
    pub normal: DMatrix<f64>,
    pub residual: Vec<f64>,
    /// Weighted residual sum of squares.
    pub rss: f64,
    /// Rows that count.
    pub rows: usize,
}

impl Fitted {
    /// The number of fitted coefficients (geometry and effects).
    pub fn coefficients(&self) -> usize {
        self.normal.nrows()
    }
}

/// Levenberg-Marquardt on the free geometry `free` and the estimate's effects, from `est`.
pub fn refit(problem: &Problem, est: &mut Estimate, free: &[Param]) -> Fitted {
    let st = refit_stats(problem, est, free);
    let (normal, _, rss, rows) = st.total();
    Fitted {
        free: free.to_vec(),
        normal,
        residual: st.residual,
        rss,
        rows,
    }
}

/// At most this many Gauss-Newton steps per refit. A fit that starts far from its optimum
/// with many nearly collinear columns (joint compliance's general gravity basis on top of a
/// geometry that had absorbed it by hundreds of micrometres) descends by damped steps of a
/// few per cent each: one such fit on the KR 210 takes some 230 steps to converge. A fit
/// near its optimum stops on convergence after a few.
const MAX_REFIT_STEPS: usize = 300;

pub(crate) fn refit_stats(problem: &Problem, est: &mut Estimate, free: &[Param]) -> Stats {
    let cols = model_cols(est, free);
    let sel: Vec<usize> = (0..cols.len()).collect();
    let mut st = accumulate(problem, est, &cols, 1);
    // Gauss-Newton while the model is nearly linear over the step; where it is not (large
    // deflections, a geometry still moving by millimetres, nearly collinear effect columns
    // whose full step overshoots) the damping shortens and turns the step toward steepest
    // descent until it descends. A step is taken only when it descends: the fit never ends
    // worse than where it started.
    let mut lambda = 0.0;
    let mut gain = 1.0;
    for _ in 0..MAX_REFIT_STEPS {
        let before = st.rr[0];
        let mut accepted = None;
        // Near the optimum (the last, undamped step gained little), a step that does not
        // descend means the rounding floor is reached: no damping search.
        let attempts = if gain < 1e-3 && lambda == 0.0 { 1 } else { 10 };
        for _ in 0..attempts {
            let (x, _, _) = solve_damped(&st.n[0], &st.b[0], &sel, lambda);
            let mut trial = est.clone();
            add_step(&mut trial, &cols, &x);
            let st2 = accumulate(problem, &trial, &cols, 1);
            if st2.rr[0] <= before * (1.0 + 1e-9) {
                accepted = Some((trial, st2));
                lambda *= 0.1;
                if lambda < 1e-9 {
                    lambda = 0.0;
                }
                break;
            }
            lambda = if lambda == 0.0 { 1e-6 } else { lambda * 10.0 };
        }
        let Some((trial, st2)) = accepted else {
            break;
        };
        gain = 1.0 - st2.rr[0] / before.max(f64::MIN_POSITIVE);
        *est = trial;
        // Converged when a step gains less than 1e-5 of the sum of squares: the parameters
        // are then within a small fraction of their standard uncertainty of the optimum.
        let done = st2.rr[0] > before * (1.0 - 1e-5);
        st = st2;
        if done {
            break;
        }
    }
    st
}

fn add_step(est: &mut Estimate, cols: &[Col], x: &DVector<f64>) {
    let mut k = 0;
    for c in cols {
        match *c {
            Col::Geo(q) => {
                let v = est.get(q) + x[k];
                est.set(q, v);
            }
            _ => break,
        }
        k += 1;
    }
    for t in est.effects.iter_mut() {
        for v in t.coef.iter_mut() {
            *v += x[k];
            k += 1;
        }
        if t.effect == Effect::ThermalDrift && t.basis.is_lag() {
            let last = t.coef.len() - 1;
            t.coef[last] = t.coef[last].clamp(TAU_RANGE.0, TAU_RANGE.1);
        }
    }
}

/// What a fit holds at its given value by assumption.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Known {
    /// The runs' fixtures (a segment opened at a step is always estimated).
    pub fixture: bool,
    /// The MAP (tool ball centre).
    pub map: bool,
    /// The runs' length zeros (a segment's own zero after a step is always estimated).
    pub offset: bool,
}

/// Which parameters the data can identify at all (Section 2.1.2, on the recorded poses).
/// Preference order, least known first: the MAP (a tool is known to a drawing, link 6 to a
/// machined flange), each group's fixture (a fixture is never known to a micrometre in the
/// robot's frame) and length zero, then the robot's DH in Eq. 6 order. So the MAP takes the
/// place of link 6's parameters, and the first fixture's height and azimuth take d1's and θ1's
/// (the base frame's: a rigid registration removes them). Judged at the estimate `at` (a set-up
/// given far off changes which parameters the poses separate). Returns every parameter's
/// status and the identifiable ones.
pub fn structural(
    problem: &Problem,
    known: &Known,
    at: &Estimate,
) -> (Vec<(Param, model::Status)>, Vec<Param>) {
    let mut params: Vec<Param> = (MAP..N_PARAMS).map(Param::Shared).collect();
    for group in 0..problem.fix_groups.len() {
        params.extend((0..3).map(|axis| Param::Fixture { group, axis }));
    }
    for group in 0..problem.off_groups.len() {
        params.push(Param::Offset { group });
    }
    params.extend((model::ALPHA..MAP).map(Param::Shared));
    // At most ~3000 rows: the rank question does not need every sample; but every row of a
    // short group, so that a segment's own parameters are judged on all its rows.
    let n = problem.rows();
    let stride = (n / 3000).max(1);
    let short = |k: usize| {
        let g = &problem.fix_groups[problem.fix_of[k] as usize];
        let h = &problem.off_groups[problem.off_of[k] as usize];
        g.rows.len().min(h.rows.len()) < 100 * stride
    };
    let rows: Vec<usize> = (0..n)
        .filter(|&k| problem.weight[k] > 0.0 && (k % stride == 0 || short(k)))
        .collect();
    let est = Estimate {
        effects: Vec::new(),
        ..at.clone()
    };
    let prep = prepare(problem, &est);
    let mut cols = DMatrix::zeros(rows.len(), params.len());
    let geo: Vec<Col> = params.iter().map(|&q| Col::Geo(q)).collect();
    let mut x = vec![0.0; geo.len()];
    for (i, &k) in rows.iter().enumerate() {
        problem.row_values(&est, &prep, k, &geo, &mut x);
        for c in 0..geo.len() {
            cols[(i, c)] = x[c];
        }
    }
    let names: Vec<String> = params.iter().map(|&q| problem.param_name(q)).collect();
    let known: Vec<bool> = params
        .iter()
        .map(|q| match *q {
            Param::Shared(i) => model::is_map(i) && known.map,
            Param::Fixture { group, .. } => problem.fix_groups[group].given && known.fixture,
            Param::Offset { group } => problem.off_groups[group].given && known.offset,
        })
        .collect();
    let order: Vec<usize> = (0..params.len()).collect();
    let (info, identifiable) = model::identify::classify(&cols, &names, &order, &known);
    let status = params
        .iter()
        .zip(info)
        .map(|(q, i)| (*q, i.status))
        .collect();
    (
        status,
        identifiable.into_iter().map(|c| params[c]).collect(),
    )
}

/// RMS of a residual.
pub fn rms(r: &[f64]) -> f64 {
    (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt()
}

/// The values of `r` at the rows that count (weight above zero).
pub fn kept_values(r: &[f64], weight: &[f64]) -> Vec<f64> {
    r.iter()
        .zip(weight)
        .filter(|(_, w)| **w > 0.0)
        .map(|(v, _)| *v)
        .collect()
}

/// RMS of the rows that count (weight above zero).
pub fn kept_rms(r: &[f64], weight: &[f64]) -> f64 {
    let (s, n) = r
        .iter()
        .zip(weight)
        .filter(|(_, w)| **w > 0.0)
        .fold((0.0, 0usize), |(s, n), (v, _)| (s + v * v, n + 1));
    (s / n.max(1) as f64).sqrt()
}

/// Bar noise from second differences of the residual (robust: median absolute value).
pub fn noise_estimate(r: &[f64]) -> f64 {
    if r.len() < 5 {
        return rms(r);
    }
    let mut d2: Vec<f64> = r
        .windows(3)
        .map(|w| (w[0] - 2.0 * w[1] + w[2]).abs())
        .collect();
    d2.sort_by(f64::total_cmp);
    1.4826 * d2[d2.len() / 2] / 6f64.sqrt()
}

/// Lag-1 autocorrelation of a residual (white ≈ 0).
pub fn lag1(r: &[f64]) -> f64 {
    let mean = r.iter().sum::<f64>() / r.len().max(1) as f64;
    let var: f64 = r.iter().map(|v| (v - mean).powi(2)).sum();
    if var == 0.0 {
        return 0.0;
    }
    r.windows(2)
        .map(|w| (w[0] - mean) * (w[1] - mean))
        .sum::<f64>()
        / var
}

/// The integrated autocorrelation time of a residual, 1 + 2 Σ ρ_k (Geyer's initial positive
/// sequence: pairs ρ_2m + ρ_2m+1 summed while positive): the factor by which correlated rows
/// inflate the variance of a mean, the number of rows one independent reading is worth.
/// White noise gives 1; an AR(1) of lag-1 correlation ρ gives (1 + ρ)/(1 − ρ). At most n/10.
pub fn correlation_time(r: &[f64]) -> f64 {
    let n = r.len();
    if n < 8 {
        return 1.0;
    }
    let mean = r.iter().sum::<f64>() / n as f64;
    let c0: f64 = r.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
    if c0 == 0.0 {
        return 1.0;
    }
    let rho = |k: usize| -> f64 {
        (0..n - k)
            .map(|i| (r[i] - mean) * (r[i + k] - mean))
            .sum::<f64>()
            / (n as f64 * c0)
    };
    let cap = (n / 10).max(1);
    let mut sum = 0.0;
    let mut m = 0;
    // Γ_m = ρ_2m + ρ_2m+1 (with ρ_0 = 1), summed while positive and not increasing.
    let mut prev = f64::INFINITY;
    while 2 * m + 1 < n.min(2 * cap + 2) {
        let g = if m == 0 { 1.0 } else { rho(2 * m) } + rho(2 * m + 1);
        if g <= 0.0 {
            break;
        }
        let g = g.min(prev);
        sum += g;
        prev = g;
        m += 1;
    }
    (2.0 * sum - 1.0).clamp(1.0, cap as f64)
}

#[cfg(test)]
mod tests {

    /// The order screen's per-candidate sums are those of a full accumulation of the model's
    /// columns and that order's two, fold by fold.
    #[test]
    fn the_order_screen_sums_what_a_full_accumulation_of_each_order_sums() {
        let robot = crate::model::tests::nj130();
        let model = MeasurementModel::new(&robot, Vector3::new(1.2, 0.0, 0.5), Vector3::zeros());
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let q: Vec<[f64; 6]> = (0..700)
            .map(|_| std::array::from_fn(|_| rng.random_range(-1.5..1.5)))
            .collect();
        let m = Measured {
            t: (0..q.len()).map(|i| i as f64).collect(),
            length: q.iter().map(|p| 1.0 + 1e-4 * (17.0 * p[0]).sin()).collect(),
            q,
            form: Form::Static { timed: false },
            ..Measured::default()
        };
        let mut problem = Problem::new(
            &model,
            &[Run {
                measured: &m,
                fixture: model.nominal.fix,
            }],
        );
        problem.weight[3] = 0.0;
        let mut est = Estimate::nominal(&problem);
        est.add_effect(Effect::CyclicError(1), Basis::Harmonics(0b11), 0.0);
        est.effects[0].coef = vec![1e-4, -2e-4, 3e-5, 0.0];
        let free = [Param::Shared(THETA + 1), Param::Shared(A + 2)];
        let base = model_cols(&est, &free);
        let cand = [(0, 17), (1, 9), (5, 40)];
        let got = screen_orders(&problem, &est, &base, &cand, 5);
        for (p, &(j, h)) in cand.iter().enumerate() {
            let mut cols = base.clone();
            cols.extend([Col::Cyc(j, h, false), Col::Cyc(j, h, true)]);
            let want = accumulate(&problem, &est, &cols, 5);
            for f in 0..5 {
                let scale = want.n[f].amax();
                assert!(
                    (&got[p].n[f] - &want.n[f]).amax() <= 1e-12 * scale,
                    "{j} {h} {f}"
                );
                assert!((&got[p].b[f] - &want.b[f]).amax() <= 1e-12 * want.b[f].amax().max(1e-30));
                assert!((got[p].rr[f] - want.rr[f]).abs() <= 1e-12 * want.rr[f]);
                assert_eq!(got[p].rows[f], want.rows[f]);
            }
        }
    }

    /// A cyclic error gains orders in one term, its fitted coefficients kept.
    #[test]
    fn a_cyclic_error_gains_orders_in_one_term_with_its_coefficients_kept() {
        let mut est = Estimate {
            p: [0.0; N_PARAMS],
            fixtures: Vec::new(),
            offsets: Vec::new(),
            effects: Vec::new(),
        };
        est.add_effect(Effect::CyclicError(2), Basis::Harmonics(0b101), 0.0);
        est.add_effect(Effect::Backlash(0), Basis::Standard, 0.0);
        est.effects[0].coef = vec![1.0, 2.0, 3.0, 4.0];
        est.add_effect(
            Effect::CyclicError(2),
            Basis::Harmonics(1 << 16 | 0b10),
            0.0,
        );
        assert_eq!(est.effects.len(), 2);
        let t = &est.effects[1];
        assert_eq!(t.basis.orders(), vec![1, 2, 3, 17]);
        assert_eq!(t.coef, vec![1.0, 2.0, 0.0, 0.0, 3.0, 4.0, 0.0, 0.0]);
        assert_eq!(t.basis.low_orders(), 3);
        assert_eq!(Basis::Harmonics(1 << 16).low_orders(), 0);
    }
    use super::*;
    use std::f64::consts::PI;

    const DEG: f64 = PI / 180.0;

    /// Joint j's angles sweeping `from..to` (deg) densely, as a continuous recording does.
    fn swept(j: usize, spans: &[(f64, f64)]) -> Vec<[f64; 6]> {
        spans
            .iter()
            .flat_map(|&(a, b)| {
                (0..=400).map(move |k| {
                    let mut q = [0.0; 6];
                    q[j] = (a + (b - a) * k as f64 / 400.0) * DEG;
                    q
                })
            })
            .collect()
    }

    #[test]
    fn harmonic_orders_are_capped_by_the_unmeasured_gap_of_the_joint_range() {
        let whole = Some((-PI, PI));
        // The NJ-130 quick start's joint 1: -110..100° of ±180°, a 150° gap holds a whole
        // period of order 3 (120°) but not of order 2 (180°). All six orders were fitted and
        // extrapolated to 684 um RMS over the joint space.
        assert_eq!(harmonic_cap(&swept(0, &[(-110.0, 100.0)]), 0, whole), 2);
        // Measured over the whole turn: every order.
        assert_eq!(
            harmonic_cap(&swept(0, &[(-180.0, 180.0)]), 0, whole),
            MAX_HARMONIC
        );
        // The gap is the largest arc between angles, across ±180° too: two patches leaving
        // 40° out on either side.
        let two = swept(0, &[(-160.0, -20.0), (20.0, 160.0)]);
        assert_eq!(harmonic_cap(&two, 0, whole), 6);
        assert_eq!(harmonic_cap(&two, 0, None), 6);
        let gap_of_100 = swept(0, &[(-130.0, 130.0)]);
        assert_eq!(harmonic_cap(&gap_of_100, 0, whole), 3);
        // A joint of ±360° (a wrist) is a turn too: the angles taken modulo 2π.
        assert_eq!(harmonic_cap(&gap_of_100, 0, Some((-2.0 * PI, 2.0 * PI))), 3);
        // Short of a turn, only the range counts, and an end stretch counts twice: joint 2
        // of the NJ-130 (-60..85°) measured over -18..68° leaves 42° at the lower end (84°),
        // over -60..85° nothing.
        let j2 = Some((-60.0 * DEG, 85.0 * DEG));
        assert_eq!(harmonic_cap(&swept(1, &[(-18.0, 68.0)]), 1, j2), 4);
        assert_eq!(
            harmonic_cap(&swept(1, &[(-60.0, 85.0)]), 1, j2),
            MAX_HARMONIC
        );
        // The first order is always allowed: a joint hardly measured, or not at all.
        assert_eq!(harmonic_cap(&swept(0, &[(0.0, 5.0)]), 0, whole), 1);
        assert_eq!(harmonic_cap(&[], 0, whole), 1);
    }

    #[test]
    fn a_problems_harmonics_reach_past_the_fits_orders_for_the_prediction_bound() {
        // calibrate's effect-model spread compares a cyclic error of orders 1..H with orders
        // up to H + 2 for every H the fit can choose, MAX_HARMONIC included (without that
        // bound six fitted orders would have none), and the screen's single orders up to
        // MAX_ORDER.
        let q = swept(0, &[(-110.0, 100.0)]);
        let means = harmonic_means(&q);
        assert!(means[0].len() >= BOUND_HARMONIC);
        assert_eq!(means[0].len(), MAX_ORDER);
        for (s, c) in means[0] {
            assert!(s.is_finite() && c.is_finite() && s.abs() <= 1.0 && c.abs() <= 1.0);
        }
        // The mean of an order over the range, against a brute-force average.
        let (lo, hi) = (-110f64.to_radians(), 100f64.to_radians());
        let h = 17.0;
        let m = 100_000;
        let avg = (0..m)
            .map(|i| (h * (lo + (hi - lo) * (i as f64 + 0.5) / m as f64)).sin())
            .sum::<f64>()
            / m as f64;
        assert!(
            (means[0][16].0 - avg).abs() < 1e-6,
            "{} {avg}",
            means[0][16].0
        );
    }
}

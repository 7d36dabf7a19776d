//! The fit under the diagnosis and the calibration: in = the measurement model, one or more
//! recorded runs (each with its own fixture), the free parameters and the effects of the
//! model; out = the estimate, its normal equations, residuals and covariance. No file I/O.
//!
//! Every effect of the library enters as regressors that are linear in its few parameters
//! around the current estimate (joint effects: ∂L/∂θ_j · basis; thermal drift:
//! Σ(a ∂L/∂a + d ∂L/∂d) · f(t); servo lag: −Σ ∂L/∂θ_j q̇_j). One parallel pass over the rows
//! (fixed 256-row chunks, summed in order: deterministic) builds the normal equations of any set
//! of columns per contiguous time block, so candidate models and their cross-validation are
//! solved from those sums without touching the rows again. [`refit`] is Levenberg-Marquardt
//! with the effects applied exactly (e.g. the recorded angles re-interpolated at t − τ).
//!
//! A campaign of runs shares the robot (DH, MAP, effects); each run has its own fixture, so
//! the fixture coordinates are parameters per run ([`Param::Fixture`]).

use crate::model::{self, MeasurementModel, Params, A, D, FIX, N_PARAMS, THETA};
use crate::robot::kinematics::chain_frames;
use crate::robot::PointMass;
use crate::twin::effects::{gravity_torques, Effect, G, MOTION_DEADBAND};
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

/// A geometric parameter a fit can move.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Param {
    /// A parameter of the robot shared by every run: Eq. 6 index ≥ 3 (DH, MAP).
    Shared(usize),
    /// Coordinate `axis` (0 = x) of run `run`'s fixture.
    Fixture { run: usize, axis: usize },
}

impl Param {
    /// The report name: Eq. 6's (`a2`, `x_map`); a fixture coordinate is `x_fix`, or
    /// `x_fix[k]` (run k, 1-based) in a campaign of several runs.
    pub fn name(&self, runs: usize) -> String {
        match *self {
            Param::Shared(i) => model::PARAM_NAMES[i].to_string(),
            Param::Fixture { run, axis } => {
                let base = model::PARAM_NAMES[FIX + axis];
                if runs > 1 {
                    format!("{base}[{}]", run + 1)
                } else {
                    base.to_string()
                }
            }
        }
    }

    /// True for angles (rad), false for lengths (m).
    pub fn is_angle(&self) -> bool {
        match *self {
            Param::Shared(i) => model::is_angle(i),
            Param::Fixture { .. } => false,
        }
    }
}

/// How an effect enters the fit. Joint compliance has two forms: with the link masses known
/// (the robot file's inertials) the gravity torque of each joint is known and one compliance
/// per joint remains; without, a general basis (mass and first moments of every link after
/// the joint) times each joint's compliance. The selection tries both; BIC prefers the small
/// one when the masses are right.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Basis {
    Standard,
    KnownMasses,
}

/// One effect of the model and its coefficients.
#[derive(Clone, Debug, PartialEq)]
pub struct Term {
    pub effect: Effect,
    pub basis: Basis,
    pub coef: Vec<f64>,
}

/// The current estimate: shared geometry, one fixture per run, and the coefficients of the
/// effects in the model.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    /// Eq. 6 vector; its fixture entries are run 1's (see `fixtures`).
    pub p: [f64; N_PARAMS],
    pub fixtures: Vec<Vector3<f64>>,
    pub effects: Vec<Term>,
}

impl Estimate {
    /// Nominal geometry, the runs' given fixtures, no effects.
    pub fn nominal(problem: &Problem) -> Self {
        Estimate {
            p: problem.model.nominal.to_array(),
            fixtures: problem.fixtures.clone(),
            effects: Vec::new(),
        }
    }

    /// The parameters of run `run` (its own fixture).
    pub fn params(&self, run: usize) -> Params {
        let mut p = self.p;
        for a in 0..3 {
            p[FIX + a] = self.fixtures[run][a];
        }
        Params::from_array(&p)
    }

    pub fn get(&self, q: Param) -> f64 {
        match q {
            Param::Shared(i) => self.p[i],
            Param::Fixture { run, axis } => self.fixtures[run][axis],
        }
    }

    pub fn add_effect(&mut self, effect: Effect, basis: Basis, thermal_terms: usize) {
        let n = effect_cols(effect, basis, thermal_terms).len();
        self.effects.push(Term {
            effect,
            basis,
            coef: vec![0.0; n],
        });
    }

    fn tau(&self) -> f64 {
        self.effects
            .iter()
            .find(|t| t.effect == Effect::ServoLag)
            .map_or(0.0, |t| t.coef[0])
    }
}

// ---- regressors ---------------------------------------------------------------------------

#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Col {
    Geo(Param),
    /// joint, harmonic 1..3, sine?
    Cyc(usize, usize, bool),
    Back(usize),
    Servo,
    Thermal(usize),
    /// joint j, frame i, component 0 = mass at the origin, 1..3 = first moment along x, y, z.
    Comp(usize, usize, usize),
    /// joint j's compliance times its gravity torque from the known masses.
    CompKnown(usize),
}

pub(crate) fn effect_cols(e: Effect, basis: Basis, thermal_terms: usize) -> Vec<Col> {
    match e {
        Effect::JointCompliance if basis == Basis::KnownMasses => {
            (0..6).map(Col::CompKnown).collect()
        }
        Effect::Geometric => Vec::new(),
        Effect::CyclicError(j) => (1..=3)
            .flat_map(|h| [Col::Cyc(j, h, false), Col::Cyc(j, h, true)])
            .collect(),
        Effect::Backlash(j) => vec![Col::Back(j)],
        Effect::ServoLag => vec![Col::Servo],
        Effect::ThermalDrift => (1..=thermal_terms).map(Col::Thermal).collect(),
        Effect::JointCompliance => (0..6)
            .flat_map(|j| (j + 1..=6).flat_map(move |i| (0..4).map(move |c| Col::Comp(j, i, c))))
            .collect(),
    }
}

/// The columns of a model: the free geometry, then every effect's coefficients in order.
pub(crate) fn model_cols(problem: &Problem, est: &Estimate, free: &[Param]) -> Vec<Col> {
    let mut cols: Vec<Col> = free.iter().map(|&q| Col::Geo(q)).collect();
    for t in &est.effects {
        cols.extend(effect_cols(t.effect, t.basis, problem.thermal_terms));
    }
    cols
}

/// The data of a fit: every run's rows one after the other, and what does not depend on the
/// estimate.
pub struct Problem {
    pub model: MeasurementModel,
    /// The runs' rows, concatenated (each run's times start at its own 0).
    pub m: Measured,
    /// Rows of each run.
    pub ranges: Vec<Range<usize>>,
    /// The run of each row.
    run: Vec<usize>,
    /// The fixtures the runs were given.
    pub fixtures: Vec<Vector3<f64>>,
    qdot: Vec<[f64; 6]>,
    dir: Vec<[f64; 6]>,
    /// Thermal time functions per row (temp rise, or t, t², t³ normalised per run).
    therm: Vec<[f64; 3]>,
    pub thermal_terms: usize,
    /// The robot's link masses (its file's inertials), when it has them.
    pub masses: Vec<PointMass>,
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

/// Joint velocities of one run (5-point stencil inside, one-sided at the ends).
fn velocities(t: &[f64], q: &[[f64; 6]]) -> Vec<[f64; 6]> {
    let n = t.len();
    let mut qdot = vec![[0.0; 6]; n];
    for k in 0..n {
        for j in 0..6 {
            qdot[k][j] = if k >= 2 && k + 2 < n {
                let h = (t[k + 2] - t[k - 2]) / 4.0;
                (-q[k + 2][j] + 8.0 * q[k + 1][j] - 8.0 * q[k - 1][j] + q[k - 2][j]) / (12.0 * h)
            } else {
                let (a, b) = (k.saturating_sub(1), (k + 1).min(n - 1));
                if b > a {
                    (q[b][j] - q[a][j]) / (t[b] - t[a])
                } else {
                    0.0
                }
            };
        }
    }
    qdot
}

/// Backlash: direction of the last motion between samples (the twin's rule); before the first
/// motion, that of the first.
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

impl Problem {
    /// The rows of every run, in order. Temperatures are used for thermal drift only when
    /// every run has them.
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
        let (mut qdot, mut dir, mut therm) = (
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        );
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
            qdot.extend(velocities(&rm.t, &rm.q));
            dir.extend(directions(&rm.q));
            match (&mut m.temp, &rm.temp) {
                (Some(all), Some(temp)) => {
                    all.extend_from_slice(temp);
                    therm.extend(temp.iter().map(|c| [c - temp[0], 0.0, 0.0]));
                }
                _ => {
                    let (t0, t1) = (rm.t[0], rm.t[rm.len() - 1]);
                    let span = (t1 - t0).max(1e-9);
                    therm.extend(rm.t.iter().map(|t| {
                        let u = (t - t0) / span;
                        [u, u * u, u * u * u]
                    }));
                }
            }
        }
        Problem {
            model: model.clone(),
            m,
            ranges,
            run,
            fixtures: runs.iter().map(|r| r.fixture).collect(),
            qdot,
            dir,
            therm,
            thermal_terms: if with_temp { 1 } else { 3 },
            masses: Vec::new(),
        }
    }

    /// The robot's link masses, for the known-mass form of joint compliance.
    pub fn with_masses(mut self, masses: &[PointMass]) -> Self {
        self.masses = masses.to_vec();
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

    /// Recorded angles of row k's run, re-interpolated at that run's time `at`.
    fn interp_run(&self, k: usize, values: &[[f64; 6]], at: f64) -> [f64; 6] {
        let r = self.ranges[self.run[k]].clone();
        interp(&self.m.t[r.clone()], &values[r], at)
    }

    /// Effective (load-side) configuration and parameters of row k under the estimate.
    pub fn apply(&self, est: &Estimate, k: usize) -> ([f64; 6], Params) {
        let tau = est.tau();
        let q0 = if tau != 0.0 {
            self.interp_run(k, &self.m.q, self.m.t[k] - tau)
        } else {
            self.m.q[k]
        };
        let mut p = est.params(self.run[k]).to_array();
        let mut q = q0;
        let mut frames = None;
        for t in &est.effects {
            let c = &t.coef;
            match t.effect {
                Effect::CyclicError(j) => {
                    for h in 0..3 {
                        let (sn, cs) = ((h + 1) as f64 * q0[j]).sin_cos();
                        q[j] += c[2 * h] * cs + c[2 * h + 1] * sn;
                    }
                }
                Effect::Backlash(j) => q[j] -= 0.5 * c[0] * self.dir[k][j],
                Effect::ThermalDrift => {
                    let f: f64 = (0..c.len()).map(|h| c[h] * self.therm[k][h]).sum();
                    for i in 0..6 {
                        p[A + i] *= 1.0 + f;
                        p[D + i] *= 1.0 + f;
                    }
                }
                Effect::JointCompliance if t.basis == Basis::KnownMasses => {
                    let tau = gravity_torques(
                        &self.model,
                        &Params::from_array(&est.p),
                        &q0,
                        &self.masses,
                    );
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
                            &q0,
                        )
                    });
                    let cols = effect_cols(Effect::JointCompliance, Basis::Standard, 0);
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

    /// Fills the regressor values of row k for `cols`; returns the residual measured − model.
    fn row_values(&self, est: &Estimate, k: usize, cols: &[Col], out: &mut [f64]) -> f64 {
        let (q, p) = self.apply(est, k);
        let mut j = [0.0; N_PARAMS];
        let len = self.model.jacobian_row(&p, &q, &mut j);
        let needs_frames = cols.iter().any(|c| matches!(c, Col::Comp(..)));
        let fr =
            needs_frames.then(|| chain_frames(&self.model.base, &p.dh, &self.model.flange, &q));
        let needs_torques = cols.iter().any(|c| matches!(c, Col::CompKnown(..)));
        let torques = needs_torques.then(|| gravity_torques(&self.model, &p, &q, &self.masses));
        let tau = est.tau();
        let qd = if tau != 0.0 {
            self.interp_run(k, &self.qdot, self.m.t[k] - tau)
        } else {
            self.qdot[k]
        };
        let run = self.run[k];
        for (o, c) in out.iter_mut().zip(cols) {
            *o = match *c {
                Col::Geo(Param::Shared(i)) => j[i],
                Col::Geo(Param::Fixture { run: r, axis }) => {
                    if r == run {
                        j[FIX + axis]
                    } else {
                        0.0
                    }
                }
                Col::Cyc(jj, h, sine) => {
                    let a = h as f64 * q[jj];
                    j[THETA + jj] * if sine { a.sin() } else { a.cos() }
                }
                Col::Back(jj) => -0.5 * j[THETA + jj] * self.dir[k][jj],
                Col::Servo => -(0..6).map(|i| j[THETA + i] * qd[i]).sum::<f64>(),
                Col::Thermal(h) => {
                    let sens: f64 = (0..6)
                        .map(|i| est.p[A + i] * j[A + i] + est.p[D + i] * j[D + i])
                        .sum();
                    sens * self.therm[k][h - 1]
                }
                Col::Comp(jj, i, comp) => match &fr {
                    Some(fr) => j[THETA + jj] * gravity_basis(fr, jj, i, comp),
                    None => 0.0,
                },
                Col::CompKnown(jj) => match &torques {
                    Some(tau) => j[THETA + jj] * tau[jj],
                    None => 0.0,
                },
            };
        }
        self.m.length[k] - len
    }
}

/// Torque about joint j per unit mass (comp 0, mass at frame i's origin) or per unit first
/// moment along frame i's axis comp (1..3), gravity −z of the base.
fn gravity_basis(fr: &[crate::robot::Frame; 8], j: usize, i: usize, comp: usize) -> f64 {
    let z = fr[j].r.column(2);
    let f = Vector3::new(0.0, 0.0, -G);
    let arm = if comp == 0 {
        fr[i].t - fr[j].t
    } else {
        fr[i].r.column(comp - 1).into_owned()
    };
    z.dot(&arm.cross(&f))
}

/// Normal equations per fold.
pub(crate) struct Stats {
    pub c: usize,
    /// Per fold: N (c×c, full), b, rᵀr, rows.
    pub n: Vec<DMatrix<f64>>,
    pub b: Vec<DVector<f64>>,
    pub rr: Vec<f64>,
    pub rows: Vec<usize>,
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

/// One chunk's partial sums: N (row-major upper triangle), b, rᵀr, residuals.
type Partial = (Vec<f64>, Vec<f64>, f64, Vec<f64>);

pub(crate) fn accumulate(problem: &Problem, est: &Estimate, cols: &[Col], folds: usize) -> Stats {
    let n = problem.rows();
    let c = cols.len();
    let chunks = n.div_ceil(CHUNK);
    let parts: Vec<Partial> = (0..chunks)
        .into_par_iter()
        .map(|ch| {
            let mut nn = vec![0.0; c * c];
            let mut b = vec![0.0; c];
            let mut rr = 0.0;
            let mut res = Vec::with_capacity(CHUNK);
            let mut x = vec![0.0; c];
            for k in ch * CHUNK..((ch + 1) * CHUNK).min(n) {
                let r = problem.row_values(est, k, cols, &mut x);
                res.push(r);
                rr += r * r;
                for a in 0..c {
                    let xa = x[a];
                    if xa == 0.0 {
                        continue;
                    }
                    b[a] += xa * r;
                    let row = &mut nn[a * c..a * c + c];
                    for bb in a..c {
                        row[bb] += xa * x[bb];
                    }
                }
            }
            (nn, b, rr, res)
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
    for (ch, (nn, b, rr, res)) in parts.into_iter().enumerate() {
        let f = ch * folds / chunks.max(1);
        for a in 0..c {
            st.b[f][a] += b[a];
            for bb in a..c {
                st.n[f][(a, bb)] += nn[a * c + bb];
            }
        }
        st.rr[f] += rr;
        st.rows[f] += res.len();
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

/// Score of the model on columns `sel`: (RSS, rank, BIC, CV sum of squares).
pub(crate) fn score(st: &Stats, sel: &[usize]) -> (f64, usize, f64, f64) {
    let folds = st.n.len();
    let (nt, bt, rr, rows) = st.total();
    let (x, _, rank) = solve(&nt, &bt, sel);
    let bsel = DVector::from_fn(sel.len(), |a, _| bt[sel[a]]);
    let rss = (rr - x.dot(&bsel)).max(rr * 1e-15);
    let nf = rows as f64;
    let bic = nf * (rss / nf).ln() + rank as f64 * nf.ln();
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

/// A converged fit: the model's columns (free geometry, then the effects' coefficients), its
/// normal matrix N = JᵀJ at the estimate, and the residual measured − model per row.
pub struct Fitted {
    pub free: Vec<Param>,
    pub normal: DMatrix<f64>,
    pub residual: Vec<f64>,
    pub rss: f64,
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
    let (normal, _, rss, _) = st.total();
    Fitted {
        free: free.to_vec(),
        normal,
        residual: st.residual,
        rss,
    }
}

pub(crate) fn refit_stats(problem: &Problem, est: &mut Estimate, free: &[Param]) -> Stats {
    let cols = model_cols(problem, est, free);
    let sel: Vec<usize> = (0..cols.len()).collect();
    let mut st = accumulate(problem, est, &cols, 1);
    // Gauss-Newton while the model is nearly linear over the step; where it is not (large
    // deflections, a geometry still moving by millimetres, nearly collinear effect columns
    // whose full step overshoots) the damping shortens and turns the step toward steepest
    // descent until it descends. A step is taken only when it descends: the fit never ends
    // worse than where it started.
    let mut lambda = 0.0;
    for _ in 0..30 {
        let before = st.rr[0];
        let mut accepted = None;
        for _ in 0..8 {
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
        *est = trial;
        let done = st2.rr[0] > before * (1.0 - 1e-6);
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
            Col::Geo(Param::Shared(i)) => est.p[i] += x[k],
            Col::Geo(Param::Fixture { run, axis }) => est.fixtures[run][axis] += x[k],
            _ => break,
        }
        k += 1;
    }
    for t in est.effects.iter_mut() {
        for v in t.coef.iter_mut() {
            *v += x[k];
            k += 1;
        }
    }
}

/// Which parameters the data can identify at all (Section 2.1.2, on the recorded poses): the
/// shared geometry in Eq. 6's preference order (DH, then the MAP), then the fixtures run by
/// run. Returns every parameter's status and the identifiable ones.
pub fn structural(
    problem: &Problem,
    fixture_free: bool,
    map_free: bool,
) -> (Vec<(Param, model::Status)>, Vec<Param>) {
    let runs = problem.runs();
    let mut params: Vec<Param> = (model::ALPHA..N_PARAMS).map(Param::Shared).collect();
    for run in 0..runs {
        params.extend((0..3).map(|axis| Param::Fixture { run, axis }));
    }
    // At most ~3000 rows: the rank question does not need every sample.
    let stride = (problem.rows() / 3000).max(1);
    let rows: Vec<usize> = (0..problem.rows()).step_by(stride).collect();
    let est = Estimate::nominal(problem);
    let cols = DMatrix::from_fn(rows.len(), params.len(), |_, _| 0.0);
    let mut cols = cols;
    for (i, &k) in rows.iter().enumerate() {
        let mut j = [0.0; N_PARAMS];
        let run = problem.run_of(k);
        problem
            .model
            .jacobian_row(&est.params(run), &problem.m.q[k], &mut j);
        for (c, q) in params.iter().enumerate() {
            cols[(i, c)] = match *q {
                Param::Shared(s) => j[s],
                Param::Fixture { run: r, axis } if r == run => j[FIX + axis],
                Param::Fixture { .. } => 0.0,
            };
        }
    }
    let names: Vec<String> = params.iter().map(|q| q.name(runs)).collect();
    let known: Vec<bool> = params
        .iter()
        .map(|q| match *q {
            Param::Shared(i) => model::is_map(i) && !map_free,
            Param::Fixture { .. } => !fixture_free,
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

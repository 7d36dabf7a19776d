//! Diagnosis: in = measurement model + measured EDBB data; out = where simulation and
//! measurement disagree, the calibrated geometry, the effects that explain what remains, and
//! the `edbbgen.diagnose/1` report (DESIGN.md). No file I/O.
//!
//! Method. Every effect of the library enters as regressors that are linear in its few
//! parameters around the current estimate (joint effects: ∂L/∂θ_j · basis; thermal drift:
//! Σ(a ∂L/∂a + d ∂L/∂d) · f(t); servo lag: −Σ ∂L/∂θ_j q̇_j). One pass over the rows builds the
//! normal equations of the geometry *and every candidate* per contiguous time block; any
//! candidate model, and its k-fold cross-validation over the blocks, is then solved from those
//! sums without touching the rows again. A candidate is accepted only when it lowers both the
//! BIC and the cross-validated error clearly and explains a good part of the excess over the
//! noise; the accepted model is refitted by Gauss-Newton (exact effect application, e.g. the
//! recorded angles re-interpolated at t − τ), and the loop repeats until the residual is at the
//! noise level and white, or nothing helps.

pub mod plot;

use crate::model::{self, IdentifyOptions, MeasurementModel, Params, A, D, N_PARAMS, THETA};
use crate::robot::kinematics::chain_frames;
use crate::twin::effects::{Effect, G, MOTION_DEADBAND};
use crate::twin::Measured;
use crate::units::{fmt_fixed, to_deg, DEG, MM};
use nalgebra::{DMatrix, DVector, SymmetricEigen, Vector3};
use rayon::prelude::*;
use serde::Serialize;

#[derive(Clone, Debug)]
pub struct DiagnoseOptions {
    /// Contiguous time blocks for cross-validation.
    pub folds: usize,
    /// At most this many effects after the geometry.
    pub max_effects: usize,
}

impl Default for DiagnoseOptions {
    fn default() -> Self {
        DiagnoseOptions {
            folds: 8,
            max_effects: 3,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error("{0}")]
    Data(String),
}

/// Where a residual is largest: time span, joint ranges, peak.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Where {
    pub t_s: [f64; 2],
    pub joints_deg: Vec<[f64; 2]>,
    pub peak_um: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct StepReport {
    pub effect: &'static str,
    pub joint: Option<usize>,
    pub rms_after_um: f64,
    pub params: serde_json::Map<String, serde_json::Value>,
    /// Standard uncertainties of `params` (same keys, same units).
    pub std: serde_json::Map<String, serde_json::Value>,
    pub bic: f64,
    pub cv_rms_um: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct NamedEffect {
    pub effect: &'static str,
    pub joint: Option<usize>,
}

/// The `edbbgen.diagnose/1` report (DESIGN.md); keys after `steps` are additions.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub rms_nominal_um: f64,
    pub named_effects: Vec<NamedEffect>,
    pub unexplained: bool,
    #[serde(rename = "where")]
    pub where_: Option<Where>,
    pub rms_final_um: f64,
    pub steps: Vec<StepReport>,
    pub rows: usize,
    pub duration_s: f64,
    /// Noise of the bar estimated from the high-frequency part of the residual.
    pub noise_um: f64,
    /// Lag-1 autocorrelation of the final residual (white ≈ 0).
    pub lag1_final: f64,
    /// Where the nominal model and the measurement disagree most.
    pub nominal_where: Option<Where>,
}

/// The report plus the residual after each stage (for the plot) and a human summary.
#[derive(Clone, Debug)]
pub struct Diagnosis {
    pub report: Report,
    pub t: Vec<f64>,
    /// (stage label, residual in metres per row).
    pub stages: Vec<(String, Vec<f64>)>,
    pub summary: String,
}

// ---- regressors ---------------------------------------------------------------------------

#[derive(Clone, Copy, Debug, PartialEq)]
enum Col {
    Geo(usize),
    /// joint, harmonic 1..3, sine?
    Cyc(usize, usize, bool),
    Back(usize),
    Servo,
    Thermal(usize),
    /// joint j, frame i, component 0 = mass at the origin, 1..3 = first moment along x, y, z.
    Comp(usize, usize, usize),
}

fn effect_cols(e: Effect, thermal_terms: usize) -> Vec<Col> {
    match e {
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

/// Per-row data that does not depend on the estimate.
struct Data<'a> {
    m: &'a Measured,
    qdot: Vec<[f64; 6]>,
    dir: Vec<[f64; 6]>,
    /// Thermal time functions per row (temp rise, or t, t², t³ normalised).
    therm: Vec<[f64; 3]>,
    thermal_terms: usize,
}

/// The current estimate: geometry and the coefficients of the accepted effects.
#[derive(Clone, Debug)]
struct State {
    p: [f64; N_PARAMS],
    effects: Vec<(Effect, Vec<f64>)>,
}

impl State {
    fn tau(&self) -> f64 {
        self.effects
            .iter()
            .find(|(e, _)| *e == Effect::ServoLag)
            .map_or(0.0, |(_, c)| c[0])
    }
}

/// Quintic (6-point) Lagrange interpolation of the recorded angles at time t: servo lags are
/// a fraction of the sample period, and the interpolation error must stay below the bar noise.
fn interp(t: &[f64], q: &[[f64; 6]], at: f64) -> [f64; 6] {
    let n = t.len();
    let k = t.partition_point(|&x| x <= at);
    let lo = k.saturating_sub(3).min(n.saturating_sub(6));
    let idx = lo..(lo + 6).min(n);
    let idx: Vec<usize> = idx.collect();
    let mut out = [0.0; 6];
    for &a in &idx {
        let mut w = 1.0;
        for &b in &idx {
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

impl Data<'_> {
    fn new(m: &Measured) -> Data<'_> {
        let n = m.len();
        let mut qdot = vec![[0.0; 6]; n];
        for k in 0..n {
            for j in 0..6 {
                qdot[k][j] = if k >= 2 && k + 2 < n {
                    let h = (m.t[k + 2] - m.t[k - 2]) / 4.0;
                    (-m.q[k + 2][j] + 8.0 * m.q[k + 1][j] - 8.0 * m.q[k - 1][j] + m.q[k - 2][j])
                        / (12.0 * h)
                } else {
                    let (a, b) = (k.saturating_sub(1), (k + 1).min(n - 1));
                    if b > a {
                        (m.q[b][j] - m.q[a][j]) / (m.t[b] - m.t[a])
                    } else {
                        0.0
                    }
                };
            }
        }
        // Backlash: direction of the last motion between samples (the twin's rule); before the
        // first motion, that of the first.
        let mut dir = vec![[0.0; 6]; n];
        for j in 0..6 {
            let step = |k: usize| m.q[k][j] - m.q[k - 1][j];
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
        let (t0, t1) = (m.t[0], m.t[n - 1]);
        let span = (t1 - t0).max(1e-9);
        let (therm, thermal_terms) = match &m.temp {
            Some(temp) => (temp.iter().map(|c| [c - temp[0], 0.0, 0.0]).collect(), 1),
            None => (
                m.t.iter()
                    .map(|t| {
                        let u = (t - t0) / span;
                        [u, u * u, u * u * u]
                    })
                    .collect(),
                3,
            ),
        };
        Data {
            m,
            qdot,
            dir,
            therm,
            thermal_terms,
        }
    }
}

/// Effective (load-side) configuration and parameters of row k under the estimate.
fn apply(model: &MeasurementModel, d: &Data, s: &State, k: usize) -> ([f64; 6], Params) {
    let tau = s.tau();
    let q0 = if tau != 0.0 {
        interp(&d.m.t, &d.m.q, d.m.t[k] - tau)
    } else {
        d.m.q[k]
    };
    let mut p = s.p;
    let mut q = q0;
    let mut frames = None;
    for (e, c) in &s.effects {
        match e {
            Effect::CyclicError(j) => {
                for h in 0..3 {
                    let (sn, cs) = ((h + 1) as f64 * q0[*j]).sin_cos();
                    q[*j] += c[2 * h] * cs + c[2 * h + 1] * sn;
                }
            }
            Effect::Backlash(j) => q[*j] -= 0.5 * c[0] * d.dir[k][*j],
            Effect::ThermalDrift => {
                let f: f64 = (0..c.len()).map(|h| c[h] * d.therm[k][h]).sum();
                for i in 0..6 {
                    p[A + i] *= 1.0 + f;
                    p[D + i] *= 1.0 + f;
                }
            }
            Effect::JointCompliance => {
                let fr = frames.get_or_insert_with(|| {
                    chain_frames(
                        &model.base,
                        &Params::from_array(&s.p).dh,
                        &model.flange,
                        &q0,
                    )
                });
                for (n, col) in effect_cols(Effect::JointCompliance, 0).iter().enumerate() {
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

/// Fills the regressor values of row k for `cols`; returns the residual measured − model.
fn row_values(
    model: &MeasurementModel,
    d: &Data,
    s: &State,
    k: usize,
    cols: &[Col],
    out: &mut [f64],
) -> f64 {
    let (q, p) = apply(model, d, s, k);
    let mut j = [0.0; N_PARAMS];
    let len = model.jacobian_row(&p, &q, &mut j);
    let needs_frames = cols.iter().any(|c| matches!(c, Col::Comp(..)));
    let fr = needs_frames.then(|| chain_frames(&model.base, &p.dh, &model.flange, &q));
    let tau = s.tau();
    let qd = if tau != 0.0 {
        interp(&d.m.t, &d.qdot, d.m.t[k] - tau)
    } else {
        d.qdot[k]
    };
    let q0 = q;
    for (o, c) in out.iter_mut().zip(cols) {
        *o = match *c {
            Col::Geo(i) => j[i],
            Col::Cyc(jj, h, sine) => {
                let a = h as f64 * q0[jj];
                j[THETA + jj] * if sine { a.sin() } else { a.cos() }
            }
            Col::Back(jj) => -0.5 * j[THETA + jj] * d.dir[k][jj],
            Col::Servo => -(0..6).map(|i| j[THETA + i] * qd[i]).sum::<f64>(),
            Col::Thermal(h) => {
                let sens: f64 = (0..6)
                    .map(|i| s.p[A + i] * j[A + i] + s.p[D + i] * j[D + i])
                    .sum();
                sens * d.therm[k][h - 1]
            }
            Col::Comp(jj, i, comp) => match &fr {
                Some(fr) => j[THETA + jj] * gravity_basis(fr, jj, i, comp),
                None => 0.0,
            },
        };
    }
    d.m.length[k] - len
}

/// Normal equations per fold.
struct Stats {
    c: usize,
    /// Per fold: N (c×c, full), b, rᵀr, rows.
    n: Vec<DMatrix<f64>>,
    b: Vec<DVector<f64>>,
    rr: Vec<f64>,
    rows: Vec<usize>,
    residual: Vec<f64>,
}

const CHUNK: usize = 256;

/// One chunk's partial sums: N (row-major upper triangle), b, rᵀr, residuals.
type Partial = (Vec<f64>, Vec<f64>, f64, Vec<f64>);

fn accumulate(model: &MeasurementModel, d: &Data, s: &State, cols: &[Col], folds: usize) -> Stats {
    let n = d.m.len();
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
                let r = row_values(model, d, s, k, cols, &mut x);
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
fn solve(n: &DMatrix<f64>, b: &DVector<f64>, sel: &[usize]) -> (DVector<f64>, DVector<f64>, usize) {
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

/// Score of the model on columns `sel`: (RSS, rank, BIC, CV sum of squares).
fn score(st: &Stats, sel: &[usize]) -> (f64, usize, f64, f64) {
    let folds = st.n.len();
    let mut nt = DMatrix::zeros(st.c, st.c);
    let mut bt = DVector::zeros(st.c);
    for f in 0..folds {
        nt += &st.n[f];
        bt += &st.b[f];
    }
    let rr: f64 = st.rr.iter().sum();
    let rows: usize = st.rows.iter().sum();
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

fn rms(r: &[f64]) -> f64 {
    (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt()
}

/// Bar noise from second differences of the residual (robust: median absolute value).
fn noise_estimate(r: &[f64]) -> f64 {
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

fn lag1(r: &[f64]) -> f64 {
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

/// The time span and joint ranges of the largest residual cluster (1 s moving RMS).
fn locate(m: &Measured, r: &[f64]) -> Option<Where> {
    let n = r.len();
    if n == 0 {
        return None;
    }
    let dt = (m.t[n - 1] - m.t[0]) / (n.max(2) - 1) as f64;
    let w = ((1.0 / dt.max(1e-6)) as usize).clamp(1, n);
    let mut pre = vec![0.0; n + 1];
    for k in 0..n {
        pre[k + 1] = pre[k] + r[k] * r[k];
    }
    let mov: Vec<f64> = (0..n)
        .map(|k| {
            let (a, b) = (k.saturating_sub(w / 2), (k + w / 2 + 1).min(n));
            ((pre[b] - pre[a]) / (b - a) as f64).sqrt()
        })
        .collect();
    let (peak_k, peak) =
        mov.iter().enumerate().fold(
            (0, 0.0),
            |(bk, bv), (k, v)| if *v > bv { (k, *v) } else { (bk, bv) },
        );
    let half = 0.5 * peak;
    let mut a = peak_k;
    while a > 0 && mov[a - 1] >= half {
        a -= 1;
    }
    let mut b = peak_k;
    while b + 1 < n && mov[b + 1] >= half {
        b += 1;
    }
    let joints_deg = (0..6)
        .map(|j| {
            let (lo, hi) = m.q[a..=b].iter().fold((f64::MAX, f64::MIN), |(lo, hi), q| {
                (lo.min(q[j]), hi.max(q[j]))
            });
            [round(to_deg(lo), 3), round(to_deg(hi), 3)]
        })
        .collect();
    let peak_abs = r[a..=b].iter().fold(0.0f64, |mx, v| mx.max(v.abs()));
    Some(Where {
        t_s: [round(m.t[a], 3), round(m.t[b], 3)],
        joints_deg,
        peak_um: round(peak_abs * 1e6, 3),
    })
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

// ---- the loop -----------------------------------------------------------------------------

/// The candidates tried after the geometry.
fn candidates() -> Vec<Effect> {
    let mut c = vec![
        Effect::JointCompliance,
        Effect::ThermalDrift,
        Effect::ServoLag,
    ];
    c.extend((0..6).map(Effect::CyclicError));
    c.extend((0..6).map(Effect::Backlash));
    c
}

/// Gauss-Newton on the geometry `geo` and the accepted effects, from `s`.
fn refit(model: &MeasurementModel, d: &Data, s: &mut State, geo: &[usize]) -> Stats {
    let cols = model_cols(d, s, geo);
    let sel: Vec<usize> = (0..cols.len()).collect();
    let mut st = accumulate(model, d, s, &cols, 1);
    // Levenberg-Marquardt: Gauss-Newton while the model is nearly linear over the step; where
    // it is not (large deflections, a geometry still moving by millimetres, nearly collinear
    // effect columns whose full step overshoots) the damping shortens and turns the step
    // toward steepest descent until it descends.
    let mut lambda = 0.0;
    for _ in 0..30 {
        let before = st.rr[0];
        let mut accepted = None;
        for _ in 0..8 {
            let (x, _, _) = solve_damped(&st.n[0], &st.b[0], &sel, lambda);
            let mut trial = s.clone();
            add_step(&mut trial, &cols, &x);
            let st2 = accumulate(model, d, &trial, &cols, 1);
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
        *s = trial;
        let done = st2.rr[0] > before * (1.0 - 1e-6);
        st = st2;
        if done {
            break;
        }
    }
    st
}

fn model_cols(d: &Data, s: &State, geo: &[usize]) -> Vec<Col> {
    let mut cols: Vec<Col> = geo.iter().map(|&i| Col::Geo(i)).collect();
    for (e, _) in &s.effects {
        cols.extend(effect_cols(*e, d.thermal_terms));
    }
    cols
}

fn add_step(s: &mut State, cols: &[Col], x: &DVector<f64>) {
    let mut k = 0;
    for c in cols {
        if let Col::Geo(i) = c {
            s.p[*i] += x[k];
            k += 1;
        }
    }
    for (_, coef) in s.effects.iter_mut() {
        for v in coef.iter_mut() {
            *v += x[k];
            k += 1;
        }
    }
}

/// Runs the diagnosis.
pub fn run(
    model: &MeasurementModel,
    m: &Measured,
    opts: &DiagnoseOptions,
) -> Result<Diagnosis, DiagnoseError> {
    if m.len() < N_PARAMS + 2 {
        return Err(DiagnoseError::Data(format!(
            "{} rows: at least {} are needed",
            m.len(),
            N_PARAMS + 2
        )));
    }
    let d = Data::new(m);
    let folds = opts.folds.clamp(2, 20).min(m.len() / CHUNK).max(2);
    // Identifiable set on the recorded poses (fixture and MAP free: calibration absorbs them).
    let stride = (m.len() / 3000).max(1);
    let jrows: Vec<[f64; N_PARAMS]> = (0..m.len())
        .step_by(stride)
        .map(|k| {
            let mut r = [0.0; N_PARAMS];
            model.jacobian_row(&model.nominal, &m.q[k], &mut r);
            r
        })
        .collect();
    let id = model::analyse(
        &jrows,
        &IdentifyOptions {
            fixture_known: false,
            map_known: false,
        },
    );
    let geo = id.identifiable.clone();

    let mut s = State {
        p: model.nominal.to_array(),
        effects: Vec::new(),
    };
    let nominal_res = accumulate(model, &d, &s, &[], 1).residual;
    let rms_nominal = rms(&nominal_res);
    let mut stages = vec![("nominal".to_string(), nominal_res.clone())];

    // Calibration: the geometric fit.
    let st = refit(model, &d, &mut s, &geo);
    let mut residual = st.residual.clone();
    let (x_var, bic0, cv0) = {
        let sel: Vec<usize> = (0..st.c).collect();
        let (_, var, _) = solve(&st.n[0], &st.b[0], &sel);
        let (_, _, bic, cv) = score(&st, &sel);
        (var, bic, cv)
    };
    let n = m.len() as f64;
    let sigma2 = st.rr[0] / (n - geo.len() as f64).max(1.0);
    let mut params = serde_json::Map::new();
    let mut std = serde_json::Map::new();
    for (k, &i) in geo.iter().enumerate() {
        let unit = if model::is_angle(i) { DEG } else { MM };
        let dev = (s.p[i] - model.nominal.to_array()[i]) / unit;
        params.insert(model::PARAM_NAMES[i].into(), round(dev, 6).into());
        std.insert(
            model::PARAM_NAMES[i].into(),
            round((x_var[k] * sigma2).sqrt() / unit, 6).into(),
        );
    }
    let mut steps = vec![StepReport {
        effect: "geometric",
        joint: None,
        rms_after_um: round(rms(&residual) * 1e6, 3),
        params,
        std,
        bic: round(bic0, 1),
        cv_rms_um: round((cv0 / n).sqrt() * 1e6, 3),
    }];
    stages.push(("geometric".to_string(), residual.clone()));
    let mut named = vec![NamedEffect {
        effect: "geometric",
        joint: None,
    }];

    let mut noise = noise_estimate(&residual);
    for _ in 0..opts.max_effects {
        noise = noise.min(noise_estimate(&residual));
        let r_now = rms(&residual);
        if r_now <= 1.5 * noise && lag1(&residual) < 0.2 {
            break;
        }
        // One pass: the current model's columns plus every candidate's.
        let base_cols = model_cols(&d, &s, &geo);
        let mut cols = base_cols.clone();
        let mut groups = Vec::new();
        for e in candidates() {
            if s.effects.iter().any(|(a, _)| *a == e) {
                continue;
            }
            let ec = effect_cols(e, d.thermal_terms);
            groups.push((e, cols.len()..cols.len() + ec.len()));
            cols.extend(ec);
        }
        let st = accumulate(model, &d, &s, &cols, folds);
        let base_sel: Vec<usize> = (0..base_cols.len()).collect();
        let (rss0, _, bic0, cv0) = score(&st, &base_sel);
        let excess = (rss0 - n * noise * noise).max(0.0);
        let scored: Vec<(Effect, f64, f64, f64)> = groups
            .par_iter()
            .map(|(e, range)| {
                let sel: Vec<usize> = base_sel.iter().copied().chain(range.clone()).collect();
                let (rss, _, bic, cv) = score(&st, &sel);
                (*e, rss, bic, cv)
            })
            .collect();
        let best = scored
            .iter()
            .filter(|(_, rss, bic, cv)| {
                *bic < bic0 - 10.0 && *cv < 0.95 * cv0 && rss0 - rss >= 0.6 * excess
            })
            .min_by(|a, b| a.2.total_cmp(&b.2));
        let Some(&(e, _, bic, cv)) = best else {
            break;
        };
        let ncoef = effect_cols(e, d.thermal_terms).len();
        s.effects.push((e, vec![0.0; ncoef]));
        let st = refit(model, &d, &mut s, &geo);
        residual = st.residual.clone();
        let mut params = serde_json::Map::new();
        let coef = &s.effects.last().map(|x| x.1.clone()).unwrap_or_default();
        match e {
            Effect::CyclicError(_) => {
                let c: Vec<f64> = (0..3).map(|h| round(to_deg(coef[2 * h]), 6)).collect();
                let sn: Vec<f64> = (0..3).map(|h| round(to_deg(coef[2 * h + 1]), 6)).collect();
                params.insert("cos_deg".into(), c.into());
                params.insert("sin_deg".into(), sn.into());
            }
            Effect::Backlash(_) => {
                params.insert("play_deg".into(), round(to_deg(coef[0]), 6).into());
            }
            Effect::ServoLag => {
                params.insert("tau_s".into(), round(coef[0], 6).into());
            }
            Effect::ThermalDrift => {
                let key = if m.temp.is_some() {
                    "alpha_per_k"
                } else {
                    "scale_poly_t"
                };
                let v: Vec<f64> = coef.iter().map(|c| round(*c, 12)).collect();
                params.insert(key.into(), v.into());
            }
            Effect::JointCompliance => {
                let used = coef.iter().filter(|c| **c != 0.0).count();
                params.insert("basis_terms".into(), used.into());
            }
            Effect::Geometric => {}
        }
        let label = match e.joint() {
            Some(j) => format!("+{} (joint {j})", e.name()),
            None => format!("+{}", e.name()),
        };
        steps.push(StepReport {
            effect: e.name(),
            joint: e.joint(),
            rms_after_um: round(rms(&residual) * 1e6, 3),
            params,
            std: serde_json::Map::new(),
            bic: round(bic, 1),
            cv_rms_um: round((cv / n).sqrt() * 1e6, 3),
        });
        named.push(NamedEffect {
            effect: e.name(),
            joint: e.joint(),
        });
        stages.push((label, residual.clone()));
    }
    noise = noise.min(noise_estimate(&residual));
    let rms_final = rms(&residual);
    let l1 = lag1(&residual);
    let unexplained = rms_final > 2.0 * noise || l1 > 0.5;
    let where_ = if unexplained {
        locate(m, &residual)
    } else {
        None
    };
    let report = Report {
        schema: "edbbgen.diagnose/1",
        rms_nominal_um: round(rms_nominal * 1e6, 3),
        named_effects: named,
        unexplained,
        where_,
        rms_final_um: round(rms_final * 1e6, 3),
        steps,
        rows: m.len(),
        duration_s: round(m.t[m.len() - 1] - m.t[0], 3),
        noise_um: round(noise * 1e6, 3),
        lag1_final: round(l1, 4),
        nominal_where: locate(m, &nominal_res),
    };
    let summary = summary(&report);
    Ok(Diagnosis {
        report,
        t: m.t.clone(),
        stages,
        summary,
    })
}

fn summary(r: &Report) -> String {
    let mut s = format!(
        "{} rows over {} s; bar noise ~{} um\n",
        r.rows,
        fmt_fixed(r.duration_s, 1),
        fmt_fixed(r.noise_um, 2)
    );
    s += &format!("nominal model: RMS {} um", fmt_fixed(r.rms_nominal_um, 2));
    if let Some(w) = &r.nominal_where {
        s += &format!(
            ", largest at t {}..{} s (peak {} um)",
            fmt_fixed(w.t_s[0], 1),
            fmt_fixed(w.t_s[1], 1),
            fmt_fixed(w.peak_um, 1)
        );
    }
    s.push('\n');
    for st in &r.steps {
        let name = match st.joint {
            Some(j) => format!("{} (joint {j})", st.effect),
            None => st.effect.to_string(),
        };
        s += &format!("  + {name:<24} RMS {} um\n", fmt_fixed(st.rms_after_um, 3));
    }
    if r.unexplained {
        s += "UNEXPLAINED structure remains";
        if let Some(w) = &r.where_ {
            s += &format!(
                " at t {}..{} s, joints {}",
                fmt_fixed(w.t_s[0], 1),
                fmt_fixed(w.t_s[1], 1),
                w.joints_deg
                    .iter()
                    .enumerate()
                    .map(|(j, r)| format!(
                        "q{} {}..{}",
                        j + 1,
                        fmt_fixed(r[0], 1),
                        fmt_fixed(r[1], 1)
                    ))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        s.push('\n');
    } else {
        s += &format!(
            "residual at the noise level: RMS {} um, lag-1 autocorrelation {}\n",
            fmt_fixed(r.rms_final_um, 3),
            fmt_fixed(r.lag1_final, 3)
        );
    }
    s
}

//! Clock synchronisation of a bar log with a joint log: in = the bar's readings on its clock,
//! the controller's joints on its clock (model joints, rad) and the length the joints predict
//! (the measurement model); out = the clock relation t_bar = offset + (1 + drift)·t_joint with
//! its uncertainty, the bar's zero, and the bar's samples with the joints interpolated to them.
//!
//! The inverse of the paper's synchronisation (Section 3.1 recorded both on one clock): the
//! bar's length is matched to the one the joints predict.
//! 1. **Coarse.** Over every offset that overlaps the logs (50 ms steps, no drift), the share
//!    of bar samples whose reading − prediction falls within 10 mm of the most common value
//!    (the zero is unknown; readings while the bar is unmounted agree with nothing).
//! 2. **Finer.** Around the best: offset steps of 2 ms and drifts of ±1000 ppm in 50 ppm
//!    steps, within 2 mm.
//! 3. **Least squares.** Gauss–Newton on offset, drift and zero over the samples that agree
//!    (runs of at least 1 s within 5 robust sigmas: the bar mounted), re-selected each round.
//!    The covariance is σ²(JᵀJ)⁻¹ inflated by (1 + ρ)/(1 − ρ) for the residual's lag-1
//!    correlation ρ (a model error is smooth in time, not white).
//!
//! The joints are interpolated with a natural cubic spline per joint (error O(h⁴): a 10 ms log
//! of the twin's moves is interpolated to ~1e-7 rad); a gap in the joint log (more than five
//! sample intervals) is not bridged.

use super::LogsError;

/// A natural cubic spline through (t, q) per joint; gaps split it.
pub struct Spline {
    t: Vec<f64>,
    q: Vec<[f64; 6]>,
    /// Second derivatives at the knots.
    m: Vec<[f64; 6]>,
    /// Knot intervals longer than this are gaps (no value inside).
    gap: f64,
}

impl Spline {
    pub fn new(t: &[f64], q: &[[f64; 6]]) -> Spline {
        let n = t.len();
        let mut dt: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
        let med = {
            let mut v = dt.clone();
            if v.is_empty() {
                1.0
            } else {
                let k = v.len() / 2;
                v.select_nth_unstable_by(k, f64::total_cmp);
                v[k]
            }
        };
        let gap = 5.0 * med;
        let mut m = vec![[0.0; 6]; n];
        // Each gap-free piece is its own natural spline (Thomas algorithm per piece).
        let mut a = 0;
        while a < n {
            let mut b = a;
            while b + 1 < n && dt[b] <= gap {
                b += 1;
            }
            if b >= a + 2 {
                let len = b - a + 1;
                let mut diag = vec![0.0; len];
                let mut rhs = vec![[0.0; 6]; len];
                let mut up = vec![0.0; len];
                for k in 1..len - 1 {
                    let (h0, h1) = (dt[a + k - 1], dt[a + k]);
                    diag[k] = 2.0 * (h0 + h1);
                    up[k] = h1;
                    for j in 0..6 {
                        rhs[k][j] = 6.0
                            * ((q[a + k + 1][j] - q[a + k][j]) / h1
                                - (q[a + k][j] - q[a + k - 1][j]) / h0);
                    }
                }
                // Forward sweep over the interior rows (natural ends: m = 0).
                for k in 2..len - 1 {
                    let w = dt[a + k - 1] / diag[k - 1];
                    diag[k] -= w * up[k - 1];
                    for j in 0..6 {
                        rhs[k][j] -= w * rhs[k - 1][j];
                    }
                }
                for k in (1..len - 1).rev() {
                    for j in 0..6 {
                        let next = if k + 1 < len - 1 {
                            m[a + k + 1][j]
                        } else {
                            0.0
                        };
                        m[a + k][j] = (rhs[k][j] - up[k] * next) / diag[k];
                    }
                }
            }
            a = b + 1;
        }
        dt.clear();
        Spline {
            t: t.to_vec(),
            q: q.to_vec(),
            m,
            gap,
        }
    }

    /// The joints at time τ, or None outside the log or inside a gap.
    pub fn at(&self, tau: f64) -> Option<[f64; 6]> {
        let n = self.t.len();
        if n < 2 || tau < self.t[0] || tau > self.t[n - 1] {
            return None;
        }
        let k = self.t.partition_point(|&x| x <= tau).clamp(1, n - 1) - 1;
        let h = self.t[k + 1] - self.t[k];
        if h > self.gap {
            return None;
        }
        let a = (self.t[k + 1] - tau) / h;
        let b = 1.0 - a;
        Some(std::array::from_fn(|j| {
            a * self.q[k][j]
                + b * self.q[k + 1][j]
                + ((a * a * a - a) * self.m[k][j] + (b * b * b - b) * self.m[k + 1][j]) * h * h
                    / 6.0
        }))
    }

    pub fn range(&self) -> (f64, f64) {
        (
            self.t.first().copied().unwrap_or(0.0),
            self.t.last().copied().unwrap_or(0.0),
        )
    }
}

/// The result of a synchronisation.
#[derive(Clone, Debug, PartialEq)]
pub struct Synced {
    /// t_bar = offset + (1 + drift)·t_joint (s), with standard uncertainties.
    pub offset: f64,
    pub offset_std: f64,
    pub drift: f64,
    pub drift_std: f64,
    /// The bar's zero (m): reading − predicted length, and its standard uncertainty.
    pub zero: f64,
    pub zero_std: f64,
    /// RMS of reading − zero − prediction over the samples used (m).
    pub rms: f64,
    /// The bar rows the bar was mounted for (0-based, ascending), their joint-clock times and
    /// the joints interpolated there (rad).
    pub rows: Vec<usize>,
    pub t_joint: Vec<f64>,
    pub q: Vec<[f64; 6]>,
}

/// Coarse offset step (s), its tolerance (m); the finer search's step, drift grid, tolerance.
const COARSE_STEP: f64 = 0.05;
const COARSE_TOL: f64 = 10e-3;
const FINE_STEP: f64 = 0.002;
const FINE_SPAN: f64 = 0.1;
const DRIFT_MAX: f64 = 1000e-6;
const DRIFT_STEP: f64 = 50e-6;
const FINE_TOL: f64 = 2e-3;
/// A run of agreeing samples shorter than this (s) is chance, not a mounted bar.
const MIN_RUN: f64 = 1.0;
/// Bar samples the searches use at most (evenly spaced).
const SEARCH_SAMPLES: usize = 2000;

/// The most samples within ±tol of one value: the count (r sorted in place).
fn densest(r: &mut [f64], tol: f64) -> usize {
    r.sort_unstable_by(f64::total_cmp);
    let mut best = 0;
    let mut a = 0;
    for b in 0..r.len() {
        while r[b] - r[a] > 2.0 * tol {
            a += 1;
        }
        best = best.max(b + 1 - a);
    }
    best
}

struct Problem<'a> {
    u: &'a [f64],
    l: &'a [f64],
    spline: &'a Spline,
    length: &'a (dyn Fn(&[f64; 6]) -> f64 + Sync),
    /// Predicted length at the joint knots (for the searches: linear between knots).
    knots_t: Vec<f64>,
    knots_p: Vec<f64>,
}

impl Problem<'_> {
    fn coarse_pred(&self, tau: f64) -> Option<f64> {
        let t = &self.knots_t;
        let n = t.len();
        if n < 2 || tau < t[0] || tau > t[n - 1] {
            return None;
        }
        let k = t.partition_point(|&x| x <= tau).clamp(1, n - 1) - 1;
        let h = t[k + 1] - t[k];
        if h > self.spline.gap {
            return None;
        }
        let f = (tau - t[k]) / h;
        Some(self.knots_p[k] * (1.0 - f) + self.knots_p[k + 1] * f)
    }

    /// Samples agreeing within tol for t_joint = t_mid + (u − u_mid − shift)/(1 + drift).
    fn score(
        &self,
        idx: &[usize],
        map: &dyn Fn(f64) -> f64,
        tol: f64,
        buf: &mut Vec<f64>,
    ) -> usize {
        buf.clear();
        for &k in idx {
            if let Some(p) = self.coarse_pred(map(self.u[k])) {
                buf.push(self.l[k] - p);
            }
        }
        densest(buf, tol)
    }

    fn predict(&self, tau: f64) -> Option<f64> {
        self.spline.at(tau).map(|q| (self.length)(&q))
    }
}

/// Synchronises the bar log (u, l) with a joint log's spline; `length(q)` is the predicted
/// ball-centre distance (m).
pub fn sync(
    u: &[f64],
    l: &[f64],
    spline: &Spline,
    length: &(dyn Fn(&[f64; 6]) -> f64 + Sync),
) -> Result<Synced, LogsError> {
    use rayon::prelude::*;
    let (t0, t1) = spline.range();
    let (u0, u1) = (
        u.first().copied().unwrap_or(0.0),
        u.last().copied().unwrap_or(0.0),
    );
    if u.len() < 10 || t1 <= t0 {
        return Err(LogsError::Bad("too short a log to synchronise".into()));
    }
    let knots_t = spline.t.clone();
    let knots_p: Vec<f64> = spline.q.par_iter().map(length).collect();
    let pb = Problem {
        u,
        l,
        spline,
        length,
        knots_t,
        knots_p,
    };
    let stride = u.len().div_ceil(SEARCH_SAMPLES).max(1);
    let idx: Vec<usize> = (0..u.len()).step_by(stride).collect();
    // 1. Coarse: t_joint = u − offset over every overlapping offset.
    let (lo, hi) = (u0 - t1, u1 - t0);
    let steps = ((hi - lo) / COARSE_STEP).ceil() as usize + 1;
    let coarse: Vec<(usize, f64)> = (0..steps)
        .into_par_iter()
        .map_init(Vec::new, |buf, s| {
            let o = lo + s as f64 * COARSE_STEP;
            (pb.score(&idx, &|x| x - o, COARSE_TOL, buf), o)
        })
        .collect();
    // Highest count, the earliest offset on a tie (deterministic).
    let (best_n, best_o) = coarse
        .iter()
        .fold((0usize, lo), |b, &(n, o)| if n > b.0 { (n, o) } else { b });
    if best_n < 20 {
        return Err(LogsError::Bad(
            "the bar's readings agree with the lengths the joint log predicts at no clock offset: is this the bar log of the run the joint log recorded?".into(),
        ));
    }
    // 2. Finer, with drift, about the middle of the bar log.
    let u_mid = 0.5 * (u0 + u1);
    let t_mid = u_mid - best_o;
    let shifts = (2.0 * FINE_SPAN / FINE_STEP).round() as usize + 1;
    let drifts = (2.0 * DRIFT_MAX / DRIFT_STEP).round() as usize + 1;
    let fine: Vec<(usize, f64, f64)> = (0..shifts * drifts)
        .into_par_iter()
        .map_init(Vec::new, |buf, x| {
            let shift = -FINE_SPAN + (x / drifts) as f64 * FINE_STEP;
            let drift = -DRIFT_MAX + (x % drifts) as f64 * DRIFT_STEP;
            let map = |v: f64| t_mid + (v - u_mid - shift) / (1.0 + drift);
            (pb.score(&idx, &map, FINE_TOL, buf), shift, drift)
        })
        .collect();
    // Most agreeing samples; ties to the smallest |drift|, then the smallest |shift|.
    let (_, mut shift, mut drift) = fine.iter().fold((0usize, 0.0f64, 0.0f64), |b, &(n, s, d)| {
        let better = n > b.0 || (n == b.0 && (d.abs(), s.abs()) < (b.2.abs(), b.1.abs()));
        if better {
            (n, s, d)
        } else {
            b
        }
    });
    // 3. Gauss–Newton on (shift, drift, zero) over the mounted samples.
    let mut zero = 0.0;
    let mut tol = FINE_TOL;
    let mut used: Vec<usize> = Vec::new();
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    let mut rms = 0.0;
    for round in 0..12 {
        let map = |v: f64| t_mid + (v - u_mid - shift) / (1.0 + drift);
        // Residuals and slopes of every sample the joint log covers.
        let res: Vec<Option<(f64, f64)>> = (0..u.len())
            .into_par_iter()
            .map(|k| {
                let tau = map(u[k]);
                let p = pb.predict(tau)?;
                let h = 1e-4;
                let slope = (pb.predict(tau + h)? - pb.predict(tau - h)?) / (2.0 * h);
                Some((l[k] - p, slope))
            })
            .collect();
        if round == 0 {
            let mut r: Vec<f64> = res.iter().flatten().map(|x| x.0).collect();
            zero = mode(&mut r, FINE_TOL);
        }
        // Agreeing samples, in runs of at least MIN_RUN seconds.
        let agree: Vec<bool> = res
            .iter()
            .map(|x| x.is_some_and(|(r, _)| (r - zero).abs() <= tol))
            .collect();
        used = runs(u, &agree, MIN_RUN);
        if used.len() < 20 {
            return Err(LogsError::Bad(
                "the bar's readings agree with the joint log's lengths for less than a second at the best clock offset: no synchronisation".into(),
            ));
        }
        let mut jtj = nalgebra::Matrix3::<f64>::zeros();
        let mut jtr = nalgebra::Vector3::<f64>::zeros();
        let mut resid = Vec::with_capacity(used.len());
        for &k in &used {
            let Some((r, slope)) = res[k] else { continue };
            let r = r - zero;
            // d(prediction)/d(shift) = −slope/(1+d); d/d(drift) = −slope·(u−u_mid−shift)/(1+d)².
            let a = 1.0 + drift;
            let j =
                nalgebra::Vector3::new(-slope / a, -slope * (u[k] - u_mid - shift) / (a * a), 1.0);
            jtj += j * j.transpose();
            jtr += j * r;
            resid.push(r);
        }
        let n = resid.len() as f64;
        let rss: f64 = resid.iter().map(|r| r * r).sum();
        let sigma2 = rss / (n - 3.0).max(1.0);
        let rho = lag1(&resid).clamp(0.0, 0.99);
        let inv = jtj.try_inverse().ok_or_else(|| {
            LogsError::Bad("the readings do not determine the clock: the robot hardly moved while the bar was mounted".into())
        })?;
        cov = inv * sigma2 * (1.0 + rho) / (1.0 - rho);
        rms = (rss / n).sqrt();
        let step = inv * jtr;
        shift += step[0];
        drift += step[1];
        zero += step[2];
        let robust = 1.4826 * {
            let mut a: Vec<f64> = resid.iter().map(|r| r.abs()).collect();
            let k = a.len() / 2;
            a.select_nth_unstable_by(k, f64::total_cmp);
            a[k]
        };
        tol = (5.0 * robust).clamp(20e-6, FINE_TOL);
        if step[0].abs() < 1e-9 && step[1].abs() < 1e-12 && round >= 3 {
            break;
        }
    }
    let a = 1.0 + drift;
    let map = |v: f64| t_mid + (v - u_mid - shift) / a;
    // offset = t_bar at t_joint = 0: u_mid + shift − (1 + drift)·t_mid.
    let offset = u_mid + shift - a * t_mid;
    let var_o = cov[(0, 0)] + t_mid * t_mid * cov[(1, 1)] - 2.0 * t_mid * cov[(0, 1)];
    let mut rows = Vec::with_capacity(used.len());
    let mut t_joint = Vec::with_capacity(used.len());
    let mut q = Vec::with_capacity(used.len());
    for &k in &used {
        let tau = map(u[k]);
        if let Some(x) = spline.at(tau) {
            rows.push(k);
            t_joint.push(tau);
            q.push(x);
        }
    }
    Ok(Synced {
        offset,
        offset_std: var_o.max(0.0).sqrt(),
        drift,
        drift_std: cov[(1, 1)].max(0.0).sqrt(),
        zero,
        zero_std: cov[(2, 2)].max(0.0).sqrt(),
        rms,
        rows,
        t_joint,
        q,
    })
}

/// The centre of the densest ±tol window of r (sorted in place).
fn mode(r: &mut [f64], tol: f64) -> f64 {
    r.sort_unstable_by(f64::total_cmp);
    let (mut best, mut at) = (0, 0.0);
    let mut a = 0;
    for b in 0..r.len() {
        while r[b] - r[a] > 2.0 * tol {
            a += 1;
        }
        if b + 1 - a > best {
            best = b + 1 - a;
            at = 0.5 * (r[a] + r[b]);
        }
    }
    at
}

/// Lag-1 autocorrelation of a series.
fn lag1(r: &[f64]) -> f64 {
    let n = r.len();
    if n < 3 {
        return 0.0;
    }
    let m = r.iter().sum::<f64>() / n as f64;
    let var: f64 = r.iter().map(|x| (x - m).powi(2)).sum();
    if var <= 0.0 {
        return 0.0;
    }
    r.windows(2).map(|w| (w[0] - m) * (w[1] - m)).sum::<f64>() / var
}

/// Indices of the agreeing samples that lie in runs (consecutive rows, no gap over 0.5 s)
/// lasting at least `min` seconds.
fn runs(u: &[f64], agree: &[bool], min: f64) -> Vec<usize> {
    let mut out = Vec::new();
    let mut k = 0;
    while k < agree.len() {
        if !agree[k] {
            k += 1;
            continue;
        }
        let a = k;
        while k + 1 < agree.len() && agree[k + 1] && u[k + 1] - u[k] <= 0.5 {
            k += 1;
        }
        if u[k] - u[a] >= min {
            out.extend(a..=k);
        }
        k += 1;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_spline_interpolates_a_smooth_motion_to_fourth_order() {
        // A cycloidal move of 1 rad in 0.5 s, logged every 10 ms.
        let f = |t: f64| {
            let u = (t / 0.5).clamp(0.0, 1.0);
            u - (std::f64::consts::TAU * u).sin() / std::f64::consts::TAU
        };
        let t: Vec<f64> = (0..101).map(|k| k as f64 * 0.01).collect();
        let q: Vec<[f64; 6]> = t
            .iter()
            .map(|&x| [f(x), 0.5 * f(x), 0.0, 0.0, 0.0, 0.0])
            .collect();
        let s = Spline::new(&t, &q);
        let mut worst: f64 = 0.0;
        for k in 0..1000 {
            let x = 0.05 + k as f64 * 0.0009;
            let got = s.at(x).unwrap();
            worst = worst.max((got[0] - f(x)).abs());
        }
        assert!(worst < 1e-6, "{worst}");
        // Linear interpolation would be off by q''h²/8 ≈ 3e-4 rad here.
        assert!(s.at(-0.1).is_none() && s.at(1.01).is_none());
    }

    #[test]
    fn a_gap_is_not_bridged() {
        let t = [0.0, 0.01, 0.02, 0.03, 0.5, 0.51, 0.52];
        let q: Vec<[f64; 6]> = t.iter().map(|&x| [x; 6]).collect();
        let s = Spline::new(&t, &q);
        assert!(s.at(0.2).is_none());
        assert!((s.at(0.015).unwrap()[0] - 0.015).abs() < 1e-12);
    }
}

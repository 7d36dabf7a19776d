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
//! 3. **Least squares.** Gauss–Newton on offset, drift, zero and the bar's smoothing over the
//!    samples that agree (runs of at least 1 s within 5 robust sigmas: the bar mounted),
//!    re-selected each round. The covariance is σ²(JᵀJ)⁻¹ inflated by (1 + ρ)/(1 − ρ) for the
//!    residual's lag-1 correlation ρ (a model error is smooth in time, not white).
//!
//! **The bar's own dynamics.** A bar that filters its signal (averages over its sample period,
//! or a first-order low-pass) reads, to second order, `L(t − d) + c·L''(t)`: the delay d is
//! part of the clock offset, and c — w²/24 for an average over w seconds, T²/2 for a lag of
//! time constant T — is fitted with it (`smoothing`). A 20 ms average left unmodelled costs
//! 17 µm where the bar accelerates at 1 m/s². The readings handed on have c·L'' taken out.
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
    /// The bar's smoothing c (s²): reading = L + c·L'' (see the module's notes), and its
    /// standard uncertainty.
    pub smoothing: f64,
    pub smoothing_std: f64,
    /// RMS of reading − zero − prediction over the samples used (m).
    pub rms: f64,
    /// The bar rows the bar was mounted for (0-based, ascending), their joint-clock times and
    /// the joints interpolated there (rad).
    pub rows: Vec<usize>,
    pub t_joint: Vec<f64>,
    pub q: Vec<[f64; 6]>,
    /// Their readings with the bar's smoothing taken out: lᵢ − c·L''ᵢ (m).
    pub length: Vec<f64>,
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

    /// The predicted length at joint time tau (in `r`), its time derivatives by central
    /// differences: slope over ±0.1 ms, curvature over ±2 ms (the bar's dynamics act over
    /// milliseconds; a wider step keeps rounding out of the second difference).
    fn local(&self, tau: f64) -> Option<Local> {
        let p = self.predict(tau)?;
        let h = 1e-4;
        let slope = (self.predict(tau + h)? - self.predict(tau - h)?) / (2.0 * h);
        let g = 2e-3;
        let curvature = match (self.predict(tau + g), self.predict(tau - g)) {
            (Some(a), Some(b)) => (a - 2.0 * p + b) / (g * g),
            _ => 0.0,
        };
        Some(Local {
            r: p,
            slope,
            curvature,
        })
    }
}

/// A sample's predicted length (or its residual), and the predicted length's first and
/// second time derivatives (m/s, m/s²).
struct Local {
    r: f64,
    slope: f64,
    curvature: f64,
}

/// The bar's smoothing is kept only where its term's RMS over the samples exceeds this share
/// of the residual's RMS: below, it would fit what a joint log's interpolation misses (a
/// 100 Hz log of moves whose acceleration jumps) rather than the bar, for no gain.
const SMOOTHING_MATTERS: f64 = 0.25;

/// The bar's smoothing is 0 ± this a priori (s²): a 50 ms average.
const SMOOTHING_PRIOR: f64 = 0.05 * 0.05 / 24.0;

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
    let best_o = pb.coarse_offset(&idx, (u0 - t1, u1 - t0))?;
    // 2. Finer, with drift, about the middle of the bar log.
    let u_mid = 0.5 * (u0 + u1);
    let t_mid = u_mid - best_o;
    let start = pb.fine_search(&idx, u_mid, t_mid);
    // 3. Gauss–Newton on (shift, drift, zero, smoothing) over the mounted samples; again
    //    with the smoothing held at 0 where it does not matter (see SMOOTHING_MATTERS).
    let Fit {
        shift,
        drift,
        zero,
        smooth,
        used,
        cov,
        rms,
    } = pb.gauss_newton(u_mid, t_mid, start)?;
    let a = 1.0 + drift;
    let map = |v: f64| t_mid + (v - u_mid - shift) / a;
    // offset = t_bar at t_joint = 0: u_mid + shift − (1 + drift)·t_mid.
    let offset = u_mid + shift - a * t_mid;
    let var_o = cov[(0, 0)] + t_mid * t_mid * cov[(1, 1)] - 2.0 * t_mid * cov[(0, 1)];
    let mut rows = Vec::with_capacity(used.len());
    let mut t_joint = Vec::with_capacity(used.len());
    let mut q = Vec::with_capacity(used.len());
    let mut length = Vec::with_capacity(used.len());
    for &k in &used {
        let tau = map(u[k]);
        if let Some(x) = spline.at(tau) {
            rows.push(k);
            t_joint.push(tau);
            q.push(x);
            // Held at 0 (the usual case), the smoothing needs no curvature.
            let taken = if smooth == 0.0 {
                0.0
            } else {
                smooth * pb.local(tau).map_or(0.0, |x| x.curvature)
            };
            length.push(l[k] - taken);
        }
    }
    Ok(Synced {
        offset,
        offset_std: var_o.max(0.0).sqrt(),
        drift,
        drift_std: cov[(1, 1)].max(0.0).sqrt(),
        zero,
        zero_std: cov[(2, 2)].max(0.0).sqrt(),
        smoothing: smooth,
        smoothing_std: cov[(3, 3)].max(0.0).sqrt(),
        rms,
        rows,
        t_joint,
        q,
        length,
    })
}

/// What the Gauss–Newton refinement (step 3) ends with: the clock (shift, drift about the
/// middle of the bar log), the bar's zero and smoothing, the samples used, the covariance and
/// the RMS of the last round.
struct Fit {
    shift: f64,
    drift: f64,
    zero: f64,
    smooth: f64,
    used: Vec<usize>,
    cov: nalgebra::Matrix4<f64>,
    rms: f64,
}

impl Problem<'_> {
    /// Step 1: the offset (t_joint = u − offset) in `lo..hi` at which the most samples agree.
    fn coarse_offset(&self, idx: &[usize], (lo, hi): (f64, f64)) -> Result<f64, LogsError> {
        use rayon::prelude::*;
        let steps = ((hi - lo) / COARSE_STEP).ceil() as usize + 1;
        let coarse: Vec<(usize, f64)> = (0..steps)
            .into_par_iter()
            .map_init(Vec::new, |buf, s| {
                let o = lo + s as f64 * COARSE_STEP;
                (self.score(idx, &|x| x - o, COARSE_TOL, buf), o)
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
        Ok(best_o)
    }

    /// Step 2: the (shift, drift) about the middle of the bar log at which the most samples
    /// agree.
    fn fine_search(&self, idx: &[usize], u_mid: f64, t_mid: f64) -> (f64, f64) {
        use rayon::prelude::*;
        let shifts = (2.0 * FINE_SPAN / FINE_STEP).round() as usize + 1;
        let drifts = (2.0 * DRIFT_MAX / DRIFT_STEP).round() as usize + 1;
        let fine: Vec<(usize, f64, f64)> = (0..shifts * drifts)
            .into_par_iter()
            .map_init(Vec::new, |buf, x| {
                let shift = -FINE_SPAN + (x / drifts) as f64 * FINE_STEP;
                let drift = -DRIFT_MAX + (x % drifts) as f64 * DRIFT_STEP;
                let map = |v: f64| t_mid + (v - u_mid - shift) / (1.0 + drift);
                (self.score(idx, &map, FINE_TOL, buf), shift, drift)
            })
            .collect();
        // Most agreeing samples; ties to the smallest |drift|, then the smallest |shift|.
        let (_, shift, drift) = fine.iter().fold((0usize, 0.0f64, 0.0f64), |b, &(n, s, d)| {
            let better = n > b.0 || (n == b.0 && (d.abs(), s.abs()) < (b.2.abs(), b.1.abs()));
            if better {
                (n, s, d)
            } else {
                b
            }
        });
        (shift, drift)
    }

    /// Step 3: Gauss–Newton from `start` = (shift, drift).
    fn gauss_newton(&self, u_mid: f64, t_mid: f64, start: (f64, f64)) -> Result<Fit, LogsError> {
        let u = self.u;
        let (mut shift, mut drift) = start;
        let mut zero = 0.0;
        let mut smooth = 0.0;
        let mut used: Vec<usize> = Vec::new();
        let mut cov = nalgebra::Matrix4::<f64>::zeros();
        let mut rms = 0.0;
        for free in [true, false] {
            (shift, drift) = start;
            zero = 0.0;
            smooth = 0.0;
            let mut tol = FINE_TOL;
            let mut sigma2 = FINE_TOL * FINE_TOL;
            let mut curvature_ms = 0.0;
            for round in 0..12 {
                let map = |v: f64| t_mid + (v - u_mid - shift) / (1.0 + drift);
                let res = self.residuals(map, smooth);
                if round == 0 {
                    let mut r: Vec<f64> = res.iter().flatten().map(|x| x.r).collect();
                    zero = mode(&mut r, FINE_TOL);
                }
                // Agreeing samples, in runs of at least MIN_RUN seconds.
                let agree: Vec<bool> = res
                    .iter()
                    .map(|x| x.as_ref().is_some_and(|x| (x.r - zero).abs() <= tol))
                    .collect();
                used = runs(u, &agree, MIN_RUN);
                if used.len() < 20 {
                    return Err(LogsError::Bad(
                    "the bar's readings agree with the joint log's lengths for less than a second at the best clock offset: no synchronisation".into(),
                ));
                }
                let (mut jtj, mut jtr, resid) =
                    self.normal_equations(&res, &used, zero, (shift, drift), u_mid);
                // The smoothing's prior: 0 ± SMOOTHING_PRIOR (a motion that hardly accelerates does
                // not determine it; then it stays near 0).
                let ridge = if free {
                    sigma2 / (SMOOTHING_PRIOR * SMOOTHING_PRIOR)
                } else {
                    jtj[(3, 3)].max(1.0) * 1e12
                };
                curvature_ms = jtj[(3, 3)] / resid.len().max(1) as f64;
                jtj[(3, 3)] += ridge;
                jtr[3] -= ridge * smooth;
                let n = resid.len() as f64;
                let rss: f64 = resid.iter().map(|r| r * r).sum();
                sigma2 = rss / (n - 4.0).max(1.0);
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
                if free {
                    smooth += step[3];
                }
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
            // The smoothing kept: significant, and changing the readings by more than a share of
            // their residual.
            let effect = smooth.abs() * curvature_ms.sqrt();
            if !free
                || (smooth.abs() > 3.0 * cov[(3, 3)].max(0.0).sqrt()
                    && effect > SMOOTHING_MATTERS * rms)
            {
                break;
            }
        }
        Ok(Fit {
            shift,
            drift,
            zero,
            smooth,
            used,
            cov,
            rms,
        })
    }

    /// Residual, slope and curvature of every sample the joint log covers, at the clock `map`
    /// and the smoothing `smooth`.
    fn residuals(&self, map: impl Fn(f64) -> f64 + Sync, smooth: f64) -> Vec<Option<Local>> {
        use rayon::prelude::*;
        let (u, l) = (self.u, self.l);
        (0..u.len())
            .into_par_iter()
            .map(|k| {
                let x = self.local(map(u[k]))?;
                Some(Local {
                    r: l[k] - x.r - smooth * x.curvature,
                    ..x
                })
            })
            .collect()
    }

    /// The normal equations over the samples used (JᵀJ, Jᵀr) and their residuals (m).
    fn normal_equations(
        &self,
        res: &[Option<Local>],
        used: &[usize],
        zero: f64,
        (shift, drift): (f64, f64),
        u_mid: f64,
    ) -> (nalgebra::Matrix4<f64>, nalgebra::Vector4<f64>, Vec<f64>) {
        let u = self.u;
        let mut jtj = nalgebra::Matrix4::<f64>::zeros();
        let mut jtr = nalgebra::Vector4::<f64>::zeros();
        let mut resid = Vec::with_capacity(used.len());
        for &k in used {
            let Some(x) = &res[k] else { continue };
            let r = x.r - zero;
            // d(prediction)/d(shift) = −slope/(1+d); d/d(drift) = −slope·(u−u_mid−shift)/(1+d)².
            let a = 1.0 + drift;
            let j = nalgebra::Vector4::new(
                -x.slope / a,
                -x.slope * (u[k] - u_mid - shift) / (a * a),
                1.0,
                x.curvature,
            );
            jtj += j * j.transpose();
            jtr += j * r;
            resid.push(r);
        }
        (jtj, jtr, resid)
    }
}

/// The most rows per second a continuous run keeps after synchronisation: consecutive bar
/// samples beyond it are averaged ([`bin`]). Successive samples of a fast bar repeat nearly
/// the same pose; their information is the noise they average out, which a bin keeps, at a
/// twentieth of the rows for a 1 kHz bar.
pub const MAX_ROW_RATE: f64 = 50.0;

/// Bar samples per row that bring a bar log sampled every `interval` seconds to at most
/// [`MAX_ROW_RATE`] rows per second.
pub fn samples_per_row(interval: f64) -> usize {
    if interval > 0.0 && interval.is_finite() {
        ((1.0 / interval) / MAX_ROW_RATE + 1e-9).floor().max(1.0) as usize
    } else {
        1
    }
}

/// Synchronised samples averaged in bins: per bin its middle sample (bar row, joint-clock time,
/// joints) and the reading `length(q_mid) + mean(lᵢ − length(qᵢ))`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Bins {
    pub rows: Vec<usize>,
    pub t_joint: Vec<f64>,
    pub q: Vec<[f64; 6]>,
    pub length: Vec<f64>,
    /// Samples averaged in each bin.
    pub count: Vec<usize>,
}

/// The synchronised samples of `s` (their readings, the smoothing taken out) in bins of up to `k`
/// consecutive bar rows; a bin never spans a row the synchronisation left out. The residual
/// against `length` is averaged and the middle sample's pose kept: averaging the readings
/// themselves would mix poses (a bar length accelerating at 1 m/s² is 17 µm off its mean
/// over 20 ms), while the residual — the robot's error, the bar's zero, its noise — changes
/// over a bin by far less than the noise it averages. `k` = 1 keeps every sample.
pub fn bin(s: &Synced, length: &(dyn Fn(&[f64; 6]) -> f64 + Sync), k: usize) -> Bins {
    use rayon::prelude::*;
    let k = k.max(1);
    // Bins: runs of consecutive rows, cut every k samples.
    let mut bounds = Vec::new();
    let mut a = 0;
    while a < s.rows.len() {
        let mut b = a + 1;
        while b < s.rows.len() && b - a < k && s.rows[b] == s.rows[b - 1] + 1 {
            b += 1;
        }
        bounds.push((a, b));
        a = b;
    }
    let bins: Vec<(usize, f64)> = bounds
        .par_iter()
        .map(|&(a, b)| {
            let mid = a + (b - a - 1) / 2;
            if b - a == 1 {
                return (mid, s.length[mid]);
            }
            let r = (a..b).map(|i| s.length[i] - length(&s.q[i])).sum::<f64>() / (b - a) as f64;
            (mid, length(&s.q[mid]) + r)
        })
        .collect();
    let mut out = Bins::default();
    for (&(a, b), &(mid, reading)) in bounds.iter().zip(&bins) {
        out.rows.push(s.rows[mid]);
        out.t_joint.push(s.t_joint[mid]);
        out.q.push(s.q[mid]);
        out.length.push(reading);
        out.count.push(b - a);
    }
    out
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
    fn a_fast_bar_is_brought_to_at_most_fifty_rows_a_second() {
        assert_eq!(samples_per_row(0.001), 20);
        assert_eq!(samples_per_row(0.005), 4);
        assert_eq!(samples_per_row(0.02), 1);
        assert_eq!(samples_per_row(1.0 / 60.0), 1);
        assert_eq!(samples_per_row(1.0 / 120.0), 2);
        assert_eq!(samples_per_row(0.0), 1);
    }

    /// Bins keep the middle sample's pose and average the residual: on a bar accelerating at
    /// 2 m/s², the binned reading is the length at the middle pose plus the zero (to the noise
    /// averaged), where the mean reading is a curvature off; no bin spans a left-out row.
    #[test]
    fn bins_average_the_residual_not_the_poses() {
        let rate = 1000.0;
        let n = 400;
        let length = |q: &[f64; 6]| 0.4 + q[0];
        // q1 = a t²/2 (m through `length`), readings = length + zero.
        let acc = 2.0;
        let zero = 30e-6;
        let mut s = Synced {
            offset: 0.0,
            offset_std: 0.0,
            drift: 0.0,
            drift_std: 0.0,
            zero,
            zero_std: 0.0,
            smoothing: 0.0,
            smoothing_std: 0.0,
            rms: 0.0,
            rows: Vec::new(),
            t_joint: Vec::new(),
            q: Vec::new(),
            length: Vec::new(),
        };
        let mut l = Vec::new();
        for k in 0..n {
            let t = k as f64 / rate;
            let q = [0.5 * acc * t * t, 0.0, 0.0, 0.0, 0.0, 0.0];
            l.push(length(&q) + zero);
            // Row 100 left out (the bar unmounted for a sample).
            if k != 100 {
                s.rows.push(k);
                s.t_joint.push(t);
                s.q.push(q);
                s.length.push(l[k]);
            }
        }
        let b = bin(&s, &length, 20);
        // 0..100 in 5 bins, 101..400 in 15.
        assert_eq!(b.rows.len(), 20);
        assert_eq!(b.count.iter().sum::<usize>(), n - 1);
        assert!(b.rows.iter().all(|&r| r != 100));
        assert_eq!((b.rows[4], b.rows[5]), (89, 110));
        for i in 0..b.rows.len() {
            let want = length(&b.q[i]) + zero;
            assert!((b.length[i] - want).abs() < 1e-12, "{i}");
        }
        // The plain mean of a bin's readings is off by the curvature: a·h²/24 for the span h.
        let mean = l[0..20].iter().sum::<f64>() / 20.0;
        assert!((mean - (length(&s.q[9]) + zero)).abs() > 1e-6);
        // k = 1 keeps every sample as it is.
        let one = bin(&s, &length, 1);
        assert_eq!(one.rows, s.rows);
        assert_eq!(one.length, s.rows.iter().map(|&r| l[r]).collect::<Vec<_>>());
    }

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

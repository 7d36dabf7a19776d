//! One run onto the common angle grid: in = one run's samples (circle angle, value, joint
//! angles), out = the values at the grid nodes, a robust noise estimate and the outliers left
//! out; or the largest gap when the samples do not cover the circle.
//!
//! Runs never sample the same angles (each starts elsewhere, the clocks differ), so repeats and
//! loads can only be compared on a common grid. Each node gets a local linear fit of the
//! samples within one grid step on either side, weighted by a triangle (a smoothing
//! interpolation: it averages the noise of the ~10 samples per step the LVDT gives at 1 kHz and
//! follows the slope of the signal without bias). Where a node has too few samples on both
//! sides, the two nearest samples are interpolated linearly. A second pass leaves out the
//! samples more than 8 robust standard deviations (1.4826 · MAD) off the first pass. Angles
//! wrap at 360°: a run may start anywhere and overlap itself.

use std::f64::consts::TAU;

/// The values of one run at the grid nodes.
#[derive(Clone, Debug, PartialEq)]
pub struct RunGrid {
    pub y: Vec<f64>,
    /// Joint angles at the nodes, when the samples have them.
    pub q: Option<Vec<[f64; 6]>>,
    /// Robust standard deviation of the samples (noise), from their spread about their neighbours.
    pub noise: f64,
    pub outliers: usize,
}

/// The samples leave a hole in the circle: from `from` to `to` (rad, wrapped to [0, 2π)).
#[derive(Clone, Debug, PartialEq)]
pub struct Gap {
    pub from: f64,
    pub to: f64,
    pub samples: usize,
}

/// The largest hole the resampler bridges: two grid steps, or five median sample spacings for
/// sparse data, but never more than 10°.
pub fn max_gap(step: f64, median_spacing: f64) -> f64 {
    (2.0 * step).max((5.0 * median_spacing).min(10f64.to_radians()))
}

/// Resamples one run onto `n` nodes at k·2π/n. `angle` in rad (any range), `value` and `q`
/// per sample.
pub fn run(angle: &[f64], value: &[f64], q: Option<&[[f64; 6]]>, n: usize) -> Result<RunGrid, Gap> {
    let step = TAU / n as f64;
    let mut order: Vec<usize> = (0..angle.len()).collect();
    let wrapped: Vec<f64> = angle.iter().map(|a| a.rem_euclid(TAU)).collect();
    order.sort_by(|&a, &b| wrapped[a].total_cmp(&wrapped[b]).then(a.cmp(&b)));
    let th: Vec<f64> = order.iter().map(|&i| wrapped[i]).collect();
    let y: Vec<f64> = order.iter().map(|&i| value[i]).collect();
    let qs: Option<Vec<[f64; 6]>> = q.map(|q| order.iter().map(|&i| q[i]).collect());
    let m = th.len();
    if m < 3 {
        return Err(Gap {
            from: th.first().copied().unwrap_or(0.0),
            to: th.first().copied().unwrap_or(0.0),
            samples: m,
        });
    }
    // Coverage: the largest angular hole between consecutive samples, the wrap included.
    let mut gaps: Vec<f64> = th.windows(2).map(|w| w[1] - w[0]).collect();
    gaps.push(th[0] + TAU - th[m - 1]);
    let mut sorted = gaps.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    let (k, g) = gaps
        .iter()
        .enumerate()
        .fold((0, 0.0), |b, (k, &g)| if g > b.1 { (k, g) } else { b });
    if g > max_gap(step, median) {
        return Err(Gap {
            from: th[k],
            to: th[(k + 1) % m],
            samples: m,
        });
    }

    // Spikes and noise: each sample against a quadratic through its 10 nearest kept neighbours
    // in angle (5 on each side; itself left out), which follows slope and curvature without
    // bias. Its residual has variance σ²(1 + h), h the leverage of the prediction, so the
    // scaled residuals give the noise σ by their median absolute value. A sample more than 8σ
    // off is a spike; spikes leave the neighbourhoods and the test runs again, so a spike does
    // not condemn its neighbours.
    let mut keep = vec![true; m];
    let mut sigma = 0.0;
    for _ in 0..5 {
        let idx: Vec<usize> = (0..m).filter(|&i| keep[i]).collect();
        let mk = idx.len();
        let mut pos = vec![usize::MAX; m];
        for (p, &i) in idx.iter().enumerate() {
            pos[i] = p;
        }
        let half = 5.min((mk.saturating_sub(1)) / 2).max(1);
        let resid: Vec<Option<f64>> = (0..m)
            .map(|i| {
                // The sample's place among the kept ones (its own, or where it would be).
                let p = if keep[i] {
                    pos[i]
                } else {
                    idx.partition_point(|&k| th[k] < th[i])
                };
                let nb = (1..=half)
                    .flat_map(|d| [(p + mk - d) % mk, (p + d - usize::from(!keep[i])) % mk])
                    .map(|q| idx[q])
                    .filter(|&k| k != i);
                quadratic_residual(&th, &y, i, nb)
            })
            .collect();
        let mut dev: Vec<f64> = (0..m)
            .filter(|&i| keep[i])
            .filter_map(|i| resid[i].map(f64::abs))
            .collect();
        dev.sort_by(f64::total_cmp);
        sigma = 1.4826 * dev.get(dev.len() / 2).copied().unwrap_or(0.0);
        let next: Vec<bool> = (0..m)
            .map(|i| sigma == 0.0 || resid[i].is_none_or(|r| r.abs() <= 8.0 * sigma))
            .collect();
        if next == keep {
            break;
        }
        keep = next;
    }
    let outliers = keep.iter().filter(|k| !**k).count();
    let (yn, qn) = nodes(&th, &y, qs.as_deref(), &keep, n);
    Ok(RunGrid {
        y: yn,
        q: qn,
        noise: sigma,
        outliers,
    })
}

/// The residual of sample `i` against the least-squares quadratic through `nb` (in angle,
/// centred on the sample), scaled by √(1 + h) so that it has the noise's variance. None when
/// the neighbours do not fix a quadratic.
fn quadratic_residual(
    th: &[f64],
    y: &[f64],
    i: usize,
    nb: impl Iterator<Item = usize>,
) -> Option<f64> {
    use nalgebra::{Matrix3, Vector3};
    let mut ata = Matrix3::zeros();
    let mut aty = Vector3::zeros();
    let mut count = 0;
    for k in nb {
        let d = wrap(th[k] - th[i]);
        let row = Vector3::new(1.0, d, d * d);
        ata += row * row.transpose();
        aty += row * y[k];
        count += 1;
    }
    if count < 4 {
        return None;
    }
    let inv = ata.try_inverse()?;
    let coef = inv * aty;
    let h = inv[(0, 0)];
    (h.is_finite() && h >= 0.0).then(|| (y[i] - coef[0]) / (1.0 + h).sqrt())
}

/// Periodic linear interpolation of node values at angle `t` (rad in [0, 2π)).
pub fn interp(nodes: &[f64], t: f64) -> f64 {
    let n = nodes.len();
    let x = t.rem_euclid(TAU) / TAU * n as f64;
    let k = (x.floor() as usize).min(n - 1);
    let f = x - k as f64;
    nodes[k] * (1.0 - f) + nodes[(k + 1) % n] * f
}

/// Signed periodic difference a − b in (−π, π].
fn wrap(d: f64) -> f64 {
    let d = d.rem_euclid(TAU);
    if d > std::f64::consts::PI {
        d - TAU
    } else {
        d
    }
}

/// The node values of one pass over the kept samples (sorted by angle).
fn nodes(
    th: &[f64],
    y: &[f64],
    q: Option<&[[f64; 6]]>,
    keep: &[bool],
    n: usize,
) -> (Vec<f64>, Option<Vec<[f64; 6]>>) {
    let step = TAU / n as f64;
    let idx: Vec<usize> = (0..th.len()).filter(|&i| keep[i]).collect();
    let kept: Vec<f64> = idx.iter().map(|&i| th[i]).collect();
    let mut out = vec![0.0; n];
    let mut qout = q.map(|_| vec![[0.0; 6]; n]);
    for node in 0..n {
        let phi = node as f64 * step;
        // Weighted sums of the local linear fit: Σw, Σw·d, Σw·d², Σw·y, Σw·d·y.
        let (mut s0, mut s1, mut s2, mut t0, mut t1) = (0.0, 0.0, 0.0, 0.0, 0.0);
        let (mut tq0, mut tq1) = ([0.0; 6], [0.0; 6]);
        let (mut left, mut right, mut count) = (false, false, 0);
        // The samples with angle in [lo, hi) of the sorted kept list (lo, hi within [0, 2π]).
        let mut range = |lo: f64, hi: f64| {
            let s = kept.partition_point(|&t| t < lo);
            let e = kept.partition_point(|&t| t < hi);
            for &i in &idx[s..e] {
                let d = wrap(th[i] - phi);
                let w = 1.0 - d.abs() / step;
                if w <= 0.0 {
                    continue;
                }
                s0 += w;
                s1 += w * d;
                s2 += w * d * d;
                t0 += w * y[i];
                t1 += w * d * y[i];
                if let Some(q) = q {
                    for j in 0..6 {
                        tq0[j] += w * q[i][j];
                        tq1[j] += w * d * q[i][j];
                    }
                }
                left |= d < 0.0;
                right |= d >= 0.0;
                count += 1;
            }
        };
        let (a, b) = (phi - step, phi + step);
        if a < 0.0 {
            range(a + TAU, TAU);
            range(0.0, b);
        } else if b > TAU {
            range(a, TAU);
            range(0.0, b - TAU);
        } else {
            range(a, b);
        }
        let det = s0 * s2 - s1 * s1;
        if count >= 3 && left && right && det > 1e-9 * s0 * s2 {
            out[node] = (s2 * t0 - s1 * t1) / det;
            if let Some(qo) = qout.as_mut() {
                for j in 0..6 {
                    qo[node][j] = (s2 * tq0[j] - s1 * tq1[j]) / det;
                }
            }
        } else {
            // The nearest kept sample on each side, interpolated linearly.
            let (a, b) = neighbours(th, &idx, phi);
            let (da, db) = (wrap(phi - th[a]).abs(), wrap(th[b] - phi).abs());
            let f = if da + db > 0.0 { da / (da + db) } else { 0.5 };
            out[node] = y[a] * (1.0 - f) + y[b] * f;
            if let (Some(qo), Some(q)) = (qout.as_mut(), q) {
                for j in 0..6 {
                    qo[node][j] = q[a][j] * (1.0 - f) + q[b][j] * f;
                }
            }
        }
    }
    (out, qout)
}

/// The kept samples just before (≤) and after (>) angle `phi`, periodically.
fn neighbours(th: &[f64], idx: &[usize], phi: f64) -> (usize, usize) {
    let p = idx.partition_point(|&i| th[i] <= phi);
    let before = if p == 0 {
        idx[idx.len() - 1]
    } else {
        idx[p - 1]
    };
    let after = if p == idx.len() { idx[0] } else { idx[p] };
    (before, after)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn signal(t: f64) -> f64 {
        0.3 * (t - 0.4).sin() + 0.02 * (3.0 * t).cos() + 0.01
    }

    #[test]
    fn irregular_samples_from_any_origin_land_on_the_grid() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let start = 1.234;
        let m = 4000;
        let angle: Vec<f64> = (0..m)
            .map(|k| start + TAU * (k as f64 + rng.random_range(-0.4..0.4)) / m as f64)
            .collect();
        let mut value: Vec<f64> = angle
            .iter()
            .map(|&t| {
                // Gaussian noise, σ = 5e-4 (Box–Muller).
                let (u1, u2): (f64, f64) =
                    (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
                signal(t) + 5e-4 * (-2.0 * u1.ln()).sqrt() * (TAU * u2).cos()
            })
            .collect();
        value[100] += 5.0; // a spike
        let q: Vec<[f64; 6]> = angle
            .iter()
            .map(|&t| [t.rem_euclid(TAU).cos(); 6])
            .collect();
        let r = run(&angle, &value, Some(&q), 360).unwrap();
        assert_eq!(r.outliers, 1);
        for k in 0..360 {
            let t = k as f64 * TAU / 360.0;
            assert!(
                (r.y[k] - signal(t)).abs() < 5e-4,
                "node {k}: {}",
                r.y[k] - signal(t)
            );
            assert!((r.q.as_ref().unwrap()[k][0] - t.cos()).abs() < 1e-4);
        }
        // The robust noise estimate finds the σ of the samples.
        assert!((r.noise / 5e-4 - 1.0).abs() < 0.1, "{}", r.noise);
    }

    #[test]
    fn a_hole_in_the_circle_is_reported_where_it_is() {
        let angle: Vec<f64> = (0..3600)
            .map(|k| k as f64 * TAU / 3600.0)
            .filter(|t| !(1.0..1.2).contains(t))
            .collect();
        let value = vec![0.0; angle.len()];
        let g = run(&angle, &value, None, 360).unwrap_err();
        assert!(
            (g.from - 1.0).abs() < 0.01 && (g.to - 1.2).abs() < 0.01,
            "{g:?}"
        );
    }

    #[test]
    fn sparse_samples_are_interpolated() {
        // One sample every 2.5°, grid of 1°: the two nearest samples carry each node.
        let angle: Vec<f64> = (0..144)
            .map(|k| (k as f64 * 2.5 + 0.3).to_radians())
            .collect();
        let value: Vec<f64> = angle.iter().map(|&t| signal(t)).collect();
        let r = run(&angle, &value, None, 360).unwrap();
        for k in 0..360 {
            let t = (k as f64).to_radians();
            assert!((r.y[k] - signal(t)).abs() < 2e-4, "node {k}");
        }
    }
}

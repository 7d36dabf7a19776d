//! Pose selection (Section 2.1.3, Fig. 5): in = the candidate pool and the identifiable
//! parameters; out = [`Selection`]: the poses kept and the curve cond(n).
//!
//! Exact greedy elimination: at every step the pose whose removal leaves the lowest condition
//! number of the column-scaled identification Jacobian is removed, down to n = m. cond(J)² is the
//! eigenvalue ratio of the Gram matrix G = JᵀJ; removing row r turns it into G − r·rᵀ, whose
//! extreme eigenvalues follow from the eigen-decomposition of G by the secular equation of a
//! rank-one downdate (Golub 1973; Bunch, Nielsen & Sorensen 1978). So each candidate costs
//! O(m²) instead of an SVD, and the choice is exactly the one an SVD per candidate would make.
//!
//! Columns are scaled once, by their RMS over the whole pool, so the curve compares like with
//! like across n (the paper neglected scaling because metres and radians are comparable for a
//! robot of this size; the RMS scaling makes that explicit and robot-independent).

use crate::ir::{Pool, Selection};
use crate::model::{MeasurementModel, N_PARAMS};
use nalgebra::{DMatrix, SymmetricEigen};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SelectConfig {
    /// Fixed pose count (`--poses N`); None = the knee rule.
    pub poses: Option<usize>,
}

#[derive(Debug, thiserror::Error)]
pub enum SelectError {
    #[error("only {valid} valid poses for {m} identifiable parameters: refine --step, widen --bar or move the fixture")]
    TooFewPoses { valid: usize, m: usize },
    #[error("--poses {asked}: must be between m = {m} (identifiable parameters) and the {valid} valid poses")]
    PoseCount {
        asked: usize,
        m: usize,
        valid: usize,
    },
}

/// The knee rule's margin: at least ⌈1.5·m⌉ poses (the paper's NJ-130 optimum, 35 for m = 22,
/// is 1.6·m), and the smallest n there whose cond is within 10 % of the best cond at or above it.
pub const MARGIN: f64 = 1.5;
pub const KNEE_TOLERANCE: f64 = 1.10;

/// Column-scaled identification Jacobian of the pool on the given columns, row-major n × m.
pub fn scaled_jacobian(
    model: &MeasurementModel,
    pool: &Pool,
    columns: &[usize],
) -> (Vec<f64>, Vec<f64>) {
    let m = columns.len();
    let rows: Vec<[f64; N_PARAMS]> = pool
        .candidates
        .par_iter()
        .map(|c| {
            let mut row = [0.0; N_PARAMS];
            model.jacobian_row(&model.nominal, &c.q, &mut row);
            row
        })
        .collect();
    let n = rows.len().max(1) as f64;
    let scale: Vec<f64> = columns
        .iter()
        .map(|&j| {
            (rows.iter().map(|r| r[j] * r[j]).sum::<f64>() / n)
                .sqrt()
                .max(f64::MIN_POSITIVE)
        })
        .collect();
    let mut out = Vec::with_capacity(rows.len() * m);
    for r in &rows {
        out.extend(columns.iter().zip(&scale).map(|(&j, s)| r[j] / s));
    }
    (out, scale)
}

pub fn run(
    model: &MeasurementModel,
    pool: &Pool,
    columns: &[usize],
    cfg: &SelectConfig,
) -> Result<Selection, SelectError> {
    let m = columns.len();
    let n0 = pool.candidates.len();
    if n0 < m || m == 0 {
        return Err(SelectError::TooFewPoses { valid: n0, m });
    }
    if let Some(k) = cfg.poses {
        if k < m || k > n0 {
            return Err(SelectError::PoseCount {
                asked: k,
                m,
                valid: n0,
            });
        }
    }
    let (j, _) = scaled_jacobian(model, pool, columns);
    let (removed, curve) = eliminate(&j, m);
    let (n_sel, rule) = match cfg.poses {
        Some(k) => (k, format!("--poses {k}")),
        None => knee(&curve, m),
    };
    // The set of size n is the pool minus the first n0 − n removals.
    let mut keep = vec![true; n0];
    for &r in &removed[..n0 - n_sel] {
        keep[r] = false;
    }
    let indices = (0..n0).filter(|&i| keep[i]).collect();
    Ok(Selection {
        indices,
        curve,
        m,
        rule,
    })
}

/// The default pose count: see [`MARGIN`] and [`KNEE_TOLERANCE`].
pub fn knee(curve: &[(usize, f64)], m: usize) -> (usize, String) {
    let floor = ((m as f64) * MARGIN).ceil() as usize;
    let above: Vec<&(usize, f64)> = curve.iter().filter(|(n, _)| *n >= floor).collect();
    if above.is_empty() {
        let n = curve.first().map_or(m, |c| c.0);
        return (
            n,
            format!("all {n} valid poses (fewer than {floor} = 1.5 m)"),
        );
    }
    let best = above.iter().map(|c| c.1).fold(f64::INFINITY, f64::min);
    let n = above
        .iter()
        .filter(|c| c.1 <= KNEE_TOLERANCE * best)
        .map(|c| c.0)
        .min()
        .unwrap_or(floor);
    (
        n,
        format!(
            "knee: smallest n >= 1.5 m = {floor} with cond(n) <= 1.1 x min cond ({})",
            crate::units::fmt_fixed(best, 2)
        ),
    )
}

/// Greedy elimination on a row-major n × m matrix. Returns the removal order (row indices) and
/// the curve (n, cond) from n = rows down to n = m.
pub fn eliminate(j: &[f64], m: usize) -> (Vec<usize>, Vec<(usize, f64)>) {
    let n0 = j.len() / m;
    let row = |i: usize| &j[i * m..(i + 1) * m];
    let mut active: Vec<usize> = (0..n0).collect();
    let mut removed = Vec::with_capacity(n0.saturating_sub(m));
    let mut curve = Vec::with_capacity(n0 - m + 1);
    let gram = |active: &[usize]| {
        let mut g = DMatrix::<f64>::zeros(m, m);
        for &i in active {
            let r = row(i);
            for a in 0..m {
                for b in a..m {
                    g[(a, b)] += r[a] * r[b];
                }
            }
        }
        for a in 0..m {
            for b in 0..a {
                g[(a, b)] = g[(b, a)];
            }
        }
        g
    };
    let mut g = gram(&active);
    loop {
        let eig = SymmetricEigen::new(g.clone());
        let mut order: Vec<usize> = (0..m).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
        let lam: Vec<f64> = order.iter().map(|&k| eig.eigenvalues[k]).collect();
        let vt: Vec<f64> = order
            .iter()
            .flat_map(|&k| {
                eig.eigenvectors
                    .column(k)
                    .iter()
                    .copied()
                    .collect::<Vec<_>>()
            })
            .collect();
        curve.push((active.len(), cond_of(lam[0], lam[m - 1])));
        if active.len() == m {
            break;
        }
        let best = active
            .par_iter()
            .enumerate()
            .map_init(
                || vec![0.0; m],
                |z, (pos, &i)| {
                    let r = row(i);
                    for k in 0..m {
                        z[k] = vt[k * m..(k + 1) * m]
                            .iter()
                            .zip(r)
                            .map(|(v, x)| v * x)
                            .sum();
                    }
                    let (lo, hi) = downdated_extremes(&lam, z);
                    let score = if lo > 0.0 { hi / lo } else { f64::INFINITY };
                    (score, i, pos)
                },
            )
            .reduce(
                || (f64::INFINITY, usize::MAX, usize::MAX),
                |a, b| if (b.0, b.1) < (a.0, a.1) { b } else { a },
            );
        let (_, i, pos) = if best.2 == usize::MAX {
            (0.0, active[active.len() - 1], active.len() - 1)
        } else {
            best
        };
        active.remove(pos);
        removed.push(i);
        // Downdate; rebuild from scratch now and then (and always when few rows remain, where
        // the Gram matrix is least well conditioned) so rounding cannot accumulate.
        if active.len() < 3 * m || removed.len() % 64 == 0 {
            g = gram(&active);
        } else {
            let r = row(i);
            for a in 0..m {
                for b in 0..m {
                    g[(a, b)] -= r[a] * r[b];
                }
            }
        }
    }
    (removed, curve)
}

fn cond_of(lmin: f64, lmax: f64) -> f64 {
    if lmin > 0.0 {
        (lmax / lmin).sqrt()
    } else {
        f64::INFINITY
    }
}

/// Smallest and largest eigenvalue of diag(λ) − z·zᵀ (λ ascending), from the secular equation
/// f(x) = 1 − Σ zᵢ²/(λᵢ − x) = 0. Interlacing brackets them: λ'₁ ∈ [λ₁ − ‖z‖², λ₁] and
/// λ'ₘ ∈ [max(λₘ₋₁, λₘ − ‖z‖²), λₘ]; f decreases on both brackets.
pub fn downdated_extremes(lam: &[f64], z: &[f64]) -> (f64, f64) {
    let m = lam.len();
    let zz: f64 = z.iter().map(|v| v * v).sum();
    let lo = secular_root(lam, z, lam[0] - zz, lam[0], 0);
    let hi = if m == 1 {
        lo
    } else {
        secular_root(lam, z, (lam[m - 2]).max(lam[m - 1] - zz), lam[m - 1], m - 1)
    };
    (lo, hi)
}

/// Root of the secular function in (a, b), b = λ[pole], by a one-pole rational model fitted to
/// value and slope (quadratically convergent), safeguarded by bisection.
fn secular_root(lam: &[f64], z: &[f64], mut a: f64, mut b: f64, pole: usize) -> f64 {
    let psi = |x: f64| {
        let (mut v, mut d) = (0.0, 0.0);
        for (l, zi) in lam.iter().zip(z) {
            let t = zi / (l - x);
            v += zi * t;
            d += t * t;
        }
        (v, d)
    };
    let scale = b.abs().max(a.abs()).max(f64::MIN_POSITIVE);
    let mut x = 0.5 * (a + b);
    for _ in 0..100 {
        if b - a <= 4.0 * f64::EPSILON * scale {
            break;
        }
        let (v, d) = psi(x);
        let f = 1.0 - v;
        if f > 0.0 {
            a = x;
        } else if f < 0.0 {
            b = x;
        } else {
            return x;
        }
        // ψ(y) ≈ c/(λp − y) + e with matching value and slope at x; solve c/(λp − y) + e = 1.
        let lp = lam[pole];
        let c = d * (lp - x) * (lp - x);
        let e = v - c / (lp - x);
        let mut next = if e < 1.0 {
            lp - c / (1.0 - e)
        } else {
            f64::NAN
        };
        if !(next > a && next < b) {
            next = 0.5 * (a + b);
        }
        if (next - x).abs() <= 2.0 * f64::EPSILON * scale {
            return next;
        }
        x = next;
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_matrix(n: usize, m: usize, seed: u64) -> Vec<f64> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        // Uneven column scales and some correlation, like a real Jacobian.
        (0..n * m)
            .map(|k| rng.random_range(-1.0..1.0) * (1.0 + (k % m) as f64 * 0.3))
            .collect()
    }

    fn cond_svd(j: &[f64], rows: &[usize], m: usize) -> f64 {
        let a = DMatrix::from_fn(rows.len(), m, |i, k| j[rows[i] * m + k]);
        let sv = a.singular_values();
        sv.max() / sv.min()
    }

    #[test]
    fn secular_extremes_match_a_full_eigendecomposition() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for _ in 0..200 {
            let m = rng.random_range(2..12);
            let n = m + rng.random_range(1..20);
            let j = random_matrix(n, m, rng.random());
            let g = DMatrix::from_fn(m, m, |a, b| {
                (0..n).map(|i| j[i * m + a] * j[i * m + b]).sum::<f64>()
            });
            let eig = SymmetricEigen::new(g.clone());
            let mut idx: Vec<usize> = (0..m).collect();
            idx.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
            let lam: Vec<f64> = idx.iter().map(|&k| eig.eigenvalues[k]).collect();
            let r = &j[0..m];
            let z: Vec<f64> = idx
                .iter()
                .map(|&k| {
                    eig.eigenvectors
                        .column(k)
                        .iter()
                        .zip(r)
                        .map(|(v, x)| v * x)
                        .sum()
                })
                .collect();
            let (lo, hi) = downdated_extremes(&lam, &z);
            let rr = DMatrix::from_fn(m, m, |a, b| r[a] * r[b]);
            let want = SymmetricEigen::new(g - rr).eigenvalues;
            assert!(
                (lo - want.min()).abs() <= 1e-9 * want.max(),
                "{lo} vs {}",
                want.min()
            );
            assert!(
                (hi - want.max()).abs() <= 1e-9 * want.max(),
                "{hi} vs {}",
                want.max()
            );
        }
    }

    /// The reference: one SVD per candidate, the textbook greedy.
    fn greedy_by_svd(j: &[f64], m: usize) -> Vec<usize> {
        let mut active: Vec<usize> = (0..j.len() / m).collect();
        let mut removed = Vec::new();
        while active.len() > m {
            let (pos, _) = (0..active.len())
                .map(|p| {
                    let mut rest = active.clone();
                    rest.remove(p);
                    (p, cond_svd(j, &rest, m))
                })
                .fold((0, f64::INFINITY), |b, c| if c.1 < b.1 { c } else { b });
            removed.push(active.remove(pos));
        }
        removed
    }

    #[test]
    fn fast_elimination_equals_svd_greedy_on_small_sets() {
        for seed in 0..6 {
            let (n, m) = (30 + seed as usize * 3, 6);
            let j = random_matrix(n, m, seed);
            let (removed, curve) = eliminate(&j, m);
            assert_eq!(removed, greedy_by_svd(&j, m), "seed {seed}");
            // And every recorded cond is the true cond of the remaining rows.
            let mut active: Vec<usize> = (0..n).collect();
            for (k, &(count, c)) in curve.iter().enumerate() {
                assert_eq!(count, active.len());
                let want = cond_svd(&j, &active, m);
                assert!((c - want).abs() <= 1e-7 * want, "n={count}: {c} vs {want}");
                if k < removed.len() {
                    active.retain(|&i| i != removed[k]);
                }
            }
        }
    }

    #[test]
    fn knee_rule_respects_the_margin_and_tolerance() {
        let m = 10;
        // cond falls from 40 rows to a minimum of 2.0 at n = 20, then rises towards n = m.
        let curve: Vec<(usize, f64)> = (m..=40)
            .rev()
            .map(|n| (n, 2.0 + ((n as f64) - 20.0).powi(2) * 0.01))
            .collect();
        let (n, _) = knee(&curve, m);
        // Within 10 % of 2.0: (n − 20)² ≤ 20 → n ≥ 15.53 → 16.
        assert_eq!(n, 16);
        let short: Vec<(usize, f64)> = (m..=12).rev().map(|n| (n, 5.0)).collect();
        assert_eq!(knee(&short, m).0, 12);
    }
}

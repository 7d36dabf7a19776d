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
use crate::model::MeasurementModel;
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
    let qs: Vec<[f64; 6]> = pool.candidates.iter().map(|c| c.q).collect();
    let rows = model.rows(&qs);
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
///
/// It makes exactly the choices of [`eliminate_reference`] (which scores every candidate by the
/// secular equation at every step) but scores most candidates only by cheap lower bounds. In the
/// eigenbasis of G a candidate is z = Vᵀr and G − r·rᵀ ≅ diag(λ) − z·zᵀ; by Rayleigh-Ritz, for
/// any orthonormal U the smallest eigenvalue of Uᵀ(G − r·rᵀ)U bounds λ'min from above and, for
/// another U, the largest bounds λ'max from below. So the score λ'max/λ'min has a lower bound:
/// 1. for every candidate, from two low and two high directions in closed form (2×2 matrices).
///    U is the eigenbasis of a step at most `REFRESH` − 1 removals ago, so the projections Uᵀr
///    are reused and a step costs a few flops per candidate;
/// 2. for those not ruled out, visited in ascending order of bound 1, the sharper `ritz_bound`
///    (k directions at each end of the current eigenbasis, the rest lumped);
/// 3. the exact score for those not ruled out either.
///
/// A candidate is skipped only when a bound exceeds the best exact score of the step by a
/// relative margin far above rounding, so the skipped ones provably score worse and the choice,
/// tie-break by index included, is the exhaustive one. The Gram matrix, its eigendecomposition
/// and the exact scores use the reference's arithmetic, so the curve is bit for bit the same.
/// Greedy elimination makes the extreme eigenvalues cluster, which is why bound 1 looks at two
/// directions at each end and bound 2 at `RITZ_K`.
pub fn eliminate(j: &[f64], m: usize) -> (Vec<usize>, Vec<(usize, f64)>) {
    let n0 = j.len() / m;
    let row = |i: usize| &j[i * m..(i + 1) * m];
    let mut alive = vec![true; n0];
    // Active rows, column-major (cols[k][p] = J[ids[p], k]) so the bound pass streams each
    // column once; removal is swap_remove, the order of positions carries no meaning.
    let mut ids: Vec<usize> = (0..n0).collect();
    let mut cols: Vec<Vec<f64>> = (0..m)
        .map(|k| (0..n0).map(|i| j[i * m + k]).collect())
        .collect();
    let mut removed = Vec::with_capacity(n0.saturating_sub(m));
    let mut curve = Vec::with_capacity(n0 - m + 1);
    // Ascending index order, exactly as the reference sums.
    let gram = |alive: &[bool]| {
        let mut g = DMatrix::<f64>::zeros(m, m);
        for i in (0..n0).filter(|&i| alive[i]) {
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
    let mut g = gram(&alive);
    let mut lbs: Vec<f64> = Vec::with_capacity(n0);
    let mut queue: Vec<(f64, usize)> = Vec::new();
    let mut sharp: Vec<f64> = Vec::new();
    let norms: Vec<f64> = (0..n0)
        .map(|i| row(i).iter().map(|v| v * v).sum())
        .collect();
    let ritz_k = RITZ_K.min(m.saturating_sub(1));
    // The bound basis (4 directions, row-major) and every active row's projections on it.
    let mut basis = vec![0.0; 4 * m];
    let mut proj: Vec<[f64; 4]> = vec![[0.0; 4]; n0];
    let mut since_refresh = REFRESH;
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
        let n = ids.len();
        curve.push((n, cond_of(lam[0], lam[m - 1])));
        if n == m {
            break;
        }
        // The exact score, with the reference's arithmetic.
        let exact = |p: usize, z: &mut [f64]| {
            let r = row(ids[p]);
            for k in 0..m {
                z[k] = vt[k * m..(k + 1) * m]
                    .iter()
                    .zip(r)
                    .map(|(v, x)| v * x)
                    .sum();
            }
            let (lo, hi) = downdated_extremes(&lam, z);
            if lo > 0.0 {
                hi / lo
            } else {
                f64::INFINITY
            }
        };
        // Lower bounds for every active candidate (see the doc comment): Rayleigh-Ritz on two
        // low and two high directions U, in closed form. U is the eigenbasis of some recent
        // step; the bound holds for any orthonormal U, it is only sharpest for the current one,
        // and a stale U lets the projections Uᵀr be reused instead of recomputed every step.
        if since_refresh >= REFRESH {
            since_refresh = 0;
            let two = m >= 2;
            let dirs = if two { [0, 1, m - 2, m - 1] } else { [0; 4] };
            for (slot, &e) in basis.chunks_mut(m).zip(&dirs) {
                slot.copy_from_slice(&vt[e * m..(e + 1) * m]);
            }
            let basis = &basis;
            let cols = &cols;
            let refresh = |start: usize, zs: &mut [[f64; 4]]| {
                let len = zs.len();
                for z in zs.iter_mut() {
                    *z = [0.0; 4];
                }
                for k in 0..m {
                    let c = &cols[k][start..start + len];
                    let u = [basis[k], basis[m + k], basis[2 * m + k], basis[3 * m + k]];
                    for (z, &y) in zs.iter_mut().zip(c) {
                        for d in 0..4 {
                            z[d] += u[d] * y;
                        }
                    }
                }
            };
            if n >= PARALLEL_BOUND {
                proj.par_chunks_mut(BOUND_CHUNK)
                    .enumerate()
                    .for_each(|(c, zs)| refresh(c * BOUND_CHUNK, zs));
            } else {
                refresh(0, &mut proj[..]);
            }
        }
        since_refresh += 1;
        // UᵀGU on each pair, once per step.
        let quad = |x: usize, y: usize| -> f64 {
            let (u, v) = (&basis[x * m..(x + 1) * m], &basis[y * m..(y + 1) * m]);
            let mut s = 0.0;
            for a in 0..m {
                let mut t = 0.0;
                for b in 0..m {
                    t += g[(a, b)] * v[b];
                }
                s += u[a] * t;
            }
            s
        };
        let (la, lb_, lc) = (quad(0, 0), quad(0, 1), quad(1, 1));
        let (ha, hb, hc) = (quad(2, 2), quad(2, 3), quad(3, 3));
        lbs.clear();
        lbs.resize(n, 0.0);
        let bound_chunk = |start: usize, out: &mut [f64]| {
            let len = out.len();
            for (o, z) in out.iter_mut().zip(&proj[start..start + len]) {
                let [a1, a2, b1, b2] = *z;
                // Smallest eigenvalue of [[la, lb], [lb, lc]] − a·aᵀ, via its determinant (the
                // z⁴ terms cancel exactly), and the largest of the high pair.
                let (p1, p2, off) = (la - a1 * a1, lc - a2 * a2, lb_ - a1 * a2);
                let det = la * lc - lb_ * lb_ - la * a2 * a2 - lc * a1 * a1 + 2.0 * lb_ * a1 * a2;
                let rad = (0.25 * (p1 - p2) * (p1 - p2) + off * off).sqrt();
                // A nearly singular downdate: too much cancellation to trust; score exactly.
                let lmin = if det > DET_FLOOR * la * lc {
                    det / (0.5 * (p1 + p2) + rad)
                } else {
                    0.0
                };
                let (q1, q2, hoff) = (ha - b1 * b1, hc - b2 * b2, hb - b1 * b2);
                let hmax = 0.5 * (q1 + q2) + (0.25 * (q1 - q2) * (q1 - q2) + hoff * hoff).sqrt();
                *o = if lmin > 0.0 { hmax / lmin } else { 0.0 };
            }
        };
        if n >= PARALLEL_BOUND {
            lbs.par_chunks_mut(BOUND_CHUNK)
                .enumerate()
                .for_each(|(c, out)| bound_chunk(c * BOUND_CHUNK, out));
        } else {
            bound_chunk(0, &mut lbs[..]);
        }
        // A first exact score from the most promising candidate sets the cut; the candidates
        // whose bound does not exceed it are then visited in ascending bound order, each getting
        // the sharper Ritz bound and, if that does not rule it out either, its exact score,
        // which tightens the cut for the rest.
        let pick = |a: (f64, usize, usize), b: (f64, usize, usize)| {
            if (b.0, b.1) < (a.0, a.1) {
                b
            } else {
                a
            }
        };
        let first = (0..n)
            .min_by(|&a, &b| lbs[a].total_cmp(&lbs[b]))
            .unwrap_or(0);
        let mut z = vec![0.0; m];
        let mut best = (exact(first, &mut z), ids[first], first);
        let mut cut = best.0 * (1.0 + BOUND_MARGIN);
        queue.clear();
        queue.extend(
            (0..n)
                .filter(|&p| {
                    p != first && lbs[p].partial_cmp(&cut) != Some(std::cmp::Ordering::Greater)
                })
                .map(|p| (lbs[p], p)),
        );
        // Visit in ascending bound order, a block at a time: partial sorting, and the Ritz
        // bounds of a block computed in parallel.
        let by_bound = |a: &(f64, usize), b: &(f64, usize)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        let mut start = 0;
        'visit: while start < queue.len() {
            let end = (start + RITZ_BLOCK).min(queue.len());
            if end < queue.len() {
                queue[start..].select_nth_unstable_by(end - start - 1, by_bound);
            }
            queue[start..end].sort_unstable_by(by_bound);
            if queue[start].0 > cut {
                break;
            }
            let ritz = |&(lb, p): &(f64, usize)| {
                if lb > cut || ritz_k == 0 {
                    lb
                } else {
                    ritz_bound(&lam, &vt, row(ids[p]), norms[ids[p]], ritz_k)
                }
            };
            if end - start >= 64 && n >= PARALLEL_BOUND {
                queue[start..end]
                    .par_iter()
                    .map(ritz)
                    .collect_into_vec(&mut sharp);
            } else {
                sharp.clear();
                sharp.extend(queue[start..end].iter().map(ritz));
            }
            for (&(lb, p), &r2) in queue[start..end].iter().zip(&sharp) {
                if lb > cut {
                    break 'visit;
                }
                if r2 > cut {
                    continue;
                }
                best = pick(best, (exact(p, &mut z), ids[p], p));
                cut = best.0 * (1.0 + BOUND_MARGIN);
            }
            start = end;
        }
        let (_, i, p) = best;
        ids.swap_remove(p);
        proj.swap_remove(p);
        for c in cols.iter_mut() {
            c.swap_remove(p);
        }
        alive[i] = false;
        removed.push(i);
        // Same schedule of rebuilds and downdates as the reference.
        if ids.len() < 3 * m || removed.len() % 64 == 0 {
            g = gram(&alive);
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

/// Relative margin by which a lower bound must exceed the best exact score before a candidate is
/// skipped: far above the rounding of either (both come from the same λ and V), far below any
/// difference that matters.
const BOUND_MARGIN: f64 = 1e-9;
/// Below this relative size of the 2×2 determinant the closed-form bound is not trusted.
const DET_FLOOR: f64 = 1e-6;
/// Eigen-directions at each end of the spectrum that the sharper (Ritz) bound resolves; greedy
/// elimination clusters the extreme eigenvalues, where the one-direction bound is weak.
const RITZ_K: usize = 3;
/// Candidates per block of the ascending-bound visit.
const RITZ_BLOCK: usize = 256;
/// Steps between recomputations of the bound basis and the projections on it.
const REFRESH: usize = 4;
/// Candidates per block of the bound pass (stack buffers, one rayon task each).
const BOUND_CHUNK: usize = 1024;
/// Below this size a step is too short to pay for rayon.
const PARALLEL_BOUND: usize = 4096;

/// The reference for [`eliminate`]: the same greedy, scoring every candidate exactly at every
/// step (one secular solve pair per candidate). Kept for tests and the benchmark.
#[doc(hidden)]
pub fn eliminate_reference(j: &[f64], m: usize) -> (Vec<usize>, Vec<(usize, f64)>) {
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

/// A lower bound on the score λ'max/λ'min of removing row `r` (‖r‖² = `rr`), sharper than the
/// Rayleigh one: the k eigen-directions at each end are kept exactly and the rest of z is lumped
/// into one extra direction on the far pole. With t = ‖r‖² − Σ_{i≤k} zᵢ², the term
/// Σ_{i>k} zᵢ²/(λᵢ − x) of the secular function is at least t/(λₘ − x) for x < λ₁, so the smallest
/// root of the lumped (k+1)-term equation lies above λ'min; at the top, Σ_{i≤m−k} zᵢ²/(x − λᵢ) is
/// at least t'/(x − λ₁), so the largest lumped root lies below λ'max. 0 = no information.
fn ritz_bound(lam: &[f64], vt: &[f64], r: &[f64], rr: f64, k: usize) -> f64 {
    let m = lam.len();
    let dot = |e: usize| -> f64 {
        vt[e * m..(e + 1) * m]
            .iter()
            .zip(r)
            .map(|(v, x)| v * x)
            .sum()
    };
    let mut l = [0.0; RITZ_K + 1];
    let mut z = [0.0; RITZ_K + 1];
    for i in 0..k {
        l[i] = lam[i];
        z[i] = dot(i);
    }
    let head: f64 = z[..k].iter().map(|v| v * v).sum();
    l[k] = lam[m - 1];
    z[k] = (rr - head).max(0.0).sqrt();
    let zz: f64 = z[..=k].iter().map(|v| v * v).sum();
    let lo = secular_root(&l[..=k], &z[..=k], l[0] - zz, l[0], 0);
    l[0] = lam[0];
    for i in 0..k {
        l[i + 1] = lam[m - k + i];
        z[i + 1] = dot(m - k + i);
    }
    let tail: f64 = z[1..=k].iter().map(|v| v * v).sum();
    z[0] = (rr - tail).max(0.0).sqrt();
    let zz: f64 = z[..=k].iter().map(|v| v * v).sum();
    let hi = secular_root(&l[..=k], &z[..=k], l[k - 1].max(l[k] - zz), l[k], k);
    if lo > 0.0 {
        hi / lo
    } else {
        0.0
    }
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
        // Converged; test this before the bracket, because the model may land exactly on an
        // end of the bracket (the root itself, when f(x) rounded to the other sign), and
        // bisecting from there would only crawl back to it.
        if (next - x).abs() <= 2.0 * f64::EPSILON * scale {
            return next;
        }
        if !(next > a && next < b) {
            next = 0.5 * (a + b);
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

    /// The bounded search must make the exhaustive search's choices: same removals, and a curve
    /// no worse (here: bit for bit equal) at every n.
    fn check_against_reference(j: &[f64], m: usize, what: &str) {
        let (removed, curve) = eliminate(j, m);
        let (want_removed, want_curve) = eliminate_reference(j, m);
        assert_eq!(curve.len(), want_curve.len(), "{what}");
        for (&(n, c), &(wn, w)) in curve.iter().zip(&want_curve) {
            assert_eq!(n, wn, "{what}");
            assert!(
                c <= w * (1.0 + 1e-9),
                "{what}: n={n}: {c} > exact greedy {w}"
            );
        }
        assert_eq!(removed, want_removed, "{what}");
        assert_eq!(curve, want_curve, "{what}");
    }

    #[test]
    fn bounded_elimination_equals_exhaustive_greedy_on_random_jacobians() {
        for seed in 0..4 {
            check_against_reference(&random_matrix(200, 22, seed), 22, &format!("seed {seed}"));
        }
        // Small and degenerate shapes: m = 1, n = m + 1, duplicated rows (exact ties).
        check_against_reference(&random_matrix(9, 1, 7), 1, "m = 1");
        check_against_reference(&random_matrix(7, 6, 8), 6, "n = m + 1");
        let mut dup = random_matrix(40, 5, 9);
        dup.extend_from_within(0..20 * 5);
        check_against_reference(&dup, 5, "duplicated rows");
    }

    #[test]
    fn bounded_elimination_equals_exhaustive_greedy_on_an_nj130_pool() {
        use crate::units::{DEG, MM};
        let robot = crate::robot::load(
            std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/robots/comau_nj130/robot.dh.toml"
            )),
            &Default::default(),
        )
        .expect("bundled NJ-130");
        let fixture = nalgebra::Vector3::new(258.0, 1468.0, 708.0) * MM;
        let map = nalgebra::Vector3::new(60.0, 30.0, 120.0) * MM;
        let model = MeasurementModel::new(&robot, fixture, map);
        let cell = crate::ir::Cell::shell_only(fixture, map, 0.30, 0.52, 0.0);
        let cfg = crate::sample::SampleConfig {
            step: [10.0 * DEG; 6],
            max_candidates: 300,
            seed: 1,
            movable: [true; 6],
        };
        let (pool, _) = crate::sample::run(&robot, &model, &cell, &cfg, &crate::sample::NoProgress);
        let qs: Vec<[f64; 6]> = pool.candidates.iter().map(|c| c.q).collect();
        let rows = model.rows(&qs);
        let ids = crate::model::analyse(&rows, &Default::default()).identifiable;
        assert_eq!(ids.len(), 22);
        let (j, _) = scaled_jacobian(&model, &pool, &ids);
        check_against_reference(&j, ids.len(), "NJ-130 pool of 300");
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

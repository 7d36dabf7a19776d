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
/// secular equation at every step) but scores most candidates only by cheap lower bounds. The
/// score of removing row r is λ'max/λ'min, the extreme eigenvalues of G − r·rᵀ. By Rayleigh-Ritz,
/// for any orthonormal U the smallest eigenvalue of Uᵀ(G − r·rᵀ)U bounds λ'min from above and,
/// for another U, the largest bounds λ'max from below; and so does any Rayleigh quotient of those
/// compressions. Three tiers of lower bounds on the score:
/// 1. U holds two low and two high eigenvectors of a recent step (refreshed when the bounds grow
///    weak), so the projections Uᵀr are computed once per refresh. For every candidate the
///    extreme eigenvectors x, y of its two 2×2 compressions are kept from the step they were last
///    computed; the Rayleigh quotients yᵀ(H − b·bᵀ)y / xᵀ(L − a·aᵀ)x with this step's blocks H, L
///    of UᵀGU are a lower bound for 8 multiply-adds and no square root. Quotients are stationary
///    at eigenvectors, so a kept vector stays nearly as good as a fresh one for many steps (and
///    across refreshes: the new basis is signed like the old one and the vectors are kept);
/// 2. where that does not rule a candidate out, the 2×2 compressions are solved afresh (closed
///    form), which also renews its kept vectors; those still not ruled out are visited in
///    ascending order of this bound (a heap) and get the sharper `ritz_bound` (k directions at
///    each end of the current eigenbasis, the rest lumped, its extremes bounded by Rayleigh
///    quotients rather than solved), a block at a time, long blocks in parallel;
/// 3. the exact score for those not ruled out either.
///
/// A candidate is skipped only when a bound exceeds the best exact score of the step by a
/// relative margin above rounding (see `slack`), so the skipped ones provably score worse and
/// the choice, tie-break by index included, is the exhaustive one. The Gram matrix, its
/// eigendecomposition and the exact scores use the reference's arithmetic (the same functions),
/// so the curve is bit for bit the same. Where G is numerically singular (see `slack`) nothing is
/// skipped. The result does not depend on the thread count: parallel parts only compute bounds
/// per candidate, in fixed chunks, and every choice is made serially in a fixed order.
/// Greedy elimination makes the extreme eigenvalues
/// cluster, which is why tier 1 looks at two directions at each end and tier 2 at `RITZ_K`.
pub fn eliminate(j: &[f64], m: usize) -> (Vec<usize>, Vec<(usize, f64)>) {
    let n0 = j.len() / m;
    let row = |i: usize| &j[i * m..(i + 1) * m];
    let mut alive = vec![true; n0];
    // Active rows by position; removal is swap_remove, positions carry no meaning. `at` maps a
    // row to its position.
    let mut ids: Vec<usize> = (0..n0).collect();
    let mut at: Vec<usize> = (0..n0).collect();
    let norms: Vec<f64> = (0..n0)
        .map(|i| row(i).iter().map(|v| v * v).sum())
        .collect();
    let mut removed = Vec::with_capacity(n0.saturating_sub(m));
    let mut curve = Vec::with_capacity(n0 - m + 1);
    let mut g = gram(j, m, &(0..n0).collect::<Vec<_>>());
    let ritz_k = RITZ_K.min(m.saturating_sub(1));
    // The bound basis (4 directions, row-major) and, per position, the tier-1 data.
    let mut basis = vec![0.0; 4 * m];
    let mut hot: Vec<[f64; 8]> = vec![[0.0; 8]; n0];
    let mut kept: Vec<Kept> = vec![Kept::default(); n0];
    let mut parts: Vec<Vec<(f64, usize)>> = Vec::new();
    let mut age = usize::MAX;
    let mut max_age = REFRESH_MIN;
    let mut leaders: Vec<usize> = Vec::new();
    let mut queue: Vec<(f64, usize)> = Vec::new();
    let mut sharp: Vec<f64> = Vec::new();
    let mut heap: std::collections::BinaryHeap<Queued> = std::collections::BinaryHeap::new();
    let mut block: Vec<(f64, usize)> = Vec::new();
    let mut scored: Vec<(f64, usize, usize)> = Vec::new();
    let mut z = vec![0.0; m];
    let mut ext = vec![0.0; 2 * RITZ_K * m];
    let mut known: Vec<usize> = Vec::new();
    let mut active: Vec<usize> = Vec::with_capacity(n0);
    loop {
        let (lam, vt) = spectrum(&g);
        let n = ids.len();
        curve.push((n, cond_of(lam[0], lam[m - 1])));
        if n == m {
            break;
        }
        let slack = slack(&lam);
        extremes_transposed(&vt, m, ritz_k, &mut ext);
        if age >= max_age {
            age = 0;
            let dirs = if m >= 2 { [0, 1, m - 2, m - 1] } else { [0; 4] };
            // The new directions, signed like the old ones, so that the kept eigenvectors
            // (coordinates in this basis) stay good ones.
            for (slot, &e) in basis.chunks_mut(m).zip(&dirs) {
                let v = &vt[e * m..(e + 1) * m];
                let same: f64 = slot.iter().zip(v).map(|(a, b)| a * b).sum();
                let sign = if same < 0.0 { -1.0 } else { 1.0 };
                for (u, &x) in slot.iter_mut().zip(v) {
                    *u = sign * x;
                }
            }
            let (basis, ids) = (&basis, &ids);
            let refresh = |start: usize, ws: &mut [[f64; 8]], ks: &mut [Kept]| {
                for (k, (w, c)) in ws.iter_mut().zip(ks.iter_mut()).enumerate() {
                    let r = row(ids[start + k]);
                    let mut s = [0.0; 4];
                    for (d, sd) in s.iter_mut().enumerate() {
                        *sd = basis[d * m..(d + 1) * m]
                            .iter()
                            .zip(r)
                            .map(|(u, x)| u * x)
                            .sum();
                    }
                    c.proj = s;
                    *w = c.weights();
                }
            };
            if n >= PARALLEL_BOUND {
                hot[..n]
                    .par_chunks_mut(BOUND_CHUNK)
                    .zip(kept[..n].par_chunks_mut(BOUND_CHUNK))
                    .enumerate()
                    .for_each(|(c, (ws, ks))| refresh(c * BOUND_CHUNK, ws, ks));
            } else {
                refresh(0, &mut hot[..n], &mut kept[..n]);
            }
        }
        age += 1;
        // UᵀGU on each pair of directions, once per step: the low and the high 2×2 block.
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
        let blocks = [
            quad(0, 0),
            quad(0, 1),
            quad(1, 1),
            quad(2, 2),
            quad(2, 3),
            quad(3, 3),
        ];
        let floor = DET_FLOOR * blocks[0].abs().max(blocks[2].abs());
        // The exact extremes (λ'min, λ'max), with the reference's arithmetic.
        let exact = |i: usize, z: &mut [f64]| -> (f64, f64) {
            let r = row(i);
            for k in 0..m {
                z[k] = vt[k * m..(k + 1) * m]
                    .iter()
                    .zip(r)
                    .map(|(v, x)| v * x)
                    .sum();
            }
            downdated_extremes(&lam, z)
        };
        let score = |(lo, hi): (f64, f64)| if lo > 0.0 { hi / lo } else { f64::INFINITY };
        // The cut: the best exact score among the previous step's leaders (any candidate would
        // do; these usually come close to the best).
        scored.clear();
        for &i in leaders.iter().filter(|&&i| alive[i]) {
            scored.push((score(exact(i, &mut z)), i, at[i]));
        }
        if scored.is_empty() {
            scored.push((score(exact(ids[0], &mut z)), ids[0], 0));
        }
        let mut best = scored.iter().copied().fold(scored[0], pick);
        let mut cut = best.0 * (1.0 + slack);
        // One pass: tier 1 where it rules a candidate out, the fresh 2×2 bound otherwise; the
        // queue holds those whose fresh bound does not exceed the cut.
        known.clear();
        known.extend(scored.iter().map(|s| s.2));
        let known = &known;
        let pass =
            |start: usize, ws: &mut [[f64; 8]], ks: &mut [Kept], out: &mut Vec<(f64, usize)>| {
                out.clear();
                for (k, (w, c)) in ws.iter_mut().zip(ks.iter_mut()).enumerate() {
                    if rules_out(w, &blocks, cut, floor) {
                        continue;
                    }
                    let lb = c.renew(w, &blocks, floor);
                    let p = start + k;
                    if lb.partial_cmp(&cut) != Some(std::cmp::Ordering::Greater)
                        && !known.contains(&p)
                    {
                        out.push((lb, p));
                    }
                }
            };
        queue.clear();
        if n >= PARALLEL_BOUND {
            let chunks = n.div_ceil(BOUND_CHUNK);
            if parts.len() < chunks {
                parts.resize_with(chunks, Vec::new);
            }
            hot[..n]
                .par_chunks_mut(BOUND_CHUNK)
                .zip(kept[..n].par_chunks_mut(BOUND_CHUNK))
                .zip(parts[..chunks].par_iter_mut())
                .enumerate()
                .for_each(|(c, ((ws, ks), out))| pass(c * BOUND_CHUNK, ws, ks, out));
            for p in &parts[..chunks] {
                queue.extend_from_slice(p);
            }
        } else {
            pass(0, &mut hot[..n], &mut kept[..n], &mut queue);
        }
        // The candidate with the lowest bound usually scores best: its exact score tightens
        // the cut before the rest are looked at.
        let by_bound = |a: &(f64, usize), b: &(f64, usize)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        if let Some(k) = (0..queue.len()).min_by(|&a, &b| by_bound(&queue[a], &queue[b])) {
            let (_, p) = queue.swap_remove(k);
            let this = (score(exact(ids[p], &mut z)), ids[p], p);
            scored.push(this);
            best = pick(best, this);
            cut = best.0 * (1.0 + slack);
        }
        queue.retain(|&(lb, _)| lb <= cut);
        // Weak bounds: refresh the basis sooner; strong ones: later.
        if queue.len() > QUEUE_TOLERANCE + n / 256 {
            max_age = (max_age / 2).max(REFRESH_MIN);
        } else if age == max_age {
            max_age = (max_age * 2).min(REFRESH_MAX);
        }
        // Visit in ascending bound order (a heap: usually only a few come off it), a block at
        // a time, the Ritz bounds of a block computed in parallel when it is long. Blocks grow
        // from `RITZ_BLOCK`: the first candidates are the likeliest to tighten the cut.
        heap.clear();
        heap.extend(queue.iter().map(|&(lb, p)| Queued(lb, p)));
        let mut len = RITZ_BLOCK;
        'visit: loop {
            block.clear();
            while block.len() < len {
                match heap.peek() {
                    Some(&Queued(lb, p)) if lb <= cut => {
                        heap.pop();
                        block.push((lb, p));
                    }
                    _ => break,
                }
            }
            if block.is_empty() {
                break;
            }
            let ritz = |&(lb, p): &(f64, usize)| -> f64 {
                if lb > cut || ritz_k == 0 {
                    lb
                } else {
                    let (h, l) = ritz_bound(&lam, &ext, row(ids[p]), norms[ids[p]], ritz_k);
                    if l > 0.0 {
                        h / l
                    } else {
                        0.0
                    }
                }
            };
            if block.len() >= PARALLEL_RITZ {
                block.par_iter().map(ritz).collect_into_vec(&mut sharp);
            } else {
                sharp.clear();
                sharp.extend(block.iter().map(ritz));
            }
            for (&(lb, p), &r2) in block.iter().zip(&sharp) {
                if lb > cut {
                    break 'visit;
                }
                if r2 > cut {
                    continue;
                }
                let this = (score(exact(ids[p], &mut z)), ids[p], p);
                scored.push(this);
                best = pick(best, this);
                cut = best.0 * (1.0 + slack);
            }
            len = (2 * len).min(RITZ_BLOCK_MAX);
        }
        // The next step's first guesses: the best few of this step after the one removed.
        scored.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        leaders.clear();
        leaders.extend(scored.iter().skip(1).take(LEADERS).map(|s| s.1));
        let (_, i, p) = best;
        ids.swap_remove(p);
        hot.swap_remove(p);
        kept.swap_remove(p);
        if p < ids.len() {
            at[ids[p]] = p;
        }
        alive[i] = false;
        removed.push(i);
        // Same schedule of rebuilds and downdates as the reference.
        if ids.len() < 3 * m || removed.len() % 64 == 0 {
            active.clear();
            active.extend((0..n0).filter(|&k| alive[k]));
            g = gram(j, m, &active);
        } else {
            downdate(&mut g, row(i));
        }
    }
    (removed, curve)
}

/// A queued candidate (bound, position), ordered so that std's max-heap pops the lowest bound
/// first, ties by position: a total order, so the visit order never depends on the heap's
/// history.
#[derive(Clone, Copy)]
struct Queued(f64, usize);

impl Ord for Queued {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        o.0.total_cmp(&self.0).then(o.1.cmp(&self.1))
    }
}

impl PartialOrd for Queued {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}

impl PartialEq for Queued {
    fn eq(&self, o: &Self) -> bool {
        self.cmp(o) == std::cmp::Ordering::Equal
    }
}

impl Eq for Queued {}

/// Tier 1 of [`eliminate`] for one candidate, the hot half: the Rayleigh-quotient weights of
/// its kept eigenvectors, [hi; lo]. yᵀ(H − b·bᵀ)y / yᵀy = hi[0]·H11 + hi[1]·H12 + hi[2]·H22 +
/// hi[3] is a lower bound on λ'max, xᵀ(L − a·aᵀ)x / xᵀx likewise (lo) an upper bound on λ'min
/// (see there). True when they put the score above `cut`. All zero: nothing kept.
#[inline]
fn rules_out(w: &[f64; 8], b: &[f64; 6], cut: f64, floor: f64) -> bool {
    let num = w[0] * b[3] + w[1] * b[4] + w[2] * b[5] + w[3];
    let den = w[4] * b[0] + w[5] * b[1] + w[6] * b[2] + w[7];
    den > floor && num > cut * den
}

/// Tier 1 of [`eliminate`] for one candidate, the cold half: its projections on the bound basis
/// U and its kept eigenvectors (coordinates in U), from which the hot weights are made.
#[derive(Clone, Copy, Default)]
struct Kept {
    /// [a1, a2, b1, b2] = Uᵀr: two low, two high directions.
    proj: [f64; 4],
    /// [x1, x2, y1, y2]: the kept low and high eigenvectors; zero = none kept.
    x: [f64; 4],
}

impl Kept {
    /// The hot weights of the kept eigenvectors with the current projections.
    fn weights(&self) -> [f64; 8] {
        let [a1, a2, b1, b2] = self.proj;
        let [x1, x2, y1, y2] = self.x;
        let mut w = [0.0; 8];
        if y1 != 0.0 || y2 != 0.0 {
            w[..4].copy_from_slice(&weights([y1, y2], [b1, b2]));
        }
        if x1 != 0.0 || x2 != 0.0 {
            w[4..].copy_from_slice(&weights([x1, x2], [a1, a2]));
        }
        w
    }

    /// Solves both 2×2 compressions afresh, keeps their extreme eigenvectors (and their hot
    /// weights in `w`), and returns the bound λmax(H − b·bᵀ)/λmin(L − a·aᵀ) (0 = no
    /// information: a nearly singular downdate, too much cancellation to trust).
    #[inline]
    fn renew(&mut self, w: &mut [f64; 8], b: &[f64; 6], floor: f64) -> f64 {
        let [la, lb, lc, ha, hb, hc] = *b;
        let [a1, a2, b1, b2] = self.proj;
        // Smallest eigenvalue of L − a·aᵀ via its determinant (the z⁴ terms cancel exactly), and
        // the largest of H − b·bᵀ.
        let (p1, p2, off) = (la - a1 * a1, lc - a2 * a2, lb - a1 * a2);
        let det = la * lc - lb * lb - la * a2 * a2 - lc * a1 * a1 + 2.0 * lb * a1 * a2;
        let rad = (0.25 * (p1 - p2) * (p1 - p2) + off * off).sqrt();
        let lmin = if det > DET_FLOOR * la * lc && det > 0.0 {
            det / (0.5 * (p1 + p2) + rad)
        } else {
            0.0
        };
        let (q1, q2, hoff) = (ha - b1 * b1, hc - b2 * b2, hb - b1 * b2);
        let hrad = (0.25 * (q1 - q2) * (q1 - q2) + hoff * hoff).sqrt();
        let hmax = 0.5 * (q1 + q2) + hrad;
        let y = eigvec(q1, q2, hoff, hmax);
        w[..4].copy_from_slice(&weights(y, [b1, b2]));
        let x = if lmin > floor {
            eigvec(p1, p2, off, lmin)
        } else {
            [0.0; 2]
        };
        if lmin > floor {
            w[4..].copy_from_slice(&weights(x, [a1, a2]));
        } else {
            w[4..].fill(0.0);
        }
        self.x = [x[0], x[1], y[0], y[1]];
        if lmin > 0.0 {
            hmax / lmin
        } else {
            0.0
        }
    }
}

/// An eigenvector of [[p, o], [o, q]] for its eigenvalue `l` (the better conditioned of the two
/// formulas). Any vector gives a valid Rayleigh quotient; this one makes it sharp.
#[inline]
fn eigvec(p: f64, q: f64, o: f64, l: f64) -> [f64; 2] {
    let (u, v) = ([o, l - p], [l - q, o]);
    let nu = u[0] * u[0] + u[1] * u[1];
    let nv = v[0] * v[0] + v[1] * v[1];
    if nu >= nv && nu > 0.0 {
        u
    } else if nv > 0.0 {
        v
    } else {
        [1.0, 0.0]
    }
}

/// The Rayleigh quotient xᵀ(M − a·aᵀ)x / xᵀx as weights on M11, M12, M22 and a constant.
#[inline]
fn weights(x: [f64; 2], a: [f64; 2]) -> [f64; 4] {
    let inv = 1.0 / (x[0] * x[0] + x[1] * x[1]);
    let (w1, w2, w3) = (
        x[0] * x[0] * inv,
        2.0 * x[0] * x[1] * inv,
        x[1] * x[1] * inv,
    );
    [
        w1,
        w2,
        w3,
        -(w1 * a[0] * a[0] + w2 * a[0] * a[1] + w3 * a[1] * a[1]),
    ]
}

/// The lower (score, index) pair: the greedy's choice with its tie-break.
#[inline]
fn pick(a: (f64, usize, usize), b: (f64, usize, usize)) -> (f64, usize, usize) {
    if (b.0, b.1) < (a.0, a.1) {
        b
    } else {
        a
    }
}

/// Relative margin by which a bound must exceed the best exact score before a candidate is
/// skipped. The bounds are carried from earlier eigendecompositions, so besides a fixed margin far
/// above rounding it covers the eigenvalue error of a symmetric eigensolver (a few ε·λmax in
/// absolute terms, so ε·λmax/λmin relative to λ'min), generously.
///
/// Above [`EXHAUSTIVE_RATIO`] (λmax/λmin: G numerically singular or nearly so) rounding swamps
/// λ'min and the exact scores themselves are mostly noise; no bound is trusted there (infinite
/// slack), so every candidate is scored exactly, as the reference does.
fn slack(lam: &[f64]) -> f64 {
    let m = lam.len();
    if lam[0] > 0.0 && lam[m - 1] <= EXHAUSTIVE_RATIO * lam[0] {
        BOUND_MARGIN + 1024.0 * f64::EPSILON * lam[m - 1] / lam[0]
    } else {
        f64::INFINITY
    }
}

/// The Gram matrix JᵀJ of the given rows (ascending), each entry summed in row order: the same
/// arithmetic for the reference and the bounded search. Entries are independent sums, so rows
/// of the triangle are computed in parallel without changing a bit.
fn gram(j: &[f64], m: usize, rows: &[usize]) -> DMatrix<f64> {
    let tri = |a: usize| -> Vec<f64> {
        let mut acc = vec![0.0; m - a];
        for &i in rows {
            let r = &j[i * m..(i + 1) * m];
            let ra = r[a];
            for (s, &rb) in acc.iter_mut().zip(&r[a..]) {
                *s += ra * rb;
            }
        }
        acc
    };
    let upper: Vec<Vec<f64>> = if rows.len() * m >= PARALLEL_GRAM {
        (0..m).into_par_iter().map(tri).collect()
    } else {
        (0..m).map(tri).collect()
    };
    let mut g = DMatrix::<f64>::zeros(m, m);
    for (a, acc) in upper.iter().enumerate() {
        for (k, &v) in acc.iter().enumerate() {
            g[(a, a + k)] = v;
            g[(a + k, a)] = v;
        }
    }
    g
}

/// G ← G − r·rᵀ.
fn downdate(g: &mut DMatrix<f64>, r: &[f64]) {
    let m = r.len();
    for a in 0..m {
        for b in 0..m {
            g[(a, b)] -= r[a] * r[b];
        }
    }
}

/// Eigenvalues ascending and the eigenvectors as rows in the same order (row-major m × m).
fn spectrum(g: &DMatrix<f64>) -> (Vec<f64>, Vec<f64>) {
    let m = g.nrows();
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
    (lam, vt)
}

/// Relative margin by which a lower bound must exceed the best exact score before a candidate is
/// skipped: far above the rounding of either, far below any difference that matters.
const BOUND_MARGIN: f64 = 1e-9;
/// λmax/λmin of G (cond² of J) above which [`slack`] gives up on bounds: there 1024·ε·λmax/λmin
/// exceeds 2·10⁻³, so the bounds would have to beat the best score by that much anyway, and the
/// secular roots' absolute rounding (ε·‖z‖²) is no longer small against λ'min.
const EXHAUSTIVE_RATIO: f64 = 1e10;
/// Eigen-directions at each end of the spectrum that the sharper (Ritz) bound resolves; greedy
/// elimination clusters the extreme eigenvalues, where the one-direction bound is weak. With 3,
/// about 7 times as many candidates reached the exact score on the 20,000-pose bench pool (most
/// of them at n of a few thousand, where the extremes cluster most); 5 costs 4 more projections.
const RITZ_K: usize = 5;
/// Relative distance between a secular iterate and its Rayleigh quotient at which
/// [`secular_bound`] stops: the quotient's error is about its square, far finer than the
/// differences between candidates' scores that the bound has to resolve.
const RITZ_TOL: f64 = 1e-7;
/// Secular steps [`secular_bound`] takes at most (it stops far earlier as a rule).
const SECULAR_BOUND_STEPS: usize = 40;
/// Below this relative size of the 2×2 determinant the closed-form bound is not trusted.
const DET_FLOOR: f64 = 1e-6;
/// Steps between recomputations of the bound basis and the projections on it: at least
/// `REFRESH_MIN`, doubling up to `REFRESH_MAX` while the bounds stay strong (a queue of at most
/// `QUEUE_TOLERANCE` + n/256 candidates), halving when they do not.
const REFRESH_MIN: usize = 8;
const REFRESH_MAX: usize = 64;
const QUEUE_TOLERANCE: usize = 16;
/// How many of a step's best candidates seed the next step's cut.
const LEADERS: usize = 10;
/// Blocks of the ascending-bound visit at least this long get their Ritz bounds in parallel.
const PARALLEL_RITZ: usize = 64;
/// Candidates in the first block of the ascending-bound visit; each further block is twice as
/// long, up to `RITZ_BLOCK_MAX`.
const RITZ_BLOCK: usize = 16;
const RITZ_BLOCK_MAX: usize = 256;
/// Candidates per chunk of the bound pass (one rayon task each).
const BOUND_CHUNK: usize = 1024;
/// Below this size a step is too short to pay for rayon.
const PARALLEL_BOUND: usize = 2048;
/// Below this many row × column products a Gram rebuild is too short to pay for rayon.
const PARALLEL_GRAM: usize = 20_000;

/// The reference for [`eliminate`]: the same greedy, scoring every candidate exactly at every
/// step (one secular solve pair per candidate). Kept for tests and the benchmark.
#[doc(hidden)]
pub fn eliminate_reference(j: &[f64], m: usize) -> (Vec<usize>, Vec<(usize, f64)>) {
    let n0 = j.len() / m;
    let row = |i: usize| &j[i * m..(i + 1) * m];
    let mut active: Vec<usize> = (0..n0).collect();
    let mut removed = Vec::with_capacity(n0.saturating_sub(m));
    let mut curve = Vec::with_capacity(n0 - m + 1);
    let mut g = gram(j, m, &active);
    loop {
        let (lam, vt) = spectrum(&g);
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
            .reduce(|| (f64::INFINITY, usize::MAX, usize::MAX), pick);
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
            g = gram(j, m, &active);
        } else {
            downdate(&mut g, row(i));
        }
    }
    (removed, curve)
}

/// The 2k extreme eigenvectors for [`ritz_bound`], transposed: entry (b, e) at `b * 2 * RITZ_K + e`
/// holds component b of eigenvector e (e < k: the k lowest, ascending; k ≤ e < 2k: the k highest,
/// ascending), so a row's projections on all of them are one pass over the row with 2k
/// independent sums.
fn extremes_transposed(vt: &[f64], m: usize, k: usize, ext: &mut [f64]) {
    ext.fill(0.0);
    for b in 0..m {
        let slot = &mut ext[b * 2 * RITZ_K..(b + 1) * 2 * RITZ_K];
        for i in 0..k {
            slot[i] = vt[i * m + b];
            slot[k + i] = vt[(m - k + i) * m + b];
        }
    }
}

/// Bounds on the extremes after removing row `r` (‖r‖² = `rr`): (h, l) with λ'max ≥ h and
/// λ'min ≤ l, sharper than Rayleigh's: the k eigen-directions at each end are kept exactly and
/// the rest of z is lumped into one extra direction on the far pole. With t = ‖r‖² − Σ_{i≤k} zᵢ²,
/// the term Σ_{i>k} zᵢ²/(λᵢ − x) of the secular function is at least t/(λₘ − x) for x < λ₁, so the
/// smallest root of the lumped (k+1)-term equation lies above λ'min; at the top,
/// Σ_{i≤m−k} zᵢ²/(x − λᵢ) is at least t'/(x − λ₁), so the largest lumped root lies below λ'max.
/// The lumped equations are those of (k+1)×(k+1) matrices diag − z̃·z̃ᵀ; their extremes are bounded
/// by Rayleigh quotients ([`secular_bound`]), valid however far the iteration got. `ext` is
/// [`extremes_transposed`]. l ≤ 0 = no information.
fn ritz_bound(lam: &[f64], ext: &[f64], r: &[f64], rr: f64, k: usize) -> (f64, f64) {
    let m = lam.len();
    let mut p = [0.0; 2 * RITZ_K];
    for (slot, &x) in ext.chunks_exact(2 * RITZ_K).zip(r) {
        for (pe, &v) in p.iter_mut().zip(slot) {
            *pe += v * x;
        }
    }
    let mut l = [0.0; RITZ_K + 1];
    let mut z = [0.0; RITZ_K + 1];
    l[..k].copy_from_slice(&lam[..k]);
    z[..k].copy_from_slice(&p[..k]);
    let head: f64 = z[..k].iter().map(|v| v * v).sum();
    l[k] = lam[m - 1];
    z[k] = (rr - head).max(0.0).sqrt();
    let zz: f64 = z[..=k].iter().map(|v| v * v).sum();
    let lo = secular_bound(&l[..=k], &z[..=k], l[0] - zz, l[0], 0, true);
    l[0] = lam[0];
    l[1..=k].copy_from_slice(&lam[m - k..]);
    z[1..=k].copy_from_slice(&p[k..2 * k]);
    let tail: f64 = z[1..=k].iter().map(|v| v * v).sum();
    z[0] = (rr - tail).max(0.0).sqrt();
    let zz: f64 = z[..=k].iter().map(|v| v * v).sum();
    let hi = secular_bound(&l[..=k], &z[..=k], l[k - 1].max(l[k] - zz), l[k], k, false);
    (hi, lo)
}

/// A bound on an extreme eigenvalue of M = diag(l) − z·zᵀ, whose secular root lies in (a, b) next
/// to the pole `pole` (see [`secular_root`]): on the smallest when `low` (the result is ≥ it),
/// else on the largest (the result is ≤ it). The secular iteration is [`secular_root`]'s, but
/// each point x it visits also yields the Rayleigh quotient of w = (diag(l) − x)⁻¹z, the
/// inverse-iteration vector for shift x: a bound on the extreme whatever x is (any vector's
/// quotient is one), and one that is exact at the root with an error quadratic in x's. So a
/// coarse x gives a sharp bound: the iteration stops once x and its quotient agree to
/// [`RITZ_TOL`]. The bracket end on the far side of the root is a bound too (the fallback).
fn secular_bound(l: &[f64], z: &[f64], mut a: f64, mut b: f64, pole: usize, low: bool) -> f64 {
    let scale = b.abs().max(a.abs()).max(f64::MIN_POSITIVE);
    let lp = l[pole];
    let mut best = if low { b } else { a };
    let mut x = 0.5 * (a + b);
    for _ in 0..SECULAR_BOUND_STEPS {
        // v = zᵀw = ψ(x), d = wᵀw = ψ'(x), lw = wᵀ·diag(l)·w.
        let (mut v, mut d, mut lw) = (0.0, 0.0, 0.0);
        for (&li, &zi) in l.iter().zip(z) {
            let w = zi / (li - x);
            v += zi * w;
            d += w * w;
            lw += li * w * w;
        }
        let q = (lw - v * v) / d;
        if q.is_finite() {
            best = if low { best.min(q) } else { best.max(q) };
        }
        if (q - x).abs() <= RITZ_TOL * scale {
            break;
        }
        let f = 1.0 - v;
        if f > 0.0 {
            a = x;
        } else if f < 0.0 {
            b = x;
        } else {
            break;
        }
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
        x = next;
    }
    best
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
    for _it in 0..100 {
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

    /// Pools above `PARALLEL_BOUND` take the chunked, parallel passes; on one thread and on
    /// several they must still make the exhaustive choices.
    #[test]
    fn bounded_elimination_equals_exhaustive_greedy_in_parallel() {
        let j = random_matrix(PARALLEL_BOUND + BOUND_CHUNK / 2, 8, 11);
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("thread pool");
            pool.install(|| check_against_reference(&j, 8, &format!("{threads} threads")));
        }
    }

    /// Bit for bit: the same removals and the same curve bits as the exhaustive reference, on one
    /// thread and on two (NaN-safe: compares bits, not values).
    fn check_bits(j: &[f64], m: usize, what: &str) {
        let (want_removed, want_curve) = eliminate_reference(j, m);
        let bits = |c: &[(usize, f64)]| -> Vec<(usize, u64)> {
            c.iter().map(|&(n, v)| (n, v.to_bits())).collect()
        };
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("thread pool");
            let (removed, curve) = pool.install(|| eliminate(j, m));
            assert_eq!(
                removed, want_removed,
                "{what}, {threads} threads: removal order"
            );
            assert_eq!(
                bits(&curve),
                bits(&want_curve),
                "{what}, {threads} threads: curve"
            );
        }
    }

    #[test]
    fn bit_identical_to_reference_on_random_matrices() {
        for seed in 20..24 {
            let n = 250 + 25 * (seed as usize - 20);
            check_bits(
                &random_matrix(n, 22, seed),
                22,
                &format!("random {n} x 22, seed {seed}"),
            );
        }
        // Badly scaled columns (six decades) and a narrow one.
        let mut j = random_matrix(300, 12, 30);
        for (k, v) in j.iter_mut().enumerate() {
            *v *= 10f64.powi((k % 12) as i32 / 2 - 3);
        }
        check_bits(&j, 12, "columns over six decades");
        check_bits(&random_matrix(300, 2, 31), 2, "m = 2");
    }

    #[test]
    fn bit_identical_to_reference_on_adversarial_matrices() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(40);
        let m = 10;
        // Exact ties everywhere: ± unit vectors and their pairwise sums, each several times, so
        // the spectrum is one cluster and many removals score exactly alike.
        let mut j = Vec::new();
        for rep in 0..3 {
            for a in 0..m {
                for b in a..m {
                    let mut r = vec![0.0; m];
                    r[a] += 1.0;
                    r[b] += if (a + b + rep) % 2 == 0 { 1.0 } else { -1.0 };
                    j.extend(r);
                }
            }
        }
        check_bits(&j, m, "symmetric design with exact ties");
        // Near-ties: 100 base rows, each repeated with relative perturbations of 1e-13 .. 1e-9.
        let base = random_matrix(100, m, 41);
        let mut j = base.clone();
        for scale in [1e-13, 1e-11, 1e-9] {
            j.extend(
                base.iter()
                    .map(|v| v * (1.0 + scale * rng.random_range(-1.0..1.0))),
            );
        }
        check_bits(&j, m, "near-duplicate rows");
        // Exact duplicates in a shuffled order.
        let base = random_matrix(120, m, 42);
        let mut j = Vec::new();
        for i in 0..360 {
            let r = (i * 7) % 120;
            j.extend_from_slice(&base[r * m..(r + 1) * m]);
        }
        check_bits(&j, m, "each row three times");
        // Rank-deficient: the last column is a combination of two others (G singular
        // throughout), and a pool whose rows span only m − 2 dimensions after a few outliers.
        let mut j = random_matrix(300, m, 43);
        for i in 0..300 {
            j[i * m + m - 1] = 2.0 * j[i * m] - j[i * m + 1];
        }
        check_bits(&j, m, "dependent column");
        for (i, v) in j.iter_mut().enumerate().filter(|(i, _)| i % m == m - 1) {
            *v += 1e-6 * ((i * 37 % 101) as f64 / 50.0 - 1.0);
        }
        check_bits(&j, m, "nearly dependent column");
        let mut j = random_matrix(300, m, 44);
        for i in 5..300 {
            j[i * m + m - 1] = 0.0;
            j[i * m + m - 2] = 0.0;
        }
        check_bits(&j, m, "two directions carried by five rows");
        // A clustered spectrum: nearly orthogonal design (random signs), where the extreme
        // eigenvalues bunch up from the start.
        let j: Vec<f64> = (0..400 * 16)
            .map(|_| if rng.random_bool(0.5) { 1.0 } else { -1.0 })
            .collect();
        check_bits(&j, 16, "random sign matrix");
        // Outliers: a few rows a thousand times larger than the rest.
        let mut j = random_matrix(300, m, 45);
        for i in [3, 77, 150, 299] {
            for v in &mut j[i * m..(i + 1) * m] {
                *v *= 1e3;
            }
        }
        check_bits(&j, m, "large outlier rows");
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

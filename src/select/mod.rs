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

/// Sections of the pool (the groups of poses that safe motions join with the bar mounted):
/// each remount of the bar is worth at least `min` poses, so a selection measures a group with
/// `min` poses or more, or not at all.
#[derive(Clone, Copy, Debug)]
pub struct Groups<'g> {
    /// The group of every pool pose.
    pub label: &'g [usize],
    pub min: usize,
}

pub fn run(
    model: &MeasurementModel,
    pool: &Pool,
    columns: &[usize],
    cfg: &SelectConfig,
) -> Result<Selection, SelectError> {
    run_grouped(model, pool, columns, cfg, None)
}

/// [`run`] with the pool in [`Groups`]: the elimination removes a group's last poses with the
/// one that takes it below the minimum ([`eliminate_grouped`]), so the curve holds only sets
/// that measure every group with enough poses or not at all, and the knee is chosen among
/// them. `--poses N` takes the smallest of those sets with at least N poses.
pub fn run_grouped(
    model: &MeasurementModel,
    pool: &Pool,
    columns: &[usize],
    cfg: &SelectConfig,
    groups: Option<Groups>,
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
    let (removed, curve) = eliminate_grouped(&j, m, groups);
    let (n_sel, rule) = match cfg.poses {
        Some(k) => {
            // The curve is descending in n: the last entry at or above k (k itself unless a
            // group's last poses went with the step that reached it).
            let n = curve
                .iter()
                .rev()
                .map(|c| c.0)
                .find(|&n| n >= k)
                .unwrap_or(k);
            let rule = if n == k {
                format!("--poses {k}")
            } else {
                format!("--poses {k}: {n}, the smallest set that measures every section with at least {} poses or none", groups.map_or(1, |g| g.min))
            };
            (n, rule)
        }
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
/// secular equation at every step) but scores only a handful of candidates per step. The score
/// of removing row r is λ'max/λ'min, the extreme eigenvalues of G − r·rᵀ. By Rayleigh-Ritz, for
/// any orthonormal U the smallest eigenvalue of Uᵀ(G − r·rᵀ)U bounds λ'min from above and the
/// largest, for another U, bounds λ'max from below; interlacing adds λ'max ≥ λₘ₋₁. U holds the
/// `K_LO` (4) lowest and the two highest eigenvectors of a recent step, and every row's
/// projections on four of them are kept from that step (a refresh, when the bounds grow weak);
/// each step forms the blocks L (low) and H (high) of UᵀGU once. Greedy elimination clusters
/// the extreme eigenvalues (two to four nearly equal at each end, candidates' scores 10⁻⁵
/// apart), and a row moves them by less than the clusters are wide, so the blocks follow the
/// turning of a cluster exactly and an old basis serves well. Per step:
/// 1. every candidate's key, λmax(H − b·bᵀ)/λmin(L₂ − a·aᵀ) on the leading 2 × 2 blocks (closed
///    form; the numerator at least a lower bound on λₘ₋₁, the second root of the previous
///    step's secular equation for the row it removed), a lower bound on its score: one
///    branch-free, vectorised pass, in parallel, and computed alongside the step's
///    eigendecomposition (the keys do not need it);
/// 2. the candidates with the lowest keys (`GUESSES`, 8) are scored exactly: the best of them is
///    as a rule the step's best, and it sets the cut;
/// 3. the candidates whose key does not exceed the cut are visited in ascending key order
///    until a key exceeds it; each is tested with the whole low block (L − a·aᵀ − (h/cut)·I
///    not positive semi-definite, by LDLᵀ, means λ'min < h/cut ≤ λ'max/cut) and, if the test
///    does not rule it out, scored exactly, which tightens the cut.
///
/// A candidate is skipped only when a bound exceeds the best exact score of the step by a
/// relative margin above rounding (see `slack`), so the skipped ones provably score worse and
/// the choice, tie-break by index included, is the exhaustive one. The Gram matrix, its
/// eigendecomposition and the exact scores use the reference's arithmetic (the same functions),
/// so the curve is bit for bit the same. Where G is numerically singular (see `slack`) nothing is
/// skipped. The result does not depend on the thread count: parallel parts only compute keys
/// and projections, in fixed chunks, and every choice is made serially in a fixed order.
pub fn eliminate(j: &[f64], m: usize) -> (Vec<usize>, Vec<(usize, f64)>) {
    eliminate_grouped(j, m, None)
}

/// [`eliminate`] under [`Groups`]: when the greedy removal takes a group below `groups.min`
/// rows, the group's other rows (ascending) are removed in the same step, unless fewer than m
/// rows would be left. The curve then skips the sets in between (a group with too few rows is
/// no valid selection). A step's greedy choice is unchanged: as long as no group falls below
/// its minimum, the removals and the curve are [`eliminate`]'s bit for bit. The same rule in
/// [`eliminate_reference_grouped`].
pub fn eliminate_grouped(
    j: &[f64],
    m: usize,
    groups: Option<Groups>,
) -> (Vec<usize>, Vec<(usize, f64)>) {
    // On a pool thread, the step's parallel parts are cheap forks; from outside the pool every
    // one would be a round trip through the pool's queue and a sleeping thread.
    rayon::scope(|_| eliminate_in_pool(j, m, groups))
}

/// The rows each group still holds during an elimination, and the rule of [`Groups`].
struct Quota<'g> {
    groups: Groups<'g>,
    count: Vec<usize>,
}

impl<'g> Quota<'g> {
    fn new(groups: Option<Groups<'g>>, n0: usize) -> Option<Self> {
        let groups = groups.filter(|g| g.min > 1 && g.label.len() == n0)?;
        let mut count = vec![0; groups.label.iter().copied().max().map_or(0, |l| l + 1)];
        for &l in groups.label {
            count[l] += 1;
        }
        Some(Quota { groups, count })
    }

    /// Row `i` was removed (`alive` already says so) and `left` rows remain: the rows of its
    /// group that go with it, ascending (none while the group keeps its minimum, or when m
    /// rows would not remain).
    fn forced(&mut self, i: usize, alive: &[bool], left: usize, m: usize) -> Vec<usize> {
        let g = self.groups.label[i];
        self.count[g] -= 1;
        let c = self.count[g];
        if c == 0 || c >= self.groups.min || left < m + c {
            return Vec::new();
        }
        self.count[g] = 0;
        (0..alive.len())
            .filter(|&k| alive[k] && self.groups.label[k] == g)
            .collect()
    }
}

/// Whether the Gram matrix is rebuilt from scratch after a removal (`left` rows remain,
/// `removed` so far) rather than downdated: now and then, and always when few rows remain
/// (where it is least well conditioned), so rounding cannot accumulate. The one schedule of the
/// bounded search and the reference.
fn rebuilds(left: usize, m: usize, removed: usize) -> bool {
    left < 3 * m || removed % 64 == 0
}

fn eliminate_in_pool(
    j: &[f64],
    m: usize,
    groups: Option<Groups>,
) -> (Vec<usize>, Vec<(usize, f64)>) {
    let n0 = j.len() / m;
    let row = |i: usize| &j[i * m..(i + 1) * m];
    let mut quota = Quota::new(groups, n0);
    let active: Vec<usize> = (0..n0).collect();
    let mut rows = Rows {
        j,
        m,
        alive: vec![true; n0],
        ids: (0..n0).collect(),
        proj: std::array::from_fn(|_| vec![0.0; n0]),
        removed: Vec::with_capacity(n0.saturating_sub(m)),
        g: gram(j, m, &active),
        active,
    };
    let mut curve = Vec::with_capacity(n0 - m + 1);
    let mut bounds = Bounds::new(m);
    let mut keys = vec![0.0; n0];
    let mut heap: std::collections::BinaryHeap<Queued> = std::collections::BinaryHeap::new();
    let mut parts: Vec<Vec<Queued>> = Vec::new();
    let mut z = vec![0.0; m];
    let mut period = REFRESH_MIN;
    // Step 0's spectrum, basis and keys; every later step gets its spectrum and its keys
    // together, at the end of the step before.
    let (mut lam, mut vt) = spectrum(&rows.g);
    bounds.refresh(&vt, j, &rows.ids, &mut rows.proj);
    bounds.update(&rows.g, lam[m.saturating_sub(2)]);
    let mut lows = first_pass(&bounds, &rows.proj, &mut keys[..n0]);
    let mut age = 0;
    loop {
        let (ids, proj) = (&rows.ids, &rows.proj);
        let n = ids.len();
        curve.push((n, cond_of(lam[0], lam[m - 1])));
        if n == m {
            break;
        }
        let slack = slack(&lam);
        age += 1;
        let exact = |p: usize, z: &mut [f64]| -> (f64, usize, usize) {
            eigen_coordinates(&vt, row(ids[p]), z);
            let (lo, hi) = downdated_extremes(&lam, z);
            let score = if lo > 0.0 { hi / lo } else { f64::INFINITY };
            (score, ids[p], p)
        };
        let mut best = (f64::INFINITY, usize::MAX, usize::MAX);
        let mut cut = f64::INFINITY;
        bounds.set_cut(cut);
        let mut exacts = 0;
        let mut visit = |key: f64, p: usize, best: &mut (f64, usize, usize), cut: &mut f64| {
            if key > *cut || bounds.rules_out(proj, p, row(ids[p])) {
                return;
            }
            let this = exact(p, &mut z);
            exacts += 1;
            if best.1 == usize::MAX || pick(*best, this) != *best {
                *best = this;
                *cut = best.0 * (1.0 + slack);
                bounds.set_cut(*cut);
            }
        };
        // The lowest keys overall are the likeliest best: their exact scores make the cut.
        let mut guesses = Lowest::default();
        for &(key, p) in lows.iter().flat_map(|low| low.entries()) {
            guesses.offer(key, p);
        }
        for &(key, p) in guesses.entries() {
            visit(key, p, &mut best, &mut cut);
        }
        // The others whose key does not exceed the cut, likeliest first (a heap: as a rule only
        // a few come off it before a key exceeds the cut).
        heap = below_cut(heap, &keys[..n], cut, &guesses, &mut parts);
        while let Some(Queued(key, p)) = heap.pop() {
            if key > cut {
                break;
            }
            visit(key, p, &mut best, &mut cut);
        }
        // Many exact scores: a stale basis, refresh it sooner; few: later.
        if exacts > GUESSES + DIRECT + n / 1024 {
            period = (period / 2).max(REFRESH_MIN);
        } else if age == period {
            period = (period * 2).min(REFRESH_MAX);
        }
        let (_, i, p) = best;
        // The next step's λₘ₋₁, bounded from below without its eigendecomposition: the second
        // largest root of this step's secular equation for the row removed.
        eigen_coordinates(&vt, row(i), &mut z);
        let floor = second_downdated(&lam, &z);
        let forced = rows.remove(i, p, &mut quota);
        if rows.ids.len() == m {
            (lam, vt) = spectrum(&rows.g);
            continue;
        }
        if age >= period {
            age = 0;
            bounds.refresh(&vt, j, &rows.ids, &mut rows.proj);
        }
        let n = rows.ids.len();
        if forced {
            // The floor above was for one removal: this step's λₘ₋₁ itself bounds every
            // candidate's λ'max from below (interlacing).
            (lam, vt) = spectrum(&rows.g);
            bounds.update(&rows.g, lam[m.saturating_sub(2)] * (1.0 - 1e-12));
            lows = first_pass(&bounds, &rows.proj, &mut keys[..n]);
            continue;
        }
        // The next step's keys need no eigendecomposition of its Gram matrix: the basis may
        // come from this step's (any orthonormal one will do), and its floor is above. So its
        // spectrum is computed alongside them.
        bounds.update(&rows.g, floor);
        ((lam, vt), lows) = rayon::join(
            || spectrum(&rows.g),
            || first_pass(&bounds, &rows.proj, &mut keys[..n]),
        );
    }
    (rows.removed, curve)
}

/// The rows of an elimination: which are alive, the active ones by position (removal is
/// swap_remove, positions carry no meaning) with their projections on the keyed directions,
/// one column each, the rows removed in order and the Gram matrix of the rest.
struct Rows<'a> {
    j: &'a [f64],
    m: usize,
    alive: Vec<bool>,
    ids: Vec<usize>,
    proj: [Vec<f64>; KEYED],
    removed: Vec<usize>,
    /// The alive rows at the last rebuild of `g`.
    active: Vec<usize>,
    g: DMatrix<f64>,
}

impl Rows<'_> {
    /// Removes row `i` at position `p`, then (when its group fell below its minimum) the
    /// group's other rows; whether any row went with it.
    fn remove(&mut self, i: usize, p: usize, quota: &mut Option<Quota>) -> bool {
        let (j, m) = (self.j, self.m);
        let n0 = self.alive.len();
        let mut queue = vec![i];
        let mut k = 0;
        while k < queue.len() {
            let r = queue[k];
            let p = if k == 0 {
                p
            } else {
                self.ids
                    .iter()
                    .position(|&x| x == r)
                    .expect("a forced row is active")
            };
            self.ids.swap_remove(p);
            for col in &mut self.proj {
                col.swap_remove(p);
            }
            self.alive[r] = false;
            self.removed.push(r);
            // Same schedule of rebuilds and downdates as the reference.
            if rebuilds(self.ids.len(), m, self.removed.len()) {
                self.active.clear();
                let alive = &self.alive;
                self.active.extend((0..n0).filter(|&x| alive[x]));
                self.g = gram(j, m, &self.active);
            } else {
                downdate(&mut self.g, &j[r * m..(r + 1) * m]);
            }
            if k == 0 {
                if let Some(q) = quota.as_mut() {
                    queue.extend(q.forced(r, &self.alive, self.ids.len(), m));
                }
            }
            k += 1;
        }
        queue.len() > 1
    }
}

/// The queue of the candidates whose key does not exceed `cut`, the `guesses` left out; built
/// in the heap's own storage, in parallel chunks (`parts`) for a large pool.
fn below_cut(
    heap: std::collections::BinaryHeap<Queued>,
    keys: &[f64],
    cut: f64,
    guesses: &Lowest,
    parts: &mut Vec<Vec<Queued>>,
) -> std::collections::BinaryHeap<Queued> {
    let n = keys.len();
    let below = |start: usize, ks: &[f64], out: &mut Vec<Queued>| {
        out.clear();
        for (k, &key) in ks.iter().enumerate() {
            let p = start + k;
            if key.partial_cmp(&cut) != Some(std::cmp::Ordering::Greater) && !guesses.holds(p) {
                out.push(Queued(key, p));
            }
        }
    };
    let mut list = heap.into_vec();
    if n >= PARALLEL_BOUND {
        let chunks = n.div_ceil(BOUND_CHUNK);
        parts.resize_with(chunks.max(parts.len()), Vec::new);
        keys.par_chunks(BOUND_CHUNK)
            .zip(parts[..chunks].par_iter_mut())
            .enumerate()
            .for_each(|(c, (ks, out))| below(c * BOUND_CHUNK, ks, out));
        list.clear();
        for part in &parts[..chunks] {
            list.extend_from_slice(part);
        }
    } else {
        below(0, keys, &mut list);
    }
    std::collections::BinaryHeap::from(list)
}

/// Every candidate's key and each chunk's lowest keys.
fn first_pass(bounds: &Bounds, proj: &[Vec<f64>; KEYED], keys: &mut [f64]) -> Vec<Lowest> {
    let pass = |start: usize, ks: &mut [f64]| -> Lowest {
        bounds.keys(proj, start, ks);
        let mut low = Lowest::default();
        for (k, &key) in ks.iter().enumerate() {
            low.offer(key, start + k);
        }
        low
    };
    if keys.len() >= PARALLEL_BOUND {
        keys.par_chunks_mut(BOUND_CHUNK)
            .enumerate()
            .map(|(c, ks)| pass(c * BOUND_CHUNK, ks))
            .collect()
    } else {
        vec![pass(0, keys)]
    }
}

/// Eigen-directions at the low end of the spectrum that the full test uses: enough for the
/// clusters greedy elimination forms there (up to four nearly equal eigenvalues on the bench
/// pools). The high end uses two (clusters of two, and interlacing covers a third).
const K_LO: usize = 4;
/// Directions whose projections are kept for every row: the two lowest (slots 0, 1) and the two
/// highest (slots 2, 3). The test computes the projections on the other low ones from the row.
const KEYED: usize = 4;

/// The bounds of [`eliminate`]: the basis U (rows: `K_LO` low directions, then two high ones),
/// the current step's blocks of UᵀGU and constants.
struct Bounds {
    m: usize,
    /// Low directions used (`K_LO`, fewer when m is small); one column: no bounds at all.
    klo: usize,
    able: bool,
    basis: Vec<f64>,
    /// L = U_loᵀ G U_lo, lower triangle.
    l: [[f64; K_LO]; K_LO],
    /// H = U_hiᵀ G U_hi: [H11, H12, H22].
    h: [f64; 3],
    /// A lower bound on λ'max for every candidate (λₘ₋₁ or less).
    floor: f64,
    inv_cut: f64,
    /// False where nothing may be ruled out (no finite positive cut: G numerically singular).
    on: bool,
    /// Scratch: G·u for every basis row.
    gu: Vec<f64>,
}

impl Bounds {
    fn new(m: usize) -> Self {
        Bounds {
            m,
            klo: K_LO.min(m),
            able: m >= 2,
            basis: vec![0.0; (K_LO + 2) * m],
            l: [[0.0; K_LO]; K_LO],
            h: [0.0; 3],
            floor: f64::NEG_INFINITY,
            inv_cut: 0.0,
            on: false,
            gu: vec![0.0; (K_LO + 2) * m],
        }
    }

    /// Basis row `d`.
    fn u(&self, d: usize) -> &[f64] {
        &self.basis[d * self.m..(d + 1) * self.m]
    }

    /// The basis from the eigenvectors `vt` (rows, ascending), and the keyed projections of the
    /// active rows `ids` on it. The two blocks share directions when m is small; each is
    /// orthonormal, which is all its bound needs.
    fn refresh(&mut self, vt: &[f64], j: &[f64], ids: &[usize], proj: &mut [Vec<f64>; KEYED]) {
        let m = self.m;
        for d in 0..K_LO + 2 {
            let e = if d < K_LO {
                d.min(m - 1)
            } else {
                (m + d).saturating_sub(K_LO + 2).min(m - 1)
            };
            self.basis[d * m..(d + 1) * m].copy_from_slice(&vt[e * m..(e + 1) * m]);
        }
        let n = ids.len();
        let this = &*self;
        let project = |slot: usize, col: &mut [f64]| {
            let u = this.u(Self::basis_row(slot));
            for (c, &i) in col.iter_mut().zip(ids) {
                *c = u
                    .iter()
                    .zip(&j[i * m..(i + 1) * m])
                    .map(|(a, b)| a * b)
                    .sum();
            }
        };
        if n >= PARALLEL_BOUND {
            proj.par_iter_mut()
                .enumerate()
                .for_each(|(slot, col)| project(slot, &mut col[..n]));
        } else {
            for (slot, col) in proj.iter_mut().enumerate() {
                project(slot, &mut col[..n]);
            }
        }
    }

    /// The basis row of a keyed slot: 0, 1 → the two lowest; 2, 3 → the two highest.
    fn basis_row(slot: usize) -> usize {
        if slot < 2 {
            slot
        } else {
            K_LO + slot - 2
        }
    }

    /// The blocks of UᵀGU for the Gram matrix `g`, and the floor for λ'max.
    fn update(&mut self, g: &DMatrix<f64>, floor: f64) {
        let m = self.m;
        let gs = g.as_slice();
        // G·u for every basis row used (G is symmetric: (G·u)ₐ is column a of G times u).
        for d in (0..self.klo).chain(K_LO..K_LO + 2) {
            let u = &self.basis[d * m..(d + 1) * m];
            for (a, out) in self.gu[d * m..(d + 1) * m].iter_mut().enumerate() {
                *out = gs[a * m..(a + 1) * m]
                    .iter()
                    .zip(u)
                    .map(|(p, q)| p * q)
                    .sum();
            }
        }
        let quad = |x: usize, y: usize| -> f64 {
            self.basis[x * m..(x + 1) * m]
                .iter()
                .zip(&self.gu[y * m..(y + 1) * m])
                .map(|(p, q)| p * q)
                .sum()
        };
        let mut l = [[0.0; K_LO]; K_LO];
        for (r, lr) in l.iter_mut().enumerate().take(self.klo) {
            for (c, lrc) in lr.iter_mut().enumerate().take(r + 1) {
                *lrc = quad(r, c);
            }
        }
        let h = [
            quad(K_LO, K_LO),
            quad(K_LO, K_LO + 1),
            quad(K_LO + 1, K_LO + 1),
        ];
        self.l = l;
        self.h = h;
        self.floor = floor;
    }

    fn set_cut(&mut self, cut: f64) {
        self.inv_cut = 1.0 / cut;
        self.on = self.able && cut.is_finite() && cut > 0.0;
    }

    /// λmax(H − b·bᵀ) (closed form) or the floor, the larger: a lower bound on λ'max.
    #[inline]
    fn high(&self, b1: f64, b2: f64) -> f64 {
        let q1 = self.h[0] - b1 * b1;
        let q2 = self.h[2] - b2 * b2;
        let o = self.h[1] - b1 * b2;
        let hmax = 0.5 * (q1 + q2) + (0.25 * (q1 - q2) * (q1 - q2) + o * o).sqrt();
        if hmax > self.floor {
            hmax
        } else {
            self.floor
        }
    }

    /// Keys for the positions `start..start + ks.len()`: `high` over λmin of the leading 2 × 2
    /// block of L − a·aᵀ, a lower bound on the score (0 where that block is not positive
    /// definite: no information). Branch-free, so that it vectorises.
    fn keys(&self, proj: &[Vec<f64>; KEYED], start: usize, ks: &mut [f64]) {
        if !self.able {
            ks.fill(0.0);
            return;
        }
        let end = start + ks.len();
        let (a1, a2) = (&proj[0][start..end], &proj[1][start..end]);
        let (b1, b2) = (&proj[2][start..end], &proj[3][start..end]);
        let (l11, l21, l22) = (self.l[0][0], self.l[1][0], self.l[1][1]);
        let rows = a1.iter().zip(a2).zip(b1).zip(b2);
        for (key, (((&x1, &x2), &y1), &y2)) in ks.iter_mut().zip(rows) {
            let h = self.high(y1, y2);
            let p1 = l11 - x1 * x1;
            let p2 = l22 - x2 * x2;
            let off = l21 - x1 * x2;
            let det = p1 * p2 - off * off;
            let rad = (0.25 * (p1 - p2) * (p1 - p2) + off * off).sqrt();
            let lmin = det / (0.5 * (p1 + p2) + rad);
            *key = if det > 0.0 && lmin > 0.0 {
                h / lmin
            } else {
                0.0
            };
        }
    }

    /// True when the candidate at position `p` (row `r`) provably scores above the cut:
    /// λmin(L − a·aᵀ) < h/cut with h ≤ λ'max, i.e. a negative pivot in the LDLᵀ of
    /// L − a·aᵀ − (h/cut)·I. A zero pivot or NaN: not ruled out.
    fn rules_out(&self, proj: &[Vec<f64>; KEYED], p: usize, r: &[f64]) -> bool {
        if !self.on {
            return false;
        }
        let t = self.high(proj[2][p], proj[3][p]) * self.inv_cut;
        let a: [f64; K_LO] = std::array::from_fn(|d| match d {
            0 | 1 => proj[d][p],
            _ => self.u(d).iter().zip(r).map(|(u, x)| u * x).sum(),
        });
        let mut mm = [[0.0; K_LO]; K_LO];
        for r in 0..self.klo {
            for c in 0..=r {
                mm[r][c] = self.l[r][c] - a[r] * a[c];
            }
            mm[r][r] -= t;
        }
        for c in 0..self.klo {
            let d = mm[c][c];
            if d < 0.0 {
                return true;
            }
            if d == 0.0 || d.is_nan() {
                return false;
            }
            for r in c + 1..self.klo {
                let f = mm[r][c] / d;
                for cc in c + 1..=r {
                    mm[r][cc] -= f * mm[cc][c];
                }
            }
        }
        false
    }
}

/// The [`GUESSES`] lowest keys offered, with their positions, ascending; ties by position.
#[derive(Clone, Copy)]
struct Lowest([(f64, usize); GUESSES]);

impl Default for Lowest {
    fn default() -> Self {
        Lowest([(f64::INFINITY, usize::MAX); GUESSES])
    }
}

impl Lowest {
    #[inline]
    fn offer(&mut self, key: f64, p: usize) {
        let before = |a: (f64, usize), b: (f64, usize)| a.0 < b.0 || (a.0 == b.0 && a.1 < b.1);
        if before((key, p), self.0[GUESSES - 1]) {
            let mut k = GUESSES - 1;
            while k > 0 && before((key, p), self.0[k - 1]) {
                self.0[k] = self.0[k - 1];
                k -= 1;
            }
            self.0[k] = (key, p);
        }
    }

    /// The entries offered (fewer than `GUESSES` when fewer were).
    fn entries(&self) -> &[(f64, usize)] {
        let len = self.0.iter().take_while(|e| e.1 != usize::MAX).count();
        &self.0[..len]
    }

    fn holds(&self, p: usize) -> bool {
        self.0.iter().any(|e| e.1 == p)
    }
}

/// A candidate waiting for its exact score: (key, position), ordered so that std's max-heap
/// pops the lowest key first, ties by position.
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
    // Triangle rows a0..a1, one pass over the rows: every entry is still its own sum in row
    // order, only the memory traffic is shared.
    let band = |(a0, a1): (usize, usize)| -> Vec<f64> {
        let mut acc = vec![0.0; (a0..a1).map(|a| m - a).sum()];
        for &i in rows {
            let r = &j[i * m..(i + 1) * m];
            let mut at = 0;
            for a in a0..a1 {
                let ra = r[a];
                for (s, &rb) in acc[at..at + m - a].iter_mut().zip(&r[a..]) {
                    *s += ra * rb;
                }
                at += m - a;
            }
        }
        acc
    };
    // Bands of about equal work.
    let parts = if rows.len() * m >= PARALLEL_GRAM {
        GRAM_BANDS
    } else {
        1
    };
    let total = m * (m + 1) / 2;
    let mut cuts = vec![0];
    let mut done = 0;
    for a in 0..m {
        done += m - a;
        if done * parts >= total * cuts.len() && cuts.len() < parts {
            cuts.push(a + 1);
        }
    }
    if *cuts.last().unwrap_or(&0) != m {
        cuts.push(m);
    }
    let spans: Vec<(usize, usize)> = cuts.windows(2).map(|w| (w[0], w[1])).collect();
    let bands: Vec<Vec<f64>> = if parts > 1 {
        spans.par_iter().copied().map(band).collect()
    } else {
        spans.iter().copied().map(band).collect()
    };
    let mut g = DMatrix::<f64>::zeros(m, m);
    for (&(a0, a1), acc) in spans.iter().zip(&bands) {
        let mut at = 0;
        for a in a0..a1 {
            for (k, &v) in acc[at..at + m - a].iter().enumerate() {
                g[(a, a + k)] = v;
                g[(a + k, a)] = v;
            }
            at += m - a;
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

/// z = Vᵀr: the coordinates of row `r` in the eigenbasis `vt` (eigenvectors as rows), each a
/// sum in component order (the same bits in the reference and the bounded search).
fn eigen_coordinates(vt: &[f64], r: &[f64], z: &mut [f64]) {
    let m = r.len();
    for (k, zk) in z.iter_mut().enumerate() {
        *zk = vt[k * m..(k + 1) * m]
            .iter()
            .zip(r)
            .map(|(v, x)| v * x)
            .sum();
    }
}

/// Eigenvalues ascending and the eigenvectors as rows in the same order (row-major m × m).
fn spectrum(g: &DMatrix<f64>) -> (Vec<f64>, Vec<f64>) {
    let m = g.nrows();
    let eig = SymmetricEigen::new(g.clone());
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let lam: Vec<f64> = order.iter().map(|&k| eig.eigenvalues[k]).collect();
    let vectors = eig.eigenvectors.as_slice();
    let mut vt = Vec::with_capacity(m * m);
    for &k in &order {
        vt.extend_from_slice(&vectors[k * m..(k + 1) * m]);
    }
    (lam, vt)
}

/// Relative margin by which a lower bound must exceed the best exact score before a candidate is
/// skipped: far above the rounding of either, far below any difference that matters.
const BOUND_MARGIN: f64 = 1e-9;
/// λmax/λmin of G (cond² of J) above which [`slack`] gives up on bounds: there 1024·ε·λmax/λmin
/// exceeds 2·10⁻³, so the bounds would have to beat the best score by that much anyway, and the
/// secular roots' absolute rounding (ε·‖z‖²) is no longer small against λ'min.
const EXHAUSTIVE_RATIO: f64 = 1e10;
/// Steps between recomputations of the bound basis and the projections on it: at least
/// `REFRESH_MIN`, doubling up to `REFRESH_MAX` while the bounds stay strong (at most
/// `GUESSES` + `DIRECT` + n/1024 exact scores a step), halving when they do not.
const REFRESH_MIN: usize = 8;
const REFRESH_MAX: usize = 64;
const DIRECT: usize = 24;
/// Candidates with the lowest keys whose exact scores set a step's first cut.
const GUESSES: usize = 8;
/// Candidates per chunk of the key pass and the key filter (one rayon task each).
const BOUND_CHUNK: usize = 1024;
/// Below this size a step is too short to pay for rayon.
const PARALLEL_BOUND: usize = 2048;
/// Below this many row × column products a Gram rebuild is too short to pay for rayon.
const PARALLEL_GRAM: usize = 20_000;
/// Bands of the Gram triangle built in parallel (a few more than cores, for balance).
const GRAM_BANDS: usize = 4;

/// The reference for [`eliminate`]: the same greedy, scoring every candidate exactly at every
/// step (one secular solve pair per candidate). Kept for tests and the benchmark.
#[doc(hidden)]
pub fn eliminate_reference(j: &[f64], m: usize) -> (Vec<usize>, Vec<(usize, f64)>) {
    eliminate_reference_grouped(j, m, None)
}

/// [`eliminate_reference`] under [`Groups`] (the rule of [`eliminate_grouped`]).
#[doc(hidden)]
pub fn eliminate_reference_grouped(
    j: &[f64],
    m: usize,
    groups: Option<Groups>,
) -> (Vec<usize>, Vec<(usize, f64)>) {
    let n0 = j.len() / m;
    let row = |i: usize| &j[i * m..(i + 1) * m];
    let mut quota = Quota::new(groups, n0);
    let mut alive = vec![true; n0];
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
                    eigen_coordinates(&vt, r, z);
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
        alive[i] = false;
        let mut queue = vec![i];
        if let Some(q) = quota.as_mut() {
            queue.extend(q.forced(i, &alive, active.len(), m));
        }
        for (k, &r) in queue.iter().enumerate() {
            if k > 0 {
                active.retain(|&x| x != r);
                alive[r] = false;
            }
            removed.push(r);
            if rebuilds(active.len(), m, removed.len()) {
                g = gram(j, m, &active);
            } else {
                downdate(&mut g, row(r));
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

/// A lower bound on the second largest eigenvalue of diag(λ) − z·zᵀ (λ ascending): by
/// interlacing it lies in [λₘ₋₂, λₘ₋₁], where the secular function f(x) = 1 − Σ zᵢ²/(λᵢ − x)
/// falls through its root; bisection keeps a point where f > 0, below the root. (Where
/// zₘ₋₁ = 0, λₘ₋₁ itself stays an eigenvalue, and the point found is below it.) For m = 2 the
/// bracket is the smallest eigenvalue's, [λ₁ − ‖z‖², λ₁].
fn second_downdated(lam: &[f64], z: &[f64]) -> f64 {
    let m = lam.len();
    if m < 2 {
        return f64::NEG_INFINITY;
    }
    let zz: f64 = z.iter().map(|v| v * v).sum();
    let (mut a, mut b) = if m >= 3 {
        (lam[m - 3], lam[m - 2])
    } else {
        (lam[0] - zz, lam[0])
    };
    for _ in 0..SECOND_BISECTIONS {
        let x = 0.5 * (a + b);
        if !(x > a && x < b) {
            break;
        }
        let f: f64 = 1.0
            - lam
                .iter()
                .zip(z)
                .map(|(l, zi)| zi * zi / (l - x))
                .sum::<f64>();
        if f > 0.0 {
            a = x;
        } else {
            b = x;
        }
    }
    a
}

/// Bisection steps of [`second_downdated`]: 2⁻⁴⁰ of the bracket, far below the differences
/// between candidates' scores.
const SECOND_BISECTIONS: usize = 40;

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
            // The floor for the next step: at most the second largest, and close to it.
            let mut sorted: Vec<f64> = want.iter().copied().collect();
            sorted.sort_by(f64::total_cmp);
            let second = sorted[m - 2];
            let floor = second_downdated(&lam, &z);
            assert!(
                floor <= second + 1e-12 * want.max() && floor >= second - 1e-9 * want.max(),
                "m {m}: floor {floor} vs second largest {second}"
            );
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

    /// Under groups: the bounded search makes the reference's removals and curve, bit for bit,
    /// on one thread and two; every set on the curve measures each group with at least the
    /// minimum or not at all; the removals are the unconstrained greedy's until the first
    /// group falls below its minimum; and a group is in fact dropped whole along the way.
    #[test]
    fn grouped_elimination_keeps_every_group_at_its_minimum_or_drops_it() {
        let bits = |c: &[(usize, f64)]| -> Vec<(usize, u64)> {
            c.iter().map(|&(n, v)| (n, v.to_bits())).collect()
        };
        let mut dropped_whole = 0;
        for (seed, n, m, sizes) in [
            (21u64, 160usize, 8usize, vec![120usize, 25, 12, 3]),
            (22, 90, 6, vec![60, 20, 10]),
            (23, PARALLEL_BOUND + 300, 10, vec![PARALLEL_BOUND, 200, 100]),
            (24, 40, 12, vec![28, 6, 6]),
        ] {
            let j = random_matrix(n, m, seed);
            // Groups interleaved over the rows, as a grid's groups are.
            let mut label = Vec::with_capacity(n);
            let mut left = sizes.clone();
            let mut g = 0;
            while label.len() < n {
                if left[g] > 0 {
                    label.push(g);
                    left[g] -= 1;
                }
                g = (g + 1) % sizes.len();
            }
            let groups = Groups {
                label: &label,
                min: 3,
            };
            let (want_removed, want_curve) = eliminate_reference_grouped(&j, m, Some(groups));
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .expect("thread pool");
                let (removed, curve) = pool.install(|| eliminate_grouped(&j, m, Some(groups)));
                assert_eq!(removed, want_removed, "seed {seed}, {threads} threads");
                assert_eq!(
                    bits(&curve),
                    bits(&want_curve),
                    "seed {seed}, {threads} threads"
                );
            }
            // Every set on the curve: the pool less the first n0 - n removals.
            for &(count, _) in &want_curve {
                let gone = &want_removed[..n - count];
                let mut per = vec![0; sizes.len()];
                for (i, &l) in label.iter().enumerate() {
                    if !gone.contains(&i) {
                        per[l] += 1;
                    }
                }
                // Near n = m a group may keep fewer rows (m rows must remain).
                if count > m + 2 {
                    assert!(
                        per.iter().all(|&c| c == 0 || c >= 3),
                        "seed {seed}: n = {count} measures groups {per:?}"
                    );
                }
            }
            // Until the first forced removal, the unconstrained greedy's choices.
            let (free_removed, _) = eliminate_reference(&j, m);
            let first_skip = want_curve
                .windows(2)
                .position(|w| w[0].0 - w[1].0 > 1)
                .map_or(want_removed.len(), |k| k);
            assert_eq!(
                want_removed[..first_skip],
                free_removed[..first_skip],
                "seed {seed}"
            );
            dropped_whole += want_curve
                .windows(2)
                .filter(|w| w[0].0 - w[1].0 > 1)
                .count();
        }
        assert!(
            dropped_whole >= 3,
            "only {dropped_whole} groups dropped whole"
        );
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
        // Fewer columns than the bound basis has directions: its blocks share directions.
        check_bits(&random_matrix(300, 3, 32), 3, "m = 3");
        check_bits(&random_matrix(300, 5, 33), 5, "m = 5");
    }

    /// The bounds themselves, against exact scores: every key is at most the candidate's score,
    /// and the full test rules a candidate out only at a cut below its score, for bases that are
    /// stale (the eigenvectors of a Gram matrix with other rows), floors from interlacing and
    /// cuts on both sides of the score.
    #[test]
    fn keys_and_test_never_exceed_the_exact_score() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(50);
        for m in [2, 3, 4, 5, 8, 22] {
            for trial in 0..4 {
                let n = m + 40 + 30 * trial;
                let j = random_matrix(n + 5, m, rng.random());
                let old: Vec<usize> = (0..n + 5).collect();
                let now: Vec<usize> = (5..n + 5).collect();
                let (lam_old, vt_old) = spectrum(&gram(&j, m, &old));
                let g = gram(&j, m, &now);
                let (lam, vt) = spectrum(&g);
                let mut bounds = Bounds::new(m);
                let mut proj: [Vec<f64>; KEYED] = std::array::from_fn(|_| vec![0.0; n]);
                let ids: Vec<usize> = now.clone();
                bounds.refresh(&vt_old, &j, &ids, &mut proj);
                // λₘ₋₁ of `g` is at least λₘ₋₆ of the Gram matrix with five rows more.
                let floor = if m >= 7 {
                    lam_old[m - 7]
                } else {
                    f64::NEG_INFINITY
                };
                bounds.update(&g, floor);
                let mut keys = vec![0.0; n];
                bounds.keys(&proj, 0, &mut keys);
                let (mut ruled, mut close) = (0, 0);
                for (p, &i) in ids.iter().enumerate() {
                    let r = &j[i * m..(i + 1) * m];
                    let mut z = vec![0.0; m];
                    eigen_coordinates(&vt, r, &mut z);
                    let (lo, hi) = downdated_extremes(&lam, &z);
                    assert!(lo > 0.0, "m {m}: a random design stays regular");
                    let score = hi / lo;
                    let tol = 1e-12 * score;
                    assert!(
                        keys[p] <= score + tol,
                        "m {m}, row {i}: key {} > score {score}",
                        keys[p]
                    );
                    close += usize::from(keys[p] > 0.5 * score);
                    for rel in [-0.5, -0.1, -1e-2, -1e-3, -1e-6, -1e-9, 1e-9, 1e-6, 1e-3] {
                        let cut = score * (1.0 + rel);
                        bounds.set_cut(cut);
                        if bounds.rules_out(&proj, p, r) {
                            ruled += 1;
                            assert!(
                                score > cut - tol,
                                "m {m}, row {i}: ruled out at cut {cut} above its score {score}"
                            );
                        }
                    }
                }
                // And neither is vacuous: keys come near the scores, and cuts below the scores
                // do rule candidates out.
                assert!(
                    close > n / 2,
                    "m {m}: only {close} of {n} keys above half the score"
                );
                assert!(ruled > 0, "m {m}: the test ruled nothing out");
            }
        }
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

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig {
            cases: 24,
            ..Default::default()
        })]
        /// Random shapes and designs: the bounded search makes the exhaustive choices, bit for bit.
        #[test]
        fn bit_identical_on_random_shapes(
            m in 2usize..=24,
            extra in 1usize..=260,
            design in 0u8..4,
            seed in proptest::prelude::any::<u64>(),
        ) {
            let n = m + extra;
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let mut j = random_matrix(n, m, seed);
            match design {
                // Random signs: a nearly orthogonal design, clustered spectra from the start.
                1 => j.iter_mut().for_each(|v| *v = if rng.random_bool(0.5) { 1.0 } else { -1.0 }),
                // Columns over four decades.
                2 => j
                    .iter_mut()
                    .enumerate()
                    .for_each(|(k, v)| *v *= 10f64.powi((k % m) as i32 % 5 - 2)),
                // A third of the rows repeated (exact ties).
                3 => {
                    let copies = j[..(n / 3) * m].to_vec();
                    j[n * m - copies.len()..].copy_from_slice(&copies);
                }
                _ => {}
            }
            check_bits(&j, m, &format!("m {m}, n {n}, design {design}, seed {seed}"));
        }
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

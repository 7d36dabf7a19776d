//! The Eq. 7 cost matrix and the candidate (nearest-neighbour) lists the local search scans.

use rayon::prelude::*;

/// How many nearest poses each pose keeps as move candidates. 2-opt and Or-opt only try new edges
/// to these, which keeps a pass near O(n·k) instead of O(n²). With n ≤ NEIGHBOURS + 1 the lists
/// are complete, so small instances get the full neighbourhood.
pub(crate) const NEIGHBOURS: usize = 12;

/// Eq. 7: time of the slowest axis for a synchronous joint move from `a` to `b`.
#[inline]
pub fn move_time(a: &[f64; 6], b: &[f64; 6], max_speed: &[f64; 6]) -> f64 {
    let mut t = 0.0_f64;
    for n in 0..6 {
        t = t.max((a[n] - b[n]).abs() / max_speed[n]);
    }
    t
}

/// The symmetric Eq. 7 cost between every pair of poses, computed on demand.
///
/// Poses are stored divided by the joint speeds, so an entry is max_k |a_k/w_k − b_k/w_k|: equal
/// to `move_time(poses[i], poses[j])` up to rounding (the search compares sums of them with a
/// tolerance, and reported times always come from [`super::path_time`]). A dense matrix would be n² entries (92 MB at
/// 3,400 poses) read in random order by the local search: recomputing six differences is
/// cheaper than the cache misses, and memory stays linear in n.
pub(crate) struct Costs {
    n: usize,
    /// Poses in joint-time units (rad / (rad/s) = s).
    poses: Vec<[f64; 6]>,
    /// With accelerations (the trapezoid cost): poses divided by them (rad / (rad/s²) = s²).
    accel: Option<Vec<[f64; 6]>>,
}

impl Costs {
    pub(crate) fn new(poses: &[[f64; 6]], max_speed: &[f64; 6]) -> Self {
        Costs {
            n: poses.len(),
            poses: poses
                .iter()
                .map(|p| std::array::from_fn(|k| p[k] / max_speed[k]))
                .collect(),
            accel: None,
        }
    }

    /// The trapezoid cost ([`crate::timing::move_time`] between exact stops): Eq. 7's T₇ and
    /// the acceleration's T_a² = max |Δ|/a from poses pre-divided by speeds and accelerations.
    pub(crate) fn with_accel(poses: &[[f64; 6]], max_speed: &[f64; 6], accel: &[f64; 6]) -> Self {
        Costs {
            accel: Some(
                poses
                    .iter()
                    .map(|p| std::array::from_fn(|k| p[k] / accel[k]))
                    .collect(),
            ),
            ..Costs::new(poses, max_speed)
        }
    }

    #[inline]
    pub(crate) fn get(&self, i: usize, j: usize) -> f64 {
        let t = linf(&self.poses[i], &self.poses[j]);
        match &self.accel {
            None => t,
            Some(acc) => {
                let ta2 = linf(&acc[i], &acc[j]);
                if t * t >= ta2 {
                    if t > 0.0 {
                        t + ta2 / t
                    } else {
                        0.0
                    }
                } else {
                    2.0 * ta2.sqrt()
                }
            }
        }
    }

    /// The largest entry (a bound with accelerations: the trapezoid of the widest spreads).
    pub(crate) fn max(&self) -> f64 {
        let t = spread(&self.poses);
        match &self.accel {
            None => t,
            Some(acc) => crate::timing::trapezoid(t, spread(acc).sqrt()),
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.n
    }

    /// For every pose, the `k` other poses closest to it, nearest first; equal costs are ordered
    /// by lowest index so the lists (and everything built on them) are machine-independent.
    pub(crate) fn neighbours(&self, k: usize) -> Neighbours {
        let n = self.n;
        let k = k.min(n.saturating_sub(1));
        let mut list = vec![0usize; n * k];
        let mut cost = vec![0.0; n * k];
        if k > 0 {
            list.par_chunks_mut(k)
                .zip(cost.par_chunks_mut(k))
                .enumerate()
                .for_each(|(i, (out, out_cost))| {
                    // One sweep keeping the k best seen so far, sorted by (cost, index). Scanning j
                    // upwards, a newcomer goes after every kept entry of equal cost: lower index wins.
                    let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
                    for j in 0..n {
                        let cost = self.get(i, j);
                        if j == i || (best.len() == k && cost >= best[k - 1].0) {
                            continue;
                        }
                        let at = best.partition_point(|&(kept, _)| kept <= cost);
                        best.insert(at, (cost, j));
                        best.truncate(k);
                    }
                    for ((slot, c), &(d, j)) in out.iter_mut().zip(out_cost.iter_mut()).zip(&best) {
                        *slot = j;
                        *c = d;
                    }
                });
        }
        Neighbours { k, list, cost }
    }
}

/// Candidate lists: row `i` holds the `k` nearest other poses of pose `i`, nearest first, with
/// their costs (exactly `Costs::get(i, j)`, kept so the search need not recompute them).
pub(crate) struct Neighbours {
    k: usize,
    list: Vec<usize>,
    cost: Vec<f64>,
}

impl Neighbours {
    #[inline]
    pub(crate) fn of(&self, i: usize) -> &[usize] {
        &self.list[i * self.k..(i + 1) * self.k]
    }

    /// The candidates of `i` with their costs, nearest first.
    #[inline]
    pub(crate) fn with_cost(&self, i: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let r = i * self.k..(i + 1) * self.k;
        self.list[r.clone()]
            .iter()
            .copied()
            .zip(self.cost[r].iter().copied())
    }
}

/// The largest entry: per joint the widest spread of the poses. Exact: the pair (argmax,
/// argmin) of that joint gives the same subtraction.
fn spread(poses: &[[f64; 6]]) -> f64 {
    (0..6)
        .map(|k| {
            let (lo, hi) = poses
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                    (lo.min(p[k]), hi.max(p[k]))
                });
            if hi >= lo {
                hi - lo
            } else {
                0.0
            }
        })
        .fold(0.0, f64::max)
}

#[inline]
fn linf(a: &[f64; 6], b: &[f64; 6]) -> f64 {
    // Poses are finite (checked by `solve`), so a plain comparison is `f64::max` without
    // its NaN handling, which costs more than the rest of this function.
    let mut t = 0.0_f64;
    for k in 0..6 {
        let d = (a[k] - b[k]).abs();
        if d > t {
            t = d;
        }
    }
    t
}

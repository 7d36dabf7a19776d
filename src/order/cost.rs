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

/// Dense, symmetric n×n matrix of [`move_time`] between every pair of poses.
///
/// Entries are exactly `move_time(poses[i], poses[j])`, so sums over it agree bit for bit with
/// [`super::path_time`] evaluated in the same order.
pub(crate) struct Costs {
    n: usize,
    c: Vec<f64>,
}

impl Costs {
    pub(crate) fn new(poses: &[[f64; 6]], max_speed: &[f64; 6]) -> Self {
        let n = poses.len();
        let mut c = vec![0.0; n * n];
        // Each entry depends only on its own pair, so the parallel fill is deterministic.
        c.par_chunks_mut(n.max(1)).enumerate().for_each(|(i, row)| {
            for (j, cell) in row.iter_mut().enumerate() {
                *cell = move_time(&poses[i], &poses[j], max_speed);
            }
        });
        Costs { n, c }
    }

    #[inline]
    pub(crate) fn get(&self, i: usize, j: usize) -> f64 {
        self.c[i * self.n + j]
    }

    pub(crate) fn len(&self) -> usize {
        self.n
    }

    pub(crate) fn max(&self) -> f64 {
        self.c.iter().copied().fold(0.0, f64::max)
    }

    /// For every pose, the `k` other poses closest to it, nearest first; equal costs are ordered
    /// by lowest index so the lists (and everything built on them) are machine-independent.
    pub(crate) fn neighbours(&self, k: usize) -> Neighbours {
        let n = self.n;
        let k = k.min(n.saturating_sub(1));
        let mut list = vec![0usize; n * k];
        if k > 0 {
            list.par_chunks_mut(k).enumerate().for_each(|(i, out)| {
                let key = |j: usize| (self.get(i, j), j);
                let mut others: Vec<usize> = (0..n).filter(|&j| j != i).collect();
                // Total order on (cost, index): costs are finite (checked by the caller).
                let cmp = |a: &usize, b: &usize| key(*a).partial_cmp(&key(*b)).unwrap();
                if others.len() > k {
                    others.select_nth_unstable_by(k - 1, cmp);
                    others.truncate(k);
                }
                others.sort_unstable_by(cmp);
                out.copy_from_slice(&others);
            });
        }
        Neighbours { k, list }
    }
}

/// Candidate lists: row `i` holds the `k` nearest other poses of pose `i`, nearest first.
pub(crate) struct Neighbours {
    k: usize,
    list: Vec<usize>,
}

impl Neighbours {
    #[inline]
    pub(crate) fn of(&self, i: usize) -> &[usize] {
        &self.list[i * self.k..(i + 1) * self.k]
    }
}

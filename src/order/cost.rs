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
        // Joint-major copies so each row is six straight vectorisable sweeps. The arithmetic is
        // exactly move_time's (same subtraction order, division, and max), so entries are equal
        // bit for bit to move_time(poses[i], poses[j]).
        let cols: [Vec<f64>; 6] = std::array::from_fn(|k| poses.iter().map(|p| p[k]).collect());
        let mut c = vec![0.0_f64; n * n];
        // Each row depends only on its own pose, so the parallel fill is deterministic.
        c.par_chunks_mut(n.max(1)).enumerate().for_each(|(i, row)| {
            for k in 0..6 {
                let (a, w) = (poses[i][k], max_speed[k]);
                for (cell, &b) in row.iter_mut().zip(&cols[k]) {
                    *cell = cell.max((a - b).abs() / w);
                }
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
                // One sweep keeping the k best seen so far, sorted by (cost, index). Scanning j
                // upwards, a newcomer goes after every kept entry of equal cost: lower index wins.
                let row = &self.c[i * n..(i + 1) * n];
                let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
                for (j, &cost) in row.iter().enumerate() {
                    if j == i || (best.len() == k && cost >= best[k - 1].0) {
                        continue;
                    }
                    let at = best.partition_point(|&(kept, _)| kept <= cost);
                    best.insert(at, (cost, j));
                    best.truncate(k);
                }
                for (slot, &(_, j)) in out.iter_mut().zip(&best) {
                    *slot = j;
                }
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

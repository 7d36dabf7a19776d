//! Tour construction (nearest neighbour) and improvement (2-opt + Or-opt) on an open path whose
//! first city is fixed and whose last city is free.
//!
//! The path is kept as an array `t` (position → city) with its inverse `pos` (city → position).
//! Moves are found from candidate lists and applied at once (first improvement); cities whose
//! edges changed go back on a FIFO work queue ("don't-look bits"), so the search stops when a
//! full round over the queue finds nothing, and the order of work never depends on the machine.

use std::collections::VecDeque;

use super::cost::{Costs, Neighbours};

/// Greedy open path from `start`: always go to the cheapest unvisited pose (lowest index on ties).
pub(crate) fn nearest_neighbour(costs: &Costs, nbrs: &Neighbours, start: usize) -> Vec<usize> {
    let n = costs.len();
    let mut visited = vec![false; n];
    let mut order = Vec::with_capacity(n);
    let mut cur = start;
    visited[cur] = true;
    order.push(cur);
    for _ in 1..n {
        // The candidate list holds the k smallest (cost, index) pairs in that order, so its first
        // unvisited entry is the global choice; only when all k are visited scan the whole row.
        let next = match nbrs.of(cur).iter().find(|&&j| !visited[j]) {
            Some(&j) => j,
            None => {
                let mut best = usize::MAX;
                let mut best_cost = f64::INFINITY;
                for (j, &seen) in visited.iter().enumerate() {
                    // Strict `<` over ascending j keeps the lowest index among equal costs.
                    if !seen && (best == usize::MAX || costs.get(cur, j) < best_cost) {
                        best = j;
                        best_cost = costs.get(cur, j);
                    }
                }
                best
            }
        };
        visited[next] = true;
        order.push(next);
        cur = next;
    }
    order
}

/// Improve `order` in place by 2-opt and Or-opt moves until none strictly shortens it by more than
/// `eps`. `order[0]` never moves. Returns the number of moves applied.
pub(crate) fn improve(costs: &Costs, nbrs: &Neighbours, order: &mut [usize], eps: f64) -> usize {
    if order.len() < 3 {
        return 0; // With the first pose fixed, 0..=2 poses have exactly one open path.
    }
    let mut path = Path::new(costs, nbrs, order, eps);
    let all = path.t.to_vec();
    path.search(&all)
}

/// A kick whose repaired path is longer by less than the threshold is kept all the same, so
/// the search can leave local optima that no single kick improves (the best path seen is what
/// `perturb` returns). The threshold starts at this many mean edges of the starting path and falls
/// linearly to zero over the kicks, like a cooling schedule: early kicks roam, late ones only
/// descend. On the NJ-130 bench pool of 3,400 poses (4 kick seeds, same kicks) strict acceptance
/// gave a mean gap to LKH-3 of 0.335 %, a fixed 0.03 0.30 %, a fixed 0.2 0.53 % (it wanders off),
/// and 0.2 falling to zero 0.25 %.
const UPHILL: f64 = 0.2;

/// Iterated local search from a local optimum `order`: `kicks` times, swap two adjacent short
/// segments (a segment move, which the Or-3opt moves could undo in one step; a true double bridge,
/// A B C D E → A D C B E, did no better on the bench pools), re-optimise around the changed edges, and keep the result if the whole path got shorter
/// (by more than `eps`) or longer by less than the falling [`UPHILL`] threshold; otherwise
/// restore it. During the kicks Or-opt scans candidates only while the new edge is shorter than
/// the edges it frees (`Path::prune`); a last exact search from the best path seen makes the
/// result a local optimum of the full neighbourhoods, never longer than the input. The kicks come
/// from a ChaCha8 generator seeded with `seed`, so the outcome is the same on every machine.
/// Returns the number of kicks kept.
pub(crate) fn perturb(
    costs: &Costs,
    nbrs: &Neighbours,
    order: &mut [usize],
    eps: f64,
    kicks: usize,
    seed: u64,
) -> usize {
    use rand::{Rng, SeedableRng};
    /// Longest segment a kick moves: short swaps are cheap to repair, so many fit in the time;
    /// with the 3-opt moves repairing them. With strict acceptance 30 found shorter tours than 8,
    /// 15, 20, 50 or 100 on NJ-130 pools of 200 to 3,400 poses; with the falling threshold and
    /// the pruned Or-opt, 15 (with 1,800 kicks per 100 poses) beat 30 (1,500) at the same time.
    const MAX_SEGMENT: usize = 15;
    let n = order.len();
    if n < 3 {
        return 0; // Needs the fixed start plus two non-empty segments.
    }
    // Two segments fit behind the fixed start: lb + lc <= n - 1.
    let longest = MAX_SEGMENT.min((n - 1) / 2);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut path = Path::new(costs, nbrs, order, eps);
    let mut saved = path.t.to_vec();
    let mut best = saved.clone();
    // Costs of the current and the best tour (s), `cur` kept up to date by the kicks' deltas.
    let mut best_cost = path.cost();
    let mut cur = best_cost;
    let uphill0 = UPHILL * best_cost / (n - 1) as f64;
    path.prune = true;
    let mut kept = 0;
    for k in 0..kicks {
        let uphill = uphill0 * (1.0 - k as f64 / kicks as f64);
        // Path = A B C D with B = t[p1..p2], C = t[p2..p3]; the kick makes it A C B D.
        let lb = rng.random_range(1..=longest);
        let lc = rng.random_range(1..=longest);
        let p1 = rng.random_range(1..=n - lb - lc);
        let (p2, p3) = (p1 + lb, p1 + lb + lc);
        let t = &path.t;
        let (a, b0, b1, c0, c1) = (t[p1 - 1], t[p1], t[p2 - 1], t[p2], t[p3 - 1]);
        let d = (p3 < n).then(|| t[p3]);
        let (old_d, new_d) = match d {
            Some(d) => (path.d(c1, d), path.d(b1, d)),
            None => (0.0, 0.0),
        };
        let kick =
            path.d(a, c0) + path.d(c1, b0) + new_d - (path.d(a, b0) + path.d(b1, c0) + old_d);
        path.dirty = (n, 0);
        path.t[p1..p3].rotate_left(lb);
        path.mark(p1, p3 - 1);
        for p in p1..p3 {
            path.pos[path.t[p]] = p;
        }
        path.gain = 0.0;
        let seeds = [a, b0, b1, c0, c1, d.unwrap_or(usize::MAX)];
        path.search(&seeds);
        let (lo, hi) = path.dirty;
        let delta = kick - path.gain;
        if delta < -eps || delta < uphill {
            saved[lo..hi].copy_from_slice(&path.t[lo..hi]);
            kept += 1;
            cur += delta;
            if cur < best_cost - eps {
                // Summing the deltas drifts by rounding: a new best is judged on the real cost.
                cur = path.cost();
                if cur < best_cost - eps {
                    best_cost = cur;
                    best.copy_from_slice(path.t);
                }
            }
        } else {
            path.t[lo..hi].copy_from_slice(&saved[lo..hi]);
            for (p, &city) in saved.iter().enumerate().take(hi).skip(lo) {
                path.pos[city] = p;
            }
        }
    }
    path.t.copy_from_slice(&best);
    for (p, &city) in best.iter().enumerate() {
        path.pos[city] = p;
    }
    path.prune = false;
    path.search(&best);
    kept
}

/// Longest segment the Or-opt move shifts on its own: single cities. Longer segments, of any
/// length, are moved by the sequential 3-opt moves of [`Path::or3`] from candidate lists, which
/// find them for far less work than trying every length up to a limit: on NJ-130 pools of 200 to
/// 3,400 poses this halved the search time and left the tours as short or shorter.
const OR_OPT_MAX_SEGMENT: usize = 1;

struct Path<'a> {
    c: &'a Costs,
    nb: &'a Neighbours,
    t: &'a mut [usize],
    pos: Vec<usize>,
    eps: f64,
    /// Work-queue membership; all false between searches.
    queued: Vec<bool>,
    /// Sum of the gains of the moves applied since last reset.
    gain: f64,
    /// Positions `dirty.0..dirty.1` hold every change to `t` since last reset.
    dirty: (usize, usize),
    /// The work queue of [`Path::search`] and the cities a move touched, kept between searches
    /// so that a kick allocates nothing.
    queue: VecDeque<usize>,
    touched: Vec<usize>,
    /// Or-opt applies the LK gain criterion (the new edge at the moved segment's end must be
    /// shorter than what removing the segment saves) and stops scanning at the first candidate
    /// that fails it. That misses insertions between two far poses on whose straight line the
    /// segment lies, so exact searches (the first descent and the last one) leave it off; the
    /// kicks, which search most, save a quarter of their time with it.
    prune: bool,
}

impl<'a> Path<'a> {
    fn new(c: &'a Costs, nb: &'a Neighbours, t: &'a mut [usize], eps: f64) -> Self {
        let n = t.len();
        let mut pos = vec![0usize; n];
        for (p, &city) in t.iter().enumerate() {
            pos[city] = p;
        }
        Path {
            c,
            nb,
            t,
            pos,
            eps,
            queued: vec![false; n],
            gain: 0.0,
            dirty: (n, 0),
            queue: VecDeque::with_capacity(n),
            touched: Vec::with_capacity(8),
            prune: false,
        }
    }

    /// Apply improving moves around the `seeds` (usize::MAX = none) and every city whose edges
    /// change, until the queue runs dry. Returns the number of moves applied.
    fn search(&mut self, seeds: &[usize]) -> usize {
        // Reused buffers (empty between searches): no allocation per kick.
        let mut queue = std::mem::take(&mut self.queue);
        let mut touched = std::mem::take(&mut self.touched);
        let push = |queue: &mut VecDeque<usize>, queued: &mut [bool], x: usize| {
            // usize::MAX stands for "no city" (a missing edge at the open end).
            if x != usize::MAX && !queued[x] {
                queued[x] = true;
                queue.push_back(x);
            }
        };
        for &x in seeds {
            push(&mut queue, &mut self.queued, x);
        }
        let mut moves = 0;
        while let Some(a) = queue.pop_front() {
            self.queued[a] = false;
            touched.clear();
            // Test builds check every move's claimed gain against the path cost summed from
            // scratch: O(n) per city popped, so only on paths small enough to keep the tests
            // quick (the moves are the same code at every size).
            #[cfg(test)]
            let check = self.t.len() <= 40;
            #[cfg(test)]
            let (before, claimed) = (if check { self.cost() } else { 0.0 }, self.gain);
            if self.two_opt(a, &mut touched)
                || self.or_opt(a, &mut touched)
                || self.or3(a, &mut touched)
            {
                // Every move's claimed gain is the real change of the path's cost.
                #[cfg(test)]
                if check {
                    let real = before - self.cost();
                    assert!(
                        (real - (self.gain - claimed)).abs() <= 1e-9 * before.max(1.0),
                        "move claimed {} but changed the cost by {real}",
                        self.gain - claimed
                    );
                }
                moves += 1;
                for &x in &touched {
                    push(&mut queue, &mut self.queued, x);
                }
            }
        }
        touched.clear();
        self.queue = queue;
        self.touched = touched;
        moves
    }

    fn mark(&mut self, lo: usize, hi: usize) {
        self.dirty = (self.dirty.0.min(lo), self.dirty.1.max(hi + 1));
    }

    #[inline]
    fn d(&self, a: usize, b: usize) -> f64 {
        self.c.get(a, b)
    }

    /// Reverse the cities at positions `i..=j` (1 ≤ i ≤ j).
    fn reverse(&mut self, i: usize, j: usize) {
        debug_assert!(i >= 1 && i <= j);
        self.mark(i, j);
        // One pass swapping from both ends and renumbering as it goes (the middle city of an
        // odd range keeps its position).
        let (mut a, mut b) = (i, j);
        while a < b {
            let (x, y) = (self.t[a], self.t[b]);
            self.t[a] = y;
            self.t[b] = x;
            self.pos[y] = a;
            self.pos[x] = b;
            a += 1;
            b -= 1;
        }
    }

    /// Try the 2-opt moves that create a new edge from `a` to one of its candidates. A 2-opt move
    /// here reverses `t[i..=j]`; when `j` is the last position only the edge entering the
    /// segment changes (the open end is free), which is how the path end gets chosen.
    fn two_opt(&mut self, a: usize, touched: &mut Vec<usize>) -> bool {
        let n = self.t.len();
        let i = self.pos[a];
        let eps = self.eps;

        // New edge (a, x) replaces a's outgoing edge (a, b).
        if i + 1 < n {
            let b = self.t[i + 1];
            let d_ab = self.d(a, b);
            for (x, d_ax) in self.nb.with_cost(a) {
                if d_ax >= d_ab {
                    break; // Lists are sorted: no later x can pay for itself on this side.
                }
                let j = self.pos[x];
                if j > i + 1 {
                    // Reverse t[i+1..=j]: (a,b),(x,y) → (a,x),(b,y); y absent if x is last.
                    let (gain, y) = if j + 1 < n {
                        let y = self.t[j + 1];
                        (d_ab + self.d(x, y) - d_ax - self.d(b, y), y)
                    } else {
                        (d_ab - d_ax, usize::MAX)
                    };
                    if gain > eps {
                        self.gain += gain;
                        self.reverse(i + 1, j);
                        touched.extend([a, b, x, y]);
                        return true;
                    }
                } else if j + 1 < i {
                    // x before a: reverse t[j+1..=i]: (x,xs),(a,b) → (x,a),(xs,b).
                    let xs = self.t[j + 1];
                    let gain = self.d(x, xs) + d_ab - d_ax - self.d(xs, b);
                    if gain > eps {
                        self.gain += gain;
                        self.reverse(j + 1, i);
                        touched.extend([a, b, x, xs]);
                        return true;
                    }
                }
            }
        } else {
            // a is last: reversing t[j+1..] turns (x,xs) into (x,a) and nothing else changes.
            for (x, d_ax) in self.nb.with_cost(a) {
                let j = self.pos[x];
                if j + 2 < n {
                    let xs = self.t[j + 1];
                    let gain = self.d(x, xs) - d_ax;
                    if gain > eps {
                        self.gain += gain;
                        self.reverse(j + 1, n - 1);
                        touched.extend([a, x, xs]);
                        return true;
                    }
                }
            }
        }

        // New edge (x, a) replaces a's incoming edge (p, a). Position 0 never moves.
        if i >= 1 {
            let p = self.t[i - 1];
            let d_pa = self.d(p, a);
            for (x, d_ax) in self.nb.with_cost(a) {
                if d_ax >= d_pa {
                    break;
                }
                let j = self.pos[x];
                if j >= 1 && j + 1 < i {
                    // Reverse t[j..=i-1]: (w,x),(p,a) → (w,p),(x,a).
                    let w = self.t[j - 1];
                    let gain = self.d(w, x) + d_pa - self.d(w, p) - d_ax;
                    if gain > eps {
                        self.gain += gain;
                        self.reverse(j, i - 1);
                        touched.extend([a, p, x, w]);
                        return true;
                    }
                } else if j > i + 1 {
                    // Reverse t[i..=j-1]: (p,a),(v,x) → (p,v),(a,x).
                    let v = self.t[j - 1];
                    let gain = d_pa + self.d(v, x) - self.d(p, v) - d_ax;
                    if gain > eps {
                        self.gain += gain;
                        self.reverse(i, j - 1);
                        touched.extend([a, p, x, v]);
                        return true;
                    }
                }
            }
        }
        false
    }

    /// Try moving a segment of up to `OR_OPT_MAX_SEGMENT` cities that has `a` at one end to a place where one of its
    /// ends sits next to a candidate of that end, in either orientation.
    fn or_opt(&mut self, a: usize, touched: &mut Vec<usize>) -> bool {
        let n = self.t.len();
        let i = self.pos[a];
        if i == 0 {
            return false;
        }
        for len in 1..=OR_OPT_MAX_SEGMENT {
            // Keep at least the fixed first city and one other outside the segment.
            if len + 2 > n {
                break;
            }
            // Segment starting at a, then (for len > 1) the one ending at a.
            let starts: [Option<usize>; 2] = [
                (i + len <= n).then_some(i),
                (len > 1 && i >= len).then(|| i + 1 - len),
            ];
            for s in starts.into_iter().flatten() {
                if self.try_segment(s, s + len - 1, touched) {
                    return true;
                }
            }
        }
        false
    }

    /// Try to move the segment at positions `s..=e` (s ≥ 1) elsewhere.
    fn try_segment(&mut self, s: usize, e: usize, touched: &mut Vec<usize>) -> bool {
        let n = self.t.len();
        let eps = self.eps;
        let first = self.t[s];
        let last = self.t[e];
        let p = self.t[s - 1];
        let nx = (e + 1 < n).then(|| self.t[e + 1]);
        let removal = self.d(p, first)
            + match nx {
                Some(q) => self.d(last, q) - self.d(p, q),
                None => 0.0,
            };
        let ends: &[(usize, usize)] = if s == e {
            &[(first, last)]
        } else {
            &[(first, last), (last, first)]
        };
        for &(end, other) in ends {
            for (x, d_ex) in self.nb.with_cost(end) {
                if self.prune && d_ex >= removal {
                    break; // Lists are sorted: no later x passes the gain criterion either.
                }
                let j = self.pos[x];
                if (s..=e).contains(&j) {
                    continue;
                }
                // x on the right: w, [other .. end], x. Not into the gap the segment left.
                if j >= 1 && j - 1 != e {
                    let w = self.t[j - 1];
                    let gain = removal - (self.d(w, other) + d_ex - self.d(w, x));
                    if gain > eps {
                        self.gain += gain;
                        let reversed = end == first;
                        self.move_segment(s, e, j - 1, reversed);
                        touched.extend([first, last, p, nx.unwrap_or(usize::MAX), w, x]);
                        return true;
                    }
                }
                // x on the left: x, [end .. other], y (y absent: the segment becomes the tail).
                if j + 1 != s {
                    let (delta, y) = if j + 1 < n {
                        let y = self.t[j + 1];
                        (d_ex + self.d(other, y) - self.d(x, y), y)
                    } else {
                        (d_ex, usize::MAX)
                    };
                    let gain = removal - delta;
                    if gain > eps {
                        self.gain += gain;
                        let reversed = end == last;
                        self.move_segment(s, e, j, reversed);
                        touched.extend([first, last, p, nx.unwrap_or(usize::MAX), x, y]);
                        return true;
                    }
                }
            }
        }
        false
    }

    /// Try the sequential 3-opt moves ("Or-3opt") that start with a new edge from `a` to one of
    /// its candidates, replacing a's outgoing edge, then the same on the path read backwards
    /// (replacing a's incoming edge).
    fn or3(&mut self, a: usize, touched: &mut Vec<usize>) -> bool {
        self.or3_dir::<false>(a, touched) || self.or3_dir::<true>(a, touched)
    }

    /// City at view position `v` (the path read backwards when `M`).
    #[inline]
    fn vt<const M: bool>(&self, v: usize) -> usize {
        if M {
            self.t[self.t.len() - 1 - v]
        } else {
            self.t[v]
        }
    }

    /// View position of city `c`.
    #[inline]
    fn vp<const M: bool>(&self, c: usize) -> usize {
        if M {
            self.t.len() - 1 - self.pos[c]
        } else {
            self.pos[c]
        }
    }

    /// The real positions of the view range `lo..=hi`.
    #[inline]
    fn vrange<const M: bool>(&self, lo: usize, hi: usize) -> (usize, usize) {
        if M {
            let n = self.t.len();
            (n - 1 - hi, n - 1 - lo)
        } else {
            (lo, hi)
        }
    }

    fn vreverse<const M: bool>(&mut self, lo: usize, hi: usize) {
        let (a, b) = self.vrange::<M>(lo, hi);
        self.t[a..=b].reverse();
    }

    fn vrotate_left<const M: bool>(&mut self, lo: usize, hi: usize, k: usize) {
        let (a, b) = self.vrange::<M>(lo, hi);
        if M {
            self.t[a..=b].rotate_right(k);
        } else {
            self.t[a..=b].rotate_left(k);
        }
    }

    fn vrenumber<const M: bool>(&mut self, lo: usize, hi: usize) {
        let (a, b) = self.vrange::<M>(lo, hi);
        self.renumber(a, b);
    }

    /// One direction of [`Path::or3`], on the view: `a` at view position i, B = i+1..=j,
    /// C = j+1..=k and D the rest (empty when k is the view's last position: the free end).
    /// A B C D becomes one of
    /// - A C B D   (a segment moved, of any length: Or-opt without its length limit),
    /// - A C Bʳ D, A Cʳ B D (moved and reversed),
    /// - A Bʳ Cʳ D (two adjacent reversals),
    ///
    /// each found by the LK rule: the new edge from a is shorter than the edge it replaces, and
    /// the second new edge keeps the partial gain positive; its far end comes from a candidate
    /// list too. Backwards (`M`), the view's last position is the fixed first pose, which no
    /// range may include, and the free end is the view's first position, which none reaches.
    fn or3_dir<const M: bool>(&mut self, a: usize, touched: &mut Vec<usize>) -> bool {
        let n = self.t.len();
        // The highest view position a range may reach, and the view's last position.
        let (top, last) = if M {
            (n.wrapping_sub(2), n - 1)
        } else {
            (n - 1, n - 1)
        };
        let i = self.vp::<M>(a);
        if n < 4 || i + 2 > top {
            return false; // B and C need a city each after a.
        }
        let eps = self.eps;
        let x1 = self.vt::<M>(i + 1);
        let g0 = self.d(a, x1);
        // The edge leaving view position k, or none at the view's end.
        let out = |s: &Self, k: usize| {
            if k < last {
                s.d(s.vt::<M>(k), s.vt::<M>(k + 1))
            } else {
                0.0
            }
        };
        let next = |s: &Self, k: usize| (k < last).then(|| s.vt::<M>(k + 1));
        for (y, d_ay) in self.nb.with_cost(a) {
            if d_ay >= g0 {
                break;
            }
            let p = self.vp::<M>(y);
            if p <= i + 1 || p > top {
                continue;
            }
            // y starts C (j = p − 1): A C B D or A C Bʳ D.
            let j = p - 1;
            let yp = self.vt::<M>(j);
            let g1 = g0 - d_ay + self.d(yp, y);
            for (end, rev) in [(x1, false), (yp, true)] {
                for (w, d_ew) in self.nb.with_cost(end) {
                    if d_ew >= g1 {
                        break;
                    }
                    let k = self.vp::<M>(w);
                    if k < p || k > top {
                        continue;
                    }
                    // The other end of B meets the city after C.
                    let other = if rev { x1 } else { yp };
                    let after = next(self, k);
                    let close = after.map_or(0.0, |c| self.d(other, c));
                    let gain = g1 - d_ew + out(self, k) - close;
                    if gain > eps {
                        self.gain += gain;
                        self.vrotate_left::<M>(i + 1, k, j - i);
                        if rev {
                            // C B → C Bʳ: B now ends the range.
                            self.vreverse::<M>(i + 1 + (k - j), k);
                        }
                        self.vrenumber::<M>(i + 1, k);
                        touched.extend([a, x1, yp, y, w, after.unwrap_or(usize::MAX)]);
                        return true;
                    }
                }
            }
            // y ends B (j = p): A Bʳ Cʳ D with the new edge (x1, w), w = t[k] ending C.
            if p < top {
                let y1 = self.vt::<M>(p + 1);
                let g1 = g0 - d_ay + self.d(y, y1);
                for (w, d_xw) in self.nb.with_cost(x1) {
                    if d_xw >= g1 {
                        break;
                    }
                    let k = self.vp::<M>(w);
                    if k <= p || k > top {
                        continue;
                    }
                    let after = next(self, k);
                    let close = after.map_or(0.0, |c| self.d(y1, c));
                    let gain = g1 - d_xw + out(self, k) - close;
                    if gain > eps {
                        self.gain += gain;
                        self.vreverse::<M>(i + 1, p);
                        self.vreverse::<M>(p + 1, k);
                        self.vrenumber::<M>(i + 1, k);
                        touched.extend([a, x1, y, y1, w, after.unwrap_or(usize::MAX)]);
                        return true;
                    }
                }
            }
            // y ends C (k = p): A Cʳ B D with the new edge (x1, w), w = t[j + 1] starting C.
            let g1 = g0 - d_ay + out(self, p);
            let after = next(self, p);
            for (w, d_xw) in self.nb.with_cost(x1) {
                if d_xw >= g1 {
                    break;
                }
                let q = self.vp::<M>(w);
                if q < i + 2 || q > p {
                    continue;
                }
                let j = q - 1;
                let wp = self.vt::<M>(j);
                let close = after.map_or(0.0, |c| self.d(wp, c));
                let gain = g1 - d_xw + self.d(wp, w) - close;
                if gain > eps {
                    self.gain += gain;
                    // B C → Cʳ Bʳ → Cʳ B.
                    self.vreverse::<M>(i + 1, p);
                    self.vreverse::<M>(i + 1 + (p - j), p);
                    self.vrenumber::<M>(i + 1, p);
                    touched.extend([a, x1, wp, w, y, after.unwrap_or(usize::MAX)]);
                    return true;
                }
            }
        }
        false
    }

    /// The path's cost, summed from scratch (tests check every move's claimed gain with it; the
    /// perturbation re-anchors its running total on it whenever it may have a new best tour).
    fn cost(&self) -> f64 {
        self.t.windows(2).map(|w| self.d(w[0], w[1])).sum()
    }

    /// Positions `lo..=hi` changed: mark them and bring `pos` up to date.
    fn renumber(&mut self, lo: usize, hi: usize) {
        self.mark(lo, hi);
        for p in lo..=hi {
            self.pos[self.t[p]] = p;
        }
    }

    /// Move the segment at `s..=e` so that it follows the city now at position `g` (outside the
    /// segment and not `s - 1`), reversed if asked.
    fn move_segment(&mut self, s: usize, e: usize, g: usize, reversed: bool) {
        let len = e - s + 1;
        let (lo, hi, seg) = if g > e {
            self.t[s..=g].rotate_left(len);
            (s, g, g + 1 - len)
        } else {
            debug_assert!(g + 1 < s);
            self.t[g + 1..=e].rotate_right(len);
            (g + 1, e, g + 1)
        };
        if reversed {
            self.t[seg..seg + len].reverse();
        }
        self.mark(lo, hi);
        for p in lo..=hi {
            self.pos[self.t[p]] = p;
        }
    }
}

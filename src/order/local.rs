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

/// Iterated local search from a local optimum `order`: `kicks` times, swap two adjacent short
/// segments (a segment-local double bridge, which 2-opt and Or-opt cannot undo in one move),
/// re-optimise around the four changed edges, and keep the result only if the whole path got
/// strictly shorter (by more than `eps`); otherwise restore it. The kicks come from a ChaCha8
/// generator seeded with `seed`, so the outcome is the same on every machine. Returns the number
/// of kicks kept.
pub(crate) fn perturb(
    costs: &Costs,
    nbrs: &Neighbours,
    order: &mut [usize],
    eps: f64,
    kicks: usize,
    seed: u64,
) -> usize {
    use rand::{Rng, SeedableRng};
    /// Longest segment a kick moves: short swaps are cheap to repair, so more of them fit in the
    /// same work, which found shorter tours on NJ-130 pools of 200 to 3,400 poses.
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
    let mut kept = 0;
    for _ in 0..kicks {
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
        if kick - path.gain < -eps {
            saved[lo..hi].copy_from_slice(&path.t[lo..hi]);
            kept += 1;
        } else {
            path.t[lo..hi].copy_from_slice(&saved[lo..hi]);
            for (p, &city) in saved.iter().enumerate().take(hi).skip(lo) {
                path.pos[city] = p;
            }
        }
    }
    kept
}

/// Longest segment an Or-opt move shifts. Up to 1,000 poses segments of up to 10 cities (a
/// 3-opt "segment insertion" with or without reversal) are affordable and close about half of
/// the gap to LKH-3 on NJ-130 pools; beyond that the classic 3 keeps a 3,400-pose tour under 1 s.
/// A function of n alone, so the result stays machine-independent.
pub(crate) fn or_opt_max_segment(n: usize) -> usize {
    if n <= 1000 {
        10
    } else {
        3
    }
}

struct Path<'a> {
    c: &'a Costs,
    nb: &'a Neighbours,
    t: &'a mut [usize],
    pos: Vec<usize>,
    eps: f64,
    /// Longest segment Or-opt moves (see [`or_opt_max_segment`]).
    or_max: usize,
    /// Work-queue membership; all false between searches.
    queued: Vec<bool>,
    /// Sum of the gains of the moves applied since last reset.
    gain: f64,
    /// Positions `dirty.0..dirty.1` hold every change to `t` since last reset.
    dirty: (usize, usize),
}

impl<'a> Path<'a> {
    fn new(c: &'a Costs, nb: &'a Neighbours, t: &'a mut [usize], eps: f64) -> Self {
        let n = t.len();
        let or_max = or_opt_max_segment(n);
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
            or_max,
            queued: vec![false; n],
            gain: 0.0,
            dirty: (n, 0),
        }
    }

    /// Apply improving moves around the `seeds` (usize::MAX = none) and every city whose edges
    /// change, until the queue runs dry. Returns the number of moves applied.
    fn search(&mut self, seeds: &[usize]) -> usize {
        let mut queue = VecDeque::new();
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
        let mut touched = Vec::with_capacity(8);
        while let Some(a) = queue.pop_front() {
            self.queued[a] = false;
            touched.clear();
            if self.two_opt(a, &mut touched) || self.or_opt(a, &mut touched) {
                moves += 1;
                for &x in &touched {
                    push(&mut queue, &mut self.queued, x);
                }
            }
        }
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
        self.t[i..=j].reverse();
        self.mark(i, j);
        for p in i..=j {
            self.pos[self.t[p]] = p;
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
            for &x in self.nb.of(a) {
                let d_ax = self.d(a, x);
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
            for &x in self.nb.of(a) {
                let j = self.pos[x];
                if j + 2 < n {
                    let xs = self.t[j + 1];
                    let gain = self.d(x, xs) - self.d(x, a);
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
            for &x in self.nb.of(a) {
                let d_ax = self.d(a, x);
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

    /// Try moving a segment of 1..=3 cities that has `a` at one end to a place where one of its
    /// ends sits next to a candidate of that end, in either orientation.
    fn or_opt(&mut self, a: usize, touched: &mut Vec<usize>) -> bool {
        let n = self.t.len();
        let i = self.pos[a];
        if i == 0 {
            return false;
        }
        for len in 1..=self.or_max {
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
            for &x in self.nb.of(end) {
                let j = self.pos[x];
                if (s..=e).contains(&j) {
                    continue;
                }
                let d_ex = self.d(end, x);
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

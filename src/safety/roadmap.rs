//! Support-pose search: in = a move a → b that failed its check and the pool of admitted poses;
//! out = via points (support poses) such that every straight move along them passes.
//!
//! The admitted pool is a probabilistic roadmap: each pose links to its nearest neighbours in the
//! Eq. 7 metric (time of the slowest axis). A lazy A* walks it from a towards b — an edge is
//! checked (continuously, with [`Checker::line`]) only when the search pops it, and every node
//! tries the direct move to b. Eq. 7 is a weighted max-norm, so it satisfies the triangle
//! inequality and is an admissible heuristic: the first path found is the cheapest among the
//! edges tried. A budget bounds the work per failed move.

use super::{Checker, Extremes};
use crate::order::move_time;
use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap};

pub const NEIGHBOURS: usize = 10;
pub const EXPANSIONS: usize = 120;

const START: usize = usize::MAX;

#[derive(PartialEq)]
struct Open {
    f: f64,
    g: f64,
    node: usize,
    parent: usize,
}
impl Eq for Open {}
impl Ord for Open {
    fn cmp(&self, o: &Self) -> Ordering {
        // Min-heap on f, ties by node index for determinism.
        o.f.total_cmp(&self.f).then(o.node.cmp(&self.node))
    }
}
impl PartialOrd for Open {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}

/// Via points from the pool that make a → b safe, or None within the budget.
pub fn connect(
    ck: &Checker,
    a: &[f64; 6],
    b: &[f64; 6],
    pool: &[[f64; 6]],
    speeds: &[f64; 6],
    ext: &mut Extremes,
) -> Option<Vec<[f64; 6]>> {
    let pos = |n: usize| if n == START { a } else { &pool[n] };
    let h = |n: usize| move_time(pos(n), b, speeds);
    let mut checked: HashMap<(usize, usize), bool> = HashMap::new();
    let mut edge = |u: usize, v: usize, ext: &mut Extremes| -> bool {
        *checked.entry((u, v)).or_insert_with(|| {
            let mut e = Extremes::default();
            let ok = ck.line(pos(u), pos(v), &mut e).is_ok();
            if ok {
                ext.merge(&e);
            }
            ok
        })
    };
    let mut parent: HashMap<usize, usize> = HashMap::new();
    let mut open = BinaryHeap::new();
    open.push(Open {
        f: h(START),
        g: 0.0,
        node: START,
        parent: START,
    });
    let mut expansions = 0;
    while let Some(Open {
        g,
        node,
        parent: from,
        ..
    }) = open.pop()
    {
        if parent.contains_key(&node) {
            continue;
        }
        if node != START && !edge(from, node, ext) {
            continue;
        }
        parent.insert(node, from);
        // The direct move to b.
        let mut e = Extremes::default();
        if node != START && ck.line(pos(node), b, &mut e).is_ok() {
            ext.merge(&e);
            let mut vias = vec![pool[node]];
            let mut n = node;
            while let Some(&p) = parent.get(&n) {
                if p == START {
                    break;
                }
                vias.push(pool[p]);
                n = p;
            }
            vias.reverse();
            return Some(vias);
        }
        expansions += 1;
        if expansions > EXPANSIONS {
            return None;
        }
        // Push the nearest pool poses (lazily: their edges are checked when popped).
        let here = pos(node);
        let mut near: Vec<(f64, usize)> = pool
            .iter()
            .enumerate()
            .filter(|(i, q)| !parent.contains_key(i) && *q != here && *q != b)
            .map(|(i, q)| (move_time(here, q, speeds), i))
            .collect();
        let k = NEIGHBOURS.min(near.len());
        if k == 0 {
            continue;
        }
        near.select_nth_unstable_by(k - 1, |x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        for &(c, i) in &near[..k] {
            let g2 = g + c;
            open.push(Open {
                f: g2 + h(i),
                g: g2,
                node: i,
                parent: node,
            });
        }
    }
    None
}

/// The groups of pool poses that safe motions connect (with the bar mounted): a component
/// label per pose, labels numbered by size (0 = largest; ties by smallest member index).
/// Poses are linked to their `k` nearest neighbours (Eq. 7) when the move's quarter, middle and
/// three-quarter points pass the pose check — a fast proxy for the continuous check, good enough
/// to tell the groups apart (e.g. wrist configurations a bar in its cones cannot cross); every
/// move of the final path is still checked continuously.
pub fn components(ck: &Checker, pool: &[[f64; 6]], speeds: &[f64; 6], k: usize) -> Vec<usize> {
    use rayon::prelude::*;
    let n = pool.len();
    let edges: Vec<Vec<usize>> = (0..n)
        .into_par_iter()
        .map(|i| {
            let mut near: Vec<(f64, usize)> = (0..n)
                .filter(|&j| j != i)
                .map(|j| (move_time(&pool[i], &pool[j], speeds), j))
                .collect();
            let kk = k.min(near.len());
            if kk == 0 {
                return Vec::new();
            }
            near.select_nth_unstable_by(kk - 1, |x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
            near[..kk]
                .iter()
                .filter(|&&(_, j)| {
                    [0.25, 0.5, 0.75]
                        .iter()
                        .all(|&s| ck.pose(&super::lerp(&pool[i], &pool[j], s)).is_ok())
                })
                .map(|&(_, j)| j)
                .collect()
        })
        .collect();
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    for (i, js) in edges.iter().enumerate() {
        for &j in js {
            let (a, b) = (find(&mut parent, i), find(&mut parent, j));
            if a != b {
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let roots: Vec<usize> = (0..n).map(|i| find(&mut parent, i)).collect();
    let mut size = vec![0usize; n];
    for &r in &roots {
        size[r] += 1;
    }
    // Roots are each component's smallest member: order by size, then by root.
    let mut order: Vec<usize> = (0..n).filter(|&r| roots[r] == r).collect();
    order.sort_by(|&a, &b| size[b].cmp(&size[a]).then(a.cmp(&b)));
    let mut label = vec![0usize; n];
    for (l, &r) in order.iter().enumerate() {
        label[r] = l;
    }
    roots.iter().map(|&r| label[r]).collect()
}

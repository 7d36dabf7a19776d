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
use rayon::prelude::*;
use std::cmp::Ordering;
use std::collections::{BinaryHeap, HashMap, HashSet};

pub const NEIGHBOURS: usize = 10;
pub const EXPANSIONS: usize = 120;
/// Links per pose of the graph the sections are found in ([`components`]) and the complete
/// search walks ([`route`]): the same graph, so that a section the grouping found connected
/// is connected for the search too.
pub const LINKS: usize = 8;
/// Failed moves after which [`route`] gives up (each costs one search of the graph).
pub const ROUTE_REPAIRS: usize = 400;
/// [`free_route`]: random poses drawn in its first round (the count doubles each round), the
/// rounds, and how far (rad) beyond the box of the move's ends it draws them in the first
/// round (doubling too).
pub const FREE_SAMPLES: usize = 256;
pub const FREE_ROUNDS: usize = 4;
pub const FREE_REACH: f64 = 0.5;

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
        // Min-heap on f, ties by node index, then by parent: a total order, so the search does
        // not depend on the order entries were pushed in (on a grid-built pool the same node is
        // often reached at exactly the same cost from two parents).
        o.f.total_cmp(&self.f)
            .then(o.node.cmp(&self.node))
            .then(o.parent.cmp(&self.parent))
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
    roadmap: &Nearest,
    speeds: &[f64; 6],
    ext: &mut Extremes,
) -> Option<Vec<[f64; 6]>> {
    let pool = roadmap.pool;
    let pos = |n: usize| if n == START { a } else { &pool[n] };
    let h = |n: usize| move_time(pos(n), b, speeds);
    let mut checked: HashMap<(usize, usize), bool> = HashMap::new();
    let mut edge = |u: usize, v: usize, ext: &mut Extremes| -> bool {
        *checked.entry((u, v)).or_insert_with(|| {
            let mut e = Extremes::default();
            let ok = ck.line_passes(pos(u), pos(v), &mut e);
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
    let mut near = Vec::with_capacity(NEIGHBOURS);
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
        if node != START && ck.line_passes(pos(node), b, &mut e) {
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
        roadmap.query(
            here,
            NEIGHBOURS,
            |i| !parent.contains_key(&i) && pool[i] != *here && pool[i] != *b,
            &mut near,
        );
        for &(c, i) in &near {
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

/// A section's pool as a graph: every pose linked to its [`LINKS`] nearest (Eq. 7), both ways
/// (the links [`components`] groups the pool by), each list nearest first (ties by index).
pub struct Graph {
    adj: Vec<Vec<(f64, usize)>>,
}

impl Graph {
    pub fn new(index: &Nearest) -> Self {
        let pool = index.pool;
        let near: Vec<Vec<(f64, usize)>> = (0..pool.len())
            .into_par_iter()
            .map_init(
                || Vec::with_capacity(LINKS),
                |buf, i| {
                    index.query(&pool[i], LINKS, |j| pool[j] != pool[i], buf);
                    buf.clone()
                },
            )
            .collect();
        let mut adj = near.clone();
        for (i, list) in near.iter().enumerate() {
            for &(c, j) in list {
                adj[j].push((c, i));
            }
        }
        for list in &mut adj {
            list.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            list.dedup_by_key(|e| e.1);
        }
        Graph { adj }
    }
}

/// A section's roadmap: the nearest-neighbour index of its pool, and the graph [`route`] walks,
/// built the first time a search needs it (most plans never do).
pub struct Roadmap<'a> {
    pub index: Nearest<'a>,
    graph: std::sync::OnceLock<Graph>,
}

impl<'a> Roadmap<'a> {
    pub fn new(pool: &'a [[f64; 6]], speeds: &[f64; 6]) -> Self {
        Roadmap {
            index: Nearest::new(pool, speeds),
            graph: std::sync::OnceLock::new(),
        }
    }

    pub fn graph(&self) -> &Graph {
        self.graph.get_or_init(|| Graph::new(&self.index))
    }

    /// The pool index of the pose `x`, if it is one of the pool's.
    fn node(&self, x: &[f64; 6]) -> Option<usize> {
        let mut out = Vec::with_capacity(1);
        self.index.query(x, 1, |_| true, &mut out);
        out.first()
            .map(|&(_, i)| i)
            .filter(|&i| self.index.pool[i] == *x)
    }
}

/// Support poses for a → b (both poses of the roadmap's pool) by a complete search of the
/// roadmap's graph, where [`connect`]'s bounded one gives up: the cheapest path of the graph
/// (Eq. 7) is checked move by move from a, a move that fails is taken out and the search
/// repeated (a lazy roadmap), until a path passes; it is then shortened where a direct move
/// skips some of its poses. The sections are the graph's groups of passing links (found with
/// a proxy of the move check, [`components`]), so a and b of one section are joined as a rule;
/// None when no path of passing moves joins them (or after [`ROUTE_REPAIRS`] failed moves).
/// Every verdict is the checker's, so the result is the same on any thread count.
pub fn route(
    ck: &Checker,
    a: &[f64; 6],
    b: &[f64; 6],
    roadmap: &Roadmap,
    speeds: &[f64; 6],
    ext: &mut Extremes,
) -> Option<Vec<[f64; 6]>> {
    let (from, to) = (roadmap.node(a)?, roadmap.node(b)?);
    let graph = roadmap.graph();
    let pool = roadmap.index.pool;
    let mut bad: HashSet<(usize, usize)> = HashSet::new();
    let mut checked: HashMap<(usize, usize), Option<Extremes>> = HashMap::new();
    let mut passes = |u: usize, v: usize| -> bool {
        checked
            .entry((u, v))
            .or_insert_with(|| {
                let mut e = Extremes::default();
                ck.line_passes(&pool[u], &pool[v], &mut e).then_some(e)
            })
            .is_some()
    };
    let mut found = None;
    for _ in 0..ROUTE_REPAIRS {
        let path = cheapest(graph, pool, from, to, speeds, &bad)?;
        match path.windows(2).find(|w| !passes(w[0], w[1])) {
            Some(w) => {
                bad.insert((w[0], w[1]));
            }
            None => {
                found = Some(path);
                break;
            }
        }
    }
    Some(shorten(ck, &found?, pool, &checked, ext))
}

/// Support poses for a move without the bar (a transit between sections) where the direct
/// move fails: a lazy roadmap ([`route`]) of a, b and seeded random poses that pass `ck`'s pose
/// check, drawn where the arm can go without the bar: in the box of a and b widened by
/// [`FREE_REACH`], within the joint limits, on the program's 0.001° grid; each round draws
/// twice as many as the last in a box twice as wide. (The admitted poses are no help here:
/// the sections are the groups they do not join, and mixed with sparse random poses they
/// leave the graph's nearest-neighbour links inside their dense groups.) Deterministic for a
/// given `rng` state on any thread count.
pub fn free_route(
    ck: &Checker,
    a: &[f64; 6],
    b: &[f64; 6],
    speeds: &[f64; 6],
    rng: &mut impl rand::Rng,
    ext: &mut Extremes,
) -> Option<Vec<[f64; 6]>> {
    let (lo, hi) = ck.limits();
    let mut nodes: Vec<[f64; 6]> = vec![*a, *b];
    let (mut count, mut reach) = (FREE_SAMPLES, FREE_REACH);
    for _ in 0..FREE_ROUNDS {
        let draws: Vec<[f64; 6]> = (0..count)
            .map(|_| {
                crate::emit::emitted(&std::array::from_fn(|i| {
                    let (x, y) = (a[i].min(b[i]) - reach, a[i].max(b[i]) + reach);
                    let (x, y) = (x.max(lo[i]), y.min(hi[i]));
                    if x < y {
                        rng.random_range(x..=y)
                    } else {
                        a[i]
                    }
                }))
            })
            .collect();
        let pass: Vec<bool> = draws.par_iter().map(|q| ck.pose(q).is_ok()).collect();
        nodes.extend(
            draws
                .iter()
                .zip(pass)
                .filter(|(q, ok)| *ok && *q != a && *q != b)
                .map(|(q, _)| *q),
        );
        let roadmap = Roadmap::new(&nodes, speeds);
        if let Some(vias) = route(ck, a, b, &roadmap, speeds, ext) {
            return Some(vias);
        }
        count *= 2;
        reach *= 2.0;
    }
    None
}

/// The cheapest path from → to in the graph without the `bad` links (A* with Eq. 7 as cost and
/// admissible heuristic; ties by node index), as node indices from → to.
fn cheapest(
    graph: &Graph,
    pool: &[[f64; 6]],
    from: usize,
    to: usize,
    speeds: &[f64; 6],
    bad: &HashSet<(usize, usize)>,
) -> Option<Vec<usize>> {
    let n = pool.len();
    let mut best = vec![f64::INFINITY; n];
    let mut parent = vec![usize::MAX; n];
    let mut done = vec![false; n];
    let mut open = BinaryHeap::new();
    best[from] = 0.0;
    open.push(Open {
        f: move_time(&pool[from], &pool[to], speeds),
        g: 0.0,
        node: from,
        parent: from,
    });
    while let Some(Open { g, node, .. }) = open.pop() {
        if done[node] {
            continue;
        }
        done[node] = true;
        if node == to {
            let mut path = vec![to];
            let mut k = to;
            while k != from {
                k = parent[k];
                path.push(k);
            }
            path.reverse();
            return Some(path);
        }
        for &(c, v) in &graph.adj[node] {
            let g2 = g + c;
            if done[v] || g2 >= best[v] || bad.contains(&(node, v)) {
                continue;
            }
            best[v] = g2;
            parent[v] = node;
            open.push(Open {
                f: g2 + move_time(&pool[v], &pool[to], speeds),
                g: g2,
                node: v,
                parent: node,
            });
        }
    }
    None
}

/// A checked path made shorter: from each pose, the farthest later pose of the path a direct
/// move reaches (the last, then halfway there, ... : a few tries per pose), else the next.
/// Returns the support poses (the path less its ends) and merges the moves' extremes.
fn shorten(
    ck: &Checker,
    path: &[usize],
    pool: &[[f64; 6]],
    checked: &HashMap<(usize, usize), Option<Extremes>>,
    ext: &mut Extremes,
) -> Vec<[f64; 6]> {
    let last = path.len() - 1;
    let mut vias = Vec::new();
    let mut i = 0;
    while i < last {
        let mut next = i + 1;
        let mut met = checked
            .get(&(path[i], path[i + 1]))
            .cloned()
            .flatten()
            .unwrap_or_default();
        let mut j = last;
        while j > i + 1 {
            let mut e = Extremes::default();
            if ck.line_passes(&pool[path[i]], &pool[path[j]], &mut e) {
                next = j;
                met = e;
                break;
            }
            j = i + 1 + (j - i - 1) / 2;
        }
        ext.merge(&met);
        if next < last {
            vias.push(pool[path[next]]);
        }
        i = next;
    }
    vias
}

/// The groups of pool poses that safe motions connect (with the bar mounted): a component
/// label per pose, labels numbered by size (0 = largest; ties by smallest member index).
/// Poses are linked to their `k` nearest neighbours (Eq. 7) when the move's quarter, middle and
/// three-quarter points pass the pose check — a fast proxy for the continuous check, good enough
/// to tell the groups apart (e.g. wrist configurations a bar in its cones cannot cross); every
/// move of the final path is still checked continuously.
pub fn components(ck: &Checker, pool: &[[f64; 6]], speeds: &[f64; 6], k: usize) -> Vec<usize> {
    components_by(pool, speeds, k, |i, j| {
        [0.25, 0.5, 0.75]
            .iter()
            .all(|&s| ck.pose(&super::lerp(&pool[i], &pool[j], s)).is_ok())
    })
}

/// Edges checked together (in parallel) between the union-find's skips.
const EDGE_BATCH: usize = 256;

/// [`components`] for any link test `passes(i, j)` (called with i < j). The groups are those of
/// the graph of passing k-nearest-neighbour links. Links are taken shortest first, in batches,
/// and a link whose ends are already joined is not tested: it could not change a group. So a
/// well-connected pool costs about one test per pose, not k, and the result is the same on any
/// number of threads.
pub fn components_by(
    pool: &[[f64; 6]],
    speeds: &[f64; 6],
    k: usize,
    passes: impl Fn(usize, usize) -> bool + Sync,
) -> Vec<usize> {
    let n = pool.len();
    let index = Nearest::new(pool, speeds);
    let mut edges: Vec<(f64, usize, usize)> = (0..n)
        .into_par_iter()
        .flat_map_iter(|i| {
            let mut near = Vec::with_capacity(k);
            index.query(&pool[i], k, |j| j != i, &mut near);
            near.into_iter().map(move |(d, j)| (d, i.min(j), i.max(j)))
        })
        .collect();
    edges.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    edges.dedup_by(|a, b| a.1 == b.1 && a.2 == b.2);
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    let mut todo: Vec<(usize, usize)> = Vec::with_capacity(EDGE_BATCH);
    for batch in edges.chunks(EDGE_BATCH) {
        todo.clear();
        for &(_, i, j) in batch {
            if find(&mut parent, i) != find(&mut parent, j) {
                todo.push((i, j));
            }
        }
        let ok: Vec<bool> = todo.par_iter().map(|&(i, j)| passes(i, j)).collect();
        for (&(i, j), ok) in todo.iter().zip(ok) {
            let (a, b) = (find(&mut parent, i), find(&mut parent, j));
            if ok && a != b {
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

/// Exact nearest-neighbour queries in the Eq. 7 metric without scanning the whole pool: the
/// poses sorted along the joint that spreads them most in time; a query walks outwards from
/// its place and stops on a side once that joint alone takes longer than the k-th best so far.
/// The answer is the k smallest (time, index) pairs, exactly as a full sort would give them.
pub struct Nearest<'a> {
    pool: &'a [[f64; 6]],
    speeds: [f64; 6],
    axis: usize,
    /// (coordinate on `axis`, pool index), ascending.
    sorted: Vec<(f64, usize)>,
}

impl<'a> Nearest<'a> {
    /// The poses the queries answer from.
    pub fn pool(&self) -> &'a [[f64; 6]] {
        self.pool
    }

    pub fn new(pool: &'a [[f64; 6]], speeds: &[f64; 6]) -> Self {
        let spread = |i: usize| {
            let (lo, hi) = pool
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), q| {
                    (lo.min(q[i]), hi.max(q[i]))
                });
            (hi - lo) / speeds[i]
        };
        let axis = (0..6)
            .map(|i| (spread(i), i))
            .fold((f64::NEG_INFINITY, 0), |b, c| if c.0 > b.0 { c } else { b })
            .1;
        let mut sorted: Vec<(f64, usize)> =
            pool.iter().enumerate().map(|(i, q)| (q[axis], i)).collect();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        Nearest {
            pool,
            speeds: *speeds,
            axis,
            sorted,
        }
    }

    /// The `k` pool poses nearest to `x` among those `keep` accepts, as (time, index), nearest
    /// first (ties by index), in `out` (cleared first).
    pub fn query(
        &self,
        x: &[f64; 6],
        k: usize,
        keep: impl Fn(usize) -> bool,
        out: &mut Vec<(f64, usize)>,
    ) {
        out.clear();
        if k == 0 {
            return;
        }
        let (ax, w) = (self.axis, self.speeds[self.axis]);
        let start = self.sorted.partition_point(|e| e.0 < x[ax]);
        let (mut down, mut up) = (start, start);
        let worse = |a: &(f64, usize), b: &(f64, usize)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        loop {
            // The nearer side next; a side is done once its joint alone exceeds the k-th best
            // (equal times still count: a lower index may win the tie).
            let bd = (down > 0).then(|| (x[ax] - self.sorted[down - 1].0).abs() / w);
            let bu = (up < self.sorted.len()).then(|| (self.sorted[up].0 - x[ax]).abs() / w);
            let (bound, take_down) = match (bd, bu) {
                (None, None) => break,
                (Some(d), None) => (d, true),
                (None, Some(u)) => (u, false),
                (Some(d), Some(u)) => (d.min(u), d <= u),
            };
            if out.len() == k && bound > out[k - 1].0 {
                break;
            }
            let i = if take_down {
                down -= 1;
                self.sorted[down].1
            } else {
                up += 1;
                self.sorted[up - 1].1
            };
            if !keep(i) {
                continue;
            }
            let c = (move_time(x, &self.pool[i], &self.speeds), i);
            if out.len() == k {
                if worse(&c, &out[k - 1]).is_ge() {
                    continue;
                }
                out.pop();
            }
            let at = out.partition_point(|e| worse(e, &c).is_lt());
            out.insert(at, c);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Pairs of poses tried by the route test below.
    const PAIRS: usize = 16;

    /// The UR5 with its real meshes: pairs of poses of its largest section whose
    /// direct move fails are joined by `route` (all but at most 2 of [`PAIRS`]), through pool
    /// poses, by moves that a checker without the planner's memory passes one by one.
    #[test]
    fn route_joins_poses_of_one_section_by_moves_that_pass() {
        use crate::pipeline;
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../shared/robots/ur5/robot.urdf"
        );
        let robot = crate::robot::load(std::path::Path::new(path), &Default::default())
            .expect("the UR5 in ../shared/robots");
        let fixture = nalgebra::Vector3::new(0.45, 0.2, 0.2);
        let mut opts = pipeline::CompileOptions::new(fixture);
        opts.cell.map = Some(nalgebra::Vector3::new(0.06, 0.03, 0.12));
        let (map, _) = pipeline::resolve_map(&robot, opts.cell.map);
        let cell = pipeline::make_cell(&robot, fixture, map, &opts.cell).unwrap();
        let model = crate::model::MeasurementModel::new(&robot, fixture, map);
        let (scene, _) = pipeline::build_scene(&robot, &opts.cell, &fixture, &map).unwrap();
        let ck = Checker::new(&robot, &model, &cell, &scene, opts.cell.margin);
        let cfg = crate::sample::SampleConfig {
            step: [20f64.to_radians(); 6],
            max_candidates: 2400,
            seed: 1,
            movable: crate::model::movable_joints(&model, &robot),
        };
        let (sampled, _) = crate::sample::run(
            &robot,
            &model,
            &pipeline::inset_cell(&cell),
            &cfg,
            &crate::sample::NoProgress,
        );
        let (kept, _, _) = pipeline::collision_filter(&ck, sampled.candidates, 600);
        let speeds = robot.max_speeds();
        let all: Vec<[f64; 6]> = kept.iter().map(|c| crate::emit::emitted(&c.q)).collect();
        let label = components(&ck, &all, &speeds, LINKS);
        let section: Vec<[f64; 6]> = (0..all.len())
            .filter(|&i| label[i] == 0)
            .map(|i| all[i])
            .collect();
        let memo = crate::safety::LineMemo::default();
        let planner = ck.remembering(&memo);
        let roadmap = Roadmap::new(&section, &speeds);
        let (mut tried, mut joined, mut via_count) = (0, 0, 0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(34);
        while tried < PAIRS {
            let (a, b) = (
                section[rng.random_range(0..section.len())],
                section[rng.random_range(0..section.len())],
            );
            if a == b || ck.line(&a, &b, &mut Extremes::default()).is_ok() {
                continue;
            }
            tried += 1;
            let Some(vias) = route(
                &planner,
                &a,
                &b,
                &roadmap,
                &speeds,
                &mut Extremes::default(),
            ) else {
                continue;
            };
            let chain: Vec<[f64; 6]> = std::iter::once(a)
                .chain(vias.iter().copied())
                .chain(std::iter::once(b))
                .collect();
            for w in chain.windows(2) {
                assert!(
                    ck.line(&w[0], &w[1], &mut Extremes::default()).is_ok(),
                    "{:?} -> {:?}",
                    w[0],
                    w[1]
                );
            }
            assert!(vias.iter().all(|v| section.contains(v)));
            joined += 1;
            via_count += vias.len();
        }
        // The sections are grouped by a proxy of the move check (three poses a move), which
        // can pass a link the continuous check fails: then a pair of one section may have no
        // route, rarely.
        assert!(
            joined >= PAIRS - 2,
            "{joined} of {PAIRS} pairs of one section joined"
        );
        assert!(
            via_count >= joined,
            "{via_count} support poses for {joined} failed moves"
        );
    }

    fn pool(n: usize, seed: u64) -> Vec<[f64; 6]> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        // Coarse values, so that many times tie.
        (0..n)
            .map(|_| std::array::from_fn(|_| rng.random_range(-4i32..=4) as f64 * 0.25))
            .collect()
    }

    fn brute(
        pool: &[[f64; 6]],
        x: &[f64; 6],
        k: usize,
        sp: &[f64; 6],
        keep: impl Fn(usize) -> bool,
    ) -> Vec<(f64, usize)> {
        let mut all: Vec<(f64, usize)> = (0..pool.len())
            .filter(|&i| keep(i))
            .map(|i| (move_time(x, &pool[i], sp), i))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.truncate(k);
        all
    }

    #[test]
    fn nearest_is_the_full_sort_ties_and_exclusions_included() {
        let sp = [2.0, 1.8, 2.2, 3.5, 3.5, 5.0];
        for seed in 0..20 {
            let p = pool(300, seed);
            let index = Nearest::new(&p, &sp);
            let mut out = Vec::new();
            for (i, x) in p.iter().enumerate().step_by(7) {
                for k in [1, 8, 10, 299, 400] {
                    let keep = |j: usize| j != i && j % 5 != 3;
                    index.query(x, k, keep, &mut out);
                    assert_eq!(
                        out,
                        brute(&p, x, k, &sp, keep),
                        "seed {seed} pose {i} k {k}"
                    );
                }
                // A query point off the pool.
                let y = x.map(|v| v + 0.1);
                index.query(&y, 10, |_| true, &mut out);
                assert_eq!(out, brute(&p, &y, 10, &sp, |_| true));
            }
        }
    }

    /// The groups of the graph of every passing k-nearest link, tested in both directions.
    fn components_reference(
        p: &[[f64; 6]],
        sp: &[f64; 6],
        k: usize,
        passes: impl Fn(usize, usize) -> bool,
    ) -> Vec<usize> {
        let n = p.len();
        let mut parent: Vec<usize> = (0..n).collect();
        fn find(p: &mut [usize], mut x: usize) -> usize {
            while p[x] != x {
                x = p[x];
            }
            x
        }
        for i in 0..n {
            for (_, j) in brute(p, &p[i], k, sp, |j| j != i) {
                if passes(i.min(j), i.max(j)) {
                    let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                    parent[a.max(b)] = a.min(b);
                }
            }
        }
        // Label by size, then smallest member.
        let roots: Vec<usize> = (0..n).map(|i| find(&mut parent, i)).collect();
        let mut order: Vec<usize> = (0..n).filter(|&r| roots[r] == r).collect();
        let size = |r: usize| roots.iter().filter(|&&x| x == r).count();
        order.sort_by(|&a, &b| size(b).cmp(&size(a)).then(a.cmp(&b)));
        roots
            .iter()
            .map(|r| order.iter().position(|o| o == r).unwrap_or(usize::MAX))
            .collect()
    }

    #[test]
    fn skipping_links_within_a_group_never_changes_the_groups() {
        let sp = [2.0, 1.8, 2.2, 3.5, 3.5, 5.0];
        for seed in 0..10 {
            let p = pool(400, 100 + seed);
            // Links fail across a "wall" in joint 2 and at random elsewhere.
            let passes = |i: usize, j: usize| {
                let wall = (p[i][1] < 0.0) != (p[j][1] < 0.0);
                let h = (i * 7919 + j * 104_729 + seed as usize) % 10;
                !wall && h < 7
            };
            let got = components_by(&p, &sp, 8, passes);
            let want = components_reference(&p, &sp, 8, passes);
            assert_eq!(got, want, "seed {seed}");
            assert!(got.iter().any(|&l| l > 0), "the wall must split the pool");
            let one = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .build()
                .unwrap()
                .install(|| components_by(&p, &sp, 8, passes));
            assert_eq!(one, got);
        }
    }
}

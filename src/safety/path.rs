//! Path safety: in = measurement poses in tour order and the pool of admitted poses; out = the
//! waypoints actually commanded: every move checked continuously, support poses inserted where a
//! straight joint move fails, poses dropped where no support is found; then ([`blend_corners`])
//! a blend or an exact stop for every corner, by the controller's corner model.

use super::blend::{self, Blend};
use super::roadmap::Roadmap;
use super::{lerp, Checker, Extremes, Violation};
use crate::controller::ControllerMap;
use crate::dialect::{Corner, CornerKind};
use crate::order::move_time;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Waypoint {
    pub q: [f64; 6],
    /// A support pose (a via point inserted for safety), not a measurement pose.
    pub support: bool,
    /// The move into this waypoint is made without the bar (the approach, or a transit to the
    /// next section of the program, where the operator remounts the bar).
    #[serde(default)]
    pub transit: bool,
    /// Blend distance at this corner (m); 0 = exact stop.
    pub blend: f64,
    /// The blend instruction's value the program writes here, in the dialect's unit (its
    /// corner model's: mm for a TCP distance, axis units of path for SINUMERIK's ADIS; 0 where
    /// the instruction takes none).
    #[serde(default)]
    pub blend_value: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dropped {
    /// Index of the pose in the tour.
    pub index: usize,
    pub q: [f64; 6],
    /// Why the move to it failed.
    pub violation: Violation,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    pub waypoints: Vec<Waypoint>,
    pub supports: usize,
    pub dropped: Vec<Dropped>,
    /// Corners where the blend failed its check and the controller stops exactly instead.
    pub exact_stops: usize,
    pub extremes: Extremes,
}

impl Plan {
    /// The first waypoint that repeats the pose before it (a move of zero length), if any.
    /// The planner never makes one: a controller reads it as a move without speed (`F0`, a
    /// zero `\T`), and it measures nothing. The pipeline refuses a plan that has one.
    pub fn repeated_pose(&self) -> Option<usize> {
        (1..self.waypoints.len()).find(|&k| self.waypoints[k].q == self.waypoints[k - 1].q)
    }

    /// Sections of the program: a section starts at a transit's target that is not a support
    /// pose (the bar goes in there).
    pub fn sections(&self) -> usize {
        self.waypoints
            .iter()
            .filter(|w| w.transit && !w.support)
            .count()
    }
}

/// How hard to look for support poses.
pub const PERTURB_TRIES: usize = 32;
pub const MAX_DEPTH: u32 = 3;
pub const INSERT_TRIES: usize = 16;
pub const INSERT_WITH_SUPPORT: usize = 3;
/// Whole turns of a section tried for a transit besides the nearest (`other_turns`).
pub const TURN_TRIES: usize = 8;

pub fn plan(
    ck: &Checker,
    tour: &[[f64; 6]],
    pool: &[[f64; 6]],
    speeds: &[f64; 6],
    seed: u64,
) -> Plan {
    let roadmap = Roadmap::new(pool, speeds);
    // Pass 1: the tour as ordered; a pose that cannot be reached safely (not even through
    // support poses) is deferred, and the tour goes on from where it is. Every leg from one
    // tour pose to the next is independent of the others, so all legs are worked out in
    // parallel first (with their own seeds); a leg is used where the tour does arrive from the
    // previous pose, and worked out again from where it is after a deferred pose.
    let (draft, deferred) = walk_tour(ck, tour, &roadmap, speeds, seed);
    let Draft {
        mut wps,
        mut dropped,
        mut supports,
        mut ext,
    } = draft;
    // Pass 2: insert each deferred pose where both moves around it pass, cheapest place first.
    for (idx, violation) in deferred {
        let q = tour[idx];
        // The roadmap's poses are the pool's, measurement poses included: a chain of support
        // poses may already pass through this pose. It is measured there; inserted next to its
        // twin it would be a zero-length move (the cheapest place by far: it adds nothing).
        if let Some(w) = wps.iter_mut().find(|w| w.support && w.q == q) {
            w.support = false;
            supports -= 1;
            continue;
        }
        if let Some((i, into, out, e)) = cheapest_insertion(ck, &wps, q, &roadmap, speeds) {
            ext.merge(&e);
            supports += into.len() + out.len();
            let mut seq: Vec<Waypoint> = into.into_iter().map(support).collect();
            seq.push(measure(&q));
            seq.extend(out.into_iter().map(support));
            wps.splice(i + 1..i + 1, seq);
        } else {
            dropped.push(Dropped {
                index: idx,
                q,
                violation,
            });
        }
    }
    dropped.sort_by_key(|d| d.index);
    // Trailing support poses lead nowhere.
    while wps.last().is_some_and(|w| w.support) {
        wps.pop();
        supports -= 1;
    }
    let exact_stops = 0;
    let plan = Plan {
        waypoints: wps,
        supports,
        dropped,
        exact_stops,
        extremes: ext,
    };
    debug_assert_eq!(plan.repeated_pose(), None, "a zero-length move in the plan");
    plan
}

/// A measurement pose as a waypoint.
fn measure(q: &[f64; 6]) -> Waypoint {
    Waypoint {
        q: *q,
        support: false,
        transit: false,
        blend: 0.0,
        blend_value: 0.0,
    }
}

/// A support pose as a waypoint.
fn support(v: [f64; 6]) -> Waypoint {
    Waypoint {
        q: v,
        support: true,
        transit: false,
        blend: 0.0,
        blend_value: 0.0,
    }
}

/// A plan in the making: its waypoints, the poses dropped, the support poses and the extremes
/// met.
struct Draft {
    wps: Vec<Waypoint>,
    dropped: Vec<Dropped>,
    supports: usize,
    ext: Extremes,
}

/// Pass 1 of [`plan`]: the tour walked as ordered; returns the draft and the deferred poses
/// (tour index, why).
fn walk_tour(
    ck: &Checker,
    tour: &[[f64; 6]],
    roadmap: &Roadmap,
    speeds: &[f64; 6],
    seed: u64,
) -> (Draft, Vec<(usize, Violation)>) {
    let mut ext = Extremes::default();
    let mut wps: Vec<Waypoint> = Vec::new();
    let mut deferred: Vec<(usize, Violation)> = Vec::new();
    let mut dropped = Vec::new();
    let mut supports = 0;
    let legs: Vec<Leg> = (1..tour.len())
        .into_par_iter()
        .map(|idx| leg(ck, &tour[idx - 1], &tour[idx], roadmap, speeds, seed, idx))
        .collect();
    // Where a leg fails, its pose is deferred and the tour goes on from the pose before it: those
    // legs too are worked out in parallel beforehand (the same function of the same poses and
    // seed, so the walk below comes out as if it had made them itself).
    let skips: Vec<Option<Leg>> = (1..tour.len())
        .into_par_iter()
        .map(|idx| {
            (idx + 1 < tour.len() && legs[idx - 1].is_err()).then(|| {
                leg(
                    ck,
                    &tour[idx - 1],
                    &tour[idx + 1],
                    roadmap,
                    speeds,
                    seed,
                    idx + 1,
                )
            })
        })
        .collect();
    for (idx, q) in tour.iter().enumerate() {
        let Some(last) = wps.last().map(|w| w.q) else {
            match ck.pose(q) {
                Ok(info) => {
                    ext.add(&info);
                    wps.push(measure(q));
                }
                Err(v) => dropped.push(Dropped {
                    index: idx,
                    q: *q,
                    violation: v,
                }),
            }
            continue;
        };
        let fresh;
        let l = if last == tour[idx - 1] {
            &legs[idx - 1]
        } else if let Some(Some(skip)) =
            (idx >= 2 && last == tour[idx - 2]).then(|| &skips[idx - 2])
        {
            skip
        } else {
            fresh = leg(ck, &last, q, roadmap, speeds, seed, idx);
            &fresh
        };
        match l {
            Ok((vias, e)) => {
                ext.merge(e);
                supports += vias.len();
                wps.extend(vias.iter().map(|&v| support(v)));
                wps.push(measure(q));
            }
            Err(violation) => deferred.push((idx, violation.clone())),
        }
    }
    let draft = Draft {
        wps,
        dropped,
        supports,
        ext,
    };
    (draft, deferred)
}

/// Where deferred pose `q` goes in: the cheapest of the places (after waypoint i) where both
/// moves around it pass, with the support poses into and out of it and the extremes met.
#[allow(clippy::type_complexity)]
fn cheapest_insertion(
    ck: &Checker,
    wps: &[Waypoint],
    q: [f64; 6],
    roadmap: &Roadmap,
    speeds: &[f64; 6],
) -> Option<(usize, Vec<[f64; 6]>, Vec<[f64; 6]>, Extremes)> {
    let mut places: Vec<(f64, usize)> = (0..wps.len())
        // Never next to a waypoint at the same pose (none is left, but a move of zero
        // length must not be made whatever the plan holds).
        .filter(|&i| wps[i].q != q && wps.get(i + 1).is_none_or(|b| b.q != q))
        .map(|i| {
            let a = &wps[i].q;
            let added = match wps.get(i + 1) {
                Some(b) => {
                    move_time(a, &q, speeds) + move_time(&q, &b.q, speeds)
                        - move_time(a, &b.q, speeds)
                }
                None => move_time(a, &q, speeds),
            };
            (added, i)
        })
        .collect();
    places.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
    places.truncate(INSERT_TRIES);
    // The places are tried in parallel; the first that works, in rank order, is taken.
    let attempt = |(rank, &(_, i)): (usize, &(f64, usize))| {
        let mut e = Extremes::default();
        let a = wps[i].q;
        let b = wps.get(i + 1).map(|w| w.q);
        // Direct moves first; for the cheapest places also chains through the roadmap.
        let into = if ck.line(&a, &q, &mut e).is_ok() {
            Some(Vec::new())
        } else if rank < INSERT_WITH_SUPPORT {
            super::roadmap::connect(ck, &a, &q, &roadmap.index, speeds, &mut e)
        } else {
            None
        }?;
        let out = match b {
            None => Some(Vec::new()),
            Some(b) if ck.line(&q, &b, &mut e).is_ok() => Some(Vec::new()),
            Some(b) if rank < INSERT_WITH_SUPPORT => {
                super::roadmap::connect(ck, &q, &b, &roadmap.index, speeds, &mut e)
            }
            Some(_) => None,
        }?;
        Some((i, into, out, e))
    };
    places
        .par_iter()
        .enumerate()
        .map(attempt)
        .find_first(Option::is_some)
        .flatten()
}

/// A leg of the tour: its support poses (none for a direct move) and the extremes met, or why
/// the direct move failed when no support was found.
type Leg = Result<(Vec<[f64; 6]>, Extremes), Violation>;

/// The move a → b of tour leg `idx`: direct when it passes, else through support poses found
/// with the leg's own seed.
fn leg(
    ck: &Checker,
    a: &[f64; 6],
    b: &[f64; 6],
    roadmap: &Roadmap,
    speeds: &[f64; 6],
    seed: u64,
    idx: usize,
) -> Leg {
    let mut e = Extremes::default();
    match ck.line(a, b, &mut e) {
        Ok(()) => Ok((Vec::new(), e)),
        Err((_, violation)) => {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(
                seed ^ (idx as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15),
            );
            let mut e = Extremes::default();
            match find_support(ck, a, b, roadmap, speeds, &mut rng, MAX_DEPTH, &mut e) {
                Some(vias) => Ok((vias, e)),
                None => Err(violation),
            }
        }
    }
}

/// One section: the measurement poses in tour order and the admitted poses of its component
/// (for support poses).
pub struct Section {
    pub tour: Vec<[f64; 6]>,
    pub pool: Vec<[f64; 6]>,
}

/// Plans every section (bar mounted) and the transits between them (bar removed, `transit`).
/// A section whose transit cannot be made safe is dropped whole.
pub fn plan_sections(ck: &Checker, sections: &[Section], speeds: &[f64; 6], seed: u64) -> Plan {
    let free = ck.unmounted();
    let mut out = Plan {
        waypoints: Vec::new(),
        supports: 0,
        dropped: Vec::new(),
        exact_stops: 0,
        extremes: Extremes::default(),
    };
    let mut offset = 0;
    for (k, sec) in sections.iter().enumerate() {
        let mut p = plan(ck, &sec.tour, &sec.pool, speeds, seed ^ k as u64);
        for d in &mut p.dropped {
            d.index += offset;
        }
        offset += sec.tour.len();
        if p.waypoints.is_empty() {
            out.dropped.append(&mut p.dropped);
            continue;
        }
        // The transit from the previous section, without the bar.
        let mut vias: Vec<[f64; 6]> = Vec::new();
        if let Some(last) = out.waypoints.last().map(|w| w.q) {
            let mut rng =
                rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x0074_7261_6e73_6974 ^ k as u64);
            let planned = |tour: &[[f64; 6]], pool: &[[f64; 6]]| {
                let mut p = plan(ck, tour, pool, speeds, seed ^ k as u64);
                for d in &mut p.dropped {
                    d.index += offset - sec.tour.len();
                }
                p
            };
            match transit(&free, &last, sec, p, speeds, &mut rng, planned) {
                Ok((v, section)) => {
                    vias = v;
                    p = section;
                }
                Err(v) => {
                    // Every pose of the section goes with it (not only its first).
                    let first = offset - sec.tour.len();
                    out.dropped
                        .extend(sec.tour.iter().enumerate().map(|(k, q)| Dropped {
                            index: first + k,
                            q: *q,
                            violation: v.clone(),
                        }));
                    continue;
                }
            }
        }
        out.supports += vias.len() + p.supports;
        out.waypoints.extend(vias.into_iter().map(|q| Waypoint {
            q,
            support: true,
            transit: true,
            blend: 0.0,
            blend_value: 0.0,
        }));
        p.waypoints[0].transit = true;
        out.waypoints.append(&mut p.waypoints);
        out.dropped.append(&mut p.dropped);
        out.exact_stops += p.exact_stops;
        out.extremes.merge(&p.extremes);
    }
    out
}

/// The move without the bar from `last` into a section planned as `p` (its first waypoint):
/// direct; else, for joints that turn a whole turn or more, the section's poses turned by
/// whole turns where that shortens the move (the same poses of the arm: a wrist that would
/// turn 310° one way through its own forearm turns 50° the other way), the section planned
/// again (`planned`); else the first of the other whole turns ([`other_turns`], nearest first)
/// whose direct move passes; else through a roadmap of poses the arm reaches without the bar
/// ([`super::roadmap::free_route`]); else through perturbed midpoints. Returns the support
/// poses and the section's plan, or the direct move's violation. Dropped poses keep the
/// values of `sec`.
fn transit(
    free: &Checker,
    last: &[f64; 6],
    sec: &Section,
    p: Plan,
    speeds: &[f64; 6],
    rng: &mut rand_chacha::ChaCha8Rng,
    planned: impl Fn(&[[f64; 6]], &[[f64; 6]]) -> Plan,
) -> Result<(Vec<[f64; 6]>, Plan), Violation> {
    let first = p.waypoints[0].q;
    let mut e = Extremes::default();
    let Err((_, violation)) = free.line(last, &first, &mut e) else {
        return Ok((Vec::new(), p));
    };
    let mut candidates = vec![p];
    let (lo, hi) = free.limits();
    if let Some(turn) = whole_turns((&lo, &hi), last, &first, &sec.tour) {
        let turned = |qs: &[[f64; 6]]| -> Vec<[f64; 6]> {
            qs.iter()
                .map(|q| crate::emit::emitted(&std::array::from_fn(|i| q[i] + turn[i])))
                .collect()
        };
        let mut t = planned(&turned(&sec.tour), &turned(&sec.pool));
        // Only if it measures as much (a harness limit may hold a turned joint).
        if !t.waypoints.is_empty() && t.dropped.len() <= candidates[0].dropped.len() {
            // Dropped poses are named as the section holds them.
            for d in &mut t.dropped {
                d.q = crate::emit::emitted(&std::array::from_fn(|i| d.q[i] - turn[i]));
            }
            candidates.insert(0, t);
        }
    }
    // The turned section's direct move (the section's as planned failed above).
    if candidates.len() > 1
        && free
            .line(last, &candidates[0].waypoints[0].q, &mut e)
            .is_ok()
    {
        return Ok((Vec::new(), candidates.swap_remove(0)));
    }
    // Other whole turns, nearest first: where a wrist turns about 180°, the nearest way round
    // may sweep the tool through the forearm and the other way be free.
    let nearest = whole_turns((&lo, &hi), last, &first, &sec.tour);
    for turn in other_turns((&lo, &hi), last, &first, &sec.tour, speeds, nearest) {
        let turned = |qs: &[[f64; 6]]| -> Vec<[f64; 6]> {
            qs.iter()
                .map(|q| crate::emit::emitted(&std::array::from_fn(|i| q[i] + turn[i])))
                .collect()
        };
        let to = turned(std::slice::from_ref(&first))[0];
        if free.line(last, &to, &mut Extremes::default()).is_err() {
            continue;
        }
        let mut t = planned(&turned(&sec.tour), &turned(&sec.pool));
        let measures = !t.waypoints.is_empty()
            && t.dropped.len() <= candidates.last().map_or(0, |c| c.dropped.len());
        if measures
            && (t.waypoints[0].q == to
                || free
                    .line(last, &t.waypoints[0].q, &mut Extremes::default())
                    .is_ok())
        {
            for d in &mut t.dropped {
                d.q = crate::emit::emitted(&std::array::from_fn(|i| d.q[i] - turn[i]));
            }
            return Ok((Vec::new(), t));
        }
    }
    for k in 0..candidates.len() {
        let to = candidates[k].waypoints[0].q;
        let mut e = Extremes::default();
        if let Some(vias) = super::roadmap::free_route(free, last, &to, speeds, rng, &mut e) {
            return Ok((vias, candidates.swap_remove(k)));
        }
    }
    let p = candidates.pop().expect("the section as planned");
    let mut e = Extremes::default();
    find_support(
        free,
        last,
        &first,
        &Roadmap::new(&[], speeds),
        speeds,
        rng,
        MAX_DEPTH,
        &mut e,
    )
    .map(|vias| (vias, p))
    .ok_or(violation)
}

/// Whole turns (±2π per joint, 0 where none) that bring a section's poses `tour` (its first:
/// `first`) nearest to `last`, joint by joint, keeping every pose within the joint range
/// [lo, hi]; None when no joint turns.
fn whole_turns(
    (lo, hi): (&[f64; 6], &[f64; 6]),
    last: &[f64; 6],
    first: &[f64; 6],
    tour: &[[f64; 6]],
) -> Option<[f64; 6]> {
    let tau = std::f64::consts::TAU;
    let turn: [f64; 6] = std::array::from_fn(|i| {
        [-tau, tau]
            .into_iter()
            .filter(|t| tour.iter().all(|q| q[i] + t >= lo[i] && q[i] + t <= hi[i]))
            .map(|t| ((first[i] + t - last[i]).abs(), t))
            .fold(((first[i] - last[i]).abs(), 0.0), |b, c| {
                if c.0 < b.0 {
                    c
                } else {
                    b
                }
            })
            .1
    });
    turn.iter().any(|&t| t != 0.0).then_some(turn)
}

/// Whole turns other than `nearest` (and none) that keep a section's poses `tour` within the
/// joint range [lo, hi], by the time of the move from `last` to its turned first pose (Eq. 7;
/// ties by the sum of the joints' times, then in a fixed order): at most [`TURN_TRIES`].
fn other_turns(
    (lo, hi): (&[f64; 6], &[f64; 6]),
    last: &[f64; 6],
    first: &[f64; 6],
    tour: &[[f64; 6]],
    speeds: &[f64; 6],
    nearest: Option<[f64; 6]>,
) -> Vec<[f64; 6]> {
    let tau = std::f64::consts::TAU;
    let allowed: Vec<Vec<f64>> = (0..6)
        .map(|i| {
            [0.0, -tau, tau]
                .into_iter()
                .filter(|t| tour.iter().all(|q| q[i] + t >= lo[i] && q[i] + t <= hi[i]))
                .collect()
        })
        .collect();
    let mut combos: Vec<[f64; 6]> = vec![[0.0; 6]];
    for (i, ts) in allowed.iter().enumerate() {
        combos = combos
            .iter()
            .flat_map(|c| {
                ts.iter().map(move |&t| {
                    let mut c = *c;
                    c[i] = t;
                    c
                })
            })
            .collect();
    }
    let cost = |turn: &[f64; 6]| -> (f64, f64) {
        let t: [f64; 6] = std::array::from_fn(|i| (first[i] + turn[i] - last[i]).abs() / speeds[i]);
        (t.iter().fold(0.0, |m: f64, &x| m.max(x)), t.iter().sum())
    };
    let mut keyed: Vec<((f64, f64), usize, [f64; 6])> = combos
        .into_iter()
        .enumerate()
        .filter(|(_, c)| c.iter().any(|&t| t != 0.0) && Some(*c) != nearest)
        .map(|(k, c)| (cost(&c), k, c))
        .collect();
    keyed.sort_by(|a, b| {
        a.0 .0
            .total_cmp(&b.0 .0)
            .then(a.0 .1.total_cmp(&b.0 .1))
            .then(a.1.cmp(&b.1))
    });
    keyed.into_iter().take(TURN_TRIES).map(|k| k.2).collect()
}

/// What [`blend_corners`] blends by: the controller's corner model, the blend distance at the
/// MAP and the controller mapping (axis-path lengths are measured on the controller's axes).
pub struct CornerSpec<'a> {
    pub corner: &'a Corner,
    /// Blend distance at the MAP (m); 0 = exact stops everywhere.
    pub distance: f64,
    pub map: &'a ControllerMap,
}

/// A corner region larger than this many grid poses is not tried: an exact stop costs less than
/// proving it (a corner region spans up to half of two moves where the controller's blend
/// instruction bounds only some axes).
pub const PATCH_BUDGET: usize = 2500;

/// Decides every corner of the plan: a blend where the corner region a controller following
/// the dialect's documentation may execute is proven safe (and, at a measurement pose, its ends
/// keep the MAP within the blend distance of the pose), else an exact stop. Corners are checked
/// in parallel and taken in order. Resets what an earlier call decided.
pub fn blend_corners(ck: &Checker, plan: &mut Plan, spec: &CornerSpec) {
    let wps = &mut plan.waypoints;
    for w in wps.iter_mut() {
        w.blend = 0.0;
        w.blend_value = 0.0;
    }
    plan.exact_stops = 0;
    if spec.distance <= 0.0 || wps.len() < 3 {
        return;
    }
    let n = wps.len();
    let decided: Vec<Option<(f64, Extremes)>> = (1..n - 1)
        .into_par_iter()
        .map(|k| {
            // A blend joins two moves made with the bar: not across a pause.
            if wps[k].transit || wps[k + 1].transit {
                return None;
            }
            let (a, q, b) = (&wps[k - 1].q, &wps[k].q, &wps[k + 1].q);
            corner_blend(ck, spec, a, q, b, !wps[k].support)
        })
        .collect();
    for (k, d) in (1..).zip(decided) {
        let eligible = !wps[k].transit && !wps[k + 1].transit;
        match d {
            Some((value, e)) => {
                plan.extremes.merge(&e);
                wps[k].blend = spec.distance;
                wps[k].blend_value = value;
            }
            None if eligible => plan.exact_stops += 1,
            None => {}
        }
    }
}

/// The blend value for the corner a → q → b and the extremes its region met, or None for an
/// exact stop.
fn corner_blend(
    ck: &Checker,
    spec: &CornerSpec,
    a: &[f64; 6],
    q: &[f64; 6],
    b: &[f64; 6],
    measured: bool,
) -> Option<(f64, Extremes)> {
    let d_mm = crate::units::to_mm(spec.distance);
    let axes = |x: &[f64; 6]| {
        spec.map
            .apply(&crate::emit::emitted(x).map(crate::units::to_deg))
    };
    let len = |x: &[f64; 6], y: &[f64; 6]| {
        let (x, y) = (axes(x), axes(y));
        (0..6).map(|i| (x[i] - y[i]).powi(2)).sum::<f64>().sqrt()
    };
    let axis_len = (len(a, q), len(q, b));
    let kind = spec.corner.kind;
    let value = match kind {
        CornerKind::Unbounded => return None,
        CornerKind::Moves => 0.0,
        CornerKind::TcpDistance if spec.corner.tolerance > 0.0 => {
            // The value whose enlarged zone (ABB: up to 10 % more) is still the blend distance,
            // rounded down to what the program prints.
            let v = (d_mm / (1.0 + spec.corner.tolerance) * 1e3 * (1.0 - 1e-12)).floor() / 1e3;
            if v <= 0.0 {
                return None;
            }
            v
        }
        CornerKind::TcpDistance => d_mm,
        CornerKind::AxisPath => {
            // The axis-path distance whose ends stay within the blend distance at the MAP,
            // rounded down to what the program prints. The compiler keeps it within half of
            // each move (a controller may take more where the value allows: SINUMERIK limits
            // the rounding only by the block), so that the two roundings of a move never
            // compete for it and the controller's own reductions only shrink the region.
            let tcp = Corner {
                kind: CornerKind::TcpDistance,
                cap: spec.corner.cap.min(0.5),
                tolerance: 0.0,
                ..spec.corner.clone()
            };
            let r = blend::region(ck, &tcp, None, a, q, b, d_mm, axis_len).ok()?;
            let v = (r.s_in * axis_len.0).min(r.s_out * axis_len.1);
            let v = (v * 1e3 * (1.0 - 1e-12)).floor() / 1e3;
            if v <= 0.0 {
                return None;
            }
            v
        }
    };
    let r = blend::region(ck, spec.corner, None, a, q, b, value, axis_len).ok()?;
    // At a measurement pose the path must pass the pose within the blend distance: it runs
    // through the blend's ends (a TCP-distance blend begins within the distance by definition).
    if measured
        && kind != CornerKind::TcpDistance
        && blend::end_distance(ck, &r) > spec.distance * (1.0 + 1e-9)
    {
        return None;
    }
    let (e1, e2) = r.edges();
    let (n1, n2) = ck.patch_grid(&e1, &e2);
    if (n1 + 1) * (n2 + 1) > PATCH_BUDGET {
        return None;
    }
    let mut e = Extremes::default();
    ck.patch(&r.corner, &e1, &e2, &mut e).ok()?;
    Some((value, e))
}

pub fn check_blend(ck: &Checker, b: &Blend, ext: &mut Extremes) -> Result<(), (f64, Violation)> {
    ck.curve(&|t| b.point(t), &b.lipschitz(), ext)
}

/// Via points that make a → b safe: first a chain through the roadmap of admitted pool poses
/// ([`super::roadmap::connect`], a bounded search), then the complete search of the roadmap's
/// graph ([`super::roadmap::route`]: a and b of one section are joined as a rule), then
/// perturbed midpoints, recursively on the half that still fails.
#[allow(clippy::too_many_arguments)]
fn find_support(
    ck: &Checker,
    a: &[f64; 6],
    b: &[f64; 6],
    roadmap: &Roadmap,
    speeds: &[f64; 6],
    rng: &mut impl Rng,
    depth: u32,
    ext: &mut Extremes,
) -> Option<Vec<[f64; 6]>> {
    if depth == 0 {
        return None;
    }
    if depth == MAX_DEPTH {
        if let Some(vias) = super::roadmap::connect(ck, a, b, &roadmap.index, speeds, ext) {
            return Some(vias);
        }
        if let Some(vias) = super::roadmap::route(ck, a, b, roadmap, speeds, ext) {
            return Some(vias);
        }
    }
    let (lo, hi) = ck.limits();
    for attempt in 0..PERTURB_TRIES {
        // Growing perturbations around the midpoint, mostly in the arm joints.
        let scale = 0.15 + 0.6 * attempt as f64 / PERTURB_TRIES as f64;
        let mid = lerp(a, b, 0.5);
        let m: [f64; 6] = std::array::from_fn(|i| {
            (mid[i] + rng.random_range(-scale..=scale)).clamp(lo[i], hi[i])
        });
        // Exactly as the program will carry it.
        let m = crate::emit::emitted(&m);
        if ck.pose(&m).is_err() {
            continue;
        }
        let mut e = Extremes::default();
        if ck.line(a, &m, &mut e).is_err() {
            continue;
        }
        if ck.line(&m, b, &mut e).is_ok() {
            ext.merge(&e);
            return Some(vec![m]);
        }
        if let Some(mut rest) = find_support(ck, &m, b, roadmap, speeds, rng, depth - 1, &mut e) {
            ext.merge(&e);
            let mut out = vec![m];
            out.append(&mut rest);
            return Some(out);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_section_turns_by_whole_turns_only_where_that_is_nearer_and_stays_in_range() {
        let d = |v: f64| v.to_radians();
        let lo = [
            d(-359.0),
            d(-359.0),
            d(-179.0),
            d(-359.0),
            d(-359.0),
            d(-359.0),
        ];
        let hi = lo.map(|v| -v);
        // Wrist 1 from -140 to 170 deg: -190 is 50 deg away, 170 is 310; the elbow cannot turn.
        let last = [d(-180.0), d(-160.0), d(100.0), d(-140.0), d(90.0), 0.0];
        let first = [d(-110.0), d(-120.0), d(-10.0), d(170.0), d(70.0), d(40.0)];
        let tour = vec![
            first,
            [d(-100.0), d(-110.0), d(-20.0), d(150.0), d(60.0), d(30.0)],
        ];
        let turn = whole_turns((&lo, &hi), &last, &first, &tour).expect("wrist 1 turns");
        assert_eq!(
            turn.map(|t| t.to_degrees().round()),
            [0.0, 0.0, 0.0, -360.0, 0.0, 0.0]
        );
        // Not where a pose of the section would leave the range: one at -170 deg cannot go to
        // -530.
        let mut wide = tour.clone();
        wide.push([d(-100.0), d(-110.0), d(-20.0), d(-170.0), d(60.0), d(30.0)]);
        assert_eq!(whole_turns((&lo, &hi), &last, &first, &wide), None);
        // Nothing to turn when every joint is nearest already.
        assert_eq!(whole_turns((&lo, &hi), &first, &tour[1], &tour), None);
    }

    #[test]
    fn other_turns_come_nearest_first_without_the_nearest_and_stay_in_range() {
        let d = |v: f64| v.to_radians();
        let lo = [
            d(-359.0),
            d(-359.0),
            d(-179.0),
            d(-359.0),
            d(-359.0),
            d(-359.0),
        ];
        let hi = lo.map(|v| -v);
        let speeds = [1.0; 6];
        // Wrist 1 from -10 to 170 deg: 180 deg either way round; wrist 2 200 deg the short way.
        let last = [d(80.0), d(-20.0), d(-90.0), d(-10.0), d(-150.0), d(160.0)];
        let first = [d(-90.0), d(-140.0), d(60.0), d(170.0), d(50.0), d(30.0)];
        let tour = vec![first];
        let nearest = whole_turns((&lo, &hi), &last, &first, &tour);
        let turns = other_turns((&lo, &hi), &last, &first, &tour, &speeds, nearest);
        assert_eq!(turns.len(), TURN_TRIES);
        let deg = |t: &[f64; 6]| t.map(|x| x.to_degrees().round());
        assert!(turns
            .iter()
            .all(|t| Some(*t) != nearest && t.iter().any(|&x| x != 0.0)));
        // The elbow never turns (its range is one turn), every turned pose stays in range.
        for t in &turns {
            assert_eq!(t[2], 0.0);
            assert!((0..6).all(|i| first[i] + t[i] >= lo[i] && first[i] + t[i] <= hi[i]));
        }
        // Nearest first: the move's slowest joint, then the sum, never decreasing.
        let cost = |t: &[f64; 6]| -> (f64, f64) {
            let x: Vec<f64> = (0..6).map(|i| (first[i] + t[i] - last[i]).abs()).collect();
            (x.iter().fold(0.0, |m: f64, &v| m.max(v)), x.iter().sum())
        };
        for w in turns.windows(2) {
            let (a, b) = (cost(&w[0]), cost(&w[1]));
            assert!(
                a.0 < b.0 || (a.0 == b.0 && a.1 <= b.1),
                "{:?} before {:?}",
                deg(&w[0]),
                deg(&w[1])
            );
        }
        // Wrist 1's other way round is among them, at the same cost as the nearest.
        let nearest = nearest.expect("wrist 2 turns");
        let mut other = nearest;
        other[3] = if nearest[3] == 0.0 {
            -std::f64::consts::TAU
        } else {
            0.0
        };
        assert_eq!(turns[0], other, "{:?}", deg(&turns[0]));
    }
}

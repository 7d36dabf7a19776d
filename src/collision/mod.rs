//! Collision geometry of the cell: in = a [`Robot`] (its link shapes), a [`CellSpec`] (tool,
//! hoses, floor, environment, fixture stand), the fixture and the MAP; out = an immutable
//! [`Scene`] plus a [`SceneReport`] of the bodies and of the pairs that are not checked, and why.
//! Queries take the chain frames of one pose and answer "is any checked pair closer than the
//! margin?" ([`Scene::violation`]) or "what is the smallest clearance?" ([`Scene::clearance`]).
//!
//! This is the only module that imports parry; nothing of parry appears in its public API.
//!
//! **Meshes become convex hulls**, never BVH triangle meshes. A hull contains the mesh, so a
//! clearance measured on hulls is never larger than the true one (conservative), and GJK on a
//! hull is a handful of support-point iterations. A triangle mesh against a triangle mesh is a
//! BVH traversal with many triangle–triangle tests (one to two orders of magnitude slower here),
//! and it only sees surfaces: a thin wall or a body entirely inside another is not a contact.
//! The price is that concave links (a C-shaped housing) are fattened; the clearance lost is
//! small next to the safety margin for industrial-arm link shapes.
//!
//! **Bodies** live in one of: a DH frame 0..=7 (links, tool, MAP ball, hoses), a passive link
//! (a balancing cylinder or linkage moved by mimic joints, placed from q per query), the world
//! (= the robot base frame: floor, environment, fixture ball, stand) or the bar (rebuilt per
//! query between the two balls). Each body is a list of convex parts, each with a bounding
//! sphere.
//!
//! **Pairs** (see [`build`]): a passive link against everything except the body its joint
//! connects it to; robot bodies against each other, except bodies rigid with the same
//! frame (frame 7, the flange, is rigid with frame 6), link i against link i ± 1, and pairs that
//! are already within the margin at q = 0; robot bodies against world bodies, except the base
//! (link 0) and the floor; the bar against links, hoses and world bodies, except the tool, the
//! MAP ball, the fixture ball and the stand. Every excluded pair is listed with its reason.

mod hull;
mod mesh;
#[cfg(test)]
mod tests;

use crate::cell::{CellSpec, ShapeKind};
use crate::robot::kinematics::chain_frames;
use crate::robot::{Frame, Geometry, PassiveLink, PassiveMotion, Robot};
use hull::Hull;
use nalgebra::{Isometry3, Point3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3};
use parry3d_f64::query::gjk::{GJKResult, VoronoiSimplex};
use parry3d_f64::query::{self, details, ClosestPoints};
use parry3d_f64::shape::{
    Ball, Capsule, ConvexPolyhedron, Cuboid, Cylinder, HalfSpace, Shape, SharedShape, SupportMap,
};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Name of the bar in contacts and reports.
pub const BAR: &str = "bar";
/// Name of the floor body.
pub const FLOOR: &str = "floor";
/// Name of the ball at the MAP (diameter = the cell's ball).
pub const MAP_BALL: &str = "MAP ball";
/// Name of the ball at the fixture.
pub const FIXTURE_BALL: &str = "fixture ball";
/// Name of the fixture stand.
pub const STAND: &str = "fixture stand";
/// Name of the body made of the cell's tool shapes.
pub const TOOL: &str = "tool";

/// Automatic link capsules (DH robots without geometry): radius = this × the longest link
/// (√(a² + d²)), clamped to [`AUTO_RADIUS_MIN`, `AUTO_RADIUS_MAX`], unless the cell gives
/// `robot.link_radius`. 0.08 × 0.86 m ≈ 69 mm for the NJ-130: a thin arm; give the real
/// radius in the cell file when it matters.
pub const AUTO_RADIUS_FACTOR: f64 = 0.08;
pub const AUTO_RADIUS_MIN: f64 = 0.050;
pub const AUTO_RADIUS_MAX: f64 = 0.150;

/// The collision world of one cell: immutable and `Sync`, built once, shared by rayon threads.
/// Cloning is cheap (shapes and hulls are shared): [`Scene::with_fixture`] moves the fixture
/// of a clone without reading a mesh again.
#[derive(Clone)]
pub struct Scene {
    bodies: Vec<Body>,
    /// The robot's passive links, placed per query from q.
    passive: Vec<PassiveLink>,
    /// Checked body pairs, by index into `bodies`, in build order.
    pairs: Vec<(usize, usize)>,
    /// Bodies checked against the bar.
    bar_pairs: Vec<usize>,
    fixture: Vector3<f64>,
    bar_radius: f64,
    ball_radius: f64,
    sweep: [f64; 6],
    /// Per checked pair (`pairs`, then `bar_pairs`), per joint: how fast the pair's distance
    /// can change per radian of the joint (m/rad), for [`Scene::violation_along`].
    rates: Vec<[f64; 6]>,
}

/// What [`build`] made: the bodies, how many pairs are checked, and the pairs that are not.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneReport {
    pub bodies: Vec<String>,
    pub pairs_checked: usize,
    pub excluded: Vec<ExcludedPair>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExcludedPair {
    pub a: String,
    pub b: String,
    pub reason: String,
}

/// The distance between two named bodies (m; negative = penetration depth).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Contact {
    pub distance: f64,
    pub a: String,
    pub b: String,
}

#[derive(Debug, thiserror::Error)]
pub enum CollisionError {
    #[error("{path}: cannot read mesh: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {msg}")]
    Mesh { path: String, msg: String },
    #[error("{body}: {msg}")]
    Shape { body: String, msg: String },
    #[error("{a} vs {b}: no distance query for this pair of shapes")]
    Unsupported { a: String, b: String },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Attach {
    /// DH frame 0..=7 of `chain_frames`.
    Frame(usize),
    /// A passive link (index into `Scene::passive`): its pose follows q through mimic joints.
    Passive(usize),
    World,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Role {
    Link,
    /// A link off the chain moved by mimic joints (a balancing cylinder, a linkage).
    Passive,
    Tool,
    MapBall,
    Hose,
    Environment,
    Floor,
    FixtureBall,
    Stand,
}

/// One convex piece of a body, placed in the body's frame.
#[derive(Clone)]
struct Part {
    shape: SharedShape,
    /// Meshes: the same hull with a fast support function, used by every query (shared by
    /// clones of the scene).
    hull: Option<std::sync::Arc<Hull>>,
    local: Isometry3<f64>,
    /// Bounding sphere in the body frame (for the floor: a point on the plane, radius 0).
    center: Point3<f64>,
    radius: f64,
    /// The floor half-space: its "sphere" test is a height test.
    plane: bool,
}

#[derive(Clone)]
struct Body {
    name: String,
    attach: Attach,
    role: Role,
    parts: Vec<Part>,
    center: Point3<f64>,
    radius: f64,
    plane: bool,
}

/// A part or a bounding sphere in world coordinates, ready for a query.
struct Placed<'a> {
    shape: &'a dyn Shape,
    hull: Option<&'a Hull>,
    iso: Isometry3<f64>,
    center: Point3<f64>,
    radius: f64,
    plane: bool,
}

impl<'a> Placed<'a> {
    /// The bar capsule (world coordinates) with its bounding radius.
    fn bar(cap: &'a Capsule, radius: f64) -> Self {
        Placed {
            shape: cap,
            hull: None,
            iso: Isometry3::identity(),
            center: nalgebra::center(&cap.segment.a, &cap.segment.b),
            radius,
            plane: false,
        }
    }
}

/// A lower bound on the distance between two bounding spheres (or a sphere and the floor).
#[inline]
fn gap(ac: &Point3<f64>, ar: f64, ap: bool, bc: &Point3<f64>, br: f64, bp: bool) -> f64 {
    match (ap, bp) {
        (false, false) => (ac - bc).norm() - ar - br,
        (true, false) => bc.z - br - ac.z,
        (false, true) => ac.z - ar - bc.z,
        (true, true) => f64::NEG_INFINITY,
    }
}

/// A distance no cell reaches (m): the limit of an unlimited query.
const FAR: f64 = 1e6;

#[derive(Clone, Copy, PartialEq, Eq)]
enum Mode {
    /// Any part pair closer than the limit: return its distance at once.
    Filter,
    /// The smallest distance below the limit.
    Min,
}

/// The signed distance of two parts when it is below `limit`, else None. A pair parry cannot
/// handle counts as touching (conservative; [`build`] has already rejected such shape types).
#[inline]
fn part_query(a: &Placed, b: &Placed, limit: f64, mode: Mode) -> Option<f64> {
    if gap(&a.center, a.radius, a.plane, &b.center, b.radius, b.plane) >= limit {
        return None;
    }
    let d = if a.plane || b.plane {
        floor_distance(a, b)
    } else if a.hull.is_some() || b.hull.is_some() {
        match (support_map(a), support_map(b)) {
            (Some(ga), Some(gb)) => hull_query(&a.iso.inv_mul(&b.iso), ga, gb, limit, mode)?,
            _ => f64::NEG_INFINITY,
        }
    } else {
        match mode {
            Mode::Filter => match query::closest_points(&a.iso, a.shape, &b.iso, b.shape, limit) {
                Ok(ClosestPoints::Disjoint) => return None,
                Ok(ClosestPoints::WithinMargin(p, q)) => (p - q).norm(),
                Ok(ClosestPoints::Intersecting) => depth(a, b),
                Err(_) => f64::NEG_INFINITY,
            },
            // Not `query::distance`: in parry 0.25 it overestimates the distance of two
            // cuboids, depending on their order (dimforge/parry#431; 1.244 m for 1.081 m on
            // the NJ-130's link 1 and a box): a clearance must never be overstated.
            Mode::Min => {
                match query::closest_points(&a.iso, a.shape, &b.iso, b.shape, limit.min(FAR)) {
                    Ok(ClosestPoints::Disjoint) => return None,
                    Ok(ClosestPoints::WithinMargin(p, q)) => (p - q).norm(),
                    Ok(ClosestPoints::Intersecting) => depth(a, b),
                    Err(_) => f64::NEG_INFINITY,
                }
            }
        }
    };
    (d < limit || (mode == Mode::Filter && d <= limit)).then_some(d)
}

fn support_map<'a>(p: &Placed<'a>) -> Option<&'a dyn SupportMap> {
    match p.hull {
        Some(h) => Some(h),
        None => p.shape.as_support_map(),
    }
}

/// `part_query` for support maps (parts with a [`Hull`]), through parry's generic GJK / EPA.
#[inline]
fn hull_query(
    pos12: &Isometry3<f64>,
    ga: &dyn SupportMap,
    gb: &dyn SupportMap,
    limit: f64,
    mode: Mode,
) -> Option<f64> {
    let depth = || {
        details::contact_support_map_support_map(pos12, ga, gb, 0.0)
            .map_or(0.0, |c| c.dist.min(0.0))
    };
    Some(match mode {
        Mode::Filter => {
            let mut simplex = VoronoiSimplex::new();
            match details::closest_points_support_map_support_map_with_params(
                pos12,
                ga,
                gb,
                limit,
                &mut simplex,
                None,
            ) {
                GJKResult::NoIntersection(_) => return None,
                // Both points in the first shape's frame.
                GJKResult::ClosestPoints(p, q, _) => (p - q).norm(),
                GJKResult::Intersection => depth(),
                GJKResult::Proximity(_) => limit,
            }
        }
        Mode::Min => match details::distance_support_map_support_map(pos12, ga, gb) {
            d if d > 0.0 => d,
            _ => depth(),
        },
    })
}

/// Penetration depth (≤ 0) of two intersecting convex parts (EPA).
fn depth(a: &Placed, b: &Placed) -> f64 {
    match query::contact(&a.iso, a.shape, &b.iso, b.shape, 0.0) {
        Ok(c) => c.map_or(0.0, |c| c.dist.min(0.0)),
        Err(_) => f64::NEG_INFINITY,
    }
}

/// Signed height of a convex part above the floor: its lowest support point, exact for every
/// shape used here. (Not parry's `contact` with a `HalfSpace`: in parry 0.25 it returns a wrong
/// depth, even for separated shapes, when the half-space is the second shape.)
fn floor_distance(a: &Placed, b: &Placed) -> f64 {
    let (floor, s) = if a.plane { (a, b) } else { (b, a) };
    if s.plane {
        return f64::NEG_INFINITY;
    }
    // The hull's own support function where there is one: it climbs the vertex graph instead
    // of scanning every vertex (the same point: both are exact).
    match support_map(s) {
        Some(m) => m.support_point(&s.iso, &-Vector3::z()).z - floor.center.z,
        None => f64::NEG_INFINITY,
    }
}

/// A lower bound on the distance of two parts: exact where it is below `limit`, else the
/// bounding spheres' gap or `limit` itself (−∞ where they intersect or parry cannot tell);
/// with the direction (world, unit, from `a` to `b`) that GJK found separating them, where it
/// found one.
#[inline]
fn part_bound(a: &Placed, b: &Placed, limit: f64) -> (f64, Option<Vector3<f64>>) {
    let g = gap(&a.center, a.radius, a.plane, &b.center, b.radius, b.plane);
    if g >= limit {
        return (g, None);
    }
    if a.plane || b.plane {
        return (floor_distance(a, b), None);
    }
    if a.hull.is_some() || b.hull.is_some() {
        let (Some(ga), Some(gb)) = (support_map(a), support_map(b)) else {
            return (f64::NEG_INFINITY, None);
        };
        let mut simplex = VoronoiSimplex::new();
        // GJK's directions are in `a`'s frame.
        let world = |v: &Unit<Vector3<f64>>| Some(a.iso.rotation * v.into_inner());
        return match details::closest_points_support_map_support_map_with_params(
            &a.iso.inv_mul(&b.iso),
            ga,
            gb,
            limit,
            &mut simplex,
            None,
        ) {
            GJKResult::NoIntersection(v) => (limit, world(&v)),
            GJKResult::ClosestPoints(p, q, v) => ((p - q).norm(), world(&v)),
            GJKResult::Intersection | GJKResult::Proximity(_) => (f64::NEG_INFINITY, None),
        };
    }
    match query::closest_points(&a.iso, a.shape, &b.iso, b.shape, limit) {
        Ok(ClosestPoints::Disjoint) => (limit, None),
        Ok(ClosestPoints::WithinMargin(p, q)) => ((p - q).norm(), (q - p).try_normalize(1e-12)),
        Ok(ClosestPoints::Intersecting) | Err(_) => (f64::NEG_INFINITY, None),
    }
}

/// How far a placed part reaches along a world direction: the largest p·v over its points
/// (its support point's), or None for the floor or a shape without a support function.
#[inline]
fn extent(p: &Placed, v: &Vector3<f64>) -> Option<f64> {
    if p.plane {
        return None;
    }
    support_map(p).map(|m| m.support_point(&p.iso, v).coords.dot(v))
}

/// A pair's separating direction from its last exact measure along one motion: projected on it,
/// two bodies that moved a little since are still as far apart, and two support points prove
/// it (a separating-axis lower bound) where GJK converging to the distance takes many.
#[derive(Clone, Copy)]
struct Warm {
    /// World, unit, from the pair's first body to its second; None before the first measure.
    dir: Option<Vector3<f64>>,
    /// The bound the last exact measure gave.
    exact: f64,
}

/// How much less than the last exact measure a separation along the remembered direction may
/// be and still serve as the bound (m), at least; a quarter of the measure's excess over the
/// margin where that is more. Below it the direction has gone stale: GJK measures again.
const WARM_TOLERANCE: f64 = 1e-3;

impl Warm {
    const NONE: Warm = Warm {
        dir: None,
        exact: f64::NEG_INFINITY,
    };

    /// Whether the separation `s` along the remembered direction serves as the bound: above the
    /// margin (else the exact filter decides anyway), and near the last exact measure.
    #[inline]
    fn serves(&self, s: f64, margin: f64) -> bool {
        s > margin + 2.0 * BOUND_SLACK
            && s >= self.exact - WARM_TOLERANCE.max(0.25 * (self.exact - margin))
    }

    /// Remembers an exact measure and the direction it found (the old one where it found none).
    #[inline]
    fn measured(&mut self, bound: f64, dir: Option<Vector3<f64>>) {
        self.exact = bound;
        self.dir = dir.or(self.dir);
    }
}

impl Part {
    #[inline]
    fn place<'a>(&'a self, body: &Isometry3<f64>) -> Placed<'a> {
        Placed {
            shape: self.shape.as_ref(),
            hull: self.hull.as_deref(),
            iso: body * self.local,
            center: body * self.center,
            radius: self.radius,
            plane: self.plane,
        }
    }
}

impl Body {
    /// `a` against every part of this body placed at `iso`.
    #[inline]
    fn against(&self, iso: &Isometry3<f64>, a: &Placed, limit: f64, mode: Mode) -> Option<f64> {
        let c = iso * self.center;
        if gap(&a.center, a.radius, a.plane, &c, self.radius, self.plane) >= limit {
            return None;
        }
        let mut best: Option<f64> = None;
        let mut lim = limit;
        for p in &self.parts {
            if let Some(d) = part_query(a, &p.place(iso), lim, mode) {
                if mode == Mode::Filter {
                    return Some(d);
                }
                best = Some(d);
                lim = d;
            }
        }
        best
    }

    /// A lower bound on the distance of `a` to this body placed at `iso` (see [`part_bound`]),
    /// and the separating direction (from `a`) of the part that gave it.
    fn bound_against(
        &self,
        iso: &Isometry3<f64>,
        a: &Placed,
        limit: f64,
    ) -> (f64, Option<Vector3<f64>>) {
        let g = gap(
            &a.center,
            a.radius,
            a.plane,
            &(iso * self.center),
            self.radius,
            self.plane,
        );
        if g >= limit {
            return (g, None);
        }
        // A part farther than the best so far cannot lower the minimum: the limit shrinks.
        let mut best = (f64::INFINITY, None);
        for p in &self.parts {
            let b = part_bound(a, &p.place(iso), limit.min(best.0));
            if b.0 < best.0 {
                best = b;
            }
        }
        best
    }

    /// [`Body::bound_against`] along a motion: where the direction `warm` remembers still
    /// separates `a` from this body about as well as when it was measured, that separation is
    /// the bound (two support points per part instead of GJK); else the exact measure, which
    /// renews the direction.
    fn bound_against_along(
        &self,
        iso: &Isometry3<f64>,
        a: &Placed,
        limit: f64,
        margin: f64,
        warm: &mut Warm,
    ) -> f64 {
        if let Some(v) = warm.dir {
            let lo = self.parts.iter().try_fold(f64::INFINITY, |lo, p| {
                Some(lo.min(-extent(&p.place(iso), &-v)?))
            });
            if let (Some(lo), Some(hi)) = (lo, extent(a, &v)) {
                if warm.serves(lo - hi, margin) {
                    return lo - hi;
                }
            }
        }
        let (b, dir) = self.bound_against(iso, a, limit);
        warm.measured(b, dir);
        b
    }

    /// A lower bound on the distance of two bodies: exact where it is below `limit`.
    fn bound(
        &self,
        ia: &Isometry3<f64>,
        other: &Body,
        ib: &Isometry3<f64>,
        limit: f64,
    ) -> (f64, Option<Vector3<f64>>) {
        let g = gap(
            &(ia * self.center),
            self.radius,
            self.plane,
            &(ib * other.center),
            other.radius,
            other.plane,
        );
        if g >= limit {
            return (g, None);
        }
        let mut best = (f64::INFINITY, None);
        for p in &self.parts {
            let b = other.bound_against(ib, &p.place(ia), limit.min(best.0));
            if b.0 < best.0 {
                best = b;
            }
        }
        best
    }

    /// [`Body::bound`] along a motion, with the remembered direction (see
    /// [`Body::bound_against_along`]): a separating-axis bound from the support points of
    /// every part where it serves, else the exact measure.
    fn bound_along(
        &self,
        ia: &Isometry3<f64>,
        other: &Body,
        ib: &Isometry3<f64>,
        limit: f64,
        margin: f64,
        warm: &mut Warm,
    ) -> f64 {
        if let (Some(v), false, false) = (warm.dir, self.plane, other.plane) {
            let hi = self.parts.iter().try_fold(f64::NEG_INFINITY, |hi, p| {
                Some(hi.max(extent(&p.place(ia), &v)?))
            });
            let lo = other.parts.iter().try_fold(f64::INFINITY, |lo, p| {
                Some(lo.min(-extent(&p.place(ib), &-v)?))
            });
            if let (Some(hi), Some(lo)) = (hi, lo) {
                if warm.serves(lo - hi, margin) {
                    return lo - hi;
                }
            }
        }
        let (b, dir) = self.bound(ia, other, ib, limit);
        warm.measured(b, dir);
        b
    }

    fn pair(
        &self,
        ia: &Isometry3<f64>,
        other: &Body,
        ib: &Isometry3<f64>,
        limit: f64,
        mode: Mode,
    ) -> Option<f64> {
        let (ca, cb) = (ia * self.center, ib * other.center);
        if gap(&ca, self.radius, self.plane, &cb, other.radius, other.plane) >= limit {
            return None;
        }
        let mut best: Option<f64> = None;
        let mut lim = limit;
        for p in &self.parts {
            if let Some(d) = other.against(ib, &p.place(ia), lim, mode) {
                if mode == Mode::Filter {
                    return Some(d);
                }
                best = Some(d);
                lim = d;
            }
        }
        best
    }
}

#[inline]
fn to_iso(f: &Frame) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(f.t),
        UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(f.r)),
    )
}

/// Body poses of one query: the eight chain frames, the world, and what places the passive
/// links. Each frame's isometry is made when a pair first needs it (a continuous check skips
/// most pairs at most samples), and passive links are placed per call: no allocation.
struct Poses<'a> {
    iso: [std::cell::Cell<Option<Isometry3<f64>>>; 9],
    frames: &'a [Frame; 8],
    q: &'a [f64; 6],
    passive: &'a [PassiveLink],
}

impl<'a> Poses<'a> {
    #[inline]
    fn new(q: &'a [f64; 6], frames: &'a [Frame; 8], passive: &'a [PassiveLink]) -> Self {
        Poses {
            iso: Default::default(),
            frames,
            q,
            passive,
        }
    }

    #[inline]
    fn frame(&self, k: usize) -> Isometry3<f64> {
        if let Some(i) = self.iso[k].get() {
            return i;
        }
        let i = if k == 8 {
            Isometry3::identity()
        } else {
            to_iso(&self.frames[k])
        };
        self.iso[k].set(Some(i));
        i
    }

    #[inline]
    fn of(&self, b: &Body) -> Isometry3<f64> {
        match b.attach {
            Attach::Frame(k) => self.frame(k),
            Attach::World => self.frame(8),
            Attach::Passive(i) => to_iso(&self.passive[i].pose(self.frames, self.q)),
        }
    }
}

/// What a continuous check remembers between the samples of one motion (conservative
/// advancement): per checked pair, a lower bound on its distance where it was last measured
/// and how fast that distance can change along the motion. A pair whose bound, less the change
/// the motion allows since, still exceeds the margin cannot be the violation at a sample, and
/// is not queried there; every other pair is, so the verdict at every sample is the full
/// check's. Made by [`Scene::coherence`] for one motion; valid for that motion only.
pub struct Coherence {
    rate: Vec<f64>,
    bound: Vec<f64>,
    at: Vec<f64>,
    warm: Vec<Warm>,
}

/// How far beyond the margin a pair's distance is measured exactly (m): a pair farther than
/// this skips at least this much relative motion before it is queried again. GJK converging to
/// a distance costs more than proving a separation, so a near-sighted bound is cheaper overall
/// (on the KR 120 cell: 30-50 mm best, 10 % more CPU at 10 mm or 300 mm).
const LOOKAHEAD: f64 = 0.04;

/// Taken off every measured bound: GJK's own tolerance is far smaller.
const BOUND_SLACK: f64 = 1e-9;

impl Scene {
    /// The bar between the balls: a capsule from the fixture ball's surface to the MAP ball's
    /// surface, in world coordinates. Cheap (by value); None when the balls overlap.
    #[inline]
    fn bar(&self, fixture: &Vector3<f64>, map_world: &Vector3<f64>) -> Option<(Capsule, f64)> {
        let v = map_world - fixture;
        let len = v.norm();
        // NaN (a non-finite MAP) also falls through to "no bar": the MAP ball still answers.
        if len.is_nan() || len <= 2.0 * self.ball_radius || self.bar_radius <= 0.0 {
            return None;
        }
        let u = v / len;
        let a = Point3::from(fixture + u * self.ball_radius);
        let b = Point3::from(map_world - u * self.ball_radius);
        let half = 0.5 * len - self.ball_radius;
        Some((Capsule::new(a, b, self.bar_radius), half + self.bar_radius))
    }

    fn contact(&self, d: f64, a: usize, b: Option<usize>) -> Contact {
        Contact {
            distance: d,
            a: self.bodies[a].name.clone(),
            b: b.map_or(BAR.to_string(), |b| self.bodies[b].name.clone()),
        }
    }

    /// The first checked pair closer than `margin` (build order), or None: the fast filter.
    /// `q` = the joint vector, `frames` = `chain_frames(q)`; `map_world` = the MAP in the base
    /// frame. Allocates only the names of the contact it returns.
    pub fn violation(
        &self,
        q: &[f64; 6],
        frames: &[Frame; 8],
        map_world: &Vector3<f64>,
        margin: f64,
    ) -> Option<Contact> {
        self.violation_with(q, frames, Some(map_world), margin)
    }

    /// As [`Scene::violation`] with the bar removed (between sections of a program, when the
    /// operator has taken the EDBB out). The balls stay in the scene: conservative.
    pub fn violation_unmounted(
        &self,
        q: &[f64; 6],
        frames: &[Frame; 8],
        margin: f64,
    ) -> Option<Contact> {
        self.violation_with(q, frames, None, margin)
    }

    fn violation_with(
        &self,
        q: &[f64; 6],
        frames: &[Frame; 8],
        map_world: Option<&Vector3<f64>>,
        margin: f64,
    ) -> Option<Contact> {
        let poses = Poses::new(q, frames, &self.passive);
        for &(a, b) in &self.pairs {
            let (ba, bb) = (&self.bodies[a], &self.bodies[b]);
            if let Some(d) = ba.pair(&poses.of(ba), bb, &poses.of(bb), margin, Mode::Filter) {
                return Some(self.contact(d, a, Some(b)));
            }
        }
        let (cap, r) = self.bar(&self.fixture, map_world?)?;
        let bar = Placed::bar(&cap, r);
        for &b in &self.bar_pairs {
            let bb = &self.bodies[b];
            if let Some(d) = bb.against(&poses.of(bb), &bar, margin, Mode::Filter) {
                return Some(self.contact(d, b, None));
            }
        }
        None
    }

    /// The memory of one motion q(s), s ∈ [0, 1], whose joints move at most `lipschitz[i]`
    /// radians per unit of s (for [`Scene::violation_along`]).
    pub fn coherence(&self, lipschitz: &[f64; 6]) -> Coherence {
        let n = self.pairs.len() + self.bar_pairs.len();
        let rate = (0..n)
            .map(|k| {
                self.rates.get(k).map_or(f64::INFINITY, |r| {
                    (0..6).map(|i| r[i] * lipschitz[i].abs()).sum::<f64>()
                })
            })
            .collect();
        Coherence {
            rate,
            bound: vec![f64::NEG_INFINITY; n],
            at: vec![0.0; n],
            warm: vec![Warm::NONE; n],
        }
    }

    /// [`Scene::violation`] (or, without `map_world`, [`Scene::violation_unmounted`]) at the
    /// sample `s` of the motion `co` was made for: the same verdict and the same contact, but
    /// pairs that the motion's earlier samples prove clear are not queried.
    pub fn violation_along(
        &self,
        q: &[f64; 6],
        frames: &[Frame; 8],
        map_world: Option<&Vector3<f64>>,
        margin: f64,
        s: f64,
        co: &mut Coherence,
    ) -> Option<Contact> {
        let poses = Poses::new(q, frames, &self.passive);
        // Measure up to the distance that keeps a pair clear for the whole motion.
        let mut check = |k: usize, measure: &dyn Fn(f64, &mut Warm) -> f64| -> bool {
            if co.bound[k] - co.rate[k] * (s - co.at[k]).abs() > margin {
                return false;
            }
            let limit = margin + co.rate[k].min(LOOKAHEAD) + BOUND_SLACK;
            co.bound[k] = measure(limit, &mut co.warm[k]) - BOUND_SLACK;
            co.at[k] = s;
            co.bound[k] <= margin + 2.0 * BOUND_SLACK
        };
        for (k, &(a, b)) in self.pairs.iter().enumerate() {
            let (ba, bb) = (&self.bodies[a], &self.bodies[b]);
            let near = check(k, &|limit, warm| {
                ba.bound_along(&poses.of(ba), bb, &poses.of(bb), limit, margin, warm)
            });
            // Near the margin the filter itself decides, so the verdict and the contact are
            // exactly those of `violation`.
            if near {
                if let Some(d) = ba.pair(&poses.of(ba), bb, &poses.of(bb), margin, Mode::Filter) {
                    return Some(self.contact(d, a, Some(b)));
                }
            }
        }
        let np = self.pairs.len();
        let Some((cap, r)) = map_world.and_then(|m| self.bar(&self.fixture, m)) else {
            // No bar here: nothing is known of it at the next sample.
            co.bound[np..].fill(f64::NEG_INFINITY);
            return None;
        };
        let bar = Placed::bar(&cap, r);
        for (k, &b) in self.bar_pairs.iter().enumerate() {
            let bb = &self.bodies[b];
            let near = check(np + k, &|limit, warm| {
                bb.bound_against_along(&poses.of(bb), &bar, limit, margin, warm)
            });
            if near {
                if let Some(d) = bb.against(&poses.of(bb), &bar, margin, Mode::Filter) {
                    return Some(self.contact(d, b, None));
                }
            }
        }
        None
    }

    /// The smallest clearance over all checked pairs and the two bodies it is between.
    /// (With no checked pair at all: an infinite distance between two empty names.)
    pub fn clearance(
        &self,
        q: &[f64; 6],
        frames: &[Frame; 8],
        map_world: &Vector3<f64>,
    ) -> Contact {
        let poses = Poses::new(q, frames, &self.passive);
        let mut best = f64::INFINITY;
        let mut who: Option<(usize, Option<usize>)> = None;
        for &(a, b) in &self.pairs {
            let (ba, bb) = (&self.bodies[a], &self.bodies[b]);
            if let Some(d) = ba.pair(&poses.of(ba), bb, &poses.of(bb), best, Mode::Min) {
                best = d;
                who = Some((a, Some(b)));
            }
        }
        if let Some((cap, r)) = self.bar(&self.fixture, map_world) {
            let bar = Placed::bar(&cap, r);
            for &b in &self.bar_pairs {
                let bb = &self.bodies[b];
                if let Some(d) = bb.against(&poses.of(bb), &bar, best, Mode::Min) {
                    best = d;
                    who = Some((b, None));
                }
            }
        }
        match who {
            Some((a, b)) => self.contact(best, a, b),
            None => Contact {
                distance: f64::INFINITY,
                a: String::new(),
                b: String::new(),
            },
        }
    }

    /// For each joint i, a bound on how far any point of any robot-attached body moves per
    /// radian of joint i, at any pose. A body rigid with frame f ≥ i lies within
    /// Σ_{j=i}^{f} √(a_j² + d_j²) (+ |flange offset| for f = 7) + |sphere centre| + radius of
    /// the origin of frame i − 1, which is on joint i's axis; that distance bounds the radius
    /// of the point's circle about the axis. The bar is covered through the MAP ball: no bar
    /// point is farther from a joint axis than the MAP end plus the bar length ratio allows
    /// (the fixture end does not move).
    pub fn sweep_radius(&self) -> [f64; 6] {
        self.sweep
    }
}

// ---- building ----------------------------------------------------------------------------

/// A primitive or mesh from either the robot model or the cell file.
enum Prim<'a> {
    Box([f64; 3]),
    /// Along local z.
    Cylinder(f64, f64),
    Sphere(f64),
    Capsule([f64; 3], [f64; 3], f64),
    Mesh(&'a Path, [f64; 3]),
}

impl<'a> From<&'a Geometry> for Prim<'a> {
    fn from(g: &'a Geometry) -> Self {
        match g {
            Geometry::Box { size } => Prim::Box(*size),
            Geometry::Cylinder { radius, length } => Prim::Cylinder(*radius, *length),
            Geometry::Sphere { radius } => Prim::Sphere(*radius),
            Geometry::Mesh { path, scale } => Prim::Mesh(path, *scale),
        }
    }
}

impl<'a> From<&'a ShapeKind> for Prim<'a> {
    fn from(k: &'a ShapeKind) -> Self {
        match k {
            ShapeKind::Box { size } => Prim::Box(*size),
            ShapeKind::Cylinder { radius, length } => Prim::Cylinder(*radius, *length),
            ShapeKind::Sphere { radius } => Prim::Sphere(*radius),
            ShapeKind::Capsule { a, b, radius } => Prim::Capsule(*a, *b, *radius),
            ShapeKind::Mesh { path, scale } => Prim::Mesh(path, *scale),
        }
    }
}

fn part(origin: &Frame, prim: Prim, body: &str) -> Result<Part, CollisionError> {
    let bad = |msg: String| CollisionError::Shape {
        body: body.to_string(),
        msg,
    };
    let pos = |v: f64, what: &str| -> Result<f64, CollisionError> {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(bad(format!("{what} {v} must be positive")))
        }
    };
    if !(origin
        .r
        .iter()
        .chain(origin.t.iter())
        .all(|v| v.is_finite()))
    {
        return Err(bad("origin is not finite".into()));
    }
    let mut local = to_iso(origin);
    let mut hull = None;
    // (shape, bounding-sphere centre and radius in the shape's own frame)
    let (shape, c, r) = match prim {
        Prim::Box(s) => {
            for v in s {
                pos(v, "box size")?;
            }
            let h = Vector3::from(s) * 0.5;
            (SharedShape::new(Cuboid::new(h)), Point3::origin(), h.norm())
        }
        Prim::Cylinder(radius, length) => {
            let (radius, h) = (pos(radius, "radius")?, 0.5 * pos(length, "length")?);
            // Ours run along local z, parry's along y: RotX(+90°) takes y to z.
            local *=
                UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2);
            (
                SharedShape::new(Cylinder::new(h, radius)),
                Point3::origin(),
                radius.hypot(h),
            )
        }
        Prim::Sphere(radius) => (
            SharedShape::new(Ball::new(pos(radius, "radius")?)),
            Point3::origin(),
            radius,
        ),
        Prim::Capsule(a, b, radius) => {
            let (a, b) = (Point3::from(a), Point3::from(b));
            if !(a.iter().chain(b.iter()).all(|v| v.is_finite())) {
                return Err(bad("capsule end is not finite".into()));
            }
            let radius = pos(radius, "radius")?;
            (
                SharedShape::new(Capsule::new(a, b, radius)),
                nalgebra::center(&a, &b),
                0.5 * (b - a).norm() + radius,
            )
        }
        Prim::Mesh(path, scale) => {
            let pts = mesh::vertices(path, scale)?;
            let no_hull = || CollisionError::Mesh {
                path: path.display().to_string(),
                msg: format!(
                    "{body}: no convex hull ({} vertices; empty or flat?)",
                    pts.len()
                ),
            };
            let (vs, tris) =
                parry3d_f64::transformation::try_convex_hull(&pts).map_err(|_| no_hull())?;
            let poly = ConvexPolyhedron::from_convex_mesh(vs.clone(), &tris).ok_or_else(no_hull)?;
            let (lo, hi) = vs.iter().fold(
                (
                    Vector3::repeat(f64::INFINITY),
                    Vector3::repeat(f64::NEG_INFINITY),
                ),
                |(lo, hi), p| (lo.inf(&p.coords), hi.sup(&p.coords)),
            );
            let c = Point3::from((lo + hi) * 0.5);
            let r = vs.iter().map(|p| (p - c).norm()).fold(0.0, f64::max);
            hull = Some(std::sync::Arc::new(Hull::new(vs, &tris)));
            (SharedShape::new(poly), c, r)
        }
    };
    Ok(Part {
        shape,
        hull,
        center: local * c,
        local,
        radius: r,
        plane: false,
    })
}

fn body(name: String, attach: Attach, role: Role, parts: Vec<Part>) -> Body {
    let plane = parts.iter().any(|p| p.plane);
    let (center, radius) = if plane {
        (parts[0].center, 0.0)
    } else {
        let (lo, hi) = parts.iter().fold(
            (
                Vector3::repeat(f64::INFINITY),
                Vector3::repeat(f64::NEG_INFINITY),
            ),
            |(lo, hi), p| {
                (
                    lo.inf(&(p.center.coords.add_scalar(-p.radius))),
                    hi.sup(&(p.center.coords.add_scalar(p.radius))),
                )
            },
        );
        let c = Point3::from((lo + hi) * 0.5);
        let r = parts
            .iter()
            .map(|p| (p.center - c).norm() + p.radius)
            .fold(0.0, f64::max);
        (c, r)
    };
    Body {
        name,
        attach,
        role,
        parts,
        center,
        radius,
        plane,
    }
}

fn link_name(k: usize) -> String {
    if k == 0 {
        "link 0 (base)".into()
    } else {
        format!("link {k}")
    }
}

/// The two legs of each DH transform as capsules in frame i (d along z_{i−1}, then a along
/// x_i), a ball where both are zero, and a base column from the floor up to frame 0.
fn auto_links(robot: &Robot, cell: &CellSpec) -> Result<Vec<Vec<Part>>, CollisionError> {
    let longest = robot.dh.iter().map(|d| d.a.hypot(d.d)).fold(0.0, f64::max);
    let r = cell
        .link_radius
        .unwrap_or((AUTO_RADIUS_FACTOR * longest).clamp(AUTO_RADIUS_MIN, AUTO_RADIUS_MAX));
    let mut links: Vec<Vec<Part>> = (0..7).map(|_| Vec::new()).collect();
    let height = robot.base.t.z - cell.floor_z;
    if height > 1e-9 {
        let column = Frame::translation(Vector3::new(
            robot.base.t.x,
            robot.base.t.y,
            cell.floor_z + 0.5 * height,
        ));
        links[0].push(part(
            &robot.base.inverse().mul(&column),
            Prim::Cylinder(r, height),
            &link_name(0),
        )?);
    }
    for (k, dh) in robot.dh.iter().enumerate() {
        let (sa, ca) = dh.alpha.sin_cos();
        let p0 = [-dh.a, -dh.d * sa, -dh.d * ca];
        let p1 = [-dh.a, 0.0, 0.0];
        let name = link_name(k + 1);
        let legs = &mut links[k + 1];
        if dh.d.abs() > 1e-9 {
            legs.push(part(&Frame::IDENTITY, Prim::Capsule(p0, p1, r), &name)?);
        }
        if dh.a.abs() > 1e-9 || legs.is_empty() {
            legs.push(part(
                &Frame::IDENTITY,
                Prim::Capsule(p1, [0.0; 3], r),
                &name,
            )?);
        }
    }
    Ok(links)
}

/// Builds the scene of one cell. `fixture` is the fixture ball centre (base frame) and `map` the
/// MAP in the flange frame. Reads the mesh files the robot and the cell name.
///
/// Pair rules (each excluded pair is listed in the report with its reason):
/// - robot-attached bodies (links, tool, MAP ball, hoses) against each other, except bodies rigid
///   with the same frame, links i and i ± 1 (their joint housings overlap by design) and pairs
///   already within `cell.margin` at q = 0. Hoses and tools are not excluded merely for being on
///   an adjacent frame: a forearm hose can be folded onto the upper arm.
/// - robot bodies against the world (floor, environment, fixture ball, stand), except the base
///   and the floor, and link 1 and the floor when joint 1 turns about a vertical axis and link 1
///   already touches the floor at q = 0 (its height cannot change).
/// - the bar against links, hoses and the world, except the tool and the MAP ball (the bar ends
///   in the tool cup; the cup cone is checked elsewhere) and the fixture ball and stand (it
///   starts there).
pub fn build(
    robot: &Robot,
    cell: &CellSpec,
    fixture: &Vector3<f64>,
    map: &Vector3<f64>,
) -> Result<(Scene, SceneReport), CollisionError> {
    let (mut bodies, passive_body) = robot_bodies(robot, cell, map)?;
    let n_robot = bodies.len();
    bodies.extend(world_bodies(cell, fixture)?);

    // Pairs.
    let home = chain_frames(&robot.base, &robot.dh, &robot.flange, &[0.0; 6]);
    let home_poses = Poses::new(&[0.0; 6], &home, &robot.passive);
    let mut excluded = Vec::new();
    let pairs = body_pairs(
        robot,
        cell,
        &bodies,
        n_robot,
        &passive_body,
        &home_poses,
        &mut excluded,
    )?;
    let bar_pairs = bar_pairs(cell, &bodies, fixture, map, &home_poses, &mut excluded)?;

    // Sweep bound (see `Scene::sweep_radius`).
    let legs = legs(robot);
    let reach = body_reach(robot, &bodies, n_robot, &legs);
    let sweep: [f64; 6] = std::array::from_fn(|i| reach.iter().map(|r| r[i]).fold(0.0, f64::max));
    // The MAP's reach, for the bar: a bar point moves at most 1.5 times as fast as the MAP (the
    // fixture end is fixed; the ends sit a ball radius inside the balls), 2 is used.
    let map_reach: [f64; 6] =
        std::array::from_fn(|i| legs[i + 1..=7].iter().sum::<f64>() + map.norm());
    let rates = pair_rates(&bodies, &reach, &pairs, &bar_pairs, &map_reach);

    let report = SceneReport {
        bodies: bodies.iter().map(|b| b.name.clone()).collect(),
        pairs_checked: pairs.len() + bar_pairs.len(),
        excluded,
    };
    Ok((
        Scene {
            bodies,
            passive: robot.passive.clone(),
            pairs,
            bar_pairs,
            fixture: *fixture,
            bar_radius: 0.5 * cell.bar_diameter,
            ball_radius: 0.5 * cell.ball,
            sweep,
            rates,
        },
        report,
    ))
}

/// The robot's bodies (links, passive links, tool, MAP ball at `map`, hoses) from its shapes and
/// `cell`, and per passive link the index of its body, if it has one.
fn robot_bodies(
    robot: &Robot,
    cell: &CellSpec,
    map: &Vector3<f64>,
) -> Result<(Vec<Body>, Vec<Option<usize>>), CollisionError> {
    let mut bodies: Vec<Body> = Vec::new();
    // Links.
    let mut link_parts: Vec<Vec<Part>> = (0..7).map(|_| Vec::new()).collect();
    let mut passive_parts: Vec<Vec<Part>> = robot.passive.iter().map(|_| Vec::new()).collect();
    if robot.shapes.is_empty() {
        link_parts = auto_links(robot, cell)?;
    } else {
        for s in &robot.shapes {
            if let Some(pi) = s.passive {
                let link = robot.passive.get(pi).ok_or_else(|| CollisionError::Shape {
                    body: format!("passive link {pi}"),
                    msg: "no such passive link".into(),
                })?;
                passive_parts[pi].push(part(&s.origin, Prim::from(&s.geometry), &link.name)?);
                continue;
            }
            if s.frame > 6 {
                return Err(CollisionError::Shape {
                    body: format!("link {}", s.frame),
                    msg: "robot shapes belong to DH frames 0-6".into(),
                });
            }
            link_parts[s.frame].push(part(
                &s.origin,
                Prim::from(&s.geometry),
                &link_name(s.frame),
            )?);
        }
    }
    for (k, parts) in link_parts.into_iter().enumerate() {
        if !parts.is_empty() {
            bodies.push(body(link_name(k), Attach::Frame(k), Role::Link, parts));
        }
    }
    // Passive links: their own bodies, placed from q.
    let mut passive_body: Vec<Option<usize>> = vec![None; robot.passive.len()];
    for (i, parts) in passive_parts.into_iter().enumerate() {
        if !parts.is_empty() {
            passive_body[i] = Some(bodies.len());
            let name = robot.passive[i].name.clone();
            bodies.push(body(name, Attach::Passive(i), Role::Passive, parts));
        }
    }
    // Tool, MAP ball, hoses.
    if !cell.tool_shapes.is_empty() {
        let parts = cell
            .tool_shapes
            .iter()
            .map(|s| {
                part(
                    &s.origin,
                    Prim::from(&s.kind),
                    &format!("{TOOL} ({})", s.name),
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        bodies.push(body(TOOL.into(), Attach::Frame(7), Role::Tool, parts));
    }
    let ball_radius = 0.5 * cell.ball;
    if ball_radius > 0.0 {
        let p = part(
            &Frame::translation(*map),
            Prim::Sphere(ball_radius),
            MAP_BALL,
        )?;
        bodies.push(body(
            MAP_BALL.into(),
            Attach::Frame(7),
            Role::MapBall,
            vec![p],
        ));
    }
    for h in &cell.hoses {
        if h.frame > 7 {
            return Err(CollisionError::Shape {
                body: h.shape.name.clone(),
                msg: format!("frame {} is not a frame 0-7", h.frame),
            });
        }
        let p = part(&h.shape.origin, Prim::from(&h.shape.kind), &h.shape.name)?;
        bodies.push(body(
            h.shape.name.clone(),
            Attach::Frame(h.frame),
            Role::Hose,
            vec![p],
        ));
    }
    Ok((bodies, passive_body))
}

/// The world's bodies from `cell` and the `fixture`: the floor, the environment, the fixture
/// ball and its stand.
fn world_bodies(cell: &CellSpec, fixture: &Vector3<f64>) -> Result<Vec<Body>, CollisionError> {
    let mut bodies = Vec::new();
    let floor = Part {
        shape: SharedShape::new(HalfSpace::new(Unit::new_unchecked(Vector3::z()))),
        hull: None,
        local: Isometry3::translation(0.0, 0.0, cell.floor_z),
        center: Point3::new(0.0, 0.0, cell.floor_z),
        radius: 0.0,
        plane: true,
    };
    bodies.push(body(FLOOR.into(), Attach::World, Role::Floor, vec![floor]));
    for s in &cell.environment {
        let p = part(&s.origin, Prim::from(&s.kind), &s.name)?;
        bodies.push(body(
            s.name.clone(),
            Attach::World,
            Role::Environment,
            vec![p],
        ));
    }
    let (ball, stand) = fixture_bodies(cell, fixture)?;
    bodies.extend(ball);
    bodies.extend(stand);
    Ok(bodies)
}

/// The body pairs to check among the robot's first `n_robot` `bodies` and against the world's,
/// judged at the home pose; excluded pairs go into `excluded` with the reason.
fn body_pairs(
    robot: &Robot,
    cell: &CellSpec,
    bodies: &[Body],
    n_robot: usize,
    passive_body: &[Option<usize>],
    home_poses: &Poses,
    excluded: &mut Vec<ExcludedPair>,
) -> Result<Vec<(usize, usize)>, CollisionError> {
    let exact = |a: &Body, b: &Body| -> Result<f64, CollisionError> {
        let (ia, ib) = (&home_poses.of(a), &home_poses.of(b));
        let mut best = f64::INFINITY;
        for pa in &a.parts {
            for pb in &b.parts {
                let (x, y) = (pa.place(ia), pb.place(ib));
                if query::distance(&x.iso, x.shape, &y.iso, y.shape).is_err() {
                    return Err(CollisionError::Unsupported {
                        a: a.name.clone(),
                        b: b.name.clone(),
                    });
                }
                if let Some(d) = part_query(&x, &y, best, Mode::Min) {
                    best = d;
                }
            }
        }
        Ok(best)
    };
    // Bodies rigid with the same frame share a key; each passive link has a key of its own.
    let frame_of = |b: &Body| match b.attach {
        Attach::Frame(k) => k.min(6),
        Attach::Passive(i) => usize::MAX - 1 - i,
        Attach::World => usize::MAX,
    };
    // The body a passive link is joined to by its joint: its nearest passive ancestor with a
    // body, else the link rigid with its anchor frame.
    let joined = |a: &Body, b: &Body| -> Option<String> {
        let Attach::Passive(i) = a.attach else {
            return None;
        };
        let link = &robot.passive[i];
        let parent_is_b = match link.parent.and_then(|p| passive_body[p]) {
            Some(pb) => std::ptr::eq(&bodies[pb], b),
            None => b.role == Role::Link && b.attach == Attach::Frame(link.frame),
        };
        parent_is_b.then(|| {
            let joint = link.steps.last().map_or("", |s| s.name.as_str());
            format!("connected by joint {joint}")
        })
    };
    let mut pairs = Vec::new();
    let mut exclude = |a: &Body, b: &Body, reason: String| {
        excluded.push(ExcludedPair {
            a: a.name.clone(),
            b: b.name.clone(),
            reason,
        })
    };
    let mm = |d: f64| crate::units::fmt_fixed(d * 1e3, 1);
    for i in 0..n_robot {
        for j in i + 1..n_robot {
            let (a, b) = (&bodies[i], &bodies[j]);
            let (fa, fb) = (frame_of(a), frame_of(b));
            if fa == fb {
                exclude(a, b, format!("rigid with the same frame (DH frame {fa})"));
                continue;
            }
            if a.role == Role::Link && b.role == Role::Link && fa.abs_diff(fb) == 1 {
                exclude(a, b, "adjacent links".into());
                continue;
            }
            if let Some(reason) = joined(a, b).or_else(|| joined(b, a)) {
                exclude(a, b, reason);
                continue;
            }
            let d = exact(a, b)?;
            if d < cell.margin {
                exclude(
                    a,
                    b,
                    format!("touch at the home pose (q = 0): clearance {} mm", mm(d)),
                );
                continue;
            }
            pairs.push((i, j));
        }
    }
    let vertical_j1 = home_poses.frames[0].r.column(2).z.abs() > 1.0 - 1e-9;
    for i in 0..n_robot {
        for j in n_robot..bodies.len() {
            let (a, b) = (&bodies[i], &bodies[j]);
            let d = exact(a, b)?;
            if a.role == Role::Link && b.role == Role::Floor {
                if frame_of(a) == 0 {
                    exclude(a, b, "base on the floor".into());
                    continue;
                }
                if frame_of(a) == 1 && vertical_j1 && d < cell.margin {
                    exclude(
                        a,
                        b,
                        format!(
                            "turns about the vertical joint-1 axis and touches the floor at q = 0 \
                             (clearance {} mm)",
                            mm(d)
                        ),
                    );
                    continue;
                }
            }
            pairs.push((i, j));
        }
    }
    Ok(pairs)
}

/// The bodies the bar is checked against (by index), each shape pair proven supported with a
/// bar from the `fixture` toward the home pose's MAP at `map`; excluded bodies go into `excluded`.
fn bar_pairs(
    cell: &CellSpec,
    bodies: &[Body],
    fixture: &Vector3<f64>,
    map: &Vector3<f64>,
    home_poses: &Poses,
    excluded: &mut Vec<ExcludedPair>,
) -> Result<Vec<usize>, CollisionError> {
    let mut bar_pairs = Vec::new();
    let home_map = home_poses.frames[7].apply(map);
    let probe = {
        // Any bar will do to find unsupported shape pairs: the one at the home pose, or a
        // stand-in when the balls overlap there.
        let v = home_map - fixture;
        let u = if v.norm() > 1e-9 {
            v.normalize()
        } else {
            Vector3::z()
        };
        Capsule::new(
            Point3::from(*fixture),
            Point3::from(fixture + u),
            (0.5 * cell.bar_diameter).max(1e-6),
        )
    };
    for (j, b) in bodies.iter().enumerate() {
        match b.role {
            Role::Tool | Role::MapBall => {
                exclude_bar(excluded, b, "bar ends in the tool cup");
                continue;
            }
            Role::FixtureBall | Role::Stand => {
                exclude_bar(excluded, b, "bar starts at the fixture");
                continue;
            }
            _ => {}
        }
        let ib = home_poses.of(b);
        for p in &b.parts {
            let x = p.place(&ib);
            if query::distance(&Isometry3::identity(), &probe, &x.iso, x.shape).is_err() {
                return Err(CollisionError::Unsupported {
                    a: BAR.into(),
                    b: b.name.clone(),
                });
            }
        }
        bar_pairs.push(j);
    }
    Ok(bar_pairs)
}

/// The length of each link of `robot`'s chain (m): frame f's distance from frame f − 1.
fn legs(robot: &Robot) -> [f64; 8] {
    std::array::from_fn(|f| match f {
        1..=6 => robot.dh[f - 1].a.hypot(robot.dh[f - 1].d),
        7 => robot.flange.t.norm(),
        _ => 0.0,
    })
}

/// Per body of `bodies` (the robot's first `n_robot`, then the world's): how far any point of it
/// moves per radian of each joint, from the chain's `legs`.
fn body_reach(robot: &Robot, bodies: &[Body], n_robot: usize, legs: &[f64; 8]) -> Vec<[f64; 6]> {
    let (lo, hi) = robot.limits();
    // reach[b][i]: how far any point of body b moves per radian of joint i + 1 (0 for the world).
    let mut reach: Vec<[f64; 6]> = vec![[0.0; 6]; bodies.len()];
    for (bi, b) in bodies[..n_robot].iter().enumerate() {
        match b.attach {
            Attach::Frame(f) => {
                for i in 1..=f.min(6) {
                    reach[bi][i - 1] =
                        legs[i..=f].iter().sum::<f64>() + b.center.coords.norm() + b.radius;
                }
            }
            Attach::Passive(pi) => {
                // d[m]: a bound on the distance from the frame before step m to any point of
                // the body, over every q (prismatic steps add their largest travel).
                let link = &robot.passive[pi];
                let travel = |st: &crate::robot::PassiveStep| -> f64 {
                    if st.motion != PassiveMotion::Prismatic {
                        return 0.0;
                    }
                    let range = st.joint.map_or(0.0, |k| lo[k].abs().max(hi[k].abs()));
                    st.multiplier.abs() * range + st.offset.abs()
                };
                let n = link.steps.len();
                let mut d = vec![0.0; n + 1];
                d[n] = b.center.coords.norm() + b.radius;
                for m in (0..n).rev() {
                    d[m] = link.steps[m].origin.t.norm() + travel(&link.steps[m]) + d[m + 1];
                }
                let k = link.frame.min(6);
                for i in 1..=6 {
                    let mut r = if i <= k {
                        legs[i..=k].iter().sum::<f64>() + d[0]
                    } else {
                        0.0
                    };
                    // Steps this joint drives: a mimic turns the rest of the link about its
                    // own axis (|multiplier| × radius) or slides it (|multiplier| m per rad).
                    for (m, st) in link.steps.iter().enumerate() {
                        if st.joint == Some(i - 1) {
                            r += st.multiplier.abs()
                                * match st.motion {
                                    PassiveMotion::Revolute => d[m + 1],
                                    PassiveMotion::Prismatic => 1.0,
                                    PassiveMotion::Fixed => 0.0,
                                };
                        }
                    }
                    reach[bi][i - 1] = r;
                }
            }
            Attach::World => {}
        }
    }
    reach
}

/// Per checked pair (the body pairs, then the bar pairs): for each joint, a bound on how fast the
/// pair's distance changes per radian of that joint (m/rad). Joints that move both bodies of a
/// pair rigidly together (joints 1..=k for bodies on chain frames k < l) do not change their
/// distance and count zero; for the other joints the distal body's reach counts. Passive links,
/// whose mimic joints can move them relative to their anchor, count both bodies' reach.
fn pair_rates(
    bodies: &[Body],
    reach: &[[f64; 6]],
    pairs: &[(usize, usize)],
    bar_pairs: &[usize],
    map_reach: &[f64; 6],
) -> Vec<[f64; 6]> {
    let body_pair = |&(a, b): &(usize, usize)| -> [f64; 6] {
        match (bodies[a].attach, bodies[b].attach) {
            (Attach::Frame(fa), Attach::Frame(fb)) => {
                let (fa, fb) = (fa.min(6), fb.min(6));
                let (common, distal) = if fa <= fb { (fa, b) } else { (fb, a) };
                std::array::from_fn(|i| if i >= common { reach[distal][i] } else { 0.0 })
            }
            _ => std::array::from_fn(|i| reach[a][i] + reach[b][i]),
        }
    };
    pairs
        .iter()
        .map(body_pair)
        .chain(
            bar_pairs
                .iter()
                .map(|&b| std::array::from_fn(|i| 2.0 * map_reach[i] + reach[b][i])),
        )
        .collect()
}

/// The fixture ball and its stand (a vertical cylinder from the floor to the socket below the
/// ball), where the cell has them.
fn fixture_bodies(
    cell: &CellSpec,
    fixture: &Vector3<f64>,
) -> Result<(Option<Body>, Option<Body>), CollisionError> {
    let ball_radius = 0.5 * cell.ball;
    let ball = if ball_radius > 0.0 {
        let p = part(
            &Frame::translation(*fixture),
            Prim::Sphere(ball_radius),
            FIXTURE_BALL,
        )?;
        Some(body(
            FIXTURE_BALL.into(),
            Attach::World,
            Role::FixtureBall,
            vec![p],
        ))
    } else {
        None
    };
    let stand_height = fixture.z - ball_radius - cell.floor_z;
    let stand = if cell.stand_radius > 0.0 && stand_height > 0.0 {
        let origin = Frame::translation(Vector3::new(
            fixture.x,
            fixture.y,
            cell.floor_z + 0.5 * stand_height,
        ));
        let p = part(
            &origin,
            Prim::Cylinder(cell.stand_radius, stand_height),
            STAND,
        )?;
        Some(body(STAND.into(), Attach::World, Role::Stand, vec![p]))
    } else {
        None
    };
    Ok((ball, stand))
}

impl Scene {
    /// The same scene with the fixture (ball, stand and the bar's fixed end) at `fixture`:
    /// what [`build`] would make for it, without reading a mesh again. `cell` must be the one
    /// the scene was built from. The pair rules do not depend on the fixture (every robot body
    /// is checked against the fixture ball and stand); only whether a stand exists does (none
    /// when the ball is too low for one), and then the scene is refused: build it anew.
    pub fn with_fixture(
        &self,
        cell: &CellSpec,
        fixture: &Vector3<f64>,
    ) -> Result<Scene, CollisionError> {
        let (ball, stand) = fixture_bodies(cell, fixture)?;
        let mut out = self.clone();
        out.fixture = *fixture;
        let mut replace = |role: Role, new: Option<Body>| -> Result<(), CollisionError> {
            let at = out.bodies.iter().position(|b| b.role == role);
            match (at, new) {
                (Some(i), Some(b)) => {
                    out.bodies[i] = b;
                    Ok(())
                }
                (None, None) => Ok(()),
                _ => Err(CollisionError::Shape {
                    body: if role == Role::Stand { STAND } else { FIXTURE_BALL }.into(),
                    msg: "exists for one fixture position and not for the other: build the scene for this fixture".into(),
                }),
            }
        };
        replace(Role::FixtureBall, ball)?;
        replace(Role::Stand, stand)?;
        Ok(out)
    }

    /// Whether the fixture has room where it stands: the first static body (an environment
    /// shape, the robot's base, a body fixed to it) closer than `margin` to the fixture ball or
    /// its stand, or the ball closer than `margin` to the floor. `frames` are the chain frames
    /// of any pose (only frame 0, the base, is used: nothing that moves is judged here).
    pub fn fixture_room(&self, frames: &[Frame; 8], margin: f64) -> Option<Contact> {
        let q = [0.0; 6];
        let poses = Poses::new(&q, frames, &self.passive);
        let fixed = |b: &Body| match b.role {
            Role::Environment => true,
            Role::Link | Role::Hose => b.attach == Attach::Frame(0),
            _ => false,
        };
        for (i, f) in self.bodies.iter().enumerate() {
            if !matches!(f.role, Role::FixtureBall | Role::Stand) {
                continue;
            }
            for (j, o) in self.bodies.iter().enumerate() {
                // The stand stands on the floor; the ball must clear it.
                let floor = o.role == Role::Floor && f.role == Role::FixtureBall;
                if !(fixed(o) || floor) {
                    continue;
                }
                if let Some(d) = f.pair(&poses.of(f), o, &poses.of(o), margin, Mode::Filter) {
                    return Some(self.contact(d, i, Some(j)));
                }
            }
        }
        None
    }
}

fn exclude_bar(excluded: &mut Vec<ExcludedPair>, b: &Body, reason: &str) {
    excluded.push(ExcludedPair {
        a: BAR.into(),
        b: b.name.clone(),
        reason: reason.into(),
    });
}

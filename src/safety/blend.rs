//! The corner models, shared by the compiler and `verify`: in = a corner (the moves a → k → b),
//! the dialect's [`Corner`] model and its blend value; out = the joint-space region a controller
//! following its manual may execute there ([`Region`]), and edbbgen's own intended blend
//! ([`geometry`], which the LDBB circle program plans with).
//!
//! The region is the parallelogram k + u·(q_in − k) + w·(q_out − k), u, w ∈ [0, 1], where q_in
//! and q_out are the farthest points on the two moves where the blend may begin and end by the
//! dialect's documentation ([`region`]). It holds the triangle of those three points (every
//! rounding curve whose control polygon runs along the two moves) and every superposition of
//! the end of the first move with the start of the second (a parabolic blend, LinuxCNC's). The
//! checker proves it safe as a surface ([`crate::safety::Checker::patch`]).
//!
//! edbbgen's intended blend (used only for the LDBB circle's own planning): the
//! controller leaves the incoming move where the MAP comes within the blend distance of its
//! position at k, and joins the second where the MAP leaves that distance again, each on at most
//! half of its move, following the joint-space quadratic Bézier with k as control point.

use super::Checker;
use crate::dialect::{Corner, CornerKind};
use crate::model::MeasurementModel;
use crate::safety::lerp;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Blend {
    pub q_in: [f64; 6],
    pub corner: [f64; 6],
    pub q_out: [f64; 6],
    /// Where the blend leaves the incoming move and joins the outgoing one (fractions).
    pub s_in: f64,
    pub s_out: f64,
}

impl Blend {
    pub fn point(&self, t: f64) -> [f64; 6] {
        let (u, v, w) = ((1.0 - t) * (1.0 - t), 2.0 * t * (1.0 - t), t * t);
        std::array::from_fn(|i| u * self.q_in[i] + v * self.corner[i] + w * self.q_out[i])
    }

    /// A bound on each joint's speed along the curve, |dq/dt| (rad per unit of t): the
    /// derivative 2(1−t)(k − q_in) + 2t(q_out − k) is largest at an end, twice a leg of the
    /// control polygon. (The legs' sum, the total variation, is no bound on the speed when the
    /// legs differ: the samples of the continuous check must be spaced by the speed.)
    pub fn lipschitz(&self) -> [f64; 6] {
        std::array::from_fn(|i| {
            2.0 * (self.corner[i] - self.q_in[i])
                .abs()
                .max((self.q_out[i] - self.corner[i]).abs())
        })
    }
}

/// The corner region at via point k: k + u·(q_in − k) + w·(q_out − k), u, w ∈ [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Region {
    pub corner: [f64; 6],
    /// The farthest points where the blend may begin (on a → k) and end (on k → b).
    pub q_in: [f64; 6],
    pub q_out: [f64; 6],
    /// Their fractions of the moves, from the corner (0 = at k).
    pub s_in: f64,
    pub s_out: f64,
}

impl Region {
    pub fn point(&self, u: f64, w: f64) -> [f64; 6] {
        std::array::from_fn(|i| {
            self.corner[i]
                + u * (self.q_in[i] - self.corner[i])
                + w * (self.q_out[i] - self.corner[i])
        })
    }

    /// The parallelogram's edge vectors (q_in − k, q_out − k).
    pub fn edges(&self) -> ([f64; 6], [f64; 6]) {
        (
            std::array::from_fn(|i| self.q_in[i] - self.corner[i]),
            std::array::from_fn(|i| self.q_out[i] - self.corner[i]),
        )
    }
}

/// Why a corner has no bounded region.
pub const UNBOUNDED: &str =
    "the blend instruction bounds no documented corner region on this controller (use an exact stop)";

/// The region a controller following `corner`'s documentation may execute at k for a blend of
/// `value` (the dialect's unit: mm at the MAP for a TCP distance, enlarged by the corner's
/// `tolerance`; program axis units of path for an axis-path distance; ignored where only the
/// moves bound it), each end at most `corner.cap` of its move from k. `axis_len` are the lengths of
/// the moves a → k and k → b over the controller axes in program units (for an axis path).
/// `kind` overrides the dialect's (FANUC `CR`). Err for a model that bounds nothing.
#[allow(clippy::too_many_arguments)]
pub fn region(
    ck: &Checker,
    corner: &Corner,
    kind: Option<CornerKind>,
    a: &[f64; 6],
    k: &[f64; 6],
    b: &[f64; 6],
    value: f64,
    axis_len: (f64, f64),
) -> Result<Region, &'static str> {
    let cap = corner.cap.clamp(0.0, 1.0);
    let (s_in, s_out) = match kind.unwrap_or(corner.kind) {
        CornerKind::Unbounded => return Err(UNBOUNDED),
        CornerKind::Moves => (cap, cap),
        CornerKind::AxisPath => {
            let frac = |len: f64| {
                if len > 0.0 {
                    (value.max(0.0) / len).min(cap)
                } else {
                    0.0
                }
            };
            (frac(axis_len.0), frac(axis_len.1))
        }
        CornerKind::TcpDistance => {
            // What the controller may make of the programmed distance (ABB: up to 10 % more).
            let d = value.max(0.0) * 1e-3 * (1.0 + corner.tolerance.max(0.0));
            (tcp_reach(ck, k, a, d, cap), tcp_reach(ck, k, b, d, cap))
        }
    };
    Ok(Region {
        corner: *k,
        q_in: lerp(k, a, s_in),
        q_out: lerp(k, b, s_out),
        s_in,
        s_out,
    })
}

/// The largest fraction s ≤ `cap` of the move k → c at which the MAP may still be within `d` of
/// its position at k (a zone is entered where the TCP first comes within the distance, which
/// may be before a later exit and re-entry): every interval of a fine scan that a Lipschitz
/// bound cannot prove to lie outside counts as inside.
fn tcp_reach(ck: &Checker, k: &[f64; 6], c: &[f64; 6], d: f64, cap: f64) -> f64 {
    if d <= 0.0 || cap <= 0.0 {
        return 0.0;
    }
    const SCAN: usize = 256;
    let model = ck.model;
    let p = &model.nominal;
    let at_k = model.map_position(p, k);
    let f = |s: f64| (model.map_position(p, &lerp(k, c, s)) - at_k).norm();
    // How far the MAP moves per unit of s at most.
    let sweep = ck.sweep_radius();
    let speed: f64 = (0..6).map(|i| sweep[i] * (c[i] - k[i]).abs()).sum();
    let h = cap / SCAN as f64;
    let mut reach = 0.0;
    let mut prev = 0.0_f64;
    for j in 1..=SCAN {
        let s = j as f64 * h;
        let cur = f(s);
        if prev.min(cur) - speed * h / 2.0 <= d {
            reach = s;
        }
        prev = cur;
    }
    reach
}

/// The MAP's largest distance from its position at the corner over the blend's two ends: how
/// far from the pose the executed path may pass it (the path runs through both ends).
pub fn end_distance(ck: &Checker, r: &Region) -> f64 {
    let model = ck.model;
    let p = &model.nominal;
    let at = model.map_position(p, &r.corner);
    (model.map_position(p, &r.q_in) - at)
        .norm()
        .max((model.map_position(p, &r.q_out) - at).norm())
}

/// The blend at corner `k` (None when `distance` is zero).
pub fn geometry(
    model: &MeasurementModel,
    a: &[f64; 6],
    k: &[f64; 6],
    b: &[f64; 6],
    distance: f64,
) -> Option<Blend> {
    if distance <= 0.0 {
        return None;
    }
    let p = &model.nominal;
    let corner = model.map_position(p, k);
    let d_in = |s: f64| (model.map_position(p, &lerp(a, k, s)) - corner).norm();
    let d_out = |s: f64| (model.map_position(p, &lerp(k, b, s)) - corner).norm();
    // Incoming: from s = 1 (the corner) back to 0.5; outgoing: from 0 to 0.5.
    let s_in = 1.0 - crossing(&|t| d_in(1.0 - t), distance);
    let s_out = crossing(&d_out, distance);
    Some(Blend {
        q_in: lerp(a, k, s_in),
        corner: *k,
        q_out: lerp(k, b, s_out),
        s_in,
        s_out,
    })
}

/// The smallest t ∈ (0, 0.5] where f(t) ≥ d (f(0) = 0), found by a scan and bisection; 0.5
/// when f stays below d.
fn crossing(f: &dyn Fn(f64) -> f64, d: f64) -> f64 {
    const SCAN: usize = 64;
    let mut lo = 0.0;
    for j in 1..=SCAN {
        let t = 0.5 * j as f64 / SCAN as f64;
        if f(t) >= d {
            let mut hi = t;
            for _ in 0..50 {
                let mid = 0.5 * (lo + hi);
                if f(mid) >= d {
                    hi = mid;
                } else {
                    lo = mid;
                }
            }
            return hi;
        }
        lo = t;
    }
    0.5
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn blend_starts_and_ends_at_the_blend_distance() {
        let robot = crate::robot::load(
            std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/robots/comau_nj130/robot.dh.toml"
            )),
            &Default::default(),
        )
        .unwrap();
        let model = MeasurementModel::new(
            &robot,
            Vector3::new(0.258, 1.468, 0.708),
            Vector3::new(0.06, 0.03, 0.12),
        );
        let a = [0.9, 0.5, -0.3, 0.2, -1.2, 0.1];
        let k = [1.2, 0.6, -0.2, 0.0, -1.0, 0.4];
        let b = [1.0, 0.8, -0.4, -0.3, -1.3, 0.0];
        let bl = geometry(&model, &a, &k, &b, 0.010).unwrap();
        let c = model.map_position(&model.nominal, &k);
        let din = (model.map_position(&model.nominal, &bl.q_in) - c).norm();
        let dout = (model.map_position(&model.nominal, &bl.q_out) - c).norm();
        assert!(
            (din - 0.010).abs() < 1e-9 && (dout - 0.010).abs() < 1e-9,
            "{din} {dout}"
        );
        assert!(bl.s_in > 0.5 && bl.s_out < 0.5);
        assert_eq!(bl.point(0.0), bl.q_in);
        assert_eq!(bl.point(1.0), bl.q_out);
        // The blended MAP path stays near the corner: within the blend distance plus the
        // curve's bow (a few mm at most here).
        for j in 0..=20 {
            let p = model.map_position(&model.nominal, &bl.point(j as f64 / 20.0));
            assert!((p - c).norm() < 0.012);
        }
        assert!(geometry(&model, &a, &k, &b, 0.0).is_none());
    }
}

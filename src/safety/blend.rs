//! The blend model: how the controller rounds a corner, shared by the compiler and `verify`.
//!
//! At a via point k between the moves a → k and k → b the controller leaves the first move where
//! the MAP comes within the blend distance of its position at k, and joins the second where the
//! MAP leaves that distance again — each on at most half of its move (as controllers do, so
//! consecutive blends never overlap). Between the two it follows the joint-space quadratic Bézier
//! with k as control point: the usual parabolic blend of joint-interpolated motion, which stays
//! inside the convex hull of its three points and cuts the corner by less than the blend distance.

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

//! Forward kinematics of the DH chain: in = DH table, fixed transforms, joint vector q; out = frames.
//!
//! Allocation-free: everything lives on the stack, so the hot loops of sampling and the
//! Jacobian can call it per pose.

use super::Dh;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// A rigid transform: x ↦ r·x + t. Plain matrix form because composing 3×3 matrices is cheaper
/// than quaternions in the FK loop and the frames' axes are needed directly by the Jacobian.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    pub r: Matrix3<f64>,
    pub t: Vector3<f64>,
}

impl Default for Frame {
    fn default() -> Self {
        Frame::IDENTITY
    }
}

impl Frame {
    pub const IDENTITY: Frame = Frame {
        r: Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
        t: Vector3::new(0.0, 0.0, 0.0),
    };

    pub fn new(r: Matrix3<f64>, t: Vector3<f64>) -> Self {
        Frame { r, t }
    }

    pub fn translation(t: Vector3<f64>) -> Self {
        Frame {
            r: Matrix3::identity(),
            t,
        }
    }

    #[inline]
    pub fn mul(&self, o: &Frame) -> Frame {
        Frame {
            r: self.r * o.r,
            t: self.r * o.t + self.t,
        }
    }

    #[inline]
    pub fn apply(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.r * p + self.t
    }

    pub fn inverse(&self) -> Frame {
        let rt = self.r.transpose();
        Frame {
            r: rt,
            t: -(rt * self.t),
        }
    }

    /// URDF-style origin: translation xyz, then fixed-axis roll-pitch-yaw (R = Rz(y)·Ry(p)·Rx(r)).
    pub fn from_xyz_rpy(xyz: [f64; 3], rpy: [f64; 3]) -> Frame {
        let (sr, cr) = rpy[0].sin_cos();
        let (sp, cp) = rpy[1].sin_cos();
        let (sy, cy) = rpy[2].sin_cos();
        let r = Matrix3::new(
            cy * cp,
            cy * sp * sr - sy * cr,
            cy * sp * cr + sy * sr,
            sy * cp,
            sy * sp * sr + cy * cr,
            sy * sp * cr - cy * sr,
            -sp,
            cp * sr,
            cp * cr,
        );
        Frame {
            r,
            t: Vector3::from(xyz),
        }
    }
}

impl Frame {
    /// The fixed-axis roll-pitch-yaw of the rotation (the inverse of [`Frame::from_xyz_rpy`]),
    /// pitch in [−π/2, π/2]; at pitch ±π/2 the roll is 0.
    pub fn rpy(&self) -> [f64; 3] {
        let r = &self.r;
        let pitch = (-r[(2, 0)]).atan2(r[(0, 0)].hypot(r[(1, 0)]));
        if r[(0, 0)].hypot(r[(1, 0)]) < 1e-12 {
            // Gimbal lock: only yaw − roll (or yaw + roll) is defined; take roll = 0.
            let yaw = (-r[(0, 1)]).atan2(r[(1, 1)]);
            return [0.0, pitch, yaw];
        }
        [
            r[(2, 1)].atan2(r[(2, 2)]),
            pitch,
            r[(1, 0)].atan2(r[(0, 0)]),
        ]
    }
}

/// The DH transform of one joint at joint value `q` (Eq. 1's building block):
/// RotZ(theta + q) · TransZ(d) · TransX(a) · RotX(alpha).
#[inline]
pub fn dh_transform(dh: &Dh, q: f64) -> Frame {
    let (st, ct) = (dh.theta + q).sin_cos();
    let (sa, ca) = dh.alpha.sin_cos();
    Frame {
        r: Matrix3::new(ct, -st * ca, st * sa, st, ct * ca, -ct * sa, 0.0, sa, ca),
        t: Vector3::new(dh.a * ct, dh.a * st, dh.d),
    }
}

/// Frames of the chain in the robot base frame: `out[0]` = DH frame 0 (base transform applied),
/// `out[i]` = DH frame i, `out[7]` = flange.
#[inline]
pub fn chain_frames(base: &Frame, dh: &[Dh; 6], flange: &Frame, q: &[f64; 6]) -> [Frame; 8] {
    let mut out = [Frame::IDENTITY; 8];
    out[0] = *base;
    for i in 0..6 {
        out[i + 1] = out[i].mul(&dh_transform(&dh[i], q[i]));
    }
    out[7] = out[6].mul(flange);
    out
}

/// Flange pose in the robot base frame.
#[inline]
pub fn flange_pose(base: &Frame, dh: &[Dh; 6], flange: &Frame, q: &[f64; 6]) -> Frame {
    let mut f = *base;
    for i in 0..6 {
        f = f.mul(&dh_transform(&dh[i], q[i]));
    }
    f.mul(flange)
}

impl super::Robot {
    /// Flange pose in the robot base frame for joint vector `q` (radians).
    pub fn fk(&self, q: &[f64; 6]) -> Frame {
        flange_pose(&self.base, &self.dh, &self.flange, q)
    }

    /// Position of a point given in the flange frame (e.g. the MAP), in the robot base frame.
    pub fn point(&self, q: &[f64; 6], p_flange: &Vector3<f64>) -> Vector3<f64> {
        self.fk(q).apply(p_flange)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rpy_inverts_from_xyz_rpy_including_gimbal_lock() {
        for rpy in [
            [0.1, -0.2, 0.3],
            [3.0, 1.2, -2.9],
            [0.0, std::f64::consts::FRAC_PI_2, 0.7],
            [0.0, -std::f64::consts::FRAC_PI_2, -1.1],
        ] {
            let f = Frame::from_xyz_rpy([1.0, 2.0, 3.0], rpy);
            let back = Frame::from_xyz_rpy([1.0, 2.0, 3.0], f.rpy());
            assert!((back.r - f.r).norm() < 1e-14, "{rpy:?} -> {:?}", f.rpy());
        }
    }

    #[test]
    fn rpy_matches_composition_of_elementary_rotations() {
        let f = Frame::from_xyz_rpy([0.0; 3], [0.3, -0.7, 1.1]);
        let rx = crate::robot::axis_angle(&Vector3::x(), 0.3);
        let ry = crate::robot::axis_angle(&Vector3::y(), -0.7);
        let rz = crate::robot::axis_angle(&Vector3::z(), 1.1);
        assert!((f.r - rz * ry * rx).norm() < 1e-14);
    }

    #[test]
    fn dh_transform_is_composition_of_its_four_factors() {
        let dh = Dh {
            alpha: 0.4,
            a: 0.3,
            d: -0.2,
            theta: 0.9,
        };
        let q = -0.35;
        let rz = Frame::new(
            crate::robot::axis_angle(&Vector3::z(), dh.theta + q),
            Vector3::zeros(),
        );
        let tz = Frame::translation(Vector3::new(0.0, 0.0, dh.d));
        let tx = Frame::translation(Vector3::new(dh.a, 0.0, 0.0));
        let rx = Frame::new(
            crate::robot::axis_angle(&Vector3::x(), dh.alpha),
            Vector3::zeros(),
        );
        let want = rz.mul(&tz).mul(&tx).mul(&rx);
        let got = dh_transform(&dh, q);
        assert!((want.r - got.r).norm() < 1e-14 && (want.t - got.t).norm() < 1e-14);
    }
}

//! Measurement model: in = robot, fixture position, MAP; out = L(q, p) (Eq. 1-2), analytic
//! identification-Jacobian rows ∂L/∂p (Eq. 3-5), the identifiability of the 30 parameters
//! (Section 2.1.2) and the observability indices O1..O4 (Table 2).
//!
//! Parameter vector, Eq. 6 and DESIGN.md: p = [x_fix, y_fix, z_fix, α1..α6, a1..a6, d1..d6,
//! θ1..θ6, x_map, y_map, z_map]. The fixture is a point in the robot base frame, the MAP a point
//! in the flange frame; the robot's fixed base and flange transforms (URDF robots) sit between
//! them and the DH chain and are not parameters.

pub mod identify;

use crate::robot::kinematics::{chain_frames, dh_transform};
use crate::robot::{Dh, Frame, Robot};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

pub use identify::{
    analyse, observability, Identifiability, IdentifyOptions, Observability, ParamInfo, Status,
};

pub const N_PARAMS: usize = 30;

/// Index of the first parameter of each group in the parameter vector.
pub const FIX: usize = 0;
pub const ALPHA: usize = 3;
pub const A: usize = 9;
pub const D: usize = 15;
pub const THETA: usize = 21;
pub const MAP: usize = 27;

/// Parameter names exactly as reports print them (DESIGN.md).
pub const PARAM_NAMES: [&str; N_PARAMS] = [
    "x_fix", "y_fix", "z_fix", "alpha1", "alpha2", "alpha3", "alpha4", "alpha5", "alpha6", "a1",
    "a2", "a3", "a4", "a5", "a6", "d1", "d2", "d3", "d4", "d5", "d6", "theta1", "theta2", "theta3",
    "theta4", "theta5", "theta6", "x_map", "y_map", "z_map",
];

/// True for parameters measured in radians (α, θ), false for lengths.
pub fn is_angle(index: usize) -> bool {
    (ALPHA..A).contains(&index) || (THETA..MAP).contains(&index)
}

/// The 30 geometric parameters of the structural loop (SI).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Params {
    /// Fixture ball centre in the robot base frame.
    pub fix: Vector3<f64>,
    pub dh: [Dh; 6],
    /// MAP (tool ball centre) in the flange frame.
    pub map: Vector3<f64>,
}

impl Params {
    pub fn to_array(&self) -> [f64; N_PARAMS] {
        let mut p = [0.0; N_PARAMS];
        for k in 0..3 {
            p[FIX + k] = self.fix[k];
            p[MAP + k] = self.map[k];
        }
        for (i, dh) in self.dh.iter().enumerate() {
            p[ALPHA + i] = dh.alpha;
            p[A + i] = dh.a;
            p[D + i] = dh.d;
            p[THETA + i] = dh.theta;
        }
        p
    }

    pub fn from_array(p: &[f64; N_PARAMS]) -> Self {
        Params {
            fix: Vector3::new(p[FIX], p[FIX + 1], p[FIX + 2]),
            dh: std::array::from_fn(|i| Dh {
                alpha: p[ALPHA + i],
                a: p[A + i],
                d: p[D + i],
                theta: p[THETA + i],
            }),
            map: Vector3::new(p[MAP], p[MAP + 1], p[MAP + 2]),
        }
    }
}

/// The kinematic measurement model of one cell: the robot's fixed transforms and the nominal
/// parameters. Immutable; share it across threads.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeasurementModel {
    pub base: Frame,
    pub flange: Frame,
    pub nominal: Params,
}

impl MeasurementModel {
    pub fn new(robot: &Robot, fixture: Vector3<f64>, map: Vector3<f64>) -> Self {
        MeasurementModel {
            base: robot.base,
            flange: robot.flange,
            nominal: Params {
                fix: fixture,
                dh: robot.dh,
                map,
            },
        }
    }

    /// MAP position in the robot base frame: b_T_fl(q, p_DH) · fl_t_map.
    #[inline]
    pub fn map_position(&self, p: &Params, q: &[f64; 6]) -> Vector3<f64> {
        let mut f = self.base;
        for i in 0..6 {
            f = f.mul(&dh_transform(&p.dh[i], q[i]));
        }
        f.mul(&self.flange).apply(&p.map)
    }

    /// Eq. 1-2: L = ‖fix_t_map‖, the ball-centre distance the EDBB reads.
    #[inline]
    pub fn length(&self, p: &Params, q: &[f64; 6]) -> f64 {
        (self.map_position(p, q) - p.fix).norm()
    }

    /// The length the bar reads on a robot with `effects` (a calibrated robot file's)
    /// commanded `q`, each joint coming from `approach`, at the reference state of a drift.
    pub fn reached_length(
        &self,
        p: &Params,
        effects: &crate::robot::effects::Effects,
        q: &[f64; 6],
        approach: &[f64; 6],
    ) -> f64 {
        if effects.act_on_poses() {
            let load = effects.load(&self.base, &p.dh, &self.flange, q, approach);
            (self.map_position(p, &load) - p.fix).norm()
        } else {
            self.length(p, q)
        }
    }

    /// One row of the identification Jacobian, ∂L/∂p at (q, p), computed analytically from the
    /// joint frames (the kinematic regressor of the DH chain). Returns L. Allocation-free.
    ///
    /// For joint i with frame i−1 (origin o, axis z) and frame i (origin o_i, axis x_i):
    /// ∂P/∂θ_i = z × (P − o), ∂P/∂d_i = z, ∂P/∂a_i = x_i, ∂P/∂α_i = x_i × (P − o_i);
    /// ∂L/∂· = uᵀ ∂P/∂· with u the unit vector from the fixture to the MAP (Eq. 4's j).
    pub fn jacobian_row(&self, p: &Params, q: &[f64; 6], row: &mut [f64; N_PARAMS]) -> f64 {
        let frames = chain_frames(&self.base, &p.dh, &self.flange, q);
        let pos = frames[7].apply(&p.map);
        let diff = pos - p.fix;
        let len = diff.norm();
        let u = if len > 0.0 {
            diff / len
        } else {
            Vector3::zeros()
        };
        for k in 0..3 {
            row[FIX + k] = -u[k];
            row[MAP + k] = u.dot(&frames[7].r.column(k));
        }
        for i in 0..6 {
            let prev = &frames[i];
            let cur = &frames[i + 1];
            let z = prev.r.column(2).into_owned();
            let x = cur.r.column(0).into_owned();
            row[THETA + i] = u.dot(&z.cross(&(pos - prev.t)));
            row[D + i] = u.dot(&z);
            row[A + i] = u.dot(&x);
            row[ALPHA + i] = u.dot(&x.cross(&(pos - cur.t)));
        }
        len
    }
}

impl MeasurementModel {
    /// The MAP position and its Jacobian ∂P/∂p (3 × 30, column k = `cols[k]`) at (q, p): the
    /// positional kinematic regressor that propagates a parameter covariance to the MAP.
    /// Fixture columns are zero (the fixture does not move the MAP). Allocation-free.
    pub fn position_jacobian(
        &self,
        p: &Params,
        q: &[f64; 6],
        cols: &mut [Vector3<f64>; N_PARAMS],
    ) -> Vector3<f64> {
        let frames = chain_frames(&self.base, &p.dh, &self.flange, q);
        let pos = frames[7].apply(&p.map);
        for k in 0..3 {
            cols[FIX + k] = Vector3::zeros();
            cols[MAP + k] = frames[7].r.column(k).into_owned();
        }
        for i in 0..6 {
            let prev = &frames[i];
            let cur = &frames[i + 1];
            let z = prev.r.column(2).into_owned();
            let x = cur.r.column(0).into_owned();
            cols[THETA + i] = z.cross(&(pos - prev.t));
            cols[D + i] = z;
            cols[A + i] = x;
            cols[ALPHA + i] = x.cross(&(pos - cur.t));
        }
        pos
    }

    /// Identification-Jacobian rows at the nominal parameters for a set of poses, in order
    /// (computed in parallel; the order of the result is the order of `poses`).
    pub fn rows(&self, poses: &[[f64; 6]]) -> Vec<[f64; N_PARAMS]> {
        use rayon::prelude::*;
        poses
            .par_iter()
            .map(|q| {
                let mut r = [0.0; N_PARAMS];
                self.jacobian_row(&self.nominal, q, &mut r);
                r
            })
            .collect()
    }
}

/// Which joints can move the MAP at all. A joint whose axis passes through the MAP for every
/// configuration of the joints after it (e.g. joint 6 when the MAP lies on the flange axis)
/// cannot change L; sampling holds such joints fixed.
pub fn movable_joints(model: &MeasurementModel, robot: &Robot) -> [bool; 6] {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x6d6f7661626c65);
    let (lo, hi) = robot.limits();
    let mut movable = [false; 6];
    // Eight random configurations decide it: an axis that misses the MAP in one of them moves it.
    for _ in 0..8 {
        let q: [f64; 6] = std::array::from_fn(|i| rng.random_range(lo[i]..=hi[i]));
        let frames = chain_frames(&model.base, &model.nominal.dh, &model.flange, &q);
        let pos = frames[7].apply(&model.nominal.map);
        for i in 0..6 {
            let z = frames[i].r.column(2);
            let r = pos - frames[i].t;
            if (r - z * z.dot(&r)).norm() > AXIS_TOLERANCE {
                movable[i] = true;
            }
        }
    }
    movable
}

/// A MAP closer than this to a joint axis is taken to lie on it (1 µm).
pub const AXIS_TOLERANCE: f64 = 1e-6;

/// Distance of the MAP from the axis of joint 6 (the flange axis for usual tools), metres.
pub fn map_offset_from_joint6_axis(model: &MeasurementModel) -> f64 {
    // In DH frame 5 the joint-6 axis is z; the MAP's distance from it does not depend on q.
    let t6 = dh_transform(&model.nominal.dh[5], 0.0).mul(&model.flange);
    let p = t6.apply(&model.nominal.map);
    (p.x * p.x + p.y * p.y).sqrt()
}

pub fn is_fixture(index: usize) -> bool {
    (FIX..ALPHA).contains(&index)
}

pub fn is_map(index: usize) -> bool {
    (MAP..N_PARAMS).contains(&index)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The bundled NJ-130 (DH), for unit tests across modules.
    pub(crate) fn nj130() -> Robot {
        crate::robot::load(
            std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/robots/comau_nj130/robot.dh.toml"
            )),
            &Default::default(),
        )
        .expect("bundled NJ-130")
    }

    #[test]
    fn analytic_jacobian_matches_central_differences() {
        let robot = nj130();
        let model = MeasurementModel::new(
            &robot,
            Vector3::new(0.258, 1.468, 0.708),
            Vector3::new(0.06, 0.03, 0.12),
        );
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let h = f64::EPSILON.cbrt();
        let p0 = model.nominal.to_array();
        let mut worst: f64 = 0.0;
        for _ in 0..200 {
            let q: [f64; 6] = std::array::from_fn(|_| rng.random_range(-3.0..3.0));
            let mut row = [0.0; N_PARAMS];
            model.jacobian_row(&model.nominal, &q, &mut row);
            for k in 0..N_PARAMS {
                let (mut pp, mut pm) = (p0, p0);
                pp[k] += h;
                pm[k] -= h;
                let fd = (model.length(&Params::from_array(&pp), &q)
                    - model.length(&Params::from_array(&pm), &q))
                    / (2.0 * h);
                // Relative to the row's scale: entries are O(1) (m/m) or O(reach) (m/rad).
                let scale = row.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                worst = worst.max((fd - row[k]).abs() / scale);
            }
        }
        assert!(worst < 1e-6, "worst relative error {worst:e}");
    }

    #[test]
    fn position_jacobian_matches_central_differences() {
        let robot = nj130();
        let model = MeasurementModel::new(
            &robot,
            Vector3::new(0.258, 1.468, 0.708),
            Vector3::new(0.06, 0.03, 0.12),
        );
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let h = f64::EPSILON.cbrt();
        let p0 = model.nominal.to_array();
        let mut worst: f64 = 0.0;
        for _ in 0..100 {
            let q: [f64; 6] = std::array::from_fn(|_| rng.random_range(-3.0..3.0));
            let mut cols = [Vector3::zeros(); N_PARAMS];
            let pos = model.position_jacobian(&model.nominal, &q, &mut cols);
            assert!((pos - model.map_position(&model.nominal, &q)).norm() < 1e-15);
            for k in 0..N_PARAMS {
                let (mut pp, mut pm) = (p0, p0);
                pp[k] += h;
                pm[k] -= h;
                let fd = (model.map_position(&Params::from_array(&pp), &q)
                    - model.map_position(&Params::from_array(&pm), &q))
                    / (2.0 * h);
                worst = worst.max((fd - cols[k]).norm() / 3.0);
            }
        }
        assert!(worst < 1e-8, "worst error {worst:e}");
    }

    #[test]
    fn length_of_zero_pose_is_flange_distance() {
        let robot = nj130();
        let fix = Vector3::new(0.258, 1.468, 0.708);
        let model = MeasurementModel::new(&robot, fix, Vector3::zeros());
        // Zero pose of the corrected table: flange at (1.37158, 0, 1.62).
        let l = model.length(&model.nominal, &[0.0; 6]);
        let want = (Vector3::new(1.37158, 0.0, 1.62) - fix).norm();
        assert!((l - want).abs() < 1e-12, "{l} vs {want}");
    }

    #[test]
    fn joint6_cannot_move_a_map_on_the_flange_axis() {
        let robot = nj130();
        let fix = Vector3::new(0.258, 1.468, 0.708);
        let on_axis = MeasurementModel::new(&robot, fix, Vector3::new(0.0, 0.0, 0.12));
        assert_eq!(
            movable_joints(&on_axis, &robot),
            [true, true, true, true, true, false]
        );
        assert!(map_offset_from_joint6_axis(&on_axis) < 1e-12);
        let off_axis = MeasurementModel::new(&robot, fix, Vector3::new(0.06, 0.03, 0.12));
        assert_eq!(movable_joints(&off_axis, &robot), [true; 6]);
        assert!((map_offset_from_joint6_axis(&off_axis) - (0.06f64.hypot(0.03))).abs() < 1e-12);
    }
}

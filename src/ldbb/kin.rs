//! Robot kinematics for the loaded circle: in = the robot, the tool ball in the end link frame,
//! the constant tool orientation; out = joint angles on the circle (numerical IK), the tool
//! ball's positional Jacobian, and the compliance regressor of one pose.
//!
//! The IK is damped least squares on position and orientation (6×6), continued along the
//! circle from the previous solution so that the branch never changes. The branch itself is
//! chosen once, deterministically, from a fixed set of seeds: the one that keeps farthest from
//! the joint limits around the whole circle.

use super::setup::Setup;
use crate::robot::kinematics::chain_frames;
use crate::robot::{Frame, Robot};
use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};

/// The arm with its tool: the pieces every kinematic function here needs.
#[derive(Clone, Debug)]
pub struct Arm<'a> {
    pub robot: &'a Robot,
    /// Tool ball centre in the end link (flange) frame (m).
    pub map: Vector3<f64>,
}

impl Arm<'_> {
    pub fn frames(&self, q: &[f64; 6]) -> [Frame; 8] {
        chain_frames(&self.robot.base, &self.robot.dh, &self.robot.flange, q)
    }

    pub fn map_position(&self, q: &[f64; 6]) -> Vector3<f64> {
        self.frames(q)[7].apply(&self.map)
    }

    /// The tool ball position and the columns of its positional Jacobian ∂p/∂q_i = z_i × (p − o_i).
    pub fn jacobian(&self, q: &[f64; 6]) -> (Vector3<f64>, [Vector3<f64>; 6]) {
        let f = self.frames(q);
        let p = f[7].apply(&self.map);
        (
            p,
            std::array::from_fn(|i| f[i].r.column(2).cross(&(p - f[i].t))),
        )
    }

    /// Regressor of the compliance along the bar: c = Σ_i (uᵀ J_i)² / k_i, so row_i = (uᵀ J_i)²
    /// (m²): the bar deflection per newton of load and per rad/(N·m) of joint compliance.
    /// `u` is the unit bar direction (table ball → tool ball).
    pub fn compliance_row(&self, q: &[f64; 6], u: &Vector3<f64>) -> [f64; 6] {
        let (_, j) = self.jacobian(q);
        std::array::from_fn(|i| u.dot(&j[i]).powi(2))
    }

    /// Solves position (tool ball at `p`) and orientation (end link axes `r`) from `seed`.
    /// None when it does not converge within the joint limits.
    pub fn ik(&self, p: &Vector3<f64>, r: &Matrix3<f64>, seed: &[f64; 6]) -> Option<[f64; 6]> {
        let (lo, hi) = self.robot.limits();
        let mut q = *seed;
        // Orientation errors are weighted by a length so that 1 mrad counts like 0.5 mm.
        const W: f64 = 0.5;
        for _ in 0..100 {
            let f = self.frames(&q);
            let pc = f[7].apply(&self.map);
            let rc = f[7].r;
            let ep = p - pc;
            let eo = 0.5
                * (rc.column(0).cross(&r.column(0))
                    + rc.column(1).cross(&r.column(1))
                    + rc.column(2).cross(&r.column(2)));
            if ep.norm() < 1e-11 && eo.norm() < 1e-11 {
                return Some(q);
            }
            let mut jm = Matrix6::zeros();
            for i in 0..6 {
                let z = f[i].r.column(2).into_owned();
                let jp = z.cross(&(pc - f[i].t));
                for k in 0..3 {
                    jm[(k, i)] = jp[k];
                    jm[(k + 3, i)] = W * z[k];
                }
            }
            let e = Vector6::new(ep.x, ep.y, ep.z, W * eo.x, W * eo.y, W * eo.z);
            let lambda2 = if e.norm() > 1e-3 { 1e-4 } else { 1e-12 };
            let y = (jm * jm.transpose() + Matrix6::identity() * lambda2).try_inverse()? * e;
            let dq = jm.transpose() * y;
            // Large steps are cut: the linearisation holds for small ones only.
            let scale = (0.3 / dq.amax()).min(1.0);
            for i in 0..6 {
                q[i] += dq[i] * scale;
                if !(q[i] >= lo[i] && q[i] <= hi[i]) {
                    return None;
                }
            }
        }
        None
    }
}

/// Joint angles along the setup's circle with its constant tool orientation.
#[derive(Clone, Debug)]
pub struct CircleIk<'a> {
    pub arm: Arm<'a>,
    pub orientation: Matrix3<f64>,
    /// Solutions at `NODES` equally spaced circle angles, 0 included.
    pub nodes: Vec<[f64; 6]>,
}

/// Nodes per circle of the continued solution (0.5°).
const NODES: usize = 720;

/// A joint step of more than this per node means the IK jumped branches.
const MAX_NODE_STEP: f64 = 0.2;

impl<'a> CircleIk<'a> {
    /// Chooses the branch and solves the circle. Errors name the angle that is out of reach.
    pub fn new(arm: Arm<'a>, orientation: Matrix3<f64>, setup: &Setup) -> Result<Self, String> {
        let (lo, hi) = arm.robot.limits();
        let c = &setup.circle;
        let p0 = c.point(0.0);
        let az = p0.y.atan2(p0.x);
        let mut seeds: Vec<[f64; 6]> = Vec::new();
        for q1 in [az, az + std::f64::consts::PI, az - std::f64::consts::PI] {
            for q2 in [-0.5, 0.0, 0.5] {
                for q3 in [-0.5, 0.0, 0.5] {
                    for q5 in [-1.2, -0.6, 0.6, 1.2] {
                        for q46 in [0.0, std::f64::consts::PI] {
                            let s = [q1, q2, q3, q46, q5, q46];
                            seeds.push(std::array::from_fn(|i| s[i].clamp(lo[i], hi[i])));
                        }
                    }
                }
            }
        }
        let mut best: Option<(f64, Vec<[f64; 6]>)> = None;
        let mut starts: Vec<[f64; 6]> = Vec::new();
        for s in &seeds {
            let Some(q0) = arm.ik(&p0, &orientation, s) else {
                continue;
            };
            if starts
                .iter()
                .any(|t| (0..6).all(|i| (t[i] - q0[i]).abs() < 1e-4))
            {
                continue;
            }
            starts.push(q0);
            let Some(nodes) = continue_around(&arm, &orientation, setup, q0) else {
                continue;
            };
            // Distance to the limits, as a share of each range, at the worst node.
            let score = nodes
                .iter()
                .flat_map(|q| {
                    (0..6).map(move |i| (q[i] - lo[i]).min(hi[i] - q[i]) / (hi[i] - lo[i]))
                })
                .fold(f64::INFINITY, f64::min);
            if best.as_ref().is_none_or(|(b, _)| score > *b + 1e-9) {
                best = Some((score, nodes));
            }
        }
        match best {
            Some((_, nodes)) => Ok(CircleIk {
                arm,
                orientation,
                nodes,
            }),
            None => Err(format!(
                "the circle is out of reach: no joint solution with the tool orientation of the setup at ({:.1}, {:.1}, {:.1}) mm (angle 0) within the joint limits",
                p0.x * 1e3,
                p0.y * 1e3,
                p0.z * 1e3
            )),
        }
    }

    /// Joint angles at circle angle `theta` (rad, any value; wrapped), seeded from the nearest
    /// node of the branch.
    pub fn at(&self, setup: &Setup, theta: f64) -> Option<[f64; 6]> {
        let t = theta.rem_euclid(std::f64::consts::TAU);
        let k = ((t / std::f64::consts::TAU * NODES as f64).round() as usize) % NODES;
        self.arm
            .ik(&setup.circle.point(t), &self.orientation, &self.nodes[k])
    }
}

fn continue_around(
    arm: &Arm,
    r: &Matrix3<f64>,
    setup: &Setup,
    q0: [f64; 6],
) -> Option<Vec<[f64; 6]>> {
    let mut nodes = Vec::with_capacity(NODES);
    let mut q = q0;
    nodes.push(q0);
    for k in 1..=NODES {
        let t = std::f64::consts::TAU * k as f64 / NODES as f64;
        let next = arm.ik(&setup.circle.point(t), r, &q)?;
        if (0..6).any(|i| (next[i] - q[i]).abs() > MAX_NODE_STEP) {
            return None;
        }
        q = next;
        if k < NODES {
            nodes.push(q);
        }
    }
    // Around once, the branch must close on itself (no joint wound up by a turn).
    (0..6).all(|i| (q[i] - q0[i]).abs() < 1e-6).then_some(nodes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::units::DEG;

    fn abb() -> Robot {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../shared/robots/abb_irb6700_200_260/robot.urdf");
        crate::robot::load(
            &path,
            &crate::robot::LoadOptions {
                flange_link: Some("tool0".into()),
                ..Default::default()
            },
        )
        .unwrap()
    }

    #[test]
    fn circle_ik_holds_position_and_orientation_and_jacobian_matches_differences() {
        let robot = abb();
        let setup = super::super::setup::tests_support::paper_setup();
        let (map, r) = setup.tool().unwrap();
        let arm = Arm { robot: &robot, map };
        let ik = CircleIk::new(arm.clone(), r, &setup).unwrap();
        for k in 0..12 {
            let t = k as f64 * 31.0 * DEG;
            let q = ik.at(&setup, t).unwrap();
            let f = arm.frames(&q);
            assert!((f[7].apply(&map) - setup.circle.point(t)).norm() < 1e-9);
            assert!((f[7].r - r).norm() < 1e-8);
            // Central differences of the tool-ball position.
            let (_, j) = arm.jacobian(&q);
            for i in 0..6 {
                let h = 1e-6;
                let (mut a, mut b) = (q, q);
                a[i] += h;
                b[i] -= h;
                let d = (arm.map_position(&a) - arm.map_position(&b)) / (2.0 * h);
                assert!((d - j[i]).norm() < 1e-7, "joint {}", i + 1);
            }
        }
        // The tool ball lies on the axis of joint 6: no lever for k6.
        let q = ik.at(&setup, 0.7).unwrap();
        let row = arm.compliance_row(&q, &setup.bar_direction(0.7));
        assert!(row[5] < 1e-20 && row[0] > 1e-3, "{row:?}");
    }
}

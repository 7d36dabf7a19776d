//! Numerical inverse kinematics of a 6R chain: in = the chain (base, DH table, flange and tool
//! point), a goal (a full TCP pose, or a TCP position with the orientation free) and a seed;
//! out = the joint vector the damped least-squares iteration reaches from the seed, its
//! remaining position and orientation error, and how far the chain is from a singularity.
//!
//! Why numerical: a closed form exists only for particular geometries (a spherical wrist, the
//! UR's offset wrist), and a calibrated robot has none of them exactly: its axes are skew by
//! the very deviations the calibration found. Levenberg–Marquardt on the geometric Jacobian
//! works for every chain the loaders produce (parallelograms are the controller mapping's
//! business: the IK works on model joints). It keeps the branch of its seed: the steps are
//! damped and bounded, so from a seed near a solution it converges to that solution and not to
//! another configuration of the arm.
//!
//! Units: metres and radians. Allocation-free (fixed-size matrices only).

use crate::robot::kinematics::{chain_frames, flange_pose};
use crate::robot::{Dh, Frame, Robot};
use nalgebra::{Matrix3, Matrix6, Rotation3, Vector3, Vector6};

/// Orientation errors are weighed against position errors at this length: a rotation of
/// 1 mrad counts like 1 mm (m per rad), in the damping and in the singularity measure.
pub const ANGLE_SCALE: f64 = 1.0;

/// A 6R chain from the robot base to a tool point: `base` · DH joints · `end`, where `end` is
/// the flange transform followed by the tool frame (flange → TCP).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chain {
    pub base: Frame,
    pub dh: [Dh; 6],
    pub end: Frame,
}

impl Chain {
    /// The robot's chain ending at `tcp` (a frame in the flange frame).
    pub fn new(robot: &Robot, tcp: &Frame) -> Chain {
        Chain {
            base: robot.base,
            dh: robot.dh,
            end: robot.flange.mul(tcp),
        }
    }

    /// The TCP frame in the robot base frame at `q`.
    #[inline]
    pub fn pose(&self, q: &[f64; 6]) -> Frame {
        flange_pose(&self.base, &self.dh, &self.end, q)
    }

    /// The TCP frame and the geometric Jacobian at `q`: column i is [z × (p − o); z] of joint
    /// i's axis (DH frame i − 1: origin o, axis z) for the TCP at p (linear rows m/rad,
    /// angular rows rad/rad, in the base frame).
    #[inline]
    pub fn jacobian(&self, q: &[f64; 6]) -> (Frame, Matrix6<f64>) {
        let f = chain_frames(&self.base, &self.dh, &self.end, q);
        let p = f[7].t;
        let mut j = Matrix6::zeros();
        for i in 0..6 {
            let z = f[i].r.column(2).into_owned();
            let v = z.cross(&(p - f[i].t));
            for a in 0..3 {
                j[(a, i)] = v[a];
                j[(a + 3, i)] = z[a];
            }
        }
        (f[7], j)
    }
}

/// What the TCP must reach.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Goal {
    /// Position and orientation.
    Pose(Frame),
    /// Position only: the orientation is free (the iteration's minimum-norm steps keep it
    /// near the seed's).
    Position(Vector3<f64>),
}

/// Iteration limits and tolerances.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Options {
    pub max_iterations: usize,
    /// Converged when the position error is below this (m) ...
    pub tol_position: f64,
    /// ... and, for a pose, the orientation error below this (rad).
    pub tol_angle: f64,
    /// No joint moves more than this per step (rad): keeps the seed's branch.
    pub max_step: f64,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            max_iterations: 200,
            tol_position: 1e-10,
            tol_angle: 1e-10,
            max_step: 0.2,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Solution {
    pub q: [f64; 6],
    /// Remaining TCP position error (m) and, for a pose, orientation error (rad).
    pub position_error: f64,
    pub angle_error: f64,
    pub converged: bool,
    pub iterations: usize,
}

/// The rotation vector (axis · angle, base frame) that turns `from` into `to`: log(to · fromᵀ).
/// Below 90° from the skew-symmetric part, sin θ · axis, and θ = atan2(sin θ, cos θ): exact to
/// the last bits for the tiny rotations a convergence test compares (the usual acos of the
/// trace resolves no angle below ~1e-8 rad).
#[inline]
pub fn rotation_error(to: &Matrix3<f64>, from: &Matrix3<f64>) -> Vector3<f64> {
    let m = to * from.transpose();
    let c = 0.5 * (m.trace() - 1.0);
    if c <= 0.0 {
        return Rotation3::from_matrix_unchecked(m).scaled_axis();
    }
    let v = 0.5
        * Vector3::new(
            m[(2, 1)] - m[(1, 2)],
            m[(0, 2)] - m[(2, 0)],
            m[(1, 0)] - m[(0, 1)],
        );
    let s = v.norm();
    if s == 0.0 {
        return Vector3::zeros();
    }
    v * (s.atan2(c) / s)
}

/// The error vector of `cur` against `goal`: position (m), then orientation scaled by
/// [`ANGLE_SCALE`] (zero for a position goal).
#[inline]
fn error(goal: &Goal, cur: &Frame) -> Vector6<f64> {
    match goal {
        Goal::Pose(g) => {
            let dp = g.t - cur.t;
            let dr = rotation_error(&g.r, &cur.r) * ANGLE_SCALE;
            Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
        }
        Goal::Position(p) => {
            let dp = p - cur.t;
            Vector6::new(dp.x, dp.y, dp.z, 0.0, 0.0, 0.0)
        }
    }
}

fn split(e: &Vector6<f64>) -> (f64, f64) {
    (
        Vector3::new(e[0], e[1], e[2]).norm(),
        Vector3::new(e[3], e[4], e[5]).norm() / ANGLE_SCALE,
    )
}

/// The damped least-squares step Jᵀ(JJᵀ + λI)⁻¹e: the minimum-norm joint change for the error
/// when λ → 0, bounded near singularities. A position goal uses only the three linear rows.
#[inline]
fn step(goal: &Goal, j: &Matrix6<f64>, e: &Vector6<f64>, lambda: f64) -> Option<[f64; 6]> {
    match goal {
        Goal::Pose(_) => {
            let mut js = *j;
            for c in 0..6 {
                for a in 3..6 {
                    js[(a, c)] *= ANGLE_SCALE;
                }
            }
            let a = js * js.transpose() + Matrix6::identity() * lambda;
            let y = a.cholesky()?.solve(e);
            let d = js.transpose() * y;
            Some(std::array::from_fn(|i| d[i]))
        }
        Goal::Position(_) => {
            let jv = j.fixed_view::<3, 6>(0, 0);
            let a = jv * jv.transpose() + Matrix3::identity() * lambda;
            let y = a.cholesky()?.solve(&Vector3::new(e[0], e[1], e[2]));
            let d = jv.transpose() * y;
            Some(std::array::from_fn(|i| d[i]))
        }
    }
}

/// Levenberg–Marquardt from `seed` towards `goal`.
pub fn solve(chain: &Chain, goal: &Goal, seed: &[f64; 6], opts: &Options) -> Solution {
    let mut q = *seed;
    let (mut cur, mut j) = chain.jacobian(&q);
    let mut e = error(goal, &cur);
    let mut cost = e.norm_squared();
    // Damping in m² (the units of JJᵀ): tiny near a regular solution (Gauss–Newton, quadratic
    // convergence), raised whenever a step fails to descend.
    let mut lambda = 1e-8;
    let converged = |e: &Vector6<f64>| {
        let (p, a) = split(e);
        p <= opts.tol_position && a <= opts.tol_angle
    };
    let mut it = 0;
    while it < opts.max_iterations && !converged(&e) {
        it += 1;
        let Some(mut d) = step(goal, &j, &e, lambda) else {
            lambda *= 10.0;
            continue;
        };
        let big = d.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        if big > opts.max_step {
            d.iter_mut().for_each(|x| *x *= opts.max_step / big);
        }
        let trial: [f64; 6] = std::array::from_fn(|i| q[i] + d[i]);
        let pose = chain.pose(&trial);
        let et = error(goal, &pose);
        let ct = et.norm_squared();
        if ct < cost {
            q = trial;
            (cur, j) = chain.jacobian(&q);
            e = error(goal, &cur);
            cost = e.norm_squared();
            lambda = (lambda * 0.1).max(1e-14);
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    let (p, a) = split(&e);
    Solution {
        q,
        position_error: p,
        angle_error: a,
        converged: converged(&e),
        iterations: it,
    }
}

/// Trades orientation error (rad) against joint motion (rad) in [`solve_position_first`]: a
/// direction of the orientation that costs more than 1/ORIENTATION_DAMPING rad of joint motion
/// per rad is given up rather than chased (near a wrist singularity); the same scale as the
/// singularity threshold of the compensation (`SINGULAR_MIN`).
pub const ORIENTATION_DAMPING: f64 = 0.01;

/// The TCP position of `goal` exactly, and its orientation as closely as the chain allows
/// without large joint motions: the Gauss–Newton iteration of min ‖orientation error‖² +
/// μ²‖q − seed‖² subject to the position (μ = [`ORIENTATION_DAMPING`]), each step the
/// minimum-norm position step plus the damped orientation step in the position's null space.
/// Where the orientation can be reached without strain (away from singularities) it is reached
/// exactly; near a wrist singularity the unreachable part stays as the remaining angle error.
pub fn solve_position_first(
    chain: &Chain,
    goal: &Frame,
    seed: &[f64; 6],
    opts: &Options,
) -> Solution {
    // The position first, by the robust iteration; the orientation is then improved without
    // giving it up.
    let turn = |q: &[f64; 6]| rotation_error(&goal.r, &chain.pose(q).r).norm();
    let plain = solve(chain, &Goal::Position(goal.t), seed, opts);
    let plain = Solution {
        angle_error: turn(&plain.q),
        ..plain
    };
    if !plain.converged {
        return plain;
    }
    let mu2 = ORIENTATION_DAMPING * ORIENTATION_DAMPING;
    let anchor = Vector6::from_column_slice(seed);
    let mut q = plain.q;
    for it in 1..=opts.max_iterations {
        let (cur, j) = chain.jacobian(&q);
        let ep = goal.t - cur.t;
        let eo = rotation_error(&goal.r, &cur.r);
        let jp = j.fixed_view::<3, 6>(0, 0).into_owned();
        let jo = j.fixed_view::<3, 6>(3, 0).into_owned();
        let Some(a) = (jp * jp.transpose() + Matrix3::identity() * 1e-12).try_inverse() else {
            break;
        };
        let pinv = jp.transpose() * a; // 6 × 3
        let d1 = pinv * ep;
        let n = Matrix6::identity() - pinv * jp;
        let jon = jo * n;
        let r = Vector6::from_column_slice(&q) - anchor + d1;
        let rhs = jon.transpose() * (eo - jo * d1) - n * r * mu2;
        let m = jon.transpose() * jon + Matrix6::identity() * mu2;
        let Some(z) = m.cholesky().map(|c| c.solve(&rhs)) else {
            break;
        };
        let mut d = d1 + n * z;
        let big = d.amax();
        if big > opts.max_step {
            d *= opts.max_step / big;
        }
        for i in 0..6 {
            q[i] += d[i];
        }
        if big < 1e-12 {
            let pe = (goal.t - chain.pose(&q).t).norm();
            let t = turn(&q);
            // Kept only when it holds the position and turns less than the plain solution.
            if pe <= opts.tol_position && t <= plain.angle_error {
                return Solution {
                    q,
                    position_error: pe,
                    angle_error: t,
                    converged: true,
                    iterations: plain.iterations + it,
                };
            }
            break;
        }
    }
    plain
}

/// How far from singular the chain is at `q` for a goal of this kind: the smallest over the
/// largest singular value of the Jacobian (orientation rows scaled by [`ANGLE_SCALE`]; only the
/// linear rows for a position goal). 0 = singular, 1 = isotropic.
pub fn conditioning(chain: &Chain, q: &[f64; 6], position_only: bool) -> f64 {
    let (_, j) = chain.jacobian(q);
    let sv: Vec<f64> = if position_only {
        let jv = j.fixed_view::<3, 6>(0, 0).into_owned();
        (jv * jv.transpose())
            .symmetric_eigenvalues()
            .iter()
            .map(|v| v.max(0.0).sqrt())
            .collect()
    } else {
        let mut js = j;
        for c in 0..6 {
            for a in 3..6 {
                js[(a, c)] *= ANGLE_SCALE;
            }
        }
        (js * js.transpose())
            .symmetric_eigenvalues()
            .iter()
            .map(|v| v.max(0.0).sqrt())
            .collect()
    };
    let max = sv.iter().fold(0.0f64, |m, v| m.max(*v));
    let min = sv.iter().fold(f64::INFINITY, |m, v| m.min(*v));
    if max > 0.0 {
        min / max
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn nj130() -> Robot {
        crate::robot::load(
            std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/robots/comau_nj130/robot.dh.toml"
            )),
            &Default::default(),
        )
        .unwrap()
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let robot = nj130();
        let chain = Chain::new(
            &robot,
            &Frame::from_xyz_rpy([0.06, 0.03, 0.12], [0.1, -0.2, 0.3]),
        );
        let q = [0.3, -0.2, 0.4, 1.1, -0.7, 2.0];
        let (f0, j) = chain.jacobian(&q);
        let h = 1e-7;
        for i in 0..6 {
            let mut qp = q;
            qp[i] += h;
            let f1 = chain.pose(&qp);
            let dv = (f1.t - f0.t) / h;
            let dw = rotation_error(&f1.r, &f0.r) / h;
            for a in 0..3 {
                assert!((dv[a] - j[(a, i)]).abs() < 1e-6, "joint {i} v{a}");
                assert!((dw[a] - j[(a + 3, i)]).abs() < 1e-6, "joint {i} w{a}");
            }
        }
    }

    #[test]
    fn rotation_error_is_exact_for_tiny_and_large_rotations() {
        let axis = Vector3::new(0.3, -0.5, 0.8).normalize();
        let base = crate::robot::axis_angle(&Vector3::new(0.1, 0.7, -0.2).normalize(), 1.3);
        for angle in [1e-12, 3e-9, 1e-4, 0.5, 1.5, 2.5, 3.1] {
            let to = crate::robot::axis_angle(&axis, angle) * base;
            let e = rotation_error(&to, &base);
            assert!(
                (e - axis * angle).norm() <= 1e-15 + 1e-12 * angle,
                "{angle}: {e:?}"
            );
        }
    }

    #[test]
    fn position_first_keeps_the_position_exact_and_the_orientation_close() {
        let robot = nj130();
        let chain = Chain::new(&robot, &Frame::translation(Vector3::new(0.06, 0.03, 0.12)));
        // Near (q5 = 0.6) and at the wrist singularity (q5 = 0): the position exact, the
        // orientation closer than the plain position solve (minimum joint change) leaves it;
        // at the singularity the part of the turn the wrist cannot make (one direction) stays.
        let mut errors = Vec::new();
        for q5 in [0.6, 0.0] {
            let q = [0.3, -0.2, 0.4, 1.1, q5, 2.0];
            let mut goal = chain.pose(&q);
            goal.r =
                crate::robot::axis_angle(&Vector3::new(0.3, 0.8, -0.5).normalize(), 3e-4) * goal.r;
            goal.t += Vector3::new(1e-4, -2e-4, 5e-5);
            let s = solve_position_first(&chain, &goal, &q, &Options::default());
            assert!(s.converged && s.position_error < 1e-10, "{s:?}");
            let plain = solve(&chain, &Goal::Position(goal.t), &q, &Options::default());
            let plain_turn = rotation_error(&goal.r, &chain.pose(&plain.q).r).norm();
            let turn = rotation_error(&goal.r, &chain.pose(&s.q).r).norm();
            assert!((turn - s.angle_error).abs() < 1e-15);
            assert!(turn < plain_turn, "{turn} against {plain_turn}");
            errors.push(turn);
        }
        assert!(errors[0] < 0.1 * 3e-4 && errors[1] < 3e-4, "{errors:?}");
        assert!(errors[0] < errors[1], "{errors:?}");
    }

    #[test]
    fn recovers_random_poses_from_nearby_seeds() {
        let robot = nj130();
        let chain = Chain::new(&robot, &Frame::translation(Vector3::new(0.06, 0.03, 0.12)));
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (lo, hi) = robot.limits();
        for _ in 0..200 {
            let q: [f64; 6] = std::array::from_fn(|i| rng.random_range(lo[i]..hi[i]));
            let seed: [f64; 6] = std::array::from_fn(|i| q[i] + rng.random_range(-0.05..0.05));
            if conditioning(&chain, &q, false) < 0.02 {
                continue;
            }
            let goal = Goal::Pose(chain.pose(&q));
            let s = solve(&chain, &goal, &seed, &Options::default());
            assert!(s.converged, "{q:?}: {s:?}");
            // The seed's branch: the very configuration it was taken near.
            for i in 0..6 {
                assert!((s.q[i] - q[i]).abs() < 1e-8, "{q:?} -> {:?}", s.q);
            }
        }
    }
}

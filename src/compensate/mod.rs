//! Applying a calibration: in = the nominal robot (what the controller computes with), the
//! calibrated robot (what the arm is), the tool point and targets; out = per target the
//! compensated joints (the calibrated robot reaches the nominal robot's pose with them), the
//! compensated Cartesian target for a controller that runs its own nominal inverse kinematics,
//! and the residual, or the reason the target cannot be compensated. Also, in the submodules:
//! the target file ([`targets`]), joint-move programs rewritten with compensated joints
//! ([`program`]), the mastering offsets and what they alone achieve ([`offsets`]), and the drift
//! of a robot since its last calibration ([`drift`]). Pure functions, no file I/O.
//!
//! No controller loads a DH table or a URDF, so a calibration reaches the arm by one of two
//! routes that work on every controller: the targets are rewritten (what the controller is
//! told, so that the real arm ends where the nominal one would), or the joint zeros are
//! corrected in the controller's mastering data (which recovers only part of the error).
//!
//! **The compensation of one target.**
//! 1. *The nominal solution* — the joints the controller would command: the target's own
//!    joints, or the nominal robot's inverse kinematics from the seed (damped least squares,
//!    so the seed's branch); without a seed, from fixed starts, the solution nearest the
//!    middle of the joint ranges. A position-only target's orientation is then the nominal
//!    solution's: the free orientation is chosen as the one the nominal robot has there.
//! 2. *The compensated joints* — the calibrated robot's inverse kinematics for that TCP pose,
//!    started at the nominal solution. Near a wrist singularity the full pose asks large joint
//!    motions for tiny orientation changes; there the position is solved exactly and the
//!    orientation as closely as small joint motions allow ([`ik::solve_position_first`]), and
//!    the result is accepted when the orientation stays within [`ORIENTATION_TOLERANCE`] of the
//!    target's.
//! 3. *Checks* — converged (else out of reach), conditioned (else near a singularity), the same
//!    branch (no joint moves more than [`BRANCH_LIMIT`] from the nominal solution), within the
//!    joint limits. A target that fails is reported with the reason and never written as
//!    compensated.
//! 4. *The Cartesian target for a nominal-IK controller* — the nominal robot's TCP pose at the
//!    compensated joints: a controller that inverts its nominal model on it commands exactly
//!    the compensated joints.

pub mod drift;
pub mod ik;
pub mod offsets;
pub mod program;
pub mod setup;
pub mod summary;
pub mod targets;

use crate::robot::effects::{Effects, ThermalState};
use crate::robot::{Dh, Frame, Robot};
use crate::units::{fmt_fixed, DEG, MM};
use ik::{Chain, Goal, Options};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

/// A chain whose conditioning ([`ik::conditioning`]) is below this is near a singularity: a
/// compensation there would swing joints for a tiny pose change, and the model's uncertainty
/// with them.
pub const SINGULAR_MIN: f64 = 0.01;
/// A position-only compensation keeps the orientation within this of the target's (rad).
pub const ORIENTATION_TOLERANCE: f64 = 0.05 * DEG;
/// A compensation that moves a joint more than this from the nominal solution has left its
/// branch (rad): calibration deviations move joints by hundredths of a degree.
pub const BRANCH_LIMIT: f64 = 5.0 * DEG;
/// Fixed starts for targets without a seed.
pub const STARTS: usize = 32;

/// What a target asks for (model joints, SI).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Target {
    /// The joints a controller with the nominal model commands: the pose they give the
    /// nominal robot's TCP.
    Joints([f64; 6]),
    /// A TCP pose in the base frame, with an optional seed that picks the branch.
    Pose {
        frame: Frame,
        seed: Option<[f64; 6]>,
    },
    /// A TCP position; the orientation is free (the nominal solution's).
    Position {
        position: Vector3<f64>,
        seed: Option<[f64; 6]>,
    },
}

/// Why a target is not compensated.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Status {
    Ok,
    /// The nominal robot does not reach the target: its controller could not run it either.
    NominalOutOfReach {
        residual: f64,
    },
    /// The calibrated robot does not reach it.
    OutOfReach {
        residual: f64,
    },
    /// Too close to a singularity (conditioning below [`SINGULAR_MIN`]).
    Singular {
        conditioning: f64,
    },
    /// The compensation moves `joint` (0-based) by `moved` rad: another branch.
    Branch {
        joint: usize,
        moved: f64,
    },
    /// Joint `joint` (0-based) at `value` beyond `limit` (rad); `target`: already the
    /// nominal joints are.
    Limit {
        joint: usize,
        value: f64,
        limit: f64,
        target: bool,
    },
}

impl Status {
    pub fn is_ok(&self) -> bool {
        matches!(self, Status::Ok)
    }
}

/// The `status` column: `ok` or the reason, without commas (one CSV field).
impl std::fmt::Display for Status {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Status::Ok => write!(f, "ok"),
            Status::NominalOutOfReach { residual } => write!(
                f,
                "out of reach: the nominal robot misses it by {} mm",
                fmt_fixed(residual / MM, 3)
            ),
            Status::OutOfReach { residual } => write!(
                f,
                "out of reach: the calibrated robot misses it by {} mm",
                fmt_fixed(residual / MM, 3)
            ),
            Status::Singular { conditioning } => write!(
                f,
                "near a singularity: conditioning {} below {}",
                fmt_fixed(conditioning, 4),
                fmt_fixed(SINGULAR_MIN, 4)
            ),
            Status::Branch { joint, moved } => write!(
                f,
                "branch change: joint {} moves {} deg (more than {} deg)",
                joint + 1,
                fmt_fixed(moved / DEG, 3),
                fmt_fixed(BRANCH_LIMIT / DEG, 1)
            ),
            Status::Limit {
                joint,
                value,
                limit,
                target,
            } => write!(
                f,
                "joint limit: {}joint {} at {} deg beyond its limit {} deg",
                if target { "the target's " } else { "" },
                joint + 1,
                fmt_fixed(value / DEG, 4),
                fmt_fixed(limit / DEG, 4)
            ),
        }
    }
}

/// The compensation of one target.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Compensated {
    pub status: Status,
    /// The TCP pose the calibrated robot is to reach (base frame); for a position-only target
    /// its orientation is the nominal solution's.
    pub target: Frame,
    /// The orientation was left free (a position-only compensation, within
    /// [`ORIENTATION_TOLERANCE`]).
    pub orientation_free: bool,
    /// The nominal solution: the joints the controller would command for the target.
    pub nominal: Option<[f64; 6]>,
    /// The compensated joints (model joints, rad); only when the status is ok.
    pub q: Option<[f64; 6]>,
    /// The TCP position error (m) of the compensated joints, or of the best attempt.
    pub residual: Option<f64>,
    /// The direction each joint came from into the pose (+1, −1, 0: not known), which a
    /// backlash of the calibrated robot depends on.
    pub approach: [f64; 6],
}

/// A value rounded to 6 decimals, with no negative zero (the reports' numbers).
pub fn round6(v: f64) -> f64 {
    let r = (v * 1e6).round() / 1e6;
    if r == 0.0 {
        0.0
    } else {
        r
    }
}

/// The two robots with their tool points, and the joint limits the compensation keeps. The
/// calibrated robot is its geometry at a thermal state and the effects its file carries: the
/// compensation solves for the load-side joints that reach the target, then for the commands
/// that give those load-side joints.
#[derive(Clone, Debug)]
pub struct Compensator {
    pub nominal: Chain,
    /// The calibrated robot's geometry at the thermal state, ending at its TCP.
    pub calibrated: Chain,
    pub lower: [f64; 6],
    pub upper: [f64; 6],
    starts: Vec<[f64; 6]>,
    /// The calibrated robot's effects and its reference geometry (base, DH, flange), which
    /// the joint corrections are evaluated on.
    effects: Effects,
    reference: (Frame, [Dh; 6], Frame),
    state: ThermalState,
}

impl Compensator {
    /// `tcp_nominal` and `tcp_calibrated`: the tool frame (flange → TCP) on each robot.
    pub fn new(
        nominal: &Robot,
        calibrated: &Robot,
        tcp_nominal: &Frame,
        tcp_calibrated: &Frame,
    ) -> Self {
        let (lower, upper) = calibrated.limits();
        let mid: [f64; 6] = std::array::from_fn(|i| 0.5 * (lower[i] + upper[i]));
        // Fixed starts (the middle of the ranges, then seeded random poses): the same targets
        // give the same solutions on every machine.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(24);
        let mut starts = vec![mid];
        starts.extend((1..STARTS).map(|_| -> [f64; 6] {
            std::array::from_fn(|i| rng.random_range(lower[i]..=upper[i]))
        }));
        Compensator {
            nominal: Chain::new(nominal, tcp_nominal),
            calibrated: Chain::new(calibrated, tcp_calibrated),
            lower,
            upper,
            starts,
            effects: calibrated.effects.clone(),
            reference: (calibrated.base, calibrated.dh, calibrated.flange),
            state: ThermalState::Reference,
        }
    }

    /// The calibrated robot at a thermal state (its file's geometry is the reference state).
    pub fn at_state(mut self, state: ThermalState) -> Self {
        self.calibrated.dh = self.effects.at_state(&self.reference.1, state);
        self.state = state;
        self
    }

    /// The thermal state the calibrated robot is evaluated at.
    pub fn state(&self) -> ThermalState {
        self.state
    }

    /// The calibrated robot's effects.
    pub fn effects(&self) -> &Effects {
        &self.effects
    }

    /// The load-side joints the calibrated robot reaches when commanded `q`.
    pub fn load(&self, q: &[f64; 6], approach: &[f64; 6]) -> [f64; 6] {
        let (b, dh, f) = &self.reference;
        self.effects.load(b, dh, f, q, approach)
    }

    /// The TCP pose the calibrated robot reaches when commanded `q`, each joint coming from
    /// `approach`.
    pub fn reached(&self, q: &[f64; 6], approach: &[f64; 6]) -> Frame {
        self.calibrated.pose(&self.load(q, approach))
    }

    /// The commands that give the calibrated robot the load-side joints `load`.
    fn command(&self, load: &[f64; 6], approach: &[f64; 6]) -> [f64; 6] {
        let (b, dh, f) = &self.reference;
        self.effects.command(b, dh, f, load, approach)
    }

    /// The Cartesian target a controller with the nominal model needs for the arm to end
    /// where `q` puts the calibrated robot: the nominal TCP pose at `q`.
    pub fn controller_pose(&self, q: &[f64; 6]) -> Frame {
        self.nominal.pose(q)
    }

    /// The calibrated robot's TCP position error at the command `q` (each joint coming from
    /// `approach`) against `target` (m).
    pub fn residual(&self, target: &Frame, q: &[f64; 6], approach: &[f64; 6]) -> f64 {
        (self.reached(q, approach).t - target.t).norm()
    }

    fn within(&self, q: &[f64; 6]) -> bool {
        (0..6).all(|i| q[i] >= self.lower[i] && q[i] <= self.upper[i])
    }

    fn limit(&self, q: &[f64; 6], target: bool) -> Option<Status> {
        (0..6).find_map(|i| {
            let limit = if q[i] < self.lower[i] {
                self.lower[i]
            } else if q[i] > self.upper[i] {
                self.upper[i]
            } else {
                return None;
            };
            Some(Status::Limit {
                joint: i,
                value: q[i],
                limit,
                target,
            })
        })
    }

    /// The nominal solution of a Cartesian goal: from the seed, or the solution within the
    /// limits nearest the middle of the ranges among those reached from the fixed starts.
    fn nominal_solution(&self, goal: &Goal, seed: Option<[f64; 6]>) -> ik::Solution {
        let opts = Options::default();
        if let Some(s) = seed {
            return ik::solve(&self.nominal, goal, &s, &opts);
        }
        let mid = self.starts[0];
        let cost = |q: &[f64; 6]| -> f64 {
            (0..6)
                .map(|i| ((q[i] - mid[i]) / (self.upper[i] - self.lower[i]).max(1e-9)).powi(2))
                .sum()
        };
        let mut best: Option<(f64, ik::Solution)> = None;
        let mut closest: Option<ik::Solution> = None;
        for s in &self.starts {
            let sol = ik::solve(&self.nominal, goal, s, &opts);
            if sol.converged && self.within(&sol.q) {
                let c = cost(&sol.q);
                if best.as_ref().is_none_or(|b| c < b.0) {
                    best = Some((c, sol));
                }
            } else if closest
                .as_ref()
                .is_none_or(|b| sol.position_error < b.position_error)
            {
                closest = Some(sol);
            }
        }
        match (best, closest) {
            (Some((_, s)), _) => s,
            (None, Some(s)) => s,
            (None, None) => unreachable!("STARTS > 0"),
        }
    }

    /// Compensates one target, each joint of the calibrated robot coming into it from
    /// `approach` (+1 from below, −1 from above, 0 not known: the centre of a backlash).
    pub fn compensate(&self, target: &Target, approach: &[f64; 6]) -> Compensated {
        let approach = *approach;
        let fail =
            |status: Status, target: Frame, nominal: Option<[f64; 6]>, residual| Compensated {
                status,
                target,
                orientation_free: false,
                nominal,
                q: None,
                residual,
                approach,
            };
        // 1. The nominal solution and the TCP pose to reach.
        let (qn, pose) = match *target {
            Target::Joints(q) => {
                let pose = self.nominal.pose(&q);
                if let Some(s) = self.limit(&q, true) {
                    return fail(s, pose, Some(q), None);
                }
                (q, pose)
            }
            Target::Pose { frame, seed } => {
                let s = self.nominal_solution(&Goal::Pose(frame), seed);
                if !s.converged {
                    return fail(
                        Status::NominalOutOfReach {
                            residual: s.position_error,
                        },
                        frame,
                        None,
                        Some(s.position_error),
                    );
                }
                (s.q, frame)
            }
            Target::Position { position, seed } => {
                let s = self.nominal_solution(&Goal::Position(position), seed);
                if !s.converged {
                    return fail(
                        Status::NominalOutOfReach {
                            residual: s.position_error,
                        },
                        Frame::translation(position),
                        None,
                        Some(s.position_error),
                    );
                }
                let r = self.nominal.pose(&s.q).r;
                (s.q, Frame::new(r, position))
            }
        };
        if let Some(s) = self.limit(&qn, true) {
            return fail(s, pose, Some(qn), None);
        }
        // 2. The calibrated robot to the same pose, from the nominal solution.
        let opts = Options::default();
        let full = ik::solve(&self.calibrated, &Goal::Pose(pose), &qn, &opts);
        let full_cond = ik::conditioning(&self.calibrated, &full.q, false);
        let (q, free) = if full.converged && full_cond >= SINGULAR_MIN {
            (full.q, false)
        } else {
            // The position exactly, the orientation as close as small joint motions allow.
            let pos = ik::solve_position_first(&self.calibrated, &pose, &qn, &opts);
            let pos_cond = ik::conditioning(&self.calibrated, &pos.q, true);
            if !pos.converged {
                let status = if pos_cond < SINGULAR_MIN {
                    Status::Singular {
                        conditioning: pos_cond,
                    }
                } else {
                    Status::OutOfReach {
                        residual: pos.position_error,
                    }
                };
                return fail(status, pose, Some(qn), Some(pos.position_error));
            }
            let turn = ik::rotation_error(&pose.r, &self.calibrated.pose(&pos.q).r).norm();
            if pos_cond < SINGULAR_MIN || turn > ORIENTATION_TOLERANCE {
                return fail(
                    Status::Singular {
                        conditioning: full_cond.min(pos_cond),
                    },
                    pose,
                    Some(qn),
                    Some(pos.position_error),
                );
            }
            (pos.q, true)
        };
        // The commands that give the calibrated robot those load-side joints.
        let q = self.command(&q, &approach);
        // 3. The same branch, within the limits.
        let residual = self.residual(&pose, &q, &approach);
        if let Some((joint, moved)) = (0..6)
            .map(|i| (i, (q[i] - qn[i]).abs()))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .filter(|m| m.1 > BRANCH_LIMIT)
        {
            return fail(
                Status::Branch { joint, moved },
                pose,
                Some(qn),
                Some(residual),
            );
        }
        if let Some(s) = self.limit(&q, false) {
            return fail(s, pose, Some(qn), Some(residual));
        }
        Compensated {
            status: Status::Ok,
            target: pose,
            orientation_free: free,
            nominal: Some(qn),
            q: Some(q),
            residual: Some(residual),
            approach,
        }
    }

    /// Compensates every target, each with its approach (in parallel; the result in the order
    /// of `targets`).
    pub fn compensate_all(&self, targets: &[(Target, [f64; 6])]) -> Vec<Compensated> {
        targets
            .par_iter()
            .map(|(t, a)| self.compensate(t, a))
            .collect()
    }
}

/// The `edbbgen.compensate/1` report.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Report {
    pub schema: &'static str,
    /// The robot files (names only).
    pub calibrated: String,
    pub nominal: String,
    /// The tool point compensated (flange frame, mm; orientation fixed-axis X-Y-Z, deg) on the
    /// nominal and the calibrated robot.
    pub tcp_nominal_mm: [f64; 3],
    pub tcp_calibrated_mm: [f64; 3],
    pub tcp_rpy_deg: [f64; 3],
    /// The controller mapping the joint values are read and written with.
    pub controller: String,
    pub limits: Limits,
    pub targets: Option<TargetsReport>,
    pub program: Option<ProgramReport>,
    pub mastering: Option<offsets::Mastering>,
    pub accuracy: offsets::Accuracy,
    pub notes: Vec<String>,
}

/// The thresholds the statuses use.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct Limits {
    pub singular_min: f64,
    pub orientation_tolerance_deg: f64,
    pub branch_limit_deg: f64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            singular_min: SINGULAR_MIN,
            orientation_tolerance_deg: ORIENTATION_TOLERANCE / DEG,
            branch_limit_deg: BRANCH_LIMIT / DEG,
        }
    }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct NotCompensated {
    pub line: usize,
    pub name: Option<String>,
    pub status: String,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct TargetsReport {
    pub file: String,
    pub kind: &'static str,
    pub rows: usize,
    pub compensated: usize,
    /// Position-only compensations near a wrist singularity (orientation held within the
    /// tolerance, not exactly).
    pub orientation_free: usize,
    pub not_compensated: Vec<NotCompensated>,
    /// The TCP error the compensation removes (the calibrated robot at the nominal joints
    /// against the target) and what remains at the printed joints (µm), over the compensated
    /// rows.
    pub before_um: offsets::Um,
    pub residual_um: offsets::Um,
    /// Per compensated row, sorted (µm), for the figure.
    #[serde(skip)]
    pub sorted_um: (Vec<f64>, Vec<f64>),
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct ProgramReport {
    pub file: String,
    pub dialect: String,
    pub moves: usize,
    pub decimals: usize,
    /// The calibrated robot's TCP error at the printed values (µm): the text's resolution.
    pub printed_residual_um: offsets::Um,
    /// Lines whose stated duration was lengthened so that no axis runs faster than allowed.
    pub retimed_lines: Vec<usize>,
    /// The largest change of a joint by the compensation (deg).
    pub largest_change_deg: f64,
    /// Moves whose compensated joints leave the cell's joint margin (a program planned up to
    /// the margin's edge crosses it by up to the largest change): line, joint (1-based), by
    /// how much (deg).
    pub beyond_joint_margin: Vec<(usize, usize, f64)>,
}

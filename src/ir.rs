//! The data passed between stages (the "IR"). Plain data, SI units, serde for `--emit STAGE`.
//!
//! ```text
//! Robot + Cell ─sample─▶ Pool ─select─▶ Selection ─order─▶ Tour ─(pipeline)─▶ Program ─emit─▶ text
//! ```

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// The measurement cell: where the EDBB fixture is and what the bar can reach.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cell {
    /// Fixture ball centre in the robot base frame (m).
    pub fixture: Vector3<f64>,
    /// MAP (tool ball centre) in the flange frame (m).
    pub map: Vector3<f64>,
    /// Usable bar length range: ball-centre distance [min, max] (m).
    pub bar_min: f64,
    pub bar_max: f64,
    /// Height of the floor in the robot base frame (m); the MAP must stay above it.
    pub floor_z: f64,
}

impl Cell {
    /// True when a MAP position (base frame) lies in the EDBB shell and above the floor.
    #[inline]
    pub fn admits(&self, map: &Vector3<f64>) -> bool {
        let d2 = (map - self.fixture).norm_squared();
        d2 >= self.bar_min * self.bar_min
            && d2 <= self.bar_max * self.bar_max
            && map.z > self.floor_z
    }
}

/// One candidate measurement pose.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    /// Joint vector (rad).
    pub q: [f64; 6],
    /// MAP position in the robot base frame (m).
    pub map: [f64; 3],
    /// Nominal bar length L (m).
    pub length: f64,
    /// Position in the joint grid (mixed-radix index): the stable identity of the pose.
    pub grid: u64,
}

/// The candidate pool: valid poses in grid order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pool {
    pub candidates: Vec<Candidate>,
}

/// The result of condition-number pruning.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Selection {
    /// Indices into the pool of the selected poses, ascending.
    pub indices: Vec<usize>,
    /// cond(n) of the scaled identification Jacobian along the elimination, from the pool size
    /// down to m: `curve[k] = (n, cond)`, n descending.
    pub curve: Vec<(usize, f64)>,
    /// Number of identifiable parameters (columns).
    pub m: usize,
    /// How the pose count was chosen.
    pub rule: String,
}

/// An ordered measurement path.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Path {
    /// Joint vectors (rad) in visiting order.
    pub poses: Vec<[f64; 6]>,
    /// Duration of each move into pose k from pose k−1 (Eq. 7), s; 0 for the first pose.
    pub move_times: Vec<f64>,
    /// Estimated time of the selected poses in their pool order and in tour order (Eq. 7), s.
    pub time_unsorted: f64,
    pub time_sorted: f64,
}

/// Dialect-free program: what `emit` renders.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Program {
    pub header: Header,
    pub moves: Vec<Move>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub tool_version: String,
    pub robot: String,
    pub robot_file: String,
    pub fixture_mm: [f64; 3],
    pub map_mm: [f64; 3],
    pub bar_mm: [f64; 2],
    pub blend_mm: f64,
    pub poses: usize,
    pub identifiable: usize,
    pub cond: f64,
    pub time_unsorted_s: f64,
    pub time_s: f64,
    pub inputs_sha256: String,
    pub joint_names: Vec<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Move {
    /// Target joint vector in degrees.
    pub q_deg: [f64; 6],
    /// Planned duration (s): the slowest axis at its maximum speed (Eq. 7).
    pub time_s: f64,
    /// Predicted bar length at the target (mm).
    pub length_mm: f64,
}

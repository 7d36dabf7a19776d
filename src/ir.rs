//! The data passed between stages (the "IR"). Plain data, SI units, serde for `--emit STAGE`.
//!
//! ```text
//! Robot + Cell ─sample─▶ Pool ─select─▶ Selection ─order─▶ Tour ─(pipeline)─▶ Program ─emit─▶ text
//! ```

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// The measurement cell as the stages see it: where the fixture is, what the bar can reach, and
/// the instrument's and the harness's own limits (SI).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cell {
    /// Fixture ball centre in the robot base frame (m).
    pub fixture: Vector3<f64>,
    /// MAP (tool ball centre) in the flange frame (m).
    pub map: Vector3<f64>,
    /// Usable bar length range: ball-centre distance [min, max] (m).
    pub bar_min: f64,
    pub bar_max: f64,
    /// Height of the floor in the robot base frame (m); the MAP stays above it.
    pub floor_z: f64,
    /// Unit socket axis (base frame) and the cosine of the socket cone's half-angle.
    pub fixture_axis: Vector3<f64>,
    pub fixture_cone_cos: f64,
    /// Unit tool-cup axis (flange frame) and the cosine of the cup cone's half-angle.
    pub tool_axis: Vector3<f64>,
    pub tool_cone_cos: f64,
    /// Wiring-harness limits (rad) on q4, q6 and q4 + q6.
    pub cables: [Option<[f64; 2]>; 3],
    /// Distance kept from every joint limit (rad), for poses and motions alike.
    #[serde(default)]
    pub joint_margin: f64,
}

/// Why a pose is not admitted (report keys).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Reason {
    JointLimit,
    JointSpeed,
    CableLimit,
    BarLength,
    Floor,
    SocketCone,
    CupCone,
    Collision,
    /// The program text itself: unreadable, or written for another controller mapping.
    Program,
}

impl Reason {
    pub const ALL: [Reason; 9] = [
        Reason::JointLimit,
        Reason::JointSpeed,
        Reason::CableLimit,
        Reason::BarLength,
        Reason::Floor,
        Reason::SocketCone,
        Reason::CupCone,
        Reason::Collision,
        Reason::Program,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Reason::JointLimit => "joint_limit",
            Reason::JointSpeed => "joint_speed",
            Reason::CableLimit => "cable_limit",
            Reason::BarLength => "bar_length",
            Reason::Floor => "floor",
            Reason::SocketCone => "socket_cone",
            Reason::CupCone => "cup_cone",
            Reason::Collision => "collision",
            Reason::Program => "program",
        }
    }
}

impl Cell {
    /// A cell with only the shell and the floor (no cones, no harness limits): for tests and
    /// benchmarks of the geometry alone.
    pub fn shell_only(
        fixture: Vector3<f64>,
        map: Vector3<f64>,
        bar_min: f64,
        bar_max: f64,
        floor_z: f64,
    ) -> Self {
        Cell {
            fixture,
            map,
            bar_min,
            bar_max,
            floor_z,
            fixture_axis: Vector3::z(),
            fixture_cone_cos: -1.0,
            tool_axis: Vector3::z(),
            tool_cone_cos: -1.0,
            cables: [None; 3],
            joint_margin: 0.0,
        }
    }

    /// True when a MAP position (base frame) lies in the EDBB shell and above the floor.
    #[inline]
    pub fn admits(&self, map: &Vector3<f64>) -> bool {
        let d2 = (map - self.fixture).norm_squared();
        d2 >= self.bar_min * self.bar_min
            && d2 <= self.bar_max * self.bar_max
            && map.z > self.floor_z
    }

    /// The instrument and harness checks of one pose, cheapest first: cables, shell, floor,
    /// socket cone, cup cone. `cup_axis` is the tool-cup axis in the base frame.
    #[inline]
    pub fn verdict(
        &self,
        q: &[f64; 6],
        map: &Vector3<f64>,
        cup_axis: &Vector3<f64>,
    ) -> Result<(), Reason> {
        if !self.cables_admit(q) {
            return Err(Reason::CableLimit);
        }
        let d = map - self.fixture;
        let l2 = d.norm_squared();
        if l2 < self.bar_min * self.bar_min || l2 > self.bar_max * self.bar_max {
            return Err(Reason::BarLength);
        }
        if map.z <= self.floor_z {
            return Err(Reason::Floor);
        }
        let l = l2.sqrt();
        // Socket: the bar leaves the fixture ball along d; cup: it arrives at the MAP along −d.
        if d.dot(&self.fixture_axis) < self.fixture_cone_cos * l {
            return Err(Reason::SocketCone);
        }
        if -d.dot(cup_axis) < self.tool_cone_cos * l {
            return Err(Reason::CupCone);
        }
        Ok(())
    }

    #[inline]
    pub fn cables_admit(&self, q: &[f64; 6]) -> bool {
        let v = [q[3], q[5], q[3] + q[5]];
        self.cables
            .iter()
            .zip(v)
            .all(|(r, x)| r.is_none_or(|r| x >= r[0] && x <= r[1]))
    }

    /// Angle between the bar and the socket axis, and between the bar and the cup axis (rad).
    pub fn cone_angles(&self, map: &Vector3<f64>, cup_axis: &Vector3<f64>) -> (f64, f64) {
        let d = (map - self.fixture).normalize();
        (
            d.dot(&self.fixture_axis).clamp(-1.0, 1.0).acos(),
            (-d).dot(cup_axis).clamp(-1.0, 1.0).acos(),
        )
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
    /// Seeded hash of `grid`: the pool is the valid poses with the smallest keys, and later
    /// filters visit candidates in key order, so every subset stays uniform.
    pub key: u64,
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
    /// Duration of each move into pose k from pose k−1, its acceleration ramps included
    /// ([`crate::timing`]), s; 0 for the first pose.
    pub move_times: Vec<f64>,
    /// The same moves at their cruise speed alone (Eq. 7: the slowest joint at its maximum
    /// speed), s: what a feed or speed percentage states.
    #[serde(default)]
    pub cruise_times: Vec<f64>,
    /// Estimated times, s. `time_unsorted`: the selected poses in their pool order by direct
    /// moves (each with its ramps, exact stops, no support poses). `time_sorted`: the program
    /// as planned, in tour order with its support poses, every ramp and blend
    /// ([`crate::timing::program`]).
    pub time_unsorted: f64,
    pub time_sorted: f64,
    /// The same poses as `time_unsorted` in the program's order (the tour, with any pose the
    /// safe planner deferred where it went), by the same direct moves: the like-for-like
    /// comparison with `time_unsorted` (what the ordering gains; the paper's Fig. 6), s.
    #[serde(default)]
    pub time_direct: f64,
}

/// The program: what `emit` renders, and the whole context of every template (`h` = the
/// header, `moves`). The plan (poses, order, blends, times) is the same for every dialect;
/// [`crate::emit::target`] fills the fields that depend on the controller (the dialect, the
/// mapping, each move's axis values and speed percentage) before rendering.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Program {
    pub header: Header,
    pub moves: Vec<Move>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// The program's first line: what it is ("EDBB error-sensitive measurement program").
    #[serde(default = "edbb_title")]
    pub title: String,
    /// The instrument the pauses mount and remove ("EDBB", "LDBB").
    #[serde(default = "edbb_instrument")]
    pub instrument: String,
    /// Further header lines a program kind adds (each one comment line), after the standard ones.
    #[serde(default)]
    pub notes: Vec<String>,
    pub tool_version: String,
    pub robot: String,
    pub robot_file: String,
    pub fixture_mm: [f64; 3],
    pub map_mm: [f64; 3],
    pub bar_mm: [f64; 2],
    pub blend_mm: f64,
    pub margin_mm: f64,
    /// Distance every pose and motion keeps from the joint limits (deg).
    pub joint_margin_deg: f64,
    pub poses: usize,
    pub supports: usize,
    /// Sections of the program (the bar is remounted between them).
    pub sections: usize,
    pub identifiable: usize,
    pub cond: f64,
    /// The measurement poses in pool order by direct moves with exact stops (no support poses,
    /// no blends), s.
    pub time_unsorted_s: f64,
    /// The program's estimated time as planned: support poses, detours and blends included, s.
    pub time_s: f64,
    /// The measurement poses in the program's order by the same direct moves as
    /// `time_unsorted_s`, s.
    #[serde(default)]
    pub time_direct_s: f64,
    /// The joint accelerations the times assume: deg/s² per model joint in the dialect-neutral
    /// program, per controller axis in its units (per s²) once `emit::target` has filled it.
    #[serde(default)]
    pub accelerations: [f64; 6],
    pub inputs_sha256: String,
    pub joint_names: Vec<String>,
    /// What the program buys: the predicted 1σ MAP position uncertainty after calibrating
    /// from its recording, RMS over the joint space (µm), at this bar noise (µm per reading)
    /// and sample rate (Hz).
    pub predicted_std_um: f64,
    pub bar_noise_um: f64,
    pub bar_rate_hz: f64,
    /// The program's name (the output file's stem): KRL's DEF, FANUC's /PROG, RAPID's MODULE.
    #[serde(default)]
    pub program_name: String,
    /// The dialect the program is written in (`ngc`, `krl`, ...).
    #[serde(default)]
    pub dialect: String,
    /// The controller mapping in one line (`J1 = q1, ..., J3 = q3 - q2, ..., in deg`):
    /// `verify` refuses a program whose mapping differs from the one in force.
    #[serde(default)]
    pub controller: String,
    /// The controller's axis names, their unit (`deg` or `rad`) and printed decimals.
    #[serde(default)]
    pub axis_names: Vec<String>,
    #[serde(default)]
    pub axis_units: String,
    #[serde(default)]
    pub axis_decimals: usize,
    /// Stop-and-measure (`--dwell S`): the dwell (s) at every measurement pose after an exact
    /// stop; 0 for a continuous program.
    #[serde(default)]
    pub dwell_s: f64,
    /// Stop-and-measure: the nominal bar length (mm) of each measurement pose in the order the
    /// program dwells at them (pose k = entry k − 1), printed in the header: the key that turns
    /// a bar log's plateaus back into pose readings. Empty for a continuous program.
    #[serde(default)]
    pub measure_mm: Vec<f64>,
    /// Stop-and-measure: the bar samples the prediction averages per plateau, and the predicted
    /// MAP position uncertainty (µm RMS over the joint space) were the same program recorded
    /// continuously with a synchronous joint log (`predicted_std_um` is then the plateaus').
    #[serde(default)]
    pub plateau_samples: usize,
    #[serde(default)]
    pub predicted_continuous_std_um: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Move {
    /// Target joint vector in degrees.
    pub q_deg: [f64; 6],
    /// A support pose (inserted for safety), not a measurement pose.
    pub support: bool,
    /// Made without the bar: the approach, or a transit to the next section.
    pub transit: bool,
    /// Measurement pose number (1-based) for measurement poses.
    pub pose: usize,
    /// Blend distance at the corner this move ends in (mm); 0 = exact stop.
    pub blend_mm: f64,
    /// Planned duration (s), the ramps at the joints' accelerations included.
    pub time_s: f64,
    /// The move at its cruise speed alone (s): the slowest axis at its maximum speed (Eq. 7).
    /// What a feed (G93 F) or a speed percentage states; the controller adds the ramps.
    #[serde(default)]
    pub cruise_s: f64,
    /// The blend instruction's value at this corner in the dialect's unit (SINUMERIK's ADIS in
    /// degrees of axis path); 0 where the instruction takes none.
    #[serde(default)]
    pub blend_value: f64,
    /// Predicted bar length at the target (mm).
    pub length_mm: f64,
    /// The annotation of the move's line when not empty (else pose, length and time).
    #[serde(default)]
    pub note: String,
    /// A transit's instruction at the pause after it, when not empty (else: mount the bar).
    #[serde(default)]
    pub pause: String,
    /// A transit's instruction at the pause before it, when not empty (else: remove the bar).
    #[serde(default)]
    pub pause_before: String,
    /// Section (1-based): the bar is remounted between sections.
    #[serde(default)]
    pub section: usize,
    /// The operator removes the bar before this move (the transit to the next section).
    #[serde(default)]
    pub remove_before: bool,
    /// The operator mounts the bar after this move (its target is a section's first pose).
    #[serde(default)]
    pub mount_after: bool,
    /// The target as controller axis values (the header's units), exactly as printed.
    #[serde(default)]
    pub axes: [f64; 6],
    /// The percentage of every controller axis's maximum speed that makes this move take
    /// `time_s`, the slowest axis leading (100 for the approach; above 100 where the move
    /// cannot be that fast on the controller's axes: the template caps it).
    #[serde(default)]
    pub speed_pct: f64,
    /// Stop-and-measure: the dwell (s) at this move's target, after the exact stop (and, at a
    /// section's first pose, after the mount pause); 0 = none.
    #[serde(default)]
    pub dwell_s: f64,
}

pub const EDBB_TITLE: &str = "EDBB error-sensitive measurement program";

fn edbb_title() -> String {
    EDBB_TITLE.to_string()
}

fn edbb_instrument() -> String {
    "EDBB".to_string()
}

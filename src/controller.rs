//! Controller axes: in = the model's joint values (deg), the cell file's `[controller]` section
//! and a dialect's defaults; out = [`ControllerMap`], the one mapping between model joints and
//! the axis values a controller program carries, applied on emit and undone on read-back.
//!
//! A robot file's joint values are not always the controller's. Signs and zero offsets differ
//! between a URDF and its controller, and FANUC's J3 is the forearm angle from the horizontal,
//! so it moves with J2 (a parallelogram linkage): J3 = q3 ± q2. The mapping is, per axis,
//!
//! ```text
//! c_i = sign_i · q_i + offset_i          (deg)
//! c_3 = sign_3 · q_3 + k · q_2 + offset_3  (k = j3_coupling ∈ {−1, 0, 1})
//! ```
//!
//! then converted to the program's units (deg or rad). It is invertible whatever the values, so
//! a reader recovers the model joints exactly from the printed axis values.
//!
//! **Why the coupling is restricted to −1, 0, 1 and offsets to 0.001°.** The plan lives on the
//! 0.001° grid ([`crate::units::DEG_DECIMALS`]); with integer coupling and grid offsets every
//! controller value of a planned pose lies on that grid too, so the text carries the planned
//! pose exactly in every degree dialect.

use crate::robot::kinematics::chain_frames;
use crate::robot::Robot;
use crate::units::{fmt_fixed, DEG_DECIMALS};
use serde::{Deserialize, Serialize};

/// Angle unit of the axis values in a program text.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Units {
    Deg,
    Rad,
}

impl Units {
    pub fn name(self) -> &'static str {
        match self {
            Units::Deg => "deg",
            Units::Rad => "rad",
        }
    }

    /// Decimals the program prints axis values with: the 0.001° grid in degrees; in radians
    /// 1e-7 rad (6e-6°), far below the grid.
    pub fn decimals(self) -> usize {
        match self {
            Units::Deg => DEG_DECIMALS as usize,
            Units::Rad => 7,
        }
    }

    fn of_deg(self, v: f64) -> f64 {
        match self {
            Units::Deg => v,
            Units::Rad => v.to_radians(),
        }
    }

    fn to_deg(self, v: f64) -> f64 {
        match self {
            Units::Deg => v,
            Units::Rad => v.to_degrees(),
        }
    }
}

/// How J3 follows J2: a fixed factor, or derived from the robot's geometry (the controller's
/// J3 is the forearm angle from the horizontal).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Coupling {
    Factor(i8),
    Auto(AutoWord),
}

/// The word `"auto"` (a unit enum so that serde accepts nothing else).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AutoWord {
    Auto,
}

/// The cell file's `[controller]` section: every key optional; what is missing comes from the
/// dialect's defaults.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerSpec {
    /// +1 or −1 per joint.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sign: Option<[f64; 6]>,
    /// Controller value at model zero, per joint (deg).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset: Option<[f64; 6]>,
    /// J3 = sign3 · q3 + k · q2 + offset3: k = −1, 0, 1 or "auto".
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub j3_coupling: Option<Coupling>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub units: Option<Units>,
    /// Axis names (only where the language takes them from the machine's configuration).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub axis_names: Option<[String; 6]>,
    /// Encoder pulses per degree of each controller axis (signed: the counts grow with the
    /// axis value when positive). Only for mastering offsets as master-count changes
    /// (`edbbgen compensate`, FANUC); the mapping does not use it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pulses_per_deg: Option<[f64; 6]>,
}

/// What a dialect assumes when the cell says nothing (its template's front matter).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControllerDefaults {
    pub units: Units,
    /// False: the language fixes the unit (radians in URScript, degrees in KRL, ...).
    pub units_configurable: bool,
    pub axis_names: [String; 6],
    /// False: the language fixes the names (A1..A6 in KRL, J1..J6 in FANUC LS, ...).
    pub axis_names_configurable: bool,
    pub j3_coupling: Coupling,
    /// The coupling this controller uses on a parallel-arm robot ([`parallel_arm`]) when the
    /// cell does not state one; None: `j3_coupling` whatever the arm (with a warning on a
    /// parallel arm, see [`ControllerMap::coupling_note`]).
    pub j3_coupling_parallel_arm: Option<Coupling>,
}

/// The resolved mapping model joints ↔ controller axes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ControllerMap {
    pub sign: [f64; 6],
    pub offset_deg: [f64; 6],
    pub j3_coupling: f64,
    pub units: Units,
    pub axis_names: [String; 6],
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ControllerError {
    #[error("[controller] {0}")]
    Invalid(String),
}

fn bad(msg: impl Into<String>) -> ControllerError {
    ControllerError::Invalid(msg.into())
}

impl ControllerMap {
    /// The mapping without a dialect (compensated targets): the cell's `[controller]` over
    /// model joints (deg, J1..J6, no coupling unless the cell says so), else the identity.
    pub fn plain(
        spec: Option<&ControllerSpec>,
        robot: &crate::robot::Robot,
    ) -> Result<ControllerMap, ControllerError> {
        let defaults = ControllerDefaults {
            units: Units::Deg,
            units_configurable: true,
            axis_names: ["J1", "J2", "J3", "J4", "J5", "J6"].map(str::to_string),
            axis_names_configurable: true,
            j3_coupling: Coupling::Factor(0),
            j3_coupling_parallel_arm: None,
        };
        ControllerMap::resolve(spec, &defaults, "targets", robot)
    }

    /// Model joints are controller axes (RS274/NGC's default).
    pub fn identity(units: Units, names: [&str; 6]) -> Self {
        ControllerMap {
            sign: [1.0; 6],
            offset_deg: [0.0; 6],
            j3_coupling: 0.0,
            units,
            axis_names: names.map(str::to_string),
        }
    }

    /// Controller axis values (program units) of a model joint vector (deg).
    pub fn apply(&self, q_deg: &[f64; 6]) -> [f64; 6] {
        let c = grid_exact(q_deg, &self.offset_deg, |q, o| {
            let mut c: [f64; 6] = std::array::from_fn(|i| self.sign[i] * q[i] + o[i]);
            c[2] += self.j3_coupling * q[1];
            c
        });
        c.map(|v| self.units.of_deg(v))
    }

    /// The model joint vector (deg) of controller axis values (program units): the inverse of
    /// [`Self::apply`]. Degree values on the 0.001° grid are combined in exact integer
    /// thousandths, so a planned pose read back is the very same number (not one ulp off a
    /// limit it touches).
    pub fn undo(&self, c: &[f64; 6]) -> [f64; 6] {
        let c = c.map(|v| self.units.to_deg(v));
        grid_exact(&c, &self.offset_deg, |c, o| {
            let mut q: [f64; 6] = std::array::from_fn(|i| (c[i] - o[i]) * self.sign[i]);
            q[2] = (c[2] - o[2] - self.j3_coupling * q[1]) * self.sign[2];
            q
        })
    }

    /// Model joints (rad) as the controller's axis values in the form a joint log holds them:
    /// degree axes (a radian axis converted to degrees first) written in radians.
    pub fn log_axes(&self, q: &[f64; 6]) -> [f64; 6] {
        let c = self.apply(&q.map(f64::to_degrees));
        let deg = match self.units {
            Units::Deg => c,
            Units::Rad => c.map(f64::to_degrees),
        };
        deg.map(f64::to_radians)
    }

    /// The controller's axis values as a joint log holds them (rad) as model joints (rad): the
    /// inverse of [`Self::log_axes`].
    pub fn log_joints(&self, c: &[f64; 6]) -> [f64; 6] {
        let deg = c.map(f64::to_degrees);
        let prog = match self.units {
            Units::Deg => deg,
            Units::Rad => deg.map(f64::to_radians),
        };
        self.undo(&prog).map(f64::to_radians)
    }

    /// The maximum speed of each controller axis (program units per second), taking the robot
    /// file's joint speeds (rad/s) as each axis's 100 %. A coupled J3 is driven by its own
    /// motor, whose limit the robot file's joint-3 speed stands for.
    pub fn axis_speeds(&self, model_speeds: &[f64; 6]) -> [f64; 6] {
        model_speeds.map(|v| match self.units {
            Units::Deg => v.to_degrees(),
            Units::Rad => v,
        })
    }

    /// One line that names the mapping, e.g. `J1 = q1, J2 = q2 - 90.000, J3 = q3 - q2, ..., in
    /// deg` (no brackets or semicolons, so it fits every language's comments). Programs print
    /// it; `verify` compares it with the mapping in force.
    pub fn describe(&self) -> String {
        let axes: Vec<String> = (0..6)
            .map(|i| {
                let mut s = format!(
                    "{} = {}q{}",
                    self.axis_names[i],
                    if self.sign[i] < 0.0 { "-" } else { "" },
                    i + 1
                );
                if i == 2 && self.j3_coupling != 0.0 {
                    s += if self.j3_coupling > 0.0 {
                        " + q2"
                    } else {
                        " - q2"
                    };
                }
                let o = self.offset_deg[i];
                if o != 0.0 {
                    s += &format!(
                        " {} {}",
                        if o < 0.0 { "-" } else { "+" },
                        fmt_fixed(o.abs(), DEG_DECIMALS as usize)
                    );
                }
                s
            })
            .collect();
        format!("{}, in {}", axes.join(", "), self.units.name())
    }

    /// Builds the mapping from the cell's section over the dialect's defaults. `auto` coupling
    /// needs the robot (joints 2 and 3 must be parallel).
    pub fn resolve(
        spec: Option<&ControllerSpec>,
        defaults: &ControllerDefaults,
        dialect: &str,
        robot: &Robot,
    ) -> Result<ControllerMap, ControllerError> {
        let empty = ControllerSpec::default();
        let spec = spec.unwrap_or(&empty);
        let sign = spec.sign.unwrap_or([1.0; 6]);
        if let Some(i) = sign.iter().position(|s| *s != 1.0 && *s != -1.0) {
            return Err(bad(format!(
                "sign: joint {} has {}, expected 1 or -1",
                i + 1,
                sign[i]
            )));
        }
        let offset = spec.offset.unwrap_or([0.0; 6]);
        let k = 10f64.powi(DEG_DECIMALS);
        for (i, o) in offset.iter().enumerate() {
            if !(o.is_finite() && o.abs() <= 720.0 && ((o * k).round() - o * k).abs() < 1e-6) {
                return Err(bad(format!(
                    "offset: joint {} has {o} deg; offsets must lie within ±720 deg on the 0.001 deg grid the program carries",
                    i + 1
                )));
            }
        }
        let units = match spec.units {
            Some(u) if u != defaults.units && !defaults.units_configurable => {
                return Err(bad(format!(
                    "units = \"{}\": the {dialect} language writes joint values in {}",
                    u.name(),
                    defaults.units.name()
                )))
            }
            Some(u) => u,
            None => defaults.units,
        };
        let axis_names = match &spec.axis_names {
            Some(n) if !defaults.axis_names_configurable && n != &defaults.axis_names => {
                return Err(bad(format!(
                    "axis_names: the {dialect} language names its axes {}",
                    defaults.axis_names.join(", ")
                )))
            }
            Some(n) => {
                for name in n {
                    let ok = name.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
                        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                        && name.len() <= 16;
                    if !ok {
                        return Err(bad(format!(
                            "axis_names: '{name}' is not an axis name (a letter, then letters, digits or _; at most 16)"
                        )));
                    }
                }
                for i in 0..6 {
                    if n[..i].contains(&n[i]) {
                        return Err(bad(format!("axis_names: '{}' given twice", n[i])));
                    }
                }
                n.clone()
            }
            None => defaults.axis_names.clone(),
        };
        let default_coupling = match (defaults.j3_coupling_parallel_arm, parallel_arm(robot)) {
            (Some(c), Some(_)) => c,
            _ => defaults.j3_coupling,
        };
        let j3_coupling = match spec.j3_coupling.unwrap_or(default_coupling) {
            Coupling::Factor(f) if (-1..=1).contains(&f) => f64::from(f),
            Coupling::Factor(f) => {
                return Err(bad(format!(
                    "j3_coupling: {f}; expected -1, 0, 1 or \"auto\" (a parallelogram couples J3 to J2 one to one)"
                )))
            }
            Coupling::Auto(_) => sign[2] * forearm_coupling(robot).ok_or_else(|| {
                bad(format!(
                    "j3_coupling = \"auto\" (the {dialect} default) needs joints 2 and 3 parallel; set j3_coupling to -1, 0 or 1 for this robot"
                ))
            })?,
        };
        Ok(ControllerMap {
            sign,
            offset_deg: offset,
            j3_coupling,
            units,
            axis_names,
        })
    }
}

impl ControllerMap {
    /// What a user must know about axis 3 when the cell does not state `j3_coupling` and the
    /// robot is a parallel-arm robot ([`parallel_arm`]): such a controller may measure axis 3
    /// from the horizontal (the motor drives the forearm through the parallelogram), and a
    /// program written for the other convention commands axis 3 wrong by q2. None when the
    /// cell states the coupling or the robot shows no parallel arm. The compiler puts the note
    /// in its warnings, the report and the program header.
    pub fn coupling_note(
        spec: Option<&ControllerSpec>,
        defaults: &ControllerDefaults,
        dialect: &str,
        robot: &Robot,
    ) -> Option<String> {
        if spec.is_some_and(|s| s.j3_coupling.is_some()) {
            return None;
        }
        let why = parallel_arm(robot)?;
        Some(match defaults.j3_coupling_parallel_arm {
            Some(_) => format!(
                "J3: {why}; the {dialect} controller measures axis 3 of a parallel-arm robot from the horizontal, so the program writes J3 = q3 {} q2 (j3_coupling = \"auto\"); if this controller measures it from the upper arm, set [controller] j3_coupling = 0 in the cell file",
                if forearm_coupling(robot).unwrap_or(1.0) < 0.0 { "-" } else { "+" }
            ),
            None => match defaults.j3_coupling {
                Coupling::Factor(0) => format!(
                    "J3: {why}; the program writes J3 = q3 (the {dialect} default, j3_coupling = 0); if this controller measures axis 3 from the horizontal (the forearm angle, as ABB and FANUC controllers do on parallel-arm robots), set [controller] j3_coupling = \"auto\" in the cell file, else axis 3 is commanded wrong by q2"
                ),
                _ => return None,
            },
        })
    }
}

/// Robots that are parallel-arm (J2/J3 parallelogram) robots by name, lowercase with spaces,
/// dashes and underscores removed: (name fragment, robot, source). The J3 motor of such a
/// robot sits on the base and drives the forearm through a tie rod, so its controller may
/// count axis 3 from the horizontal.
pub const PARALLEL_ARMS: &[(&str, &str, &str)] = &[
    (
        "irb2400",
        "ABB IRB 2400",
        "ROS-Industrial's abb_driver runs it with J23_coupled = true, abb_irb2400_support",
    ),
    (
        "irb4400",
        "ABB IRB 4400",
        "a parallel arm and tie rod: ABB's IRB 4400 product manual, 3HAC022032-001",
    ),
    (
        "irb5400",
        "ABB IRB 5400",
        "ROS-Industrial's abb_driver runs it with J23_coupled = true, abb_irb5400_support",
    ),
];

/// Why the robot looks like a parallel-arm robot, or None: a passive link (a link with
/// collision geometry behind a mimic joint, [`Robot::passive`]) that follows q3 but hangs off
/// a frame before joint 3 (the base, link 1 or the upper arm):
/// the J3 motion then reaches the forearm through a linkage from behind joint 3, a
/// parallelogram; or a name of [`PARALLEL_ARMS`]. A balancing cylinder that follows q2 (the
/// IRB 6700's) is no such link.
pub fn parallel_arm(robot: &Robot) -> Option<String> {
    if let Some(p) = robot
        .passive
        .iter()
        .find(|p| p.frame < 3 && p.steps.iter().any(|s| s.joint == Some(2)))
    {
        return Some(format!(
            "the robot file's passive link '{}' follows joint 3 from before joint 3 (a parallelogram between joints 2 and 3)",
            p.name
        ));
    }
    let key: String = robot
        .name
        .to_ascii_lowercase()
        .chars()
        .filter(|c| c.is_ascii_alphanumeric())
        .collect();
    PARALLEL_ARMS
        .iter()
        .find(|(frag, _, _)| key.contains(frag))
        .map(|(_, what, src)| {
            format!(
                "the robot '{}' is an {what}, a parallel-arm robot ({src})",
                robot.name
            )
        })
}

/// `f(values, offsets)`, in exact integer thousandths of a degree when every value lies on the
/// 0.001° grid (the plan's values, and what the program prints), else in floating point.
fn grid_exact(
    v: &[f64; 6],
    o: &[f64; 6],
    f: impl Fn(&[f64; 6], &[f64; 6]) -> [f64; 6],
) -> [f64; 6] {
    let k = 10f64.powi(DEG_DECIMALS);
    let on_grid = |x: &f64| x.abs() < 1e12 && ((x * k).round() - x * k).abs() < 1e-6;
    if v.iter().chain(o.iter()).all(on_grid) {
        let vi = v.map(|x| (x * k).round());
        let oi = o.map(|x| (x * k).round());
        // Integers below 2^53 combine exactly; one division per value rounds once.
        f(&vi, &oi).map(|x| x / k)
    } else {
        f(v, o)
    }
}

/// d = ±1 such that q3 + d·q2 is the forearm's angle in the fixed frame (the axes of joints 2
/// and 3 parallel, d = +1 when they point the same way), or None when they are not parallel.
pub fn forearm_coupling(robot: &Robot) -> Option<f64> {
    let f = chain_frames(&robot.base, &robot.dh, &robot.flange, &[0.0; 6]);
    // Frame i−1's z is the axis of joint i.
    let (z2, z3) = (f[1].r.column(2).into_owned(), f[2].r.column(2).into_owned());
    let c = z2.dot(&z3);
    (c.abs() > 1.0 - 1e-6).then(|| c.signum())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(sign: [f64; 6], offset: [f64; 6], k: f64, units: Units) -> ControllerMap {
        ControllerMap {
            sign,
            offset_deg: offset,
            j3_coupling: k,
            units,
            axis_names: ["J1", "J2", "J3", "J4", "J5", "J6"].map(str::to_string),
        }
    }

    #[test]
    fn undo_inverts_apply() {
        let q = [12.345, -67.891, 23.456, 170.0, -95.5, 300.125];
        for m in [
            map([1.0; 6], [0.0; 6], 0.0, Units::Deg),
            map(
                [-1.0, 1.0, -1.0, 1.0, -1.0, 1.0],
                [0.0, -90.0, 90.0, 0.0, 12.5, 0.0],
                1.0,
                Units::Deg,
            ),
            map([1.0; 6], [0.0; 6], -1.0, Units::Rad),
        ] {
            let back = m.undo(&m.apply(&q));
            for i in 0..6 {
                assert!((back[i] - q[i]).abs() < 1e-12, "{m:?}: {back:?}");
            }
        }
        // J3 = q3 − q2, the controller's forearm angle.
        let c = map([1.0; 6], [0.0; 6], -1.0, Units::Deg).apply(&q);
        assert!((c[2] - (q[2] - q[1])).abs() < 1e-12);
    }

    #[test]
    fn describe_names_signs_offsets_and_coupling() {
        let m = map(
            [1.0, 1.0, 1.0, -1.0, 1.0, 1.0],
            [0.0, -90.0, 0.0, 0.0, 0.0, 0.0],
            -1.0,
            Units::Deg,
        );
        assert_eq!(
            m.describe(),
            "J1 = q1, J2 = q2 - 90.000, J3 = q3 - q2, J4 = -q4, J5 = q5, J6 = q6, in deg"
        );
    }

    #[test]
    fn auto_coupling_keeps_the_forearm_angle() {
        // Independent check on the shared FANUC arm: moving q2 by δ and q3 by −d·δ leaves the
        // forearm (joint 3 → wrist centre) pointing the same way in the base frame.
        let path = std::path::Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../shared/robots/fanuc_r2000ic_165f/robot.urdf"
        ));
        let robot = crate::robot::load(path, &Default::default()).unwrap();
        let d = forearm_coupling(&robot).expect("parallel");
        let forearm = |q: &[f64; 6]| {
            let f = chain_frames(&robot.base, &robot.dh, &robot.flange, q);
            (f[4].t - f[2].t).normalize()
        };
        let q = [0.3, 0.2, -0.4, 0.5, 0.6, 0.7];
        let dq = 0.25;
        let moved = [q[0], q[1] + dq, q[2] - d * dq, q[3], q[4], q[5]];
        assert!((forearm(&q) - forearm(&moved)).norm() < 1e-9);
        // The ROS-Industrial FANUC URDF turns J3 about −y and J2 about +y: J3 = q3 − q2.
        assert_eq!(d, -1.0);
        let wrong = [q[0], q[1] + dq, q[2] + d * dq, q[3], q[4], q[5]];
        assert!((forearm(&q) - forearm(&wrong)).norm() > 0.1);
    }

    #[test]
    fn resolve_checks_the_section() {
        let robot = crate::robot::load(
            std::path::Path::new(concat!(
                env!("CARGO_MANIFEST_DIR"),
                "/robots/comau_nj130/robot.dh.toml"
            )),
            &Default::default(),
        )
        .unwrap();
        let defaults = ControllerDefaults {
            units: Units::Deg,
            units_configurable: false,
            axis_names: ["A1", "A2", "A3", "A4", "A5", "A6"].map(str::to_string),
            axis_names_configurable: false,
            j3_coupling: Coupling::Factor(0),
            j3_coupling_parallel_arm: None,
        };
        let ok = ControllerMap::resolve(None, &defaults, "krl", &robot).unwrap();
        assert_eq!(ok.sign, [1.0; 6]);
        for (spec, needle) in [
            (
                ControllerSpec {
                    sign: Some([1.0, 2.0, 1.0, 1.0, 1.0, 1.0]),
                    ..Default::default()
                },
                "sign: joint 2",
            ),
            (
                ControllerSpec {
                    offset: Some([0.0, 0.0005, 0.0, 0.0, 0.0, 0.0]),
                    ..Default::default()
                },
                "offset: joint 2",
            ),
            (
                ControllerSpec {
                    units: Some(Units::Rad),
                    ..Default::default()
                },
                "writes joint values in deg",
            ),
            (
                ControllerSpec {
                    j3_coupling: Some(Coupling::Factor(2)),
                    ..Default::default()
                },
                "j3_coupling: 2",
            ),
        ] {
            let e = ControllerMap::resolve(Some(&spec), &defaults, "krl", &robot)
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{e}");
        }
        // The NJ-130 table (corrected, α2 = −180°): the axes of joints 2 and 3 are antiparallel,
        // so the forearm angle is q3 − q2.
        assert_eq!(forearm_coupling(&robot), Some(-1.0));
    }
}

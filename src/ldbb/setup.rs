//! The LDBB setup (`SETUP.toml`, DESIGN.md "LDBB loaded circle data"): in = TOML text in user
//! units (mm, deg, N, s); out = [`Setup`] in SI, with the circle's geometry.
//!
//! Angle convention (DESIGN.md): the circle angle θ is 0 at +x of the circle frame (the robot
//! base axes moved to the circle centre) and grows along the direction of travel. Clockwise
//! seen from +z means P(θ) = centre + R·[cos θ, −sin θ, 0]; counterclockwise
//! P(θ) = centre + R·[cos θ, sin θ, 0]. Unknown keys are errors: a typo must not pass silently.

use crate::units::{DEG, MM};
use nalgebra::{Matrix3, Vector3};
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// Direction of travel, seen from +z of the robot base.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    Clockwise,
    Counterclockwise,
}

/// The circle the tool ball runs on (SI).
#[derive(Clone, Debug, PartialEq)]
pub struct Circle {
    pub centre: Vector3<f64>,
    pub radius: f64,
    pub direction: Direction,
    /// Tool-ball speed along the circle (m/s).
    pub speed: f64,
    /// Lead-in and lead-out travel around each load's measured circles (rad).
    pub overshoot: f64,
    /// Samples per circle the simulator records (the paper: 15,899 at 1 kHz).
    pub samples_per_circle: usize,
}

impl Circle {
    /// Unit direction from the centre to the tool ball at circle angle `theta` (rad).
    #[inline]
    pub fn radial(&self, theta: f64) -> Vector3<f64> {
        let (s, c) = theta.sin_cos();
        match self.direction {
            Direction::Clockwise => Vector3::new(c, -s, 0.0),
            Direction::Counterclockwise => Vector3::new(c, s, 0.0),
        }
    }

    /// The nominal tool-ball position at circle angle `theta` (rad).
    #[inline]
    pub fn point(&self, theta: f64) -> Vector3<f64> {
        self.centre + self.radius * self.radial(theta)
    }
}

/// The LDBB setup in SI units.
#[derive(Clone, Debug, PartialEq)]
pub struct Setup {
    /// The robot file, resolved against the setup file's directory.
    pub robot: Option<PathBuf>,
    pub base_link: Option<String>,
    pub end_link: Option<String>,
    pub circle: Circle,
    /// Table ball centre, robot base frame (m).
    pub table_ball: Vector3<f64>,
    /// Nominal bar length: ball-centre distance the LVDT reads as zero deflection (m).
    pub bar_length: f64,
    /// Tool ball centre in the end link frame (m).
    pub map_offset: Option<Vector3<f64>>,
    /// Constant tool orientation: the end link's axes in the base frame (columns).
    pub orientation: Option<Matrix3<f64>>,
    /// Laser-tracker point in the end link frame (m).
    pub lt_map_offset: Option<Vector3<f64>>,
    /// Nominal loads (N), ascending.
    pub loads: Vec<f64>,
    /// Circles recorded per load.
    pub repeats: usize,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SetupT {
    robot: Option<String>,
    base_link: Option<String>,
    end_link: Option<String>,
    circle: CircleT,
    table_ball: TableT,
    tool: Option<ToolT>,
    loads: LoadsT,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CircleT {
    centre_mm: [f64; 3],
    diameter_mm: f64,
    direction: String,
    #[allow(dead_code)]
    angle_definition: Option<String>,
    speed_mm_s: Option<f64>,
    overshoot_deg: Option<f64>,
    samples_per_circle: Option<usize>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TableT {
    position_mm: [f64; 3],
    bar_length_mm: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ToolT {
    map_offset_mm: Option<[f64; 3]>,
    orientation_matrix: Option<[[f64; 3]; 3]>,
    lt_map_offset_mm: Option<[f64; 3]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LoadsT {
    loads_n: Vec<f64>,
    repeats: usize,
}

pub const DEFAULT_SPEED_MM_S: f64 = 50.0;
pub const DEFAULT_OVERSHOOT_DEG: f64 = 180.0;
pub const DEFAULT_SAMPLES_PER_CIRCLE: usize = 4000;

fn finite(key: &str, v: &[f64]) -> Result<(), String> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(format!("{key}: values must be finite numbers"))
    }
}

impl Setup {
    /// Parses SETUP.toml. `dir` is the setup file's directory (the robot path is relative to
    /// it). Errors are one line naming the line and column or the key.
    pub fn from_toml(text: &str, dir: &Path) -> Result<Setup, String> {
        let s: SetupT = toml::from_str(text).map_err(|e| crate::robot::dh::toml_error(text, &e))?;
        let c = &s.circle;
        finite("circle.centre_mm", &c.centre_mm)?;
        if !(c.diameter_mm.is_finite() && c.diameter_mm > 0.0) {
            return Err(format!(
                "circle.diameter_mm: {} must be a positive number",
                c.diameter_mm
            ));
        }
        let direction = match c.direction.trim() {
            "clockwise seen from +z" | "clockwise" => Direction::Clockwise,
            "counterclockwise seen from +z" | "counterclockwise" => Direction::Counterclockwise,
            d => {
                return Err(format!(
                    "circle.direction: \"{d}\" is not \"clockwise seen from +z\" or \"counterclockwise seen from +z\""
                ))
            }
        };
        let speed = c.speed_mm_s.unwrap_or(DEFAULT_SPEED_MM_S);
        if !(speed.is_finite() && speed > 0.0 && speed <= 2000.0) {
            return Err(format!(
                "circle.speed_mm_s: {speed} must be in (0, 2000] mm/s"
            ));
        }
        let overshoot = c.overshoot_deg.unwrap_or(DEFAULT_OVERSHOOT_DEG);
        if !(overshoot.is_finite() && (0.0..=720.0).contains(&overshoot)) {
            return Err(format!(
                "circle.overshoot_deg: {overshoot} must be in [0, 720] deg"
            ));
        }
        let samples = c.samples_per_circle.unwrap_or(DEFAULT_SAMPLES_PER_CIRCLE);
        if !(36..=10_000_000).contains(&samples) {
            return Err(format!(
                "circle.samples_per_circle: {samples} must be in 36..10000000"
            ));
        }
        finite("table_ball.position_mm", &s.table_ball.position_mm)?;
        let bar = s.table_ball.bar_length_mm;
        if !(bar.is_finite() && bar > 0.0) {
            return Err(format!(
                "table_ball.bar_length_mm: {bar} must be a positive number"
            ));
        }
        let (mut map_offset, mut orientation, mut lt) = (None, None, None);
        if let Some(t) = &s.tool {
            if let Some(m) = t.map_offset_mm {
                finite("tool.map_offset_mm", &m)?;
                map_offset = Some(Vector3::from(m) * MM);
            }
            if let Some(m) = t.lt_map_offset_mm {
                finite("tool.lt_map_offset_mm", &m)?;
                lt = Some(Vector3::from(m) * MM);
            }
            if let Some(r) = t.orientation_matrix {
                let m = Matrix3::from_fn(|i, j| r[i][j]);
                if !m.iter().all(|v| v.is_finite())
                    || (m.transpose() * m - Matrix3::identity()).abs().max() > 1e-6
                    || m.determinant() < 0.0
                {
                    return Err(
                        "tool.orientation_matrix: must be a rotation (orthonormal rows, determinant +1; rows of base_R_end, its columns are the end link's axes in the base frame)"
                            .into(),
                    );
                }
                // Re-orthonormalise the 1e-6 the check allows, so IK aims at a true rotation.
                let svd = m.svd(true, true);
                orientation = match (svd.u, svd.v_t) {
                    (Some(u), Some(vt)) => Some(u * vt),
                    _ => Some(m),
                };
            }
        }
        let loads = s.loads.loads_n.clone();
        if loads.len() < 2 {
            return Err(format!(
                "loads.loads_n: {} load(s); the mechanical base load reference needs at least 2",
                loads.len()
            ));
        }
        if loads.iter().any(|f| !(f.is_finite() && *f > 0.0)) {
            return Err("loads.loads_n: every load must be a positive number (N)".into());
        }
        if loads.windows(2).any(|w| w[1] <= w[0]) {
            return Err("loads.loads_n: loads must be strictly ascending".into());
        }
        if !(1..=1000).contains(&s.loads.repeats) {
            return Err(format!(
                "loads.repeats: {} must be in 1..1000",
                s.loads.repeats
            ));
        }
        Ok(Setup {
            robot: s.robot.as_ref().map(|r| dir.join(r)),
            base_link: s.base_link.clone(),
            end_link: s.end_link.clone(),
            circle: Circle {
                centre: Vector3::from(c.centre_mm) * MM,
                radius: 0.5 * c.diameter_mm * MM,
                direction,
                speed: speed * MM,
                overshoot: overshoot * DEG,
                samples_per_circle: samples,
            },
            table_ball: Vector3::from(s.table_ball.position_mm) * MM,
            bar_length: bar * MM,
            map_offset,
            orientation,
            lt_map_offset: lt,
            loads,
            repeats: s.loads.repeats,
        })
    }

    /// The nominal bar direction (unit, from the table ball to the tool ball) at angle `theta`.
    pub fn bar_direction(&self, theta: f64) -> Vector3<f64> {
        (self.circle.point(theta) - self.table_ball).normalize()
    }

    /// What a user must know about the geometry: the bar length the circle and the table ball
    /// imply, against the one the setup states.
    pub fn warnings(&self) -> Vec<String> {
        let mut w = Vec::new();
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for k in 0..360 {
            let l = (self.circle.point(k as f64 * DEG) - self.table_ball).norm();
            lo = lo.min(l);
            hi = hi.max(l);
        }
        let off = (self.bar_length - lo)
            .abs()
            .max((self.bar_length - hi).abs());
        if off > 0.5 * MM {
            w.push(format!(
                "the circle and the table ball give a bar length of {:.3}..{:.3} mm, the setup states {:.3} mm: check table_ball.position_mm and bar_length_mm",
                lo / MM,
                hi / MM,
                self.bar_length / MM
            ));
        }
        w
    }

    /// The tool settings a robot needs (IK, stiffness, program).
    pub fn tool(&self) -> Result<(Vector3<f64>, Matrix3<f64>), String> {
        match (self.map_offset, self.orientation) {
            (Some(m), Some(r)) => Ok((m, r)),
            (None, _) => Err("[tool] map_offset_mm: needed with a robot (the tool ball centre in the end link frame)".into()),
            (_, None) => Err("[tool] orientation_matrix: needed with a robot (the constant tool orientation)".into()),
        }
    }
}

/// The DESIGN.md example setup (the paper's circle on the ABB IRB 6700), for unit tests.
#[cfg(test)]
pub(crate) mod tests_support {
    use super::Setup;

    pub const PAPER: &str = r#"
robot = "abb_irb6700_200_260/robot.urdf"
base_link = "base_link"
end_link = "tool0"
[circle]
centre_mm = [1350.0, -125.0, 1250.0]
diameter_mm = 250.0
direction = "clockwise seen from +z"
angle_definition = "P(angle) = centre + 125 mm * [cos(angle), -sin(angle), 0]"
speed_mm_s = 50.0
overshoot_deg = 180.0
samples_per_circle = 4000
[table_ball]
position_mm = [1350.0, -125.0, 1205.805826]
bar_length_mm = 132.582521
[tool]
map_offset_mm = [0.0, 0.0, 150.0]
orientation_matrix = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]
lt_map_offset_mm = [6.0, 0.0, 150.0]
[loads]
loads_n = [125.0, 250.0, 375.0, 500.0, 625.0]
repeats = 3
"#;

    pub fn paper_setup() -> Setup {
        Setup::from_toml(PAPER, std::path::Path::new(".")).unwrap()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tests_support::PAPER;

    #[test]
    fn reads_the_design_example_and_follows_its_angle_convention() {
        let s = Setup::from_toml(PAPER, Path::new("/x")).unwrap();
        assert_eq!(
            s.robot.as_deref(),
            Some(Path::new("/x/abb_irb6700_200_260/robot.urdf"))
        );
        assert!(s.warnings().is_empty(), "{:?}", s.warnings());
        // Clockwise seen from +z: at 90° the ball is at −y of the centre.
        let p = s.circle.point(90.0 * DEG);
        assert!((p - Vector3::new(1.350, -0.250, 1.250)).norm() < 1e-12);
        // The bar length the geometry gives is the stated one.
        for k in 0..8 {
            let l = (s.circle.point(k as f64 * 0.8) - s.table_ball).norm();
            assert!((l - s.bar_length).abs() < 1e-9);
        }
        // The load's vertical share is a third, as in the paper's Fig. 8.
        assert!((s.bar_direction(0.3).z - 1.0 / 3.0).abs() < 1e-6);
    }

    #[test]
    fn a_key_typo_names_line_and_column() {
        let bad = PAPER.replace("bar_length_mm", "bar_lenght_mm");
        let e = Setup::from_toml(&bad, Path::new(".")).unwrap_err();
        assert!(e.contains("line") && e.contains("bar_lenght_mm"), "{e}");
        let bad = PAPER.replace("clockwise seen from +z\"", "clockwise from above\"");
        let e = Setup::from_toml(&bad, Path::new(".")).unwrap_err();
        assert!(e.contains("circle.direction"), "{e}");
        let bad = PAPER.replace(
            "[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]",
            "[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]",
        );
        let e = Setup::from_toml(&bad, Path::new(".")).unwrap_err();
        assert!(e.contains("orientation_matrix"), "{e}");
        let bad = PAPER.replace("[125.0, 250.0", "[250.0, 125.0");
        assert!(Setup::from_toml(&bad, Path::new("."))
            .unwrap_err()
            .contains("ascending"));
    }
}

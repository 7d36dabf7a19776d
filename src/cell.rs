//! The cell description (`--cell cell.toml`): in = TOML text (millimetres, degrees); out =
//! [`CellSpec`] in SI units. CLI flags override what the file says; without a file every value
//! has a documented default, so the compiler's first form keeps working unchanged.
//!
//! ```toml
//! [fixture]
//! position = [258.0, 1468.0, 708.0]   # fixture ball centre, robot base frame (mm)
//! axis = [0.0, 0.0, 1.0]              # socket axis: from the socket into free space
//! cone = 60.0                         # bar direction within this half-angle of the axis (deg)
//! stand_radius = 40.0                 # fixture stand: vertical cylinder from the floor to the
//!                                     # socket below the ball (0 = no stand)
//! [bar]
//! min = 300.0                         # usable ball-centre distance (mm)
//! max = 520.0
//! diameter = 30.0                     # bar body diameter (a capsule between the balls)
//! ball = 25.0                         # ball diameter
//! [tool]
//! map = [60.0, 30.0, 120.0]           # MAP (tool ball centre) in the flange frame (mm)
//! axis = [0.0, 0.0, 1.0]              # tool cup axis in the flange frame (opening direction;
//!                                     # default: along joint 6, away from the wrist)
//! cone = 60.0                         # bar direction within this half-angle of the cup axis
//! [[tool.shapes]]                     # the tool body, in the flange frame
//! type = "cylinder"                   # box | cylinder | sphere | capsule | mesh
//! radius = 45.0
//! length = 90.0
//! origin = [0.0, 0.0, 45.0]           # centre; cylinders and capsules run along local z
//! rpy = [0.0, 0.0, 0.0]               # deg, fixed-axis roll-pitch-yaw
//! [floor]
//! z = 0.0
//! [[environment]]                     # static obstacles, robot base frame
//! name = "table"
//! type = "box"
//! size = [800.0, 600.0, 700.0]
//! origin = [1200.0, -900.0, 350.0]
//! [cables]                            # wiring-harness limits on the joint variables (deg)
//! q4 = [-270.0, 270.0]
//! q6 = [-270.0, 270.0]
//! q4_plus_q6 = [-300.0, 300.0]
//! [[cables.hoses]]                    # dress pack, attached to DH frame `frame`
//! name = "forearm hose"
//! frame = 3
//! type = "capsule"
//! from = [0.0, -150.0, 0.0]
//! to = [0.0, -150.0, 700.0]
//! radius = 45.0
//! [robot]
//! link_radius = 90.0                  # DH robots without geometry: capsule radius per link
//! speeds = [110, 100, 110, 180, 180, 260]   # deg/s, for URDFs without joint velocities
//! accelerations = [220, 200, 220, 360, 360, 520]   # deg/s², the controller's joint accelerations
//! [safety]
//! margin = 10.0                       # minimum clearance between any two bodies (mm)
//! joint_margin = 1.0                  # distance kept from every joint limit (deg)
//! [controller]                        # model joints -> the controller's axes (every key
//!                                     # optional; the dialect's defaults fill the rest)
//! sign = [1, 1, 1, 1, 1, 1]           # +1 or -1 per joint
//! offset = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]   # controller value at model zero (deg)
//! j3_coupling = 0                     # J3 = sign3*q3 + k*q2 + offset3: -1, 0, 1 or "auto"
//! units = "deg"                       # "deg" | "rad", where the language leaves it open
//! # pulses_per_deg = [1e4, 1e4, 1e4, 1e4, 1e4, 1e4]   # encoder pulses per axis degree, for
//!                                     # compensate's FANUC master-count changes (optional)
//! ```

use crate::controller::ControllerSpec;
use crate::robot::Frame;
use crate::units::{DEG, MM};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A primitive or mesh in some frame (SI).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ShapeKind {
    Box {
        size: [f64; 3],
    },
    /// Along local z, centred on the origin.
    Cylinder {
        radius: f64,
        length: f64,
    },
    Sphere {
        radius: f64,
    },
    /// Segment from `a` to `b` (local coordinates) swept by `radius`.
    Capsule {
        a: [f64; 3],
        b: [f64; 3],
        radius: f64,
    },
    Mesh {
        path: PathBuf,
        scale: [f64; 3],
    },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Shape {
    pub name: String,
    pub origin: Frame,
    pub kind: ShapeKind,
}

/// A shape moving with a DH frame (0 = robot base ... 6, 7 = flange).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AttachedShape {
    pub frame: usize,
    pub shape: Shape,
}

/// Everything about the cell, resolved to SI units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellSpec {
    pub fixture: Option<Vector3<f64>>,
    /// Unit socket axis in the base frame.
    pub fixture_axis: Vector3<f64>,
    /// Half-angle of the socket cone (rad).
    pub fixture_cone: f64,
    pub stand_radius: f64,
    pub bar_min: f64,
    pub bar_max: f64,
    pub bar_diameter: f64,
    pub ball: f64,
    pub map: Option<Vector3<f64>>,
    /// Unit cup axis in the flange frame; None = the joint-6 axis pointing away from the wrist
    /// (the compiler's default).
    pub tool_axis: Option<Vector3<f64>>,
    pub tool_cone: f64,
    pub tool_shapes: Vec<Shape>,
    pub floor_z: f64,
    pub environment: Vec<Shape>,
    /// Harness limits (rad): q4, q6, q4 + q6.
    pub cable_q4: Option<[f64; 2]>,
    pub cable_q6: Option<[f64; 2]>,
    pub cable_q4_q6: Option<[f64; 2]>,
    pub hoses: Vec<AttachedShape>,
    pub link_radius: Option<f64>,
    pub speeds: Option<[f64; 6]>,
    /// Joint accelerations (rad/s²) replacing the robot file's (`[robot] accelerations`).
    /// Skipped when absent so that cells without it keep their input hash.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub accelerations: Option<[f64; 6]>,
    pub margin: f64,
    /// Distance kept from every joint limit (rad): controllers enforce soft limits and
    /// overshoot slightly when blending, so no pose or motion may come closer.
    pub joint_margin: f64,
    /// Model joints → controller axes (`[controller]`); None = the dialect's defaults.
    /// Skipped when absent so that cells without it keep their input hash.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub controller: Option<ControllerSpec>,
    /// Which limits the cell file (or a flag) stated rather than left at their defaults:
    /// `verify` takes the others from the program's header. Not part of the input hash (the
    /// values are).
    #[serde(skip)]
    pub stated: Stated,
}

/// The limits a cell file or a flag stated (see [`CellSpec::stated`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stated {
    pub bar_min: bool,
    pub bar_max: bool,
    pub ball: bool,
    pub margin: bool,
    pub joint_margin: bool,
}

/// Usable bar length (ball-centre distance) when neither the cell nor `--bar` gives one (mm).
pub const DEFAULT_BAR_MM: (f64, f64) = (300.0, 520.0);
/// Ball diameter assumed when none is given (precision ball-bar balls are 12.7–25.4 mm).
pub const DEFAULT_BALL_MM: f64 = 25.0;
pub const DEFAULT_CONE_DEG: f64 = 60.0;
pub const DEFAULT_JOINT_MARGIN_DEG: f64 = 1.0;
pub const DEFAULT_BAR_DIAMETER_MM: f64 = 30.0;
pub const DEFAULT_STAND_RADIUS_MM: f64 = 0.0;
pub const DEFAULT_MARGIN_MM: f64 = 10.0;

impl Default for CellSpec {
    fn default() -> Self {
        CellSpec {
            fixture: None,
            fixture_axis: Vector3::z(),
            fixture_cone: DEFAULT_CONE_DEG * DEG,
            stand_radius: DEFAULT_STAND_RADIUS_MM * MM,
            bar_min: DEFAULT_BAR_MM.0 * MM,
            bar_max: DEFAULT_BAR_MM.1 * MM,
            bar_diameter: DEFAULT_BAR_DIAMETER_MM * MM,
            ball: DEFAULT_BALL_MM * MM,
            map: None,
            tool_axis: None,
            tool_cone: DEFAULT_CONE_DEG * DEG,
            tool_shapes: Vec::new(),
            floor_z: 0.0,
            environment: Vec::new(),
            cable_q4: None,
            cable_q6: None,
            cable_q4_q6: None,
            hoses: Vec::new(),
            link_radius: None,
            speeds: None,
            accelerations: None,
            margin: DEFAULT_MARGIN_MM * MM,
            joint_margin: DEFAULT_JOINT_MARGIN_DEG * DEG,
            controller: None,
            stated: Stated::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum CellError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {msg}")]
    Invalid { path: String, msg: String },
}

// ---- the TOML form (millimetres and degrees) ---------------------------------------------

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    fixture: Option<FixtureT>,
    #[serde(default)]
    bar: Option<BarT>,
    #[serde(default)]
    tool: Option<ToolT>,
    #[serde(default)]
    floor: Option<FloorT>,
    #[serde(default)]
    environment: Vec<ShapeT>,
    #[serde(default)]
    cables: Option<CablesT>,
    #[serde(default)]
    robot: Option<RobotT>,
    #[serde(default)]
    safety: Option<SafetyT>,
    #[serde(default)]
    controller: Option<ControllerSpec>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FixtureT {
    position: Option<[f64; 3]>,
    axis: Option<[f64; 3]>,
    cone: Option<f64>,
    stand_radius: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BarT {
    min: Option<f64>,
    max: Option<f64>,
    diameter: Option<f64>,
    ball: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ToolT {
    map: Option<[f64; 3]>,
    axis: Option<[f64; 3]>,
    cone: Option<f64>,
    #[serde(default)]
    shapes: Vec<ShapeT>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FloorT {
    z: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CablesT {
    q4: Option<[f64; 2]>,
    q6: Option<[f64; 2]>,
    q4_plus_q6: Option<[f64; 2]>,
    #[serde(default)]
    hoses: Vec<ShapeT>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RobotT {
    link_radius: Option<f64>,
    speeds: Option<[f64; 6]>,
    accelerations: Option<[f64; 6]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SafetyT {
    margin: Option<f64>,
    joint_margin: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ShapeT {
    #[serde(default)]
    name: Option<String>,
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    frame: Option<usize>,
    #[serde(default)]
    origin: Option<[f64; 3]>,
    #[serde(default)]
    rpy: Option<[f64; 3]>,
    #[serde(default)]
    size: Option<[f64; 3]>,
    #[serde(default)]
    radius: Option<f64>,
    #[serde(default)]
    length: Option<f64>,
    #[serde(default)]
    from: Option<[f64; 3]>,
    #[serde(default)]
    to: Option<[f64; 3]>,
    #[serde(default)]
    file: Option<String>,
    #[serde(default)]
    scale: Option<[f64; 3]>,
}

/// Loads a cell file. Relative mesh paths resolve against the file's folder.
pub fn load(path: &Path) -> Result<CellSpec, CellError> {
    let text = crate::files::read_text(path, crate::files::Kind::Config).map_err(|e| match e {
        crate::files::ReadError::Io(source) => CellError::Io {
            path: path.display().to_string(),
            source,
        },
        other => CellError::Invalid {
            path: path.display().to_string(),
            msg: other.to_string(),
        },
    })?;
    from_str(&text, path)
}

pub fn from_str(text: &str, path: &Path) -> Result<CellSpec, CellError> {
    let bad = |msg: String| CellError::Invalid {
        path: path.display().to_string(),
        msg,
    };
    let f: File = toml::from_str(text).map_err(|e| bad(crate::robot::dh::toml_error(text, &e)))?;
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let mut c = CellSpec::default();
    let v3 = |a: [f64; 3]| Vector3::new(a[0], a[1], a[2]) * MM;
    let unit = |a: [f64; 3], field: &str| -> Result<Vector3<f64>, CellError> {
        let v = Vector3::from(a);
        let n = v.norm();
        if !(n.is_finite() && n > 1e-12) {
            return Err(bad(format!("{field}: must be a non-zero direction")));
        }
        Ok(v / n)
    };
    let cone = |deg: f64, field: &str| -> Result<f64, CellError> {
        if !(deg > 0.0 && deg <= 180.0) {
            return Err(bad(format!("{field}: {deg} deg must be in (0, 180]")));
        }
        Ok(deg * DEG)
    };
    let positive = |v: f64, field: &str| -> Result<f64, CellError> {
        if !(v.is_finite() && v >= 0.0) {
            return Err(bad(format!("{field}: {v} must be >= 0")));
        }
        Ok(v * MM)
    };
    if let Some(x) = f.fixture {
        c.fixture = x.position.map(v3);
        if let Some(a) = x.axis {
            c.fixture_axis = unit(a, "fixture.axis")?;
        }
        if let Some(d) = x.cone {
            c.fixture_cone = cone(d, "fixture.cone")?;
        }
        if let Some(r) = x.stand_radius {
            c.stand_radius = positive(r, "fixture.stand_radius")?;
        }
    }
    if let Some(b) = f.bar {
        if let Some(v) = b.min {
            c.bar_min = positive(v, "bar.min")?;
            c.stated.bar_min = true;
        }
        if let Some(v) = b.max {
            c.bar_max = positive(v, "bar.max")?;
            c.stated.bar_max = true;
        }
        if c.bar_max <= c.bar_min {
            return Err(bad("bar: max must be greater than min".into()));
        }
        if let Some(v) = b.diameter {
            c.bar_diameter = positive(v, "bar.diameter")?;
        }
        if let Some(v) = b.ball {
            c.ball = positive(v, "bar.ball")?;
            c.stated.ball = true;
        }
    }
    if let Some(t) = f.tool {
        c.map = t.map.map(v3);
        if let Some(a) = t.axis {
            c.tool_axis = Some(unit(a, "tool.axis")?);
        }
        if let Some(d) = t.cone {
            c.tool_cone = cone(d, "tool.cone")?;
        }
        for (k, s) in t.shapes.iter().enumerate() {
            c.tool_shapes
                .push(shape(s, &format!("tool.shapes[{k}]"), &dir).map_err(bad)?);
        }
    }
    if let Some(fl) = f.floor {
        c.floor_z = fl.z * MM;
    }
    for (k, s) in f.environment.iter().enumerate() {
        c.environment
            .push(shape(s, &format!("environment[{k}]"), &dir).map_err(bad)?);
    }
    if let Some(cb) = f.cables {
        let range = |r: [f64; 2], field: &str| -> Result<[f64; 2], CellError> {
            if !(r[0].is_finite() && r[1].is_finite() && r[0] < r[1]) {
                return Err(bad(format!(
                    "cables.{field}: needs [lower, upper] with lower < upper"
                )));
            }
            Ok([r[0] * DEG, r[1] * DEG])
        };
        c.cable_q4 = cb.q4.map(|r| range(r, "q4")).transpose()?;
        c.cable_q6 = cb.q6.map(|r| range(r, "q6")).transpose()?;
        c.cable_q4_q6 = cb.q4_plus_q6.map(|r| range(r, "q4_plus_q6")).transpose()?;
        for (k, s) in cb.hoses.iter().enumerate() {
            let field = format!("cables.hoses[{k}]");
            let frame = s.frame.ok_or_else(|| {
                bad(format!(
                    "{field}.frame: which DH frame (0-7) the hose moves with"
                ))
            })?;
            if frame > 7 {
                return Err(bad(format!("{field}.frame: {frame} is not a frame 0-7")));
            }
            c.hoses.push(AttachedShape {
                frame,
                shape: shape(s, &field, &dir).map_err(bad)?,
            });
        }
    }
    if let Some(r) = f.robot {
        c.link_radius = r
            .link_radius
            .map(|v| positive(v, "robot.link_radius"))
            .transpose()?;
        if let Some(s) = r.speeds {
            if s.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(bad("robot.speeds: six positive joint speeds (deg/s)".into()));
            }
            c.speeds = Some(s.map(|v| v * DEG));
        }
        if let Some(a) = r.accelerations {
            if a.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(bad(
                    "robot.accelerations: six positive joint accelerations (deg/s^2)".into(),
                ));
            }
            c.accelerations = Some(a.map(|v| v * DEG));
        }
    }
    if let Some(s) = f.safety {
        if let Some(m) = s.margin {
            c.margin = positive(m, "safety.margin")?;
            c.stated.margin = true;
        }
        if let Some(m) = s.joint_margin {
            if !(m.is_finite() && (0.0..=30.0).contains(&m)) {
                return Err(bad(format!(
                    "safety.joint_margin: {m} deg must be between 0 and 30 deg"
                )));
            }
            c.joint_margin = m * DEG;
            c.stated.joint_margin = true;
        }
    }
    c.controller = f.controller;
    Ok(c)
}

fn shape(s: &ShapeT, field: &str, dir: &Path) -> Result<Shape, String> {
    let need = |v: Option<f64>, what: &str| -> Result<f64, String> {
        match v {
            Some(x) if x.is_finite() && x > 0.0 => Ok(x * MM),
            Some(x) => Err(format!("{field}.{what}: {x} must be > 0")),
            None => Err(format!("{field}.{what}: missing")),
        }
    };
    let origin = Frame::from_xyz_rpy(
        s.origin.unwrap_or([0.0; 3]).map(|v| v * MM),
        s.rpy.unwrap_or([0.0; 3]).map(|v| v * DEG),
    );
    let kind = match s.kind.as_str() {
        "box" => {
            let size = s.size.ok_or_else(|| format!("{field}.size: missing"))?;
            if size.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(format!("{field}.size: three positive lengths"));
            }
            ShapeKind::Box {
                size: size.map(|v| v * MM),
            }
        }
        "cylinder" => ShapeKind::Cylinder {
            radius: need(s.radius, "radius")?,
            length: need(s.length, "length")?,
        },
        "sphere" => ShapeKind::Sphere {
            radius: need(s.radius, "radius")?,
        },
        "capsule" => ShapeKind::Capsule {
            a: s.from
                .ok_or_else(|| format!("{field}.from: missing"))?
                .map(|v| v * MM),
            b: s.to
                .ok_or_else(|| format!("{field}.to: missing"))?
                .map(|v| v * MM),
            radius: need(s.radius, "radius")?,
        },
        "mesh" => {
            let file = s
                .file
                .as_ref()
                .ok_or_else(|| format!("{field}.file: missing"))?;
            let p = dir.join(file);
            if !p.exists() {
                return Err(format!("{field}.file: {} does not exist", p.display()));
            }
            // Mesh vertices are in mm like everything else in the cell file.
            ShapeKind::Mesh {
                path: p,
                scale: s.scale.unwrap_or([1.0; 3]).map(|v| v * MM),
            }
        }
        k => {
            return Err(format!(
                "{field}.type: '{k}' (expected box, cylinder, sphere, capsule or mesh)"
            ))
        }
    };
    Ok(Shape {
        name: s.name.clone().unwrap_or_else(|| field.to_string()),
        origin,
        kind,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_documented_example_parses() {
        let doc = include_str!("cell.rs");
        let example: String = doc
            .lines()
            .skip_while(|l| !l.starts_with("//! ```toml"))
            .skip(1)
            .take_while(|l| !l.starts_with("//! ```"))
            .map(|l| {
                l.trim_start_matches("//!")
                    .strip_prefix(' ')
                    .unwrap_or("")
                    .to_string()
                    + "\n"
            })
            .collect();
        let c = from_str(&example, Path::new("cell.toml")).expect("example parses");
        assert_eq!(c.fixture, Some(Vector3::new(0.258, 1.468, 0.708)));
        assert_eq!(c.hoses.len(), 1);
        assert_eq!(c.hoses[0].frame, 3);
        assert!((c.cable_q4_q6.unwrap()[1] - 300.0 * DEG).abs() < 1e-12);
        assert!((c.margin - 0.010).abs() < 1e-15);
        assert_eq!(c.environment.len(), 1);
    }

    #[test]
    fn errors_name_the_field() {
        for (text, needle) in [
            ("[fixture]\naxis = [0, 0, 0]\n", "fixture.axis"),
            ("[bar]\nmin = 500\nmax = 300\n", "bar: max"),
            ("[[environment]]\ntype = \"cone\"\n", "environment[0].type"),
            ("[cables]\nq4 = [10, -10]\n", "cables.q4"),
            (
                "[[cables.hoses]]\ntype = \"sphere\"\nradius = 3\n",
                "cables.hoses[0].frame",
            ),
            ("[tool]\nmapp = [1, 2, 3]\n", "line 2"),
        ] {
            let e = from_str(text, Path::new("c.toml")).unwrap_err().to_string();
            assert!(e.contains(needle), "{text:?}: {e}");
            assert!(!e.contains('\n'));
        }
    }
}

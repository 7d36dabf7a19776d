//! Robot model: in = a `.dh.toml` or `.urdf` file; out = [`Robot`], a 6-revolute-joint chain in
//! standard DH form between two fixed transforms (robot base → DH frame 0, DH frame 6 → flange).
//!
//! Every robot, whatever file it came from, ends up in this one form so that the measurement
//! model (Eq. 1-6) and its 30-parameter vector work the same for all of them.

pub mod dh;
pub mod effects;
pub mod kinematics;
pub mod urdf;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub use kinematics::Frame;

/// One row of a standard DH table (SI: metres, radians).
/// T_i = RotZ(theta + q) · TransZ(d) · TransX(a) · RotX(alpha).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dh {
    pub alpha: f64,
    pub a: f64,
    pub d: f64,
    pub theta: f64,
}

/// A revolute joint as the controller sees it (SI: radians, radians per second).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Joint {
    pub name: String,
    pub lower: f64,
    pub upper: f64,
    pub max_speed: f64,
    /// Maximum joint acceleration (rad/s²): the robot file's `max_acceleration`, the cell's
    /// `[robot] accelerations`, else [`DEFAULT_ACCELERATION_PER_S`] × `max_speed`.
    #[serde(default)]
    pub max_acceleration: f64,
}

/// A joint's acceleration when neither the robot file nor the cell gives one: this many times its
/// maximum speed per second (full speed in 0.5 s). Industrial arms reach theirs in 0.2-0.5 s, so
/// the default errs on the slow side: planned times are then long rather than short.
pub const DEFAULT_ACCELERATION_PER_S: f64 = 2.0;

/// A collision primitive attached to a DH frame (0 = base frame, i = after joint i), or to a
/// passive link. Used by later stages; the URDF and DH loaders fill it where the file has
/// geometry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LinkShape {
    /// DH frame the shape (or its passive link's chain) is attached to: 0 = robot base,
    /// i = moves with joint i.
    pub frame: usize,
    /// Pose of the shape in that frame, or in its passive link's frame.
    pub origin: Frame,
    pub geometry: Geometry,
    /// Index into [`Robot::passive`] when the shape belongs to a passive link.
    #[serde(default)]
    pub passive: Option<usize>,
}

/// A link that hangs off the 6-joint chain through joints the controller does not drive
/// itself: mimic joints (a balancing cylinder and its piston, a parallelogram linkage, a gas
/// spring) and, held at a fixed value, undriven joints. Its pose is a function of q:
/// DH frame `frame` · step 1 · step 2 · …
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassiveLink {
    /// The URDF link name (the body's name in reports).
    pub name: String,
    /// DH frame of the rigid ancestor the chain of steps starts from.
    pub frame: usize,
    /// The nearest ancestor that is itself a passive link (index into [`Robot::passive`]);
    /// None: the rigid ancestor (DH frame `frame`). The two are joined by a joint.
    pub parent: Option<usize>,
    pub steps: Vec<PassiveStep>,
}

/// One joint between a rigid ancestor (or a passive link) and a passive link:
/// `origin` · motion(value), value = `multiplier` · q\[`joint`\] + `offset` (rad or m).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassiveStep {
    /// The URDF joint.
    pub name: String,
    /// The joint's origin in its parent's frame (the first step: in DH frame `frame`).
    pub origin: Frame,
    pub motion: PassiveMotion,
    /// Unit axis in the joint frame (ignored for `Fixed`).
    pub axis: Vector3<f64>,
    /// The chain joint (0-based) the value follows; `None` = held at `offset`.
    pub joint: Option<usize>,
    pub multiplier: f64,
    pub offset: f64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PassiveMotion {
    Fixed,
    Revolute,
    Prismatic,
}

impl PassiveStep {
    /// The joint value at q (rad or m).
    #[inline]
    pub fn value(&self, q: &[f64; 6]) -> f64 {
        match self.joint {
            Some(k) => self.multiplier * q[k] + self.offset,
            None => self.offset,
        }
    }

    /// origin · motion(value at q).
    #[inline]
    pub fn transform(&self, q: &[f64; 6]) -> Frame {
        match self.motion {
            PassiveMotion::Fixed => self.origin,
            PassiveMotion::Revolute => self.origin.mul(&Frame::new(
                axis_angle(&self.axis, self.value(q)),
                Vector3::zeros(),
            )),
            PassiveMotion::Prismatic => self
                .origin
                .mul(&Frame::translation(self.axis * self.value(q))),
        }
    }
}

impl PassiveLink {
    /// The link's frame in the robot base frame, from the chain frames of q (allocation-free).
    #[inline]
    pub fn pose(&self, frames: &[Frame; 8], q: &[f64; 6]) -> Frame {
        self.steps
            .iter()
            .fold(frames[self.frame], |f, s| f.mul(&s.transform(q)))
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Geometry {
    Box { size: [f64; 3] },
    Cylinder { radius: f64, length: f64 },
    Sphere { radius: f64 },
    Mesh { path: PathBuf, scale: [f64; 3] },
}

/// A link's mass lumped at its centre of mass, attached to a DH frame like [`LinkShape`]
/// (URDF `<inertial>`; a DH spec has none). Used by the digital twin's joint compliance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PointMass {
    /// DH frame the link is rigid with: 0 = robot base, i = moves with joint i.
    pub frame: usize,
    /// Centre of mass in that frame (m).
    pub com: Vector3<f64>,
    /// kg.
    pub mass: f64,
}

/// The robot: the immutable model every stage shares (across rayon threads too).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Robot {
    pub name: String,
    /// File name the robot came from (no directory: output must not depend on where it lives).
    pub source: String,
    /// Robot base frame (URDF root link) → DH frame 0. Identity for a DH file.
    pub base: Frame,
    pub dh: [Dh; 6],
    /// DH frame 6 → flange. Identity for a DH file.
    pub flange: Frame,
    pub joints: [Joint; 6],
    /// The measurement application point (tool ball centre) in the flange frame, metres,
    /// when the robot file declares one.
    pub tool: Option<Vector3<f64>>,
    pub shapes: Vec<LinkShape>,
    /// Links off the chain that move with it (mimic linkages), for the collision scene.
    #[serde(default)]
    pub passive: Vec<PassiveLink>,
    /// What the loader assumed that a user must know (e.g. an undriven joint held at a value).
    #[serde(default)]
    pub notes: Vec<String>,
    /// Link masses from the URDF inertials, by frame; empty when the file has none.
    #[serde(default)]
    pub masses: Vec<PointMass>,
    /// The effects a calibration adopted beside the geometry (`[effects]` of a `.dh.toml`, a
    /// URDF's sidecar file); none for a nominal robot.
    #[serde(default)]
    pub effects: effects::Effects,
    /// SHA-256 of the robot file's bytes (set by [`load`]): part of the program's input hash.
    pub digest: String,
}

/// How to find and resolve the robot in its file.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// URDF: the link that ends the chain (default: `flange`, `tool0`, or the chain's last link).
    pub flange_link: Option<String>,
    /// URDF: the link whose frame is the robot base frame (default: the root link). It must be
    /// rigid with the root (fixed joints only).
    pub base_link: Option<String>,
    /// URDF: directories searched for `package://NAME/...` mesh paths.
    pub package_paths: Vec<PathBuf>,
    /// Joint speeds (rad/s) that replace the file's (e.g. from the cell file, for URDFs
    /// without joint velocities).
    pub speeds: Option<[f64; 6]>,
    /// Joint accelerations (rad/s²) that replace the file's (the cell's `[robot] accelerations`).
    pub accelerations: Option<[f64; 6]>,
}

#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    #[error("{path}: cannot read: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {msg}")]
    Invalid { path: String, msg: String },
}

impl LoadError {
    pub fn invalid(path: &Path, msg: impl Into<String>) -> Self {
        LoadError::Invalid {
            path: path.display().to_string(),
            msg: msg.into(),
        }
    }
}

/// True for a URDF robot file (`.urdf`, `.xml`), by its extension.
pub fn is_urdf(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("urdf") || e.eq_ignore_ascii_case("xml"))
}

/// True for a DH robot file (`.dh.toml`, any `.toml`), by its extension.
pub fn is_toml(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("toml"))
}

/// Loads a robot from a `.urdf` or a `.dh.toml` (any `.toml`) file.
pub fn load(path: &Path, opts: &LoadOptions) -> Result<Robot, LoadError> {
    let text = crate::files::read_text(path, crate::files::Kind::Robot).map_err(|e| match e {
        crate::files::ReadError::Io(source) => LoadError::Io {
            path: path.display().to_string(),
            source,
        },
        other => LoadError::invalid(path, other.to_string()),
    })?;
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let mut robot = match ext.as_str() {
        "urdf" | "xml" => urdf::from_str(&text, path, opts)?,
        "toml" => dh::from_str(&text, path)?,
        _ => {
            return Err(LoadError::invalid(
                path,
                "unknown robot file type (expected .urdf or .dh.toml)",
            ))
        }
    };
    // Speeds from the cell file replace the robot file's (e.g. a URDF without velocities).
    if let Some(s) = opts.speeds {
        for (j, v) in robot.joints.iter_mut().zip(s) {
            j.max_speed = v;
        }
    }
    if let Some(a) = opts.accelerations {
        for (j, v) in robot.joints.iter_mut().zip(a) {
            j.max_acceleration = v;
        }
    }
    // No acceleration given: the documented default, from the speed in force.
    for j in robot.joints.iter_mut() {
        if j.max_acceleration == 0.0 {
            j.max_acceleration = DEFAULT_ACCELERATION_PER_S * j.max_speed;
        }
    }
    robot.validate(path)?;
    // A calibrated URDF names the sidecar file its effects are in: read it, or fail (a robot
    // whose effects are dropped silently is not the robot that was calibrated).
    let mut digest_text = text.clone();
    if matches!(ext.as_str(), "urdf" | "xml") {
        if let Some(name) = effects::sidecar_name(&text) {
            let side = path.parent().unwrap_or(Path::new("")).join(&name);
            let side_text = crate::files::read_text(&side, crate::files::Kind::Robot).map_err(
                |e| {
                    LoadError::invalid(
                        path,
                        format!(
                            "names its effects file {name} (the calibration's sidecar), which cannot be read: {e}"
                        ),
                    )
                },
            )?;
            robot.effects =
                effects::from_sidecar(&side_text).map_err(|e| LoadError::invalid(&side, e))?;
            digest_text.push_str(&side_text);
        }
    }
    Ok(Robot {
        digest: sha256_hex(digest_text.as_bytes()),
        ..robot
    })
}

impl Robot {
    /// Checks what every stage relies on: finite numbers, ordered limits, positive speeds.
    pub fn validate(&self, path: &Path) -> Result<(), LoadError> {
        for (i, (j, dh)) in self.joints.iter().zip(&self.dh).enumerate() {
            let n = i + 1;
            if ![dh.alpha, dh.a, dh.d, dh.theta]
                .iter()
                .all(|v| v.is_finite())
            {
                return Err(LoadError::invalid(
                    path,
                    format!("joint {n} ({}): DH value is not finite", j.name),
                ));
            }
            if !(j.lower.is_finite() && j.upper.is_finite()) || j.lower >= j.upper {
                return Err(LoadError::invalid(
                    path,
                    format!(
                        "joint {n} ({}): limits must be finite with lower < upper",
                        j.name
                    ),
                ));
            }
            if !(j.max_speed.is_finite() && j.max_speed > 0.0) {
                return Err(LoadError::invalid(
                    path,
                    format!(
                        "joint {n} ({}): max speed missing or zero; give each joint a velocity limit (URDF <limit velocity=..>) or set [robot] speeds in the cell file",
                        j.name
                    ),
                ));
            }
            if !(j.max_acceleration.is_finite() && j.max_acceleration > 0.0) {
                return Err(LoadError::invalid(
                    path,
                    format!(
                        "joint {n} ({}): max_acceleration must be a positive number",
                        j.name
                    ),
                ));
            }
        }
        if let Some(t) = self.tool {
            if !t.iter().all(|v| v.is_finite()) {
                return Err(LoadError::invalid(path, "tool: not finite"));
            }
        }
        Ok(())
    }

    /// Joint limits as arrays (radians).
    pub fn limits(&self) -> ([f64; 6], [f64; 6]) {
        (
            std::array::from_fn(|i| self.joints[i].lower),
            std::array::from_fn(|i| self.joints[i].upper),
        )
    }

    /// Joint accelerations (rad/s²).
    pub fn max_accelerations(&self) -> [f64; 6] {
        std::array::from_fn(|i| self.joints[i].max_acceleration)
    }

    pub fn max_speeds(&self) -> [f64; 6] {
        std::array::from_fn(|i| self.joints[i].max_speed)
    }
}

/// A rotation about a unit axis by `angle` (Rodrigues).
pub fn axis_angle(axis: &Vector3<f64>, angle: f64) -> Matrix3<f64> {
    let (s, c) = angle.sin_cos();
    let k = axis;
    let kx = Matrix3::new(0.0, -k.z, k.y, k.z, 0.0, -k.x, -k.y, k.x, 0.0);
    Matrix3::identity() + kx * s + kx * kx * (1.0 - c)
}

/// Lower-case hex SHA-256.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

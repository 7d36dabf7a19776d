//! `.dh.toml` loader: in = the DH spec text of DESIGN.md; out = [`Robot`] (identity base and
//! flange transforms, SI units).

use super::{Dh, Frame, Joint, LoadError, Robot};
use nalgebra::Vector3;
use serde::Deserialize;
use std::path::Path;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Spec {
    name: String,
    convention: String,
    length_unit: String,
    angle_unit: String,
    #[serde(default)]
    tool: Option<[f64; 3]>,
    joints: Vec<JointSpec>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JointSpec {
    #[serde(default)]
    name: Option<String>,
    alpha: f64,
    a: f64,
    d: f64,
    theta: f64,
    limits: [f64; 2],
    max_speed: f64,
}

/// Turns a TOML error into one line: `line L, column C: message`.
pub(crate) fn toml_error(text: &str, e: &toml::de::Error) -> String {
    let msg = e.message().trim().replace('\n', " ");
    match e.span() {
        Some(span) => {
            let before = &text[..span.start.min(text.len())];
            let line = before.matches('\n').count() + 1;
            let col = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
            format!("line {line}, column {col}: {msg}")
        }
        None => msg,
    }
}

pub fn from_str(text: &str, path: &Path) -> Result<Robot, LoadError> {
    let spec: Spec =
        toml::from_str(text).map_err(|e| LoadError::invalid(path, toml_error(text, &e)))?;
    if spec.convention != "dh" {
        return Err(LoadError::invalid(
            path,
            format!(
                "convention: \"{}\" is not supported (only \"dh\", standard Denavit-Hartenberg)",
                spec.convention
            ),
        ));
    }
    let lscale = match spec.length_unit.as_str() {
        "mm" => 1e-3,
        "m" => 1.0,
        u => {
            return Err(LoadError::invalid(
                path,
                format!("length_unit: \"{u}\" (expected \"mm\" or \"m\")"),
            ))
        }
    };
    let ascale = match spec.angle_unit.as_str() {
        "deg" => std::f64::consts::PI / 180.0,
        "rad" => 1.0,
        u => {
            return Err(LoadError::invalid(
                path,
                format!("angle_unit: \"{u}\" (expected \"deg\" or \"rad\")"),
            ))
        }
    };
    if spec.joints.len() != 6 {
        return Err(LoadError::invalid(
            path,
            format!(
                "joints: {} joints given, edbbgen needs exactly 6 revolute joints",
                spec.joints.len()
            ),
        ));
    }
    let dh = std::array::from_fn(|i| {
        let j = &spec.joints[i];
        Dh {
            alpha: j.alpha * ascale,
            a: j.a * lscale,
            d: j.d * lscale,
            theta: j.theta * ascale,
        }
    });
    let joints = std::array::from_fn(|i| {
        let j = &spec.joints[i];
        Joint {
            name: j.name.clone().unwrap_or_else(|| format!("joint_{}", i + 1)),
            lower: j.limits[0] * ascale,
            upper: j.limits[1] * ascale,
            max_speed: j.max_speed * ascale,
        }
    });
    Ok(Robot {
        name: spec.name,
        source: path
            .file_name()
            .map(|f| f.to_string_lossy().into_owned())
            .unwrap_or_default(),
        base: Frame::IDENTITY,
        dh,
        flange: Frame::IDENTITY,
        joints,
        tool: spec.tool.map(|t| Vector3::from(t) * lscale),
        shapes: Vec::new(),
        passive: Vec::new(),
        notes: Vec::new(),
        masses: Vec::new(),
        digest: String::new(),
    })
}

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
    /// A calibration's effects (`robot::effects`).
    #[serde(default)]
    effects: Option<toml::Value>,
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
    /// angle_unit per s²; absent = the documented default (see `robot::DEFAULT_ACCELERATION_PER_S`).
    #[serde(default)]
    max_acceleration: Option<f64>,
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
            // 0 = not given: the loader puts the default in.
            max_acceleration: j.max_acceleration.map_or(0.0, |a| {
                if a > 0.0 {
                    a * ascale
                } else {
                    f64::NAN
                }
            }),
        }
    });
    let effects = match spec.effects {
        Some(v) => super::effects::from_toml(v).map_err(|e| LoadError::invalid(path, e))?,
        None => Default::default(),
    };
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
        effects,
        digest: String::new(),
    })
}

/// Start of the comment block edbbgen puts on a calibrated DH spec (replaced on
/// re-calibration).
const CALIBRATION_MARK: &str = "# --- edbbgen calibration ---";

/// The input DH spec with a calibrated table: `alpha`, `a`, `d`, `theta` of every joint and
/// `tool` (the MAP) set to the calibrated values in the file's own units; comments, names,
/// limits, speeds and every other key kept; `header` lines as a comment block on top.
/// Lengths are written to 1e-9 of the unit, angles to 1e-10 (far below any instrument).
/// `effects` (the `[effects]` table as text, or empty) replaces an earlier calibration's.
pub fn calibrated(
    text: &str,
    path: &Path,
    dh: &[Dh; 6],
    tool: &Vector3<f64>,
    header: &[String],
    effects: &str,
) -> Result<String, LoadError> {
    // The same checks as loading: the units, six joints.
    from_str(text, path)?;
    let spec: Spec =
        toml::from_str(text).map_err(|e| LoadError::invalid(path, toml_error(text, &e)))?;
    let lscale = if spec.length_unit == "m" { 1.0 } else { 1e-3 };
    let ascale = if spec.angle_unit == "rad" {
        1.0
    } else {
        std::f64::consts::PI / 180.0
    };
    let body = strip_calibration_block(text);
    let mut doc: toml_edit::DocumentMut = body
        .parse()
        .map_err(|e| LoadError::invalid(path, format!("cannot edit: {e}")))?;
    let round = |v: f64, d: i32| {
        let s = 10f64.powi(d);
        let r = (v * s).round() / s;
        if r == 0.0 {
            0.0
        } else {
            r
        }
    };
    let set = |item: &mut toml_edit::Item, v: f64| {
        let decor = item.as_value().map(|x| x.decor().clone());
        let mut new = toml_edit::Value::from(v);
        if let Some(d) = decor {
            *new.decor_mut() = d;
        }
        *item = toml_edit::Item::Value(new);
    };
    let joints = doc
        .get_mut("joints")
        .and_then(|j| j.as_array_of_tables_mut())
        .ok_or_else(|| LoadError::invalid(path, "joints: not an array of tables"))?;
    for (i, t) in joints.iter_mut().enumerate() {
        let d = &dh[i];
        for (key, v) in [
            ("alpha", round(d.alpha / ascale, 10)),
            ("a", round(d.a / lscale, 9)),
            ("d", round(d.d / lscale, 9)),
            ("theta", round(d.theta / ascale, 10)),
        ] {
            match t.get_mut(key) {
                Some(item) => set(item, v),
                None => {
                    t.insert(key, toml_edit::value(v));
                }
            }
        }
    }
    let mut arr = toml_edit::Array::new();
    for v in tool.iter() {
        arr.push(round(v / lscale, 9));
    }
    match doc.get_mut("tool") {
        Some(item) => {
            let decor = item.as_value().map(|x| x.decor().clone());
            let mut new = toml_edit::Value::Array(arr);
            if let Some(d) = decor {
                *new.decor_mut() = d;
            }
            *item = toml_edit::Item::Value(new);
        }
        None => {
            doc.insert("tool", toml_edit::value(arr));
        }
    }
    doc.remove("effects");
    let mut out = String::from(CALIBRATION_MARK);
    out.push('\n');
    for l in header {
        out.push_str("# ");
        out.push_str(l);
        out.push('\n');
    }
    out.push_str("# ---\n");
    let body = doc.to_string();
    if effects.is_empty() {
        out.push_str(&body);
    } else {
        out.push_str(body.trim_end());
        out.push_str("\n\n");
        out.push_str(effects);
    }
    Ok(out)
}

/// The text without an earlier calibration block (from the mark to its closing `# ---`).
fn strip_calibration_block(text: &str) -> String {
    let Some(start) = text.find(CALIBRATION_MARK) else {
        return text.to_string();
    };
    let after = &text[start + CALIBRATION_MARK.len()..];
    match after.find("\n# ---\n") {
        Some(end) => format!("{}{}", &text[..start], &after[end + "\n# ---\n".len()..]),
        None => text.to_string(),
    }
}

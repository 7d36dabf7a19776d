//! The calibrated robot's files: the robot file it started from (text, path, kind), the
//! calibration, the header lines and the output path in; the calibrated robot file's text and,
//! for a URDF with effects, its sidecar file of effects (path and text) out. Nothing is written
//! here.

use super::Calibration;
use crate::robot::{self, LoadError, LoadOptions, Robot};
use std::path::{Path, PathBuf};

/// The robot file a calibration started from.
pub struct Input<'a> {
    pub robot: &'a Robot,
    pub text: &'a str,
    pub path: &'a Path,
    /// A URDF (else a DH table).
    pub urdf: bool,
    pub load_opts: &'a LoadOptions,
}

/// What a calibration writes: the robot file and, beside a URDF, the effects it cannot hold.
pub struct Rendered {
    pub robot: String,
    pub sidecar: Option<(PathBuf, String)>,
}

/// Renders the calibrated robot file (to be written at `output`) with `header` on top.
pub fn render(
    input: &Input,
    cal: &Calibration,
    mut header: Vec<String>,
    output: &Path,
) -> Result<Rendered, LoadError> {
    let robot = input.robot;
    let p = cal.params();
    let effects = cal.file.effects.clone();
    let effects_text = robot::effects::to_toml(&effects, &cal.file.reference);
    // A URDF cannot hold the effects: they go to a sidecar file beside it, named in its header.
    let sidecar = (input.urdf && !effects_text.is_empty()).then(|| sidecar_path(output));
    if let Some(side) = &sidecar {
        let name = side
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        header.push(format!("{} {name}", robot::effects::SIDECAR_MARK));
    }
    let calibrated = if input.urdf {
        robot::urdf::calibrated(
            input.text,
            input.path,
            input.load_opts,
            robot,
            &p.dh,
            &p.map,
            &header,
        )?
    } else {
        robot::dh::calibrated(
            input.text,
            input.path,
            &p.dh,
            &p.map,
            &header,
            &effects_text,
        )?
    };
    let Some(sidecar) = sidecar else {
        return Ok(Rendered {
            robot: calibrated,
            sidecar: None,
        });
    };
    // The URDF loads to a DH table of its own (its common normals may point the other way):
    // the effects go to the sidecar referred to that table's frames.
    let (b, dh, f) = robot::urdf::dh_chain(&calibrated, input.load_opts)
        .map_err(|e| LoadError::invalid(output, e))?;
    let moved = effects.reframed((&robot.base, &p.dh, &robot.flange), (&b, &dh, &f));
    let text = format!(
        "# The effects of {} (edbbgen calibrate): the URDF names this file; keep the two together.\n{}",
        output
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        robot::effects::to_toml(&moved, &cal.file.reference)
    );
    Ok(Rendered {
        robot: calibrated,
        sidecar: Some((sidecar, text)),
    })
}

/// The sidecar file of a calibrated URDF: `robot.cal.urdf` → `robot.cal.effects.toml`.
pub fn sidecar_path(urdf: &Path) -> PathBuf {
    let stem = urdf
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "robot".into());
    urdf.with_file_name(format!("{stem}.effects.toml"))
}

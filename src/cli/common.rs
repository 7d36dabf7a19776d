//! Shared helpers of the subcommands: flags (numbers in the units the user writes) in, checked
//! SI values out; the cell and robot resolved from their flags; program dialects and controller
//! mappings; input files read within their limits, outputs written whole (temp file + rename).

use super::args::{CellArgs, Range, Xyz};
use super::{usage, Error};
use crate::cell::CellSpec;
use crate::robot::{self, LoadOptions, Robot};
use crate::units::{DEG, MM};
use nalgebra::Vector3;
use std::io::Write;
use std::path::{Path, PathBuf};

// ---- flag parsing -------------------------------------------------------------------------

pub(super) fn numbers(flag: &str, s: &str, n: Option<usize>) -> Result<Vec<f64>, Error> {
    let vals: Result<Vec<f64>, _> = s.split(',').map(|t| t.trim().parse::<f64>()).collect();
    let vals = vals.map_err(|_| {
        usage(format!(
            "{flag}: '{s}' is not a comma-separated list of numbers"
        ))
    })?;
    if vals.iter().any(|v| !v.is_finite()) {
        return Err(usage(format!(
            "{flag}: '{s}' contains a value that is not finite"
        )));
    }
    if let Some(n) = n {
        if vals.len() != n {
            return Err(usage(format!(
                "{flag}: '{s}' has {} values, expected {n}",
                vals.len()
            )));
        }
    }
    Ok(vals)
}

pub(super) fn xyz_mm(flag: &str, s: &str) -> Result<Vector3<f64>, Error> {
    let v = numbers(flag, s, Some(3))?;
    Ok(Vector3::new(v[0], v[1], v[2]) * MM)
}

pub(super) fn bar_range(r: Range) -> Result<(f64, f64), Error> {
    let Range(a, b) = r;
    if !(a > 0.0 && b > a) {
        return Err(usage(format!("--bar: {a}..{b} needs 0 < MIN < MAX")));
    }
    Ok((a * MM, b * MM))
}

pub(super) fn load_robot(path: &Path, cell: &CellArgs, spec: &CellSpec) -> Result<Robot, Error> {
    let opts = LoadOptions {
        flange_link: cell.flange.clone(),
        package_paths: cell.package_path.clone(),
        speeds: spec.speeds,
        accelerations: spec.accelerations,
        ..LoadOptions::default()
    };
    Ok(robot::load(path, &opts)?)
}

/// The cell: the file (or the defaults), then every flag that overrides it.
pub(super) fn resolve_cell(a: &CellArgs) -> Result<CellSpec, Error> {
    let mut spec = match &a.cell {
        Some(p) => crate::cell::load(p)?,
        None => CellSpec::default(),
    };
    if let Some(t) = &a.tool {
        spec.map = Some(t.m());
    }
    if let Some(b) = a.bar {
        (spec.bar_min, spec.bar_max) = bar_range(b)?;
        (spec.stated.bar_min, spec.stated.bar_max) = (true, true);
    }
    if let Some(f) = a.floor {
        spec.floor_z = f * MM;
    }
    if let Some(b) = a.ball {
        if !(b > 0.0 && b < 200.0) {
            return Err(usage(format!(
                "--ball: {b} mm must be between 0 and 200 mm"
            )));
        }
        spec.ball = b * MM;
        spec.stated.ball = true;
    }
    set_margins(&mut spec, a.margin, a.joint_margin)?;
    Ok(spec)
}

/// `--bar-noise`: the bar's noise per reading (µm), positive.
pub(super) fn bar_noise(v: f64) -> Result<f64, Error> {
    if v <= 0.0 {
        return Err(usage(format!("--bar-noise: {v} µm must be positive")));
    }
    Ok(v)
}

/// `--bar-rate`: the bar's sample rate (Hz), 1 to 100,000.
pub(super) fn bar_rate(v: f64) -> Result<f64, Error> {
    if !(1.0..=100_000.0).contains(&v) {
        return Err(usage(format!("--bar-rate: {v} Hz is outside 1..100000 Hz")));
    }
    Ok(v)
}

/// `--margin MM` and `--joint-margin DEG` over the cell's values, range-checked.
pub(super) fn set_margins(
    spec: &mut CellSpec,
    margin: Option<f64>,
    joint_margin: Option<f64>,
) -> Result<(), Error> {
    if let Some(m) = margin {
        if !(0.0..=500.0).contains(&m) {
            return Err(usage(format!(
                "--margin: {m} mm must be between 0 and 500 mm"
            )));
        }
        spec.margin = m * MM;
        spec.stated.margin = true;
    }
    if let Some(m) = joint_margin {
        if !(0.0..=30.0).contains(&m) {
            return Err(usage(format!(
                "--joint-margin: {m} deg must be between 0 and 30 deg"
            )));
        }
        spec.joint_margin = m * DEG;
        spec.stated.joint_margin = true;
    }
    Ok(())
}

/// The fixture: the flag, else the cell file's, else (verify) the program header's.
pub(super) fn resolve_fixture(
    flag: Option<Xyz>,
    spec: &CellSpec,
    header: Option<&str>,
) -> Result<Vector3<f64>, Error> {
    if let Some(f) = flag {
        return Ok(f.m());
    }
    if let Some(f) = spec.fixture {
        return Ok(f);
    }
    if let Some(h) = header {
        let nums = h.split("mm").next().unwrap_or("");
        return xyz_mm("program header (fixture)", nums.trim());
    }
    Err(usage(
        "--fixture: required (or give it in the cell file as [fixture] position)",
    ))
}

/// The controller mapping for `dialect`: the cell's `[controller]` over the dialect's defaults;
/// an error names the cell file.
pub(super) fn controller_map(
    spec: &CellSpec,
    cell: Option<&Path>,
    dialect: &crate::dialect::Dialect,
    robot: &Robot,
) -> Result<crate::controller::ControllerMap, Error> {
    crate::controller::ControllerMap::resolve(
        spec.controller.as_ref(),
        &dialect.defaults(),
        &dialect.name,
        robot,
    )
    .map_err(|e| Error::File {
        path: cell.map_or_else(
            || format!("--dialect {}", dialect.name),
            |p| p.display().to_string(),
        ),
        msg: e.to_string(),
    })
}

/// The dialect of a program file to read: `--dialect`, else its extension, else its text.
pub(super) fn program_dialect(
    flag: Option<&str>,
    path: &Path,
    text: &str,
) -> Result<&'static crate::dialect::Dialect, Error> {
    match flag {
        Some(name) => crate::dialect::by_name(name).ok_or_else(|| {
            usage(format!(
                "--dialect: unknown dialect '{name}' (available: {})",
                crate::dialect::names().join(", ")
            ))
        }),
        None => crate::dialect::detect(path, text).ok_or_else(|| Error::File {
            path: path.display().to_string(),
            msg: format!(
                "cannot tell the program's dialect from its name or text; give --dialect ({})",
                crate::dialect::names().join(", ")
            ),
        }),
    }
}

/// An input file's text, within the limit of its kind (see [`crate::files`]).
pub(super) fn read_input(
    path: &Path,
    what: &str,
    kind: crate::files::Kind,
) -> Result<String, Error> {
    crate::files::read_text(path, kind).map_err(|e| Error::File {
        path: path.display().to_string(),
        msg: match e {
            crate::files::ReadError::Io(e) => format!("cannot read {what}: {e}"),
            other => other.to_string(),
        },
    })
}

/// Where a `--json [FILE]` report goes: `-` (the flag alone) is stdout, in place of the summary.
pub(super) fn is_stdout(dest: &Path) -> bool {
    dest.as_os_str() == "-"
}

/// Writes a JSON report to its destination: stdout for `-`, else the file (atomically).
pub(super) fn write_json(dest: &Path, json: &str) -> Result<(), Error> {
    if is_stdout(dest) {
        println!("{json}");
        Ok(())
    } else {
        write_atomic(dest, &format!("{json}\n"))
    }
}

/// Refuses, before any work, an output whose directory does not exist or is not a directory:
/// a long compile must not end in "cannot write".
pub(super) fn check_outputs(paths: &[Option<&Path>]) -> Result<(), Error> {
    for path in paths.iter().flatten() {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        if !dir.is_dir() {
            return Err(Error::File {
                path: path.display().to_string(),
                msg: format!("cannot write: directory {} does not exist", dir.display()),
            });
        }
        if path.is_dir() {
            return Err(Error::File {
                path: path.display().to_string(),
                msg: "cannot write: it is a directory".into(),
            });
        }
    }
    Ok(())
}

/// Writes the whole file or nothing: a temp file beside the target, then rename.
pub(super) fn write_atomic(path: &Path, text: &str) -> Result<(), Error> {
    write_all_atomic(&[(path, text)])
}

/// Writes several files as one: every temp file is written and synced first, and only then
/// are they renamed into place, so a failure on any of them leaves none behind.
pub(super) fn write_all_atomic(files: &[(&Path, &str)]) -> Result<(), Error> {
    let mut staged = Vec::with_capacity(files.len());
    for (path, text) in files {
        let err = |msg: String| Error::File {
            path: path.display().to_string(),
            msg,
        };
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let mut builder = tempfile::Builder::new();
        builder.prefix(".edbbgen-").suffix(".tmp");
        // A temp file is private (0600) by default; the output is an ordinary file (0666 less
        // the user's umask), like one written by any other program.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            builder.permissions(std::fs::Permissions::from_mode(0o666));
        }
        let mut tmp = builder
            .tempfile_in(&dir)
            .map_err(|e| err(format!("cannot write (directory {}): {e}", dir.display())))?;
        tmp.write_all(text.as_bytes())
            .map_err(|e| err(format!("cannot write: {e}")))?;
        tmp.as_file()
            .sync_all()
            .map_err(|e| err(format!("cannot write: {e}")))?;
        staged.push((path, tmp));
    }
    for (path, tmp) in staged {
        tmp.persist(path).map_err(|e| Error::File {
            path: path.display().to_string(),
            msg: format!("cannot write: {}", e.error),
        })?;
    }
    Ok(())
}

pub(super) fn file_err(path: &Path, msg: impl std::fmt::Display) -> Error {
    Error::File {
        path: path.display().to_string(),
        msg: msg.to_string(),
    }
}

/// The file name (no directory: outputs must not depend on where the inputs live).
pub(super) fn name(path: &Path) -> String {
    path.file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

/// The first three numbers of a header value such as "258.000, 1468.000, 708.000 mm ...".
pub(super) fn header_xyz(v: &str) -> Option<Vector3<f64>> {
    let nums: Vec<f64> = v
        .split([',', ' '])
        .filter_map(|w| w.trim().parse::<f64>().ok())
        .take(3)
        .collect();
    (nums.len() == 3).then(|| Vector3::new(nums[0], nums[1], nums[2]) * MM)
}

/// The output template: a user's file (`--template`) or a bundled dialect (`--dialect`).
pub(super) fn resolve_template(dialect: &str, file: Option<&Path>) -> Result<String, Error> {
    match file {
        Some(p) => {
            let text = read_input(p, "template", crate::files::Kind::Config)?;
            // The dialect it extends decides how its programs are read back: checked first.
            crate::dialect::Template::from_source(&text).map_err(|e| Error::File {
                path: p.display().to_string(),
                msg: e.to_string(),
            })?;
            Ok(text)
        }
        None => crate::emit::dialect(dialect)
            .map(str::to_string)
            .ok_or_else(|| {
                usage(format!(
                    "--dialect: unknown dialect '{dialect}' (available: {})",
                    crate::dialect::names().join(", ")
                ))
            }),
    }
}

/// The program name from the output file's stem; languages whose program name must equal the
/// file name (KRL, FANUC) refuse a stem they cannot carry.
pub(super) fn program_name(
    output: &Path,
    dialect: &crate::dialect::Dialect,
) -> Result<String, Error> {
    let stem = output
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    if dialect.name_must_match_file && !crate::dialect::valid_name(&stem, dialect.name_max) {
        return Err(usage(format!(
            "-o: '{}': a {} program's name is its file name, which must be letters, digits and _, a letter first, at most {} characters",
            output.display(),
            dialect.name,
            dialect.name_max
        )));
    }
    Ok(stem)
}

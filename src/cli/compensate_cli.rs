//! `compensate`: flags → the two robots, the tool point, the controller mapping → compensated
//! targets (CSV) or a compensated program, the mastering offsets and the accuracy they give,
//! all written together or not at all.

use super::args::CompensateArgs;
use super::common::{
    check_outputs, controller_map, file_err, name, numbers, program_dialect, read_input,
    write_all_atomic,
};
use super::{usage, Error};
use crate::compensate::offsets::{self, JointOffsets};
use crate::compensate::program::{self, Outcome};
use crate::compensate::setup;
use crate::compensate::{self, targets, Compensator, Limits, Report};
use crate::controller::ControllerMap;
use crate::robot::effects::ThermalState;
use crate::robot::{self, Frame, LoadOptions, Robot};
use crate::units::{length_um, DEG, MM};
use nalgebra::Vector3;
use std::path::Path;

/// `edbbgen compensate`: the flags resolved, the targets or the program compensated, and the
/// files written; the exit code.
pub fn compensate(a: &CompensateArgs) -> Result<i32, Error> {
    // The command line first: nothing is read before it is sound.
    let input = check_input(a)?;
    let tcp = a.tcp;
    let spec = match &a.cell {
        Some(p) => Some(crate::cell::load(p)?),
        None => None,
    };
    let named_dialect = match &a.dialect {
        Some(n) => Some(crate::dialect::by_name(n).ok_or_else(|| {
            usage(format!(
                "--dialect: unknown dialect '{n}' (available: {})",
                crate::dialect::names().join(", ")
            ))
        })?),
        None => None,
    };

    let (nominal, calibrated) = load_robots(a, spec.as_ref())?;
    // The tool point: --tcp on both robots; else the MAP: the cell's (what the programs were
    // planned with) or the nominal file's on the nominal robot, the calibrated file's own (its
    // calibrated MAP) on the calibrated one.
    let (tcp_n, tcp_c) = tool_points(a, tcp, spec.as_ref(), &nominal, &calibrated)?;
    // The program (its dialect decides the mapping's defaults and the mastering's family).
    let program_text = match &a.program {
        Some(p) => Some(read_input(p, "program", crate::files::Kind::Program)?),
        None => None,
    };
    let dialect = match (&program_text, &a.program) {
        (Some(text), Some(p)) => Some(program_dialect(a.dialect.as_deref(), p, text)?),
        _ => named_dialect,
    };
    let (map, pulses) = resolve_map(a, spec.as_ref(), dialect, &nominal)?;
    let report_json = read_calibration(a)?;

    let approach = targets::Approach::parse(&a.approach).ok_or_else(|| {
        usage(format!(
            "--approach: '{}' (expected order, positive, negative or unknown)",
            a.approach
        ))
    })?;
    let mut calibrated = calibrated;
    let payload = parse_payload(a)?;
    let state = setup::Setup {
        payload,
        approach,
        approach_flag: &a.approach,
        program: a.program.is_some(),
        temperature: a.temperature,
        elapsed: a.elapsed,
    };
    let mut notes = setup::effects(&mut calibrated, &tcp_c, &state).map_err(|e| match e {
        setup::SetupError::Flag(m) => usage(m),
        setup::SetupError::Robot(m) => file_err(&a.calibrated, m),
    })?;
    let state = match (a.temperature, a.elapsed) {
        (Some(c), _) => ThermalState::Temperature(c),
        (None, Some(t)) => ThermalState::Elapsed(t),
        (None, None) => ThermalState::Reference,
    };
    let comp = Compensator::new(&nominal, &calibrated, &tcp_n, &tcp_c).at_state(state);
    if tcp.is_some() {
        if let (Some(tn), Some(tc)) = (nominal.tool, calibrated.tool) {
            notes.push(format!(
                "the TCP is given (--tcp): the calibrated MAP's deviation from nominal ({}), which the bar cannot tell from link 6's own, is not applied to it",
                length_um((tc - tn).norm() * 1e6)
            ));
        }
    }

    // The joint zero offsets: the calibration report's, else the two files' θ.
    let joint_offsets = joint_offsets(a, report_json.as_ref(), &nominal, &calibrated, &mut notes)?;
    let predicted = setup::predicted_accuracy(report_json.as_ref(), tcp.is_some(), &mut notes);
    let poses =
        crate::calibrate::predict::workspace(&calibrated, crate::calibrate::WORKSPACE_POSES, 1);
    let offsets_rad = joint_offsets.map_or([0.0; 6], |o| o.delta);
    let accuracy = offsets::accuracy(&comp, &offsets_rad, &poses, predicted);
    let mastering = joint_offsets
        .map(|o| offsets::mastering(&o, &map, dialect.map(|d| d.language()), pulses.as_ref()));

    let note = format!(
        "compensated by edbbgen {} for {} (sha256 {}) against {}; joint values of the calibrated robot",
        env!("CARGO_PKG_VERSION"),
        calibrated.source,
        &calibrated.digest[..16.min(calibrated.digest.len())],
        nominal.source
    );
    let mut targets_report = None;
    let mut program_report = None;
    let mut output_text = None;
    if let Some((path, true)) = &input {
        let text = read_input(path, "targets", crate::files::Kind::Measured)?;
        let file = targets::parse(&text).map_err(|e| file_err(path, e))?;
        let results = targets::compensate_file(&comp, &file, &map, approach);
        output_text = Some(targets::write(&file, &results, &comp, &map));
        targets_report = Some(targets::report(name(path), &file, &results, &comp, &map));
    }
    if let (Some((path, false)), Some(text), Some(d)) = (&input, &program_text, dialect) {
        match program::rewrite(
            text,
            d,
            &map,
            &comp,
            &crate::timing::Limits::of(&nominal),
            &note,
            approach.signs(),
        )
        .map_err(|e| file_err(path, e))?
        {
            Outcome::Refused(list) => {
                print_refused(path, &list);
                return Ok(1);
            }
            Outcome::Written(w) => {
                let margin = spec.as_ref().map(|s| s.joint_margin);
                let (report, note) = program::report(&w, margin, &nominal, name(path), &d.name);
                notes.extend(note);
                program_report = Some(report);
                output_text = Some(w.text);
            }
        }
    }

    let tcp_rpy = tcp_n.rpy().map(|v| compensate::round6(v / DEG));
    let report = Report {
        schema: "edbbgen.compensate/1",
        calibrated: calibrated.source.clone(),
        nominal: nominal.source.clone(),
        tcp_nominal_mm: [0, 1, 2].map(|i| compensate::round6(tcp_n.t[i] / MM)),
        tcp_calibrated_mm: [0, 1, 2].map(|i| compensate::round6(tcp_c.t[i] / MM)),
        tcp_rpy_deg: tcp_rpy,
        controller: map.describe(),
        limits: Limits::default(),
        targets: targets_report,
        program: program_report,
        mastering,
        accuracy,
        notes,
    };
    write_outputs(a, &report, &calibrated, output_text.as_deref())
}

/// The input the flags name (the targets file, `true`, or the program, `false`), checked
/// against `-o` and the other outputs; none without an input.
fn check_input(a: &CompensateArgs) -> Result<Option<(&std::path::PathBuf, bool)>, Error> {
    let input = match (&a.targets, &a.program) {
        (Some(t), None) => Some((t, true)),
        (None, Some(p)) => Some((p, false)),
        (None, None) => None,
        (Some(_), Some(_)) => {
            return Err(usage(
                "--targets and --program: give one of them (run compensate twice for both)",
            ))
        }
    };
    match (&input, &a.output) {
        (Some(_), None) => {
            return Err(usage(
                "-o: required with --targets or --program (the compensated file)",
            ))
        }
        (None, Some(o)) => {
            return Err(usage(format!(
                "-o {}: give --targets T.csv or --program PROGRAM to compensate",
                o.display()
            )))
        }
        _ => {}
    }
    check_outputs(&[a.output.as_deref(), a.json.as_deref(), a.html.as_deref()])?;
    Ok(input)
}

/// The nominal and the calibrated robot (the cell's `spec` gives the speeds), checked to be the
/// same robot joint by joint.
fn load_robots(
    a: &CompensateArgs,
    spec: Option<&crate::cell::CellSpec>,
) -> Result<(Robot, Robot), Error> {
    let load_opts = LoadOptions {
        flange_link: a.flange.clone(),
        package_paths: a.package_path.clone(),
        speeds: spec.and_then(|s| s.speeds),
        ..LoadOptions::default()
    };
    let nominal = robot::load(&a.nominal, &load_opts)?;
    let calibrated = robot::load(&a.calibrated, &load_opts)?;
    for (i, (n, c)) in nominal.joints.iter().zip(&calibrated.joints).enumerate() {
        if n.name != c.name {
            return Err(file_err(
                &a.calibrated,
                format!(
                    "joint {} is '{}' here but '{}' in the nominal robot {}: not a calibration of it",
                    i + 1,
                    c.name,
                    n.name,
                    a.nominal.display()
                ),
            ));
        }
    }
    Ok((nominal, calibrated))
}

/// The tool point on the nominal and on the calibrated robot: `tcp` on both, else the MAP
/// (the cell `spec`'s or the nominal file's; the calibrated file's own on the calibrated robot).
fn tool_points(
    a: &CompensateArgs,
    tcp: Option<Frame>,
    spec: Option<&crate::cell::CellSpec>,
    nominal: &Robot,
    calibrated: &Robot,
) -> Result<(Frame, Frame), Error> {
    Ok(match tcp {
        Some(t) => (t, t),
        None => {
            let n = spec
                .and_then(|s| s.map)
                .or(nominal.tool)
                .map(Frame::translation)
                .ok_or_else(|| {
                    usage(format!(
                        "--tcp: required: {} declares no MAP and no cell gives one",
                        a.nominal.display()
                    ))
                })?;
            (n, calibrated.tool.map(Frame::translation).unwrap_or(n))
        }
    })
}

/// The controller mapping (from the `dialect`'s defaults and the cell `spec`'s `[controller]`,
/// else the plain one) and the cell's encoder pulses per degree, checked.
fn resolve_map(
    a: &CompensateArgs,
    spec: Option<&crate::cell::CellSpec>,
    dialect: Option<&'static crate::dialect::Dialect>,
    nominal: &Robot,
) -> Result<(ControllerMap, Option<[f64; 6]>), Error> {
    let cell_spec = spec.and_then(|s| s.controller.as_ref());
    let map = match dialect {
        Some(d) => match spec {
            Some(s) => controller_map(s, a.cell.as_deref(), d, nominal)?,
            None => controller_map(&crate::cell::CellSpec::default(), None, d, nominal)?,
        },
        None => ControllerMap::plain(cell_spec, nominal).map_err(|e| Error::File {
            path: a
                .cell
                .as_ref()
                .map_or_else(|| "[controller]".into(), |p| p.display().to_string()),
            msg: e.to_string(),
        })?,
    };
    let pulses = cell_spec.and_then(|c| c.pulses_per_deg);
    if let Some(p) = pulses {
        if p.iter().any(|v| !(v.is_finite() && *v != 0.0)) {
            return Err(file_err(
                a.cell.as_deref().unwrap_or(Path::new("[controller]")),
                "[controller] pulses_per_deg: six non-zero numbers (encoder pulses per axis degree)",
            ));
        }
    }
    Ok((map, pulses))
}

/// `--calibration`: the calibration report as JSON, or none.
fn read_calibration(a: &CompensateArgs) -> Result<Option<serde_json::Value>, Error> {
    let read = |p: &Path| -> Result<serde_json::Value, Error> {
        let text = read_input(p, "calibration report", crate::files::Kind::Config)?;
        serde_json::from_str(&text).map_err(|e| file_err(p, format!("not JSON: {e}")))
    };
    a.calibration.as_deref().map(read).transpose()
}

/// A payload: its mass (kg) and, where given, its centre (m, flange frame).
type Payload = (f64, Option<Vector3<f64>>);

/// `--payload`: the payload the flag gives, or none.
fn parse_payload(a: &CompensateArgs) -> Result<Option<Payload>, Error> {
    Ok(match &a.payload {
        Some(p) => {
            let v = numbers("--payload", p, None)?;
            if !(v.len() == 1 || v.len() == 4) || v[0].is_nan() || v[0] < 0.0 {
                return Err(usage(format!(
                    "--payload: '{p}' needs a mass (kg, >= 0) and optionally its centre X,Y,Z (mm, flange frame)"
                )));
            }
            Some((
                v[0],
                (v.len() == 4).then(|| Vector3::new(v[1], v[2], v[3]) * MM),
            ))
        }
        None => None,
    })
}

/// The joint zero offsets: the calibration report's, else the two robots' θ; a note says why
/// there are none.
fn joint_offsets(
    a: &CompensateArgs,
    report_json: Option<&serde_json::Value>,
    nominal: &Robot,
    calibrated: &Robot,
    notes: &mut Vec<String>,
) -> Result<Option<JointOffsets>, Error> {
    Ok(match report_json {
        Some(v) => Some(
            offsets::from_report(v)
                .map_err(|e| file_err(a.calibration.as_deref().unwrap_or(Path::new("")), e))?,
        ),
        None => match offsets::from_tables(nominal, calibrated) {
            Ok(o) => Some(o),
            Err(e) => {
                notes.push(format!(
                    "no mastering offsets: {e}; give --calibration REPORT.json"
                ));
                None
            }
        },
    })
}

/// Tells on stderr which moves of the program at `path` cannot be compensated.
fn print_refused(path: &Path, list: &[program::Refused]) {
    for r in list {
        eprintln!(
            "edbbgen: {}: line {}: cannot be compensated: {}",
            path.display(),
            r.line,
            r.status
        );
    }
    eprintln!(
        "edbbgen: {}: {} of its moves cannot be compensated; nothing written",
        path.display(),
        list.len()
    );
}

/// Writes the compensated file (`output_text`), the JSON `report` and the page for `calibrated`
/// all together or not at all, and prints the summary; the exit code.
fn write_outputs(
    a: &CompensateArgs,
    report: &Report,
    calibrated: &Robot,
    output_text: Option<&str>,
) -> Result<i32, Error> {
    let json = serde_json::to_string_pretty(report).unwrap_or_default() + "\n";
    let html = match &a.html {
        Some(_) => {
            let title = format!("{} [{}]", calibrated.name, calibrated.source);
            Some(crate::report::render(&crate::report::compensate::page(
                report, &title,
            )?)?)
        }
        None => None,
    };
    let mut files: Vec<(&Path, &str)> = Vec::new();
    if let (Some(o), Some(t)) = (&a.output, output_text) {
        files.push((o.as_path(), t));
    }
    if let Some(p) = &a.json {
        files.push((p.as_path(), json.as_str()));
    }
    if let (Some(p), Some(h)) = (&a.html, &html) {
        files.push((p.as_path(), h.as_str()));
    }
    write_all_atomic(&files)?;
    say_raw!(a.quiet, "{}", compensate::summary::text(report));
    if let Some(o) = &a.output {
        say!(a.quiet, "wrote {}", o.display());
    }
    Ok(0)
}

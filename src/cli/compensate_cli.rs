//! `compensate`: flags → the two robots, the tool point, the controller mapping → compensated
//! targets (CSV) or a compensated program, the mastering offsets and the accuracy they give,
//! all written together or not at all.

use super::args::CompensateArgs;
use super::{numbers, usage, write_all_atomic, Error};
use crate::compensate::offsets::{self, JointOffsets, Um};
use crate::compensate::program::{self, Outcome};
use crate::compensate::{self, targets, Compensator, Limits, NotCompensated, Report};
use crate::controller::{ControllerDefaults, ControllerMap, Coupling, Units};
use crate::robot::effects::{ComplianceForm, ThermalState};
use crate::robot::{self, Frame, LoadOptions, PointMass, Robot};
use crate::units::{fmt_fixed, DEG, MM};
use nalgebra::Vector3;
use std::path::Path;

fn file_err(path: &Path, msg: impl std::fmt::Display) -> Error {
    Error::File {
        path: path.display().to_string(),
        msg: msg.to_string(),
    }
}

fn name(path: &Path) -> String {
    path.file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

/// `--tcp X,Y,Z[,RX,RY,RZ]` (mm, deg) → the tool frame in the flange frame.
fn parse_tcp(s: &str) -> Result<Frame, Error> {
    let v = numbers("--tcp", s, None)?;
    match v.len() {
        3 => Ok(Frame::translation(Vector3::new(v[0], v[1], v[2]) * MM)),
        6 => Ok(Frame::from_xyz_rpy(
            [v[0] * MM, v[1] * MM, v[2] * MM],
            [v[3] * DEG, v[4] * DEG, v[5] * DEG],
        )),
        n => Err(usage(format!(
            "--tcp: '{s}' has {n} values, expected X,Y,Z or X,Y,Z,RX,RY,RZ (mm, deg)"
        ))),
    }
}

/// The mapping without a dialect: the cell's `[controller]` over model joints (deg, J1..J6,
/// no coupling unless the cell says so), else the identity.
fn plain_map(
    spec: Option<&crate::controller::ControllerSpec>,
    robot: &Robot,
) -> Result<ControllerMap, crate::controller::ControllerError> {
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

pub fn compensate(a: &CompensateArgs) -> Result<i32, Error> {
    // The command line first: nothing is read before it is sound.
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
    super::check_outputs(&[a.output.as_deref(), a.json.as_deref(), a.html.as_deref()])?;
    let tcp = a.tcp.as_deref().map(parse_tcp).transpose()?;
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

    let load_opts = LoadOptions {
        flange_link: a.flange.clone(),
        package_paths: a.package_path.clone(),
        speeds: spec.as_ref().and_then(|s| s.speeds),
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
    // The tool point: --tcp on both robots; else the MAP: the cell's (what the programs were
    // planned with) or the nominal file's on the nominal robot, the calibrated file's own (its
    // calibrated MAP) on the calibrated one.
    let (tcp_n, tcp_c) = match tcp {
        Some(t) => (t, t),
        None => {
            let n = spec
                .as_ref()
                .and_then(|s| s.map)
                .or(nominal.tool)
                .map(Frame::translation)
                .ok_or_else(|| {
                    usage(format!(
                        "--tcp: required: {} declares no tool point (MAP) and no cell gives one",
                        a.nominal.display()
                    ))
                })?;
            (n, calibrated.tool.map(Frame::translation).unwrap_or(n))
        }
    };
    // The program (its dialect decides the mapping's defaults and the mastering's family).
    let program_text = match &a.program {
        Some(p) => Some(super::read_input(
            p,
            "program",
            crate::files::Kind::Program,
        )?),
        None => None,
    };
    let dialect = match (&program_text, &a.program) {
        (Some(text), Some(p)) => Some(super::program_dialect(a.dialect.as_deref(), p, text)?),
        _ => named_dialect,
    };
    let cell_spec = spec.as_ref().and_then(|s| s.controller.as_ref());
    let map = match dialect {
        Some(d) => match &spec {
            Some(s) => super::controller_map(s, a.cell.as_deref(), d, &nominal)?,
            None => super::controller_map(&crate::cell::CellSpec::default(), None, d, &nominal)?,
        },
        None => plain_map(cell_spec, &nominal).map_err(|e| Error::File {
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
    let report_json = match &a.calibration {
        Some(p) => {
            let text = super::read_input(p, "calibration report", crate::files::Kind::Config)?;
            Some(
                serde_json::from_str::<serde_json::Value>(&text)
                    .map_err(|e| file_err(p, format!("not JSON: {e}")))?,
            )
        }
        None => None,
    };

    let approach = targets::Approach::parse(&a.approach).ok_or_else(|| {
        usage(format!(
            "--approach: '{}' (expected order, positive, negative or unknown)",
            a.approach
        ))
    })?;
    let mut calibrated = calibrated;
    let mut notes = effects_setup(a, approach, &mut calibrated, &tcp_c)?;
    let state = match (a.temperature, a.elapsed) {
        (Some(c), _) => ThermalState::Temperature(c),
        (None, Some(t)) => ThermalState::Elapsed(t),
        (None, None) => ThermalState::Reference,
    };
    let comp = Compensator::new(&nominal, &calibrated, &tcp_n, &tcp_c).at_state(state);
    if tcp.is_some() {
        if let (Some(tn), Some(tc)) = (nominal.tool, calibrated.tool) {
            notes.push(format!(
                "the tool point is given (--tcp): the calibrated MAP's deviation from nominal ({} um), which the bar cannot tell from link 6's own, is not applied to it",
                fmt_fixed((tc - tn).norm() * 1e6, 1)
            ));
        }
    }

    // The joint zero offsets: the calibration report's, else the two files' θ.
    let joint_offsets: Option<JointOffsets> = match &report_json {
        Some(v) => Some(
            offsets::from_report(v)
                .map_err(|e| file_err(a.calibration.as_deref().unwrap_or(Path::new("")), e))?,
        ),
        None => match offsets::from_tables(&nominal, &calibrated) {
            Ok(o) => Some(o),
            Err(e) => {
                notes.push(format!(
                    "no mastering offsets: {e}; give --calibration REPORT.json"
                ));
                None
            }
        },
    };
    let predicted = report_json.as_ref().and_then(|v| {
        Some((
            v.pointer("/predicted_position_std_um/workspace_rms")?
                .as_f64()?,
            v.pointer("/predicted_position_std_um/workspace_p95")?
                .as_f64()?,
        ))
    });
    if predicted.is_some() && tcp.is_some() {
        notes.push("the calibration's predicted uncertainty is the MAP's: at another tool point the flange's orientation uncertainty adds, times their distance".into());
    }
    if predicted.is_none() {
        notes.push("the calibration's predicted accuracy is not known here: give --calibration REPORT.json".into());
    }
    let poses =
        crate::calibrate::predict::workspace(&calibrated, crate::calibrate::WORKSPACE_POSES, 1);
    let offsets_rad = joint_offsets.map_or([0.0; 6], |o| o.delta);
    let accuracy = offsets::accuracy(&comp, &offsets_rad, &poses, predicted);
    let mastering = joint_offsets
        .map(|o| offsets::mastering(&o, &map, dialect.map(|d| d.name.as_str()), pulses.as_ref()));

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
        let text = super::read_input(path, "targets", crate::files::Kind::Measured)?;
        let file = targets::parse(&text).map_err(|e| file_err(path, e))?;
        let list = targets::to_targets(&file, &map);
        let unknown: Vec<(compensate::Target, [f64; 6])> =
            list.iter().map(|t| (*t, [0.0; 6])).collect();
        // A backlash needs each target's approach; in file order it follows the load-side
        // joints (a first pass solves them) of the targets the robot will visit: a row that
        // cannot be compensated is not run, so the next one comes from the row before it.
        let results = if comp.effects().backlash.is_empty() {
            comp.compensate_all(&unknown)
        } else {
            let load: Vec<Option<[f64; 6]>> = comp
                .compensate_all(&unknown)
                .iter()
                .map(|c| c.q.map(|q| comp.load(&q, &[0.0; 6])))
                .collect();
            let ap = targets::approaches(&file, &map, &load, approach);
            let with: Vec<(compensate::Target, [f64; 6])> = list.iter().copied().zip(ap).collect();
            comp.compensate_all(&with)
        };
        output_text = Some(targets::write(&file, &results, &comp, &map));
        targets_report = Some(targets_summary(path, &file, &results, &comp, &map));
    }
    if let (Some((path, false)), Some(text), Some(d)) = (&input, &program_text, dialect) {
        match program::rewrite(
            text,
            d,
            &map,
            &comp,
            &crate::timing::Limits::of(&nominal),
            &note,
            match approach {
                targets::Approach::Positive => [1.0; 6],
                targets::Approach::Negative => [-1.0; 6],
                targets::Approach::Order | targets::Approach::Unknown => [0.0; 6],
            },
        )
        .map_err(|e| file_err(path, e))?
        {
            Outcome::Refused(list) => {
                for r in &list {
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
                return Ok(1);
            }
            Outcome::Written(w) => {
                // The cell's joint margin: a pose planned at its edge may cross it by the
                // compensation (hundredths of a degree); say where, and by how much.
                let margin = spec.as_ref().map_or(0.0, |s| s.joint_margin);
                let (lo, hi) = nominal.limits();
                let mut beyond = Vec::new();
                if spec.is_some() {
                    for (line, q) in &w.joints {
                        for i in 0..6 {
                            let over = (lo[i] + margin - q[i]).max(q[i] - (hi[i] - margin));
                            if over > 0.0 {
                                beyond.push((*line, i + 1, round6(over / DEG)));
                            }
                        }
                    }
                }
                if !beyond.is_empty() {
                    notes.push(format!(
                        "{} moves leave the cell's joint margin of {} deg by up to {} deg (the compensation moves joints by up to {} deg): verify the compensated program with --joint-margin {} or plan with a larger margin",
                        beyond.len(),
                        fmt_fixed(margin / DEG, 3),
                        fmt_fixed(beyond.iter().map(|b| b.2).fold(0.0, f64::max), 4),
                        fmt_fixed(w.largest_change / DEG, 4),
                        fmt_fixed(((margin / DEG) - (w.largest_change / DEG)).max(0.0) * 0.999, 3)
                    ));
                }
                program_report = Some(compensate::ProgramReport {
                    largest_change_deg: round6(w.largest_change / DEG),
                    beyond_joint_margin: beyond,
                    file: name(path),
                    dialect: d.name.clone(),
                    moves: w.moves,
                    decimals: w.decimals,
                    printed_residual_um: crate::calibrate::predict::spread(
                        &w.printed_residual
                            .iter()
                            .map(|r| r * 1e6)
                            .collect::<Vec<_>>(),
                    )
                    .into(),
                    retimed_lines: w.retimed.clone(),
                });
                output_text = Some(w.text);
            }
        }
    }

    let tcp_rpy = tcp_n.rpy().map(|v| round6(v / DEG));
    let report = Report {
        schema: "edbbgen.compensate/1",
        calibrated: calibrated.source.clone(),
        nominal: nominal.source.clone(),
        tcp_nominal_mm: [0, 1, 2].map(|i| round6(tcp_n.t[i] / MM)),
        tcp_calibrated_mm: [0, 1, 2].map(|i| round6(tcp_c.t[i] / MM)),
        tcp_rpy_deg: tcp_rpy,
        controller: map.describe(),
        limits: Limits::default(),
        targets: targets_report,
        program: program_report,
        mastering,
        accuracy,
        notes,
    };
    let json = serde_json::to_string_pretty(&report).unwrap_or_default() + "\n";
    let html = match &a.html {
        Some(_) => {
            let title = format!("{} [{}]", calibrated.name, calibrated.source);
            Some(crate::report::render(&crate::report::compensate::page(
                &report, &title,
            )?)?)
        }
        None => None,
    };
    let mut files: Vec<(&Path, &str)> = Vec::new();
    if let (Some(o), Some(t)) = (&a.output, &output_text) {
        files.push((o.as_path(), t.as_str()));
    }
    if let Some(p) = &a.json {
        files.push((p.as_path(), json.as_str()));
    }
    if let (Some(p), Some(h)) = (&a.html, &html) {
        files.push((p.as_path(), h.as_str()));
    }
    write_all_atomic(&files)?;
    print!("{}", summary(&report));
    if let Some(o) = &a.output {
        println!("wrote {}", o.display());
    }
    Ok(0)
}

fn round6(v: f64) -> f64 {
    let r = (v * 1e6).round() / 1e6;
    if r == 0.0 {
        0.0
    } else {
        r
    }
}

fn targets_summary(
    path: &Path,
    file: &targets::TargetFile,
    results: &[compensate::Compensated],
    comp: &Compensator,
    map: &ControllerMap,
) -> compensate::TargetsReport {
    // The residual at the printed joints, as the CSV states it.
    let printed = |q: &[f64; 6]| -> [f64; 6] {
        let m = ControllerMap {
            units: Units::Deg,
            ..map.clone()
        };
        let axes = m
            .apply(&q.map(|r| r / DEG))
            .map(|v| fmt_fixed(v, targets::DECIMALS).parse::<f64>().unwrap_or(v));
        m.undo(&axes).map(|d| d * DEG)
    };
    let mut before = Vec::new();
    let mut after = Vec::new();
    let mut not = Vec::new();
    let mut free = 0;
    for (row, c) in file.rows.iter().zip(results) {
        match (c.status.is_ok(), c.q, c.nominal) {
            (true, Some(q), Some(qn)) => {
                before.push(comp.residual(&c.target, &qn, &c.approach) * 1e6);
                after.push(comp.residual(&c.target, &printed(&q), &c.approach) * 1e6);
                free += usize::from(c.orientation_free);
            }
            _ => not.push(NotCompensated {
                line: row.line,
                name: row.name.clone(),
                status: c.status.to_string(),
            }),
        }
    }
    let b: Um = crate::calibrate::predict::spread(&before).into();
    let r: Um = crate::calibrate::predict::spread(&after).into();
    before.sort_by(f64::total_cmp);
    after.sort_by(f64::total_cmp);
    compensate::TargetsReport {
        file: name(path),
        kind: match file.kind {
            targets::Kind::Joints => "joints",
            targets::Kind::Pose => "pose",
            targets::Kind::Position => "position",
        },
        rows: file.rows.len(),
        compensated: before.len(),
        orientation_free: free,
        not_compensated: not,
        before_um: b,
        residual_um: r,
        sorted_um: (before, after),
    }
}

fn summary(r: &Report) -> String {
    let mut s = String::new();
    if let Some(t) = &r.targets {
        s += &format!(
            "{}: compensated {} of {} targets ({}); the calibrated robot missed them by {} um RMS, {} um max; at the written joints {} um max\n",
            t.file,
            t.compensated,
            t.rows,
            t.kind,
            fmt_fixed(t.before_um.rms, 1),
            fmt_fixed(t.before_um.max, 1),
            fmt_fixed(t.residual_um.max, 3)
        );
        if t.orientation_free > 0 {
            s += &format!(
                "{} near a wrist singularity: position exact, orientation within {} deg\n",
                t.orientation_free,
                fmt_fixed(r.limits.orientation_tolerance_deg, 2)
            );
        }
        let mut reasons: Vec<(String, usize)> = Vec::new();
        for n in &t.not_compensated {
            let why = n.status.split(':').next().unwrap_or("").to_string();
            match reasons.iter_mut().find(|x| x.0 == why) {
                Some(x) => x.1 += 1,
                None => reasons.push((why, 1)),
            }
        }
        if !reasons.is_empty() {
            s += &format!(
                "not compensated (listed with the reason in the output): {}\n",
                reasons
                    .iter()
                    .map(|(w, n)| format!("{n} {w}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    if let Some(p) = &r.program {
        s += &format!(
            "{} ({}): {} moves compensated, axis values with {} decimals: TCP error at the printed values {} um RMS, {} um max{}\n",
            p.file,
            p.dialect,
            p.moves,
            p.decimals,
            fmt_fixed(p.printed_residual_um.rms, 3),
            fmt_fixed(p.printed_residual_um.max, 3),
            if p.retimed_lines.is_empty() {
                String::new()
            } else {
                format!(
                    "; {} moves slowed to stay within the axis speeds",
                    p.retimed_lines.len()
                )
            }
        );
    }
    if let Some(m) = &r.mastering {
        s += &format!(
            "mastering offsets (from the {}; {}):\n",
            match m.source {
                offsets::Source::CalibrationReport => "calibration report",
                offsets::Source::RobotFiles => "robot files' joint zeros",
            },
            m.controller
        );
        for (a, line) in m.axes.iter().zip(&m.instructions) {
            let std = match a.std {
                Some(v) => format!(" +/- {}", fmt_fixed(v, 6)),
                None => String::new(),
            };
            s += &format!(
                "  {}: {}{} {}   {}\n",
                a.axis,
                fmt_fixed(a.delta, 6),
                std,
                a.units,
                line
            );
        }
    }
    let acc = &r.accuracy;
    s += &format!(
        "TCP accuracy over the joint space ({} random poses, registered): nothing applied {} um RMS, {} um p95; offsets only {} um RMS (model)",
        acc.poses,
        fmt_fixed(acc.uncompensated_um.rms, 1),
        fmt_fixed(acc.uncompensated_um.p95, 1),
        fmt_fixed(acc.offsets_only_model_um.rms, 1)
    );
    match (&acc.predicted_offsets_only_um, &acc.predicted_full_um) {
        (Some(o), Some(f)) => {
            s += &format!(
                ", {} um RMS predicted; full compensation {} um RMS, {} um p95 predicted (the calibration's)\n",
                fmt_fixed(o.rms, 1),
                fmt_fixed(f.rms, 2),
                fmt_fixed(f.p95, 2)
            );
        }
        _ => s += "\n",
    }
    for n in &r.notes {
        s += &format!("note: {n}\n");
    }
    s
}

/// The calibrated robot's effects as this compensation applies them: a changed payload
/// (`--payload`) added to a compliance with a mass model, and one note per effect saying how
/// it is applied (and the thermal state, the approach convention, what is not applied).
fn effects_setup(
    a: &CompensateArgs,
    approach: targets::Approach,
    calibrated: &mut Robot,
    tcp: &Frame,
) -> Result<Vec<String>, Error> {
    let mut notes = Vec::new();
    let e = &mut calibrated.effects;
    if let Some(p) = &a.payload {
        let v = numbers("--payload", p, None)?;
        if !(v.len() == 1 || v.len() == 4) || v[0].is_nan() || v[0] < 0.0 {
            return Err(usage(format!(
                "--payload: '{p}' needs a mass (kg, >= 0) and optionally its centre X,Y,Z (mm, flange frame)"
            )));
        }
        let centre = if v.len() == 4 {
            Vector3::new(v[1], v[2], v[3]) * MM
        } else {
            tcp.t
        };
        match e.compliance.as_mut().map(|c| &mut c.form) {
            Some(ComplianceForm::KnownMasses { masses, .. }) => {
                masses.push(PointMass {
                    frame: 6,
                    com: calibrated.flange.apply(&centre),
                    mass: v[0],
                });
                notes.push(format!(
                    "joint compliance: the robot file's masses plus a payload of {} kg at {}, {}, {} mm in the flange frame (--payload)",
                    fmt_fixed(v[0], 3),
                    fmt_fixed(centre.x / MM, 1),
                    fmt_fixed(centre.y / MM, 1),
                    fmt_fixed(centre.z / MM, 1)
                ));
            }
            Some(ComplianceForm::LinkMoments { .. }) => {
                return Err(file_err(
                    &a.calibrated,
                    "--payload: its joint compliance was identified without a mass model (form link_moments), for the payload carried during the calibration; a changed payload needs a new calibration with it",
                ))
            }
            None => {
                return Err(file_err(
                    &a.calibrated,
                    "--payload: the robot has no joint compliance (no [effects.joint_compliance]) for a payload to act on",
                ))
            }
        }
    } else if let Some(c) = &e.compliance {
        notes.push(match c.form {
            ComplianceForm::KnownMasses { .. } => "joint compliance: applied to every target with the robot file's masses and gravity as calibrated (--payload adds a changed payload)".to_string(),
            ComplianceForm::LinkMoments { .. } => "joint compliance: applied to every target for the payload and gravity of the calibration (identified without a mass model: a changed payload needs a new calibration)".to_string(),
        });
    }
    let e = &calibrated.effects;
    for c in &e.cyclic {
        notes.push(format!(
            "cyclic error of joint {}: applied to every target (harmonic orders {:?})",
            c.joint + 1,
            c.orders
        ));
    }
    for b in &e.backlash {
        notes.push(format!(
            "backlash of joint {} ({} deg play): applied by each target's approach ({}); a joint whose approach is not known is taken at the centre of the play",
            b.joint + 1,
            fmt_fixed(b.play / DEG, 5),
            if a.program.is_some() {
                format!(
                    "the direction of the program's move into it; into the first move {}",
                    match approach {
                        targets::Approach::Positive => "from below (--approach positive)",
                        targets::Approach::Negative => "from above (--approach negative)",
                        _ => "not known: the centre of the play, up to half of it off (--approach positive or negative says where the robot comes from)",
                    }
                )
            } else {
                format!("the targets' approach column, else --approach {}", a.approach)
            }
        ));
    }
    match (&e.thermal, a.temperature, a.elapsed) {
        (Some(_), None, None) => notes.push(
            "thermal drift: compensated at the reference state of the calibration (--temperature or --elapsed for another)".into(),
        ),
        (Some(robot::effects::Thermal::Temperature { reference_c, .. }), Some(c), _) => notes.push(format!(
            "thermal drift: compensated at {} C ({} K from the reference)",
            fmt_fixed(c, 2),
            fmt_fixed(c - reference_c, 2)
        )),
        (Some(robot::effects::Thermal::Lag { .. }), None, Some(t)) => notes.push(format!(
            "thermal drift: compensated at {} s after the reference state",
            fmt_fixed(t, 1)
        )),
        (Some(_), _, _) => {
            return Err(usage(
                "--temperature applies to a drift referred to a logged temperature, --elapsed to a warm-up lag: the robot's [effects.thermal_drift] form is the other",
            ))
        }
        (None, Some(_), _) | (None, _, Some(_)) => {
            return Err(usage(
                "--temperature/--elapsed: the calibrated robot has no thermal drift",
            ))
        }
        (None, None, None) => {}
    }
    if let Some(l) = &e.servo_lag {
        notes.push(format!(
            "servo lag ({} ms): moves no pose, so no target is changed for it; it matters where the robot measures while moving",
            fmt_fixed(l.tau * 1e3, 2)
        ));
    }
    Ok(notes)
}

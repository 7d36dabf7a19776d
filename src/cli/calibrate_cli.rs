//! `calibrate`: flags → checked campaign (runs, fixtures, options) → the calibration stage →
//! the calibrated robot file and the reports, all written together or not at all.

use super::args::CalibrateArgs;
use super::{usage, write_all_atomic, xyz_mm, Error};
use crate::calibrate::{self, CalibrateOptions, Calibration, Effects, LengthOffset};
use crate::compensate::drift;
use crate::diagnose::Run;
use crate::model::MeasurementModel;
use crate::robot::{self, LoadOptions, Robot};
use crate::twin::{self, Effect, Measured};
use crate::units::{fmt_fixed, DEG, MM};
use nalgebra::Vector3;
use std::path::Path;

/// `--effects`: auto, none, or a comma-separated list of library effects, `NAME[:JOINT]`.
pub(super) fn parse_effects(s: &str) -> Result<Effects, Error> {
    match s.trim() {
        "auto" => return Ok(Effects::Auto),
        "none" => return Ok(Effects::None),
        _ => {}
    }
    let mut list = Vec::new();
    for item in s.split(',') {
        let item = item.trim();
        let (name, joint) = match item.split_once(':') {
            Some((n, j)) => (n, Some(j)),
            None => (item, None),
        };
        let joint = |what: &str| -> Result<usize, Error> {
            let j = joint.ok_or_else(|| {
                usage(format!(
                    "--effects: {what} needs its joint, e.g. {what}:2 (joints 1-6)"
                ))
            })?;
            match j.trim().parse::<usize>() {
                Ok(n @ 1..=6) => Ok(n - 1),
                _ => Err(usage(format!(
                    "--effects: '{item}': the joint must be a number 1-6"
                ))),
            }
        };
        let no_joint = |e: Effect| -> Result<Effect, Error> {
            match joint_given(item) {
                true => Err(usage(format!(
                    "--effects: '{item}': {} belongs to no single joint",
                    e.name()
                ))),
                false => Ok(e),
            }
        };
        let e = match name {
            "cyclic_error" => Effect::CyclicError(joint("cyclic_error")?),
            "backlash" => Effect::Backlash(joint("backlash")?),
            "joint_compliance" => no_joint(Effect::JointCompliance)?,
            "thermal_drift" => no_joint(Effect::ThermalDrift)?,
            "servo_lag" => no_joint(Effect::ServoLag)?,
            _ => {
                return Err(usage(format!(
                    "--effects: '{item}' is not auto, none, or a list of joint_compliance, thermal_drift, cyclic_error:J, backlash:J, servo_lag"
                )))
            }
        };
        if list.contains(&e) {
            return Err(usage(format!("--effects: '{item}' is given twice")));
        }
        list.push(e);
    }
    Ok(Effects::List(list))
}

/// `--length-offset`: a length in mm (the reading minus the ball-centre distance), or `free`.
pub(super) fn parse_length_offset(s: Option<&str>) -> Result<LengthOffset, Error> {
    match s.map(str::trim) {
        None => Ok(LengthOffset::Known(0.0)),
        Some("free") => Ok(LengthOffset::Free),
        Some(v) => match v.parse::<f64>() {
            Ok(x) if x.is_finite() => Ok(LengthOffset::Known(x * MM)),
            _ => Err(usage(format!(
                "--length-offset: '{v}' is neither a length in mm nor 'free'"
            ))),
        },
    }
}

fn joint_given(item: &str) -> bool {
    item.contains(':')
}

fn file_err(path: &Path, msg: impl std::fmt::Display) -> Error {
    Error::File {
        path: path.display().to_string(),
        msg: msg.to_string(),
    }
}

/// The file name (no directory: outputs must not depend on where the inputs live).
fn name(path: &Path) -> String {
    path.file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.display().to_string())
}

fn is_urdf(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("urdf") || e.eq_ignore_ascii_case("xml"))
}

fn is_toml(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("toml"))
}

/// Synchronisations of continuous runs against the calibrated robot, at most; and the clock
/// change (s, anywhere in a run) below which another round would not move a reading by a
/// micrometre at the bar's speeds (up to 1 m/s).
const RESYNC_ROUNDS: usize = 5;
const RESYNC_TOL: f64 = 1e-6;

pub fn calibrate(a: &CalibrateArgs) -> Result<i32, Error> {
    // Everything about the command line first: nothing is read before it is sound.
    let logs_n = a.bar_log.len();
    let runs_n = a.measured.len() + logs_n;
    if runs_n == 0 {
        return Err(usage(
            "--measured or --bar-log: at least one run is required",
        ));
    }
    if a.fixture.len() != runs_n && a.fixture.len() > 1 {
        return Err(usage(format!(
            "--measured and --bar-log give {runs_n} runs but --fixture is given {} times: give one --fixture per run, in the same order (--measured first), or one for every run",
            a.fixture.len()
        )));
    }
    if a.fixture.is_empty() && !a.measured.is_empty() {
        return Err(usage("--fixture: required with --measured"));
    }
    if !(a.program.is_empty() || a.program.len() == 1 || a.program.len() == logs_n) {
        return Err(usage(format!(
            "--program is given {} times for {logs_n} --bar-log runs: give one for all, or one each",
            a.program.len()
        )));
    }
    if !(a.joint_log.is_empty() || a.joint_log.len() == logs_n) {
        return Err(usage(format!(
            "--joint-log is given {} times for {logs_n} --bar-log runs: give one each",
            a.joint_log.len()
        )));
    }
    if logs_n == 0 && !(a.program.is_empty() && a.joint_log.is_empty()) {
        return Err(usage("--program and --joint-log belong to a --bar-log run"));
    }
    if a.joint_log.is_empty() && a.program.is_empty() && logs_n > 0 {
        return Err(usage(
            "--bar-log: needs --program (the stop-and-measure program it recorded) or --joint-log",
        ));
    }
    let fixtures: Vec<Vector3<f64>> = a
        .fixture
        .iter()
        .map(|f| xyz_mm("--fixture", f))
        .collect::<Result<_, _>>()?;
    let fixture_flag = |k: usize| -> Option<Vector3<f64>> {
        match fixtures.len() {
            0 => None,
            1 => Some(fixtures[0]),
            _ => Some(fixtures[k]),
        }
    };
    super::check_outputs(&[
        Some(a.output.as_path()),
        a.json.as_deref(),
        a.plot.as_deref(),
        a.html.as_deref(),
    ])?;
    let urdf = is_urdf(&a.robot);
    match (urdf, is_urdf(&a.output), is_toml(&a.output)) {
        (true, true, _) | (false, _, true) => {}
        (true, _, _) => {
            return Err(usage(format!(
                "-o {}: a URDF robot calibrates to a .urdf file (the input with calibrated joint origins)",
                a.output.display()
            )))
        }
        (false, _, _) => {
            return Err(usage(format!(
                "-o {}: a DH robot calibrates to a .dh.toml file",
                a.output.display()
            )))
        }
    }
    let effects = parse_effects(&a.effects)?;
    let mut opts = CalibrateOptions {
        effects,
        fixture_known: a.fixture_known,
        tool_known: a.tool_known,
        length_offset: parse_length_offset(a.length_offset.as_deref())?,
        write_effects: !a.geometry_only,
        joint_resolution: match a.joint_resolution {
            Some(g) if !(g.is_finite() && (0.0..=10.0).contains(&g)) => {
                return Err(usage(format!(
                    "--joint-resolution: '{g}' is not a step in degrees from 0 to 10"
                )))
            }
            g => g.map(|g| g * DEG),
        },
        noise: a.noise.map(|u| u * 1e-6),
        ..CalibrateOptions::default()
    };
    if let Some(p) = &a.prior {
        let v = super::numbers("--prior", p, None)?;
        if !(v.len() == 2 || v.len() == 3) || v.iter().any(|x| *x <= 0.0) {
            return Err(usage(format!(
                "--prior: '{p}' needs a positive length (mm) and angle (deg) of the robot, and optionally of the set-up (mm)"
            )));
        }
        opts.prior_length = v[0] * MM;
        opts.prior_angle = v[1] * DEG;
        if let Some(s) = v.get(2) {
            opts.prior_setup = s * MM;
        }
    }

    // --baseline: the previous report is read before any work.
    let baseline = match &a.baseline {
        Some(path) => {
            let text = super::read_input(path, "calibration report", crate::files::Kind::Config)?;
            let value: serde_json::Value = serde_json::from_str(&text)
                .map_err(|e| file_err(path, format!("not JSON: {e}")))?;
            Some((
                drift::read_report(&value).map_err(|e| file_err(path, e))?,
                name(path),
                robot::sha256_hex(text.as_bytes()),
            ))
        }
        None => None,
    };

    let load_opts = LoadOptions {
        flange_link: a.flange.clone(),
        package_paths: a.package_path.clone(),
        ..LoadOptions::default()
    };
    let robot_text = super::read_input(&a.robot, "robot", crate::files::Kind::Robot)?;
    let robot = robot::load(&a.robot, &load_opts)?;
    let programs: Vec<super::logs_cli::Program> = a
        .program
        .iter()
        .map(|p| super::logs_cli::read_program(&robot, p))
        .collect::<Result<_, _>>()?;
    let program_of = |k: usize| match programs.len() {
        0 => None,
        1 => Some(&programs[0]),
        _ => Some(&programs[k]),
    };
    // The MAP: the flag, else the first program header's, else the robot file's.
    let map = match (
        &a.tool,
        programs.first().and_then(|p| p.parsed.header_value("MAP")),
    ) {
        (Some(s), _) => xyz_mm("--tool", s)?,
        (None, Some(h)) => super::logs_cli::header_xyz(h)
            .ok_or_else(|| usage("the program header's MAP is not X, Y, Z mm: give --tool"))?,
        (None, None) => robot.tool.unwrap_or_else(Vector3::zeros),
    };
    let mut data: Vec<(Measured, String)> = Vec::with_capacity(runs_n);
    let mut run_fixtures: Vec<Vector3<f64>> = Vec::with_capacity(runs_n);
    let mut labels: Vec<String> = Vec::with_capacity(runs_n);
    let mut sources: Vec<&Path> = Vec::with_capacity(runs_n);
    for (k, path) in a.measured.iter().enumerate() {
        let text = super::read_input(path, "measured data", crate::files::Kind::Measured)?;
        // A run of a campaign may be short when the others carry the robot; one run alone
        // must carry it.
        let min = if runs_n == 1 { calibrate::MIN_ROWS } else { 1 };
        let m = twin::parse_csv(&text, min).map_err(|e| file_err(path, e))?;
        data.push((m, robot::sha256_hex(text.as_bytes())));
        run_fixtures.push(fixture_flag(k).unwrap_or_else(Vector3::zeros));
        labels.push(name(path));
        sources.push(path);
    }
    let mut extras: Vec<Option<super::logs_cli::RunExtra>> = vec![None; a.measured.len()];
    let mut kept: Vec<Option<super::logs_cli::Logs>> =
        (0..a.measured.len()).map(|_| None).collect();
    let mut log_lines: Vec<Vec<String>> = vec![Vec::new(); a.measured.len()];
    for (i, bar) in a.bar_log.iter().enumerate() {
        let k = a.measured.len() + i;
        let run = super::logs_cli::read_run(
            &robot,
            bar,
            program_of(i),
            a.joint_log.get(i).map(|p| p.as_path()),
            fixture_flag(k),
            map,
        )?;
        // As for a measured file: one run alone must carry the robot, a campaign's run may
        // be short.
        let min = if runs_n == 1 { calibrate::MIN_ROWS } else { 1 };
        if run.measured.len() < min {
            return Err(file_err(
                bar,
                format!(
                    "{} readings, fewer than the {min} the fit needs{}",
                    run.measured.len(),
                    if runs_n == 1 {
                        " (one per parameter at least)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        log_lines.push(run.summary);
        data.push((run.measured, run.sha256));
        run_fixtures.push(run.fixture);
        labels.push(run.label);
        sources.push(bar);
        extras.push(Some(run.extra));
        kept.push(run.logs);
    }
    let fixture_of = |k: usize| run_fixtures[k];
    let model = MeasurementModel::new(&robot, fixture_of(0), map);
    let runs: Vec<Run> = data
        .iter()
        .enumerate()
        .map(|(k, (m, _))| Run {
            measured: m,
            fixture: fixture_of(k),
        })
        .collect();
    // --baseline: the fit starts from the previous calibration and states what moved since.
    let fit = |runs: &[Run]| match &baseline {
        Some((baseline, label, _)) => {
            drift::calibrate_against(&model, &robot, runs, &labels, &opts, baseline, label)
                .map(|(cal, d)| (cal, Some(d)))
                .map_err(|e| file_err(sources[0], e))
        }
        None => calibrate::run(&model, &robot, runs, &labels, &opts)
            .map(|cal| (cal, None))
            .map_err(|e| file_err(sources[0], e)),
    };
    let (mut cal, mut drift) = fit(&runs)?;
    drop(runs);
    // Continuous runs from logs were synchronised against the nominal model, whose errors
    // bias the clock (a 20 µs offset costs micrometres where the bar moves fast, a drift off
    // by 1 ppm 100 µs at the ends of a 4-minute run), and the first calibration absorbs part
    // of the clock's error: synchronised again against the calibrated robot and calibrated
    // again, until the clock moves by less than RESYNC_TOL anywhere in a run.
    for round in 0..RESYNC_ROUNDS {
        if kept.iter().all(Option::is_none) {
            break;
        }
        let before: Vec<Option<crate::logs::ClockReport>> = extras
            .iter()
            .map(|e| Some(e.as_ref()?.clock.clone()))
            .collect();
        for (k, logs) in kept.iter().enumerate() {
            let Some(logs) = logs else { continue };
            // The calibrated robot whole (its effects too: a compliance moves the bar's
            // length by hundreds of micrometres), run k's fixture.
            let mut p = cal.file.params;
            p.fix = cal.estimate.params(k).fix;
            let fx = &cal.file.effects;
            let length = |q: &[f64; 6]| model.reached_length(&p, fx, q, &[0.0; 6]);
            let i = k - a.measured.len();
            let (m, extra, summary) = super::logs_cli::resync(logs, &length, program_of(i))?;
            data[k].0 = m;
            extras[k] = Some(extra);
            log_lines[k] = summary;
        }
        let runs: Vec<Run> = data
            .iter()
            .enumerate()
            .map(|(k, (m, _))| Run {
                measured: m,
                fixture: fixture_of(k),
            })
            .collect();
        (cal, drift) = fit(&runs)?;
        let moved = extras
            .iter()
            .zip(&kept)
            .zip(&before)
            .filter_map(|((e, l), b)| {
                let t = &l.as_ref()?.bar.t;
                Some(
                    e.as_ref()?
                        .clock
                        .moved_from(b.as_ref()?, *t.first()?, *t.last()?),
                )
            })
            .fold(0.0, f64::max);
        if moved < RESYNC_TOL {
            break;
        }
        if round + 1 == RESYNC_ROUNDS {
            cal.report.warnings.push(format!(
                "the clock of a run from logs still moved by {} us in the last of {RESYNC_ROUNDS} synchronisations against the calibrated robot: the clock and the calibration have not settled, and readings where the bar moves fast carry that much timing error",
                fmt_fixed(moved * 1e6, 1)
            ));
        }
    }
    let fixtures = run_fixtures;

    // The report's keys, then `drift` (also when nothing is written as calibrated).
    #[derive(serde::Serialize)]
    struct WithDrift<'a> {
        #[serde(flatten)]
        report: &'a calibrate::Report,
        #[serde(skip_serializing_if = "Option::is_none")]
        drift: Option<&'a drift::Drift>,
    }
    let with_drift = WithDrift {
        report: &cal.report,
        drift: drift.as_ref(),
    };
    let json = if extras.iter().any(Option::is_some) {
        // Runs read from logs keep how they were read: their plateaus, missing poses and
        // clock, added to their run's keys.
        let mut report = serde_json::to_value(&with_drift).unwrap_or_default();
        if let Some(runs) = report.get_mut("runs").and_then(|r| r.as_array_mut()) {
            for (run, extra) in runs.iter_mut().zip(&extras) {
                if let (Some(obj), Some(extra)) = (run.as_object_mut(), extra) {
                    if let Ok(serde_json::Value::Object(add)) = serde_json::to_value(extra) {
                        obj.extend(add);
                    }
                }
            }
        }
        serde_json::to_string_pretty(&report)
    } else {
        serde_json::to_string_pretty(&with_drift)
    }
    .unwrap_or_default()
        + "\n";
    // Not calibrated (nothing of the robot determined, or no better than nominal held out)
    // and no set-up found either: no robot file is written; the report says why, and so does
    // one line on stderr.
    if !cal.writes_robot() {
        if let Some(p) = &a.json {
            write_all_atomic(&[(p.as_path(), json.as_str())])?;
        }
        print!("{}", cal.summary);
        eprintln!("calibrate: {}", cal.report.verdict);
        return Ok(1);
    }

    // Everything is rendered before the first file is written: a failure leaves no file.
    let mut header = header_lines(&robot, &cal, &data, &labels);
    if let (Some(d), Some(p)) = (&drift, &a.baseline) {
        header.push(format!("since {}: {}", name(p), d.verdict));
    }
    let p = cal.params();
    let effects = cal.file.effects.clone();
    let effects_text = robot::effects::to_toml(&effects, &cal.file.reference);
    // A URDF cannot hold the effects: they go to a sidecar file beside it, named in its header.
    let sidecar = (urdf && !effects_text.is_empty()).then(|| sidecar_path(&a.output));
    if let Some(side) = &sidecar {
        let name = side
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        header.push(format!("{} {name}", robot::effects::SIDECAR_MARK));
    }
    let calibrated = if urdf {
        robot::urdf::calibrated(
            &robot_text,
            &a.robot,
            &load_opts,
            &robot,
            &p.dh,
            &p.map,
            &header,
        )?
    } else {
        robot::dh::calibrated(&robot_text, &a.robot, &p.dh, &p.map, &header, &effects_text)?
    };
    // The URDF loads to a DH table of its own (its common normals may point the other way):
    // the effects go to the sidecar referred to that table's frames.
    let effects_text = if sidecar.is_some() {
        let (b, dh, f) =
            robot::urdf::dh_chain(&calibrated, &load_opts).map_err(|e| file_err(&a.output, e))?;
        let moved = effects.reframed((&robot.base, &p.dh, &robot.flange), (&b, &dh, &f));
        robot::effects::to_toml(&moved, &cal.file.reference)
    } else {
        effects_text
    };
    let sidecar_text = sidecar.as_ref().map(|_| {
        format!(
            "# The effects of {} (edbbgen calibrate): the URDF names this file; keep the two together.\n{effects_text}",
            a.output
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default()
        )
    });
    let svg = match &a.plot {
        Some(_) => Some(crate::calibrate::plot::svg(&cal)?),
        None => None,
    };
    let html = match &a.html {
        Some(_) => {
            // The baseline is an input too.
            let effects = match &baseline {
                Some((_, _, sha)) => format!("{}\nbaseline {sha}", a.effects),
                None => a.effects.clone(),
            };
            let hash = inputs_hash(&robot, &data, &fixtures, &map, &effects);
            let name = format!("{} [{}]", robot.name, robot.source);
            let mut page = crate::report::calibrate::page(&cal, &name, &hash)?;
            if let Some(d) = &drift {
                page.sections
                    .push(crate::report::compensate::drift_section(d)?);
            }
            Some(crate::report::render(&page)?)
        }
        None => None,
    };
    let mut files: Vec<(&Path, &str)> = vec![(a.output.as_path(), calibrated.as_str())];
    if let (Some(p), Some(t)) = (&sidecar, &sidecar_text) {
        files.push((p.as_path(), t.as_str()));
    }
    if let Some(p) = &a.json {
        files.push((p.as_path(), json.as_str()));
    }
    if let (Some(p), Some(svg)) = (&a.plot, &svg) {
        files.push((p.as_path(), svg.as_str()));
    }
    if let (Some(p), Some(html)) = (&a.html, &html) {
        files.push((p.as_path(), html.as_str()));
    }
    write_all_atomic(&files)?;
    for (k, lines) in log_lines.iter().enumerate() {
        for l in lines {
            println!("run {}: {l}", k + 1);
        }
    }
    print!("{}", cal.summary);
    println!("wrote {}", a.output.display());
    if let Some(p) = &sidecar {
        println!("wrote {} (the effects the URDF names)", p.display());
    }
    // The set-up only, with the nominal geometry: a result, told apart from a calibration.
    Ok(if cal.setup_only() { 3 } else { 0 })
}

/// The sidecar file of a calibrated URDF: `robot.cal.urdf` → `robot.cal.effects.toml`.
pub(super) fn sidecar_path(urdf: &Path) -> std::path::PathBuf {
    let stem = urdf
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "robot".into());
    urdf.with_file_name(format!("{stem}.effects.toml"))
}

/// The input hash of a calibration: robot, data, fixtures, tool and the effects option.
fn inputs_hash(
    robot: &Robot,
    data: &[(Measured, String)],
    fixtures: &[Vector3<f64>],
    map: &Vector3<f64>,
    effects: &str,
) -> String {
    let mut s = robot.digest.clone();
    for (_, h) in data {
        s += "\n";
        s += h;
    }
    for f in fixtures {
        s += &format!("\n{:?}", f.as_slice());
    }
    s += &format!("\n{:?}\n{effects}\n", map.as_slice());
    robot::sha256_hex(s.as_bytes())
}

/// The comment block on top of the calibrated file: where it came from and how good it is.
fn header_lines(
    robot: &Robot,
    cal: &Calibration,
    data: &[(Measured, String)],
    labels: &[String],
) -> Vec<String> {
    let r = &cal.report;
    let mut h = vec![format!(
        "{} by edbbgen {} from {} (sha256 {})",
        if cal.setup_only() {
            "set-up fitted (the geometry nominal)"
        } else {
            "calibrated"
        },
        env!("CARGO_PKG_VERSION"),
        robot.source,
        &robot.digest[..16.min(robot.digest.len())]
    )];
    for (k, run) in r.runs.iter().enumerate() {
        let f = match &r.setup {
            Some(s) if cal.setup_only() => s.fixtures_mm[k],
            _ => run.fixture_fitted_mm.unwrap_or(run.fixture_mm),
        };
        h.push(format!(
            "run {}: {} (sha256 {}, {} rows), fixture {}, {}, {} mm{}",
            k + 1,
            labels[k],
            &data[k].1[..16],
            run.rows,
            fmt_fixed(f[0], 3),
            fmt_fixed(f[1], 3),
            fmt_fixed(f[2], 3),
            if run.fixture_fitted_mm.is_some() {
                " (estimated)"
            } else {
                ""
            }
        ));
    }
    h.push(format!(
        "residual RMS {} um nominal -> {} um calibrated; bar noise {} um (lag-1 autocorrelation {})",
        fmt_fixed(r.rms_before_um, 3),
        fmt_fixed(r.rms_after_um, 3),
        fmt_fixed(r.noise_um, 3),
        fmt_fixed(r.residual_lag1, 2)
    ));
    h.push(format!(
        "determined ({}): {}",
        r.determined.len(),
        r.determined.join(", ")
    ));
    h.push(format!(
        "validation, held out: {} um RMS nominal -> {} um calibrated ({} rows)",
        fmt_fixed(r.validation.heldout_rms_um.nominal, 3),
        fmt_fixed(r.validation.heldout_rms_um.calibrated, 3),
        r.validation.rows
    ));
    for g in r.segments.iter().filter(|g| g.cause != "run start") {
        h.push(format!(
            "step in run {} at data row {}: {}",
            g.run, g.from_row, g.cause
        ));
    }
    if !r.outliers.is_empty() {
        h.push(format!("outliers dropped: {}", r.outliers.len()));
    }
    for u in &r.undetermined {
        h.push(format!("held at nominal: {}: {}", u.param, u.why));
    }
    let p = &r.predicted_position_std_um;
    if !cal.setup_only() {
        h.push(format!(
        "predicted MAP position uncertainty (1 sigma, after rigid registration): {} um RMS where measured, {} um RMS and {} um p95 over the joint space",
        fmt_fixed(p.measured_region_rms, 2),
        fmt_fixed(p.workspace_rms, 2),
        fmt_fixed(p.workspace_p95, 2)
        ));
    }
    for e in &r.effect_sizes {
        let name = match e.joint {
            Some(j) => format!("{} (joint {j})", e.effect),
            None => e.effect.to_string(),
        };
        h.push(format!(
            "effect {name}: {} um RMS over the joint space ({}); {}",
            fmt_fixed(e.workspace_rms_um, 2),
            e.at,
            if e.delivered {
                "in the [effects] of this robot"
            } else {
                "NOT in this file (--geometry-only)"
            }
        ));
    }
    for w in &r.warnings {
        h.push(format!("warning: {w}"));
    }
    if cal.setup_only() {
        h.push(r.verdict.clone());
    }
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn effect_lists_parse_and_bad_ones_are_refused() {
        assert_eq!(parse_effects("auto").unwrap(), Effects::Auto);
        assert_eq!(parse_effects("none").unwrap(), Effects::None);
        assert_eq!(
            parse_effects("cyclic_error:2, servo_lag").unwrap(),
            Effects::List(vec![Effect::CyclicError(1), Effect::ServoLag])
        );
        for bad in [
            "cyclic_error",
            "backlash:7",
            "servo_lag:2",
            "gravity",
            "servo_lag,servo_lag",
        ] {
            assert!(parse_effects(bad).is_err(), "{bad}");
        }
    }
}

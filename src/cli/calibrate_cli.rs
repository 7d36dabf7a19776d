//! `calibrate`: flags → checked campaign (runs, fixtures, options) → the calibration stage →
//! the calibrated robot file and the reports, all written together or not at all.

use super::args::CalibrateArgs;
use super::common::{check_outputs, file_err, header_xyz, name, read_input, write_all_atomic};
use super::{logruns, usage, Error};
use crate::calibrate::resync::{self, ResyncError};
use crate::calibrate::{self, CalibrateOptions, Effects, LengthOffset};
use crate::compensate::drift;
use crate::diagnose::Run;
use crate::model::MeasurementModel;
use crate::robot::{self, LoadOptions, Robot};
use crate::twin::recorded;
use crate::units::{DEG, MM};
use nalgebra::Vector3;
use std::path::Path;

pub fn calibrate(a: &CalibrateArgs) -> Result<i32, Error> {
    let fixtures = check_runs(a)?;
    let opts = calibrate_options(a)?;

    // --baseline: the previous report is read before any work.
    let baseline = read_baseline(a)?;

    let load_opts = LoadOptions {
        flange_link: a.flange.clone(),
        package_paths: a.package_path.clone(),
        ..LoadOptions::default()
    };
    let robot_text = read_input(&a.robot, "robot", crate::files::Kind::Robot)?;
    let robot = robot::load(&a.robot, &load_opts)?;
    let programs: Vec<logruns::Program> = a
        .program
        .iter()
        .map(|p| logruns::read_program(&robot, p))
        .collect::<Result<_, _>>()?;
    // The MAP: the flag, else the first program header's, else the robot file's.
    let map = match (
        &a.tool,
        programs.first().and_then(|p| p.parsed.header_value("MAP")),
    ) {
        (Some(s), _) => s.m(),
        (None, Some(h)) => header_xyz(h)
            .ok_or_else(|| usage("the program header's MAP is not X, Y, Z mm: give --tool"))?,
        (None, None) => robot.tool.unwrap_or_else(Vector3::zeros),
    };
    let mut c = logruns::read_campaign(a, &robot, &programs, &fixtures, map)?;
    let model = MeasurementModel::new(&robot, c.fixtures[0], map);
    let first = c.sources[0].bar;
    // --baseline: the fit starts from the previous calibration and states what moved since.
    let fit = |runs: &[Run]| match &baseline {
        Some((baseline, label, _)) => {
            drift::calibrate_against(&model, &robot, runs, &c.labels, &opts, baseline, label)
                .map(|(cal, d)| (cal, Some(d)))
                .map_err(|e| file_err(first, e))
        }
        None => calibrate::run(&model, &robot, runs, &c.labels, &opts)
            .map(|cal| (cal, None))
            .map_err(|e| file_err(first, e)),
    };
    let (cal, drift) =
        resync::fit_resynchronised(&model, &mut c.data, &c.fixtures, &mut c.from_logs, fit)
            .map_err(|e| match e {
                ResyncError::Fit(e) => e,
                ResyncError::Logs { run, refusal } => c.sources[run].error(refusal),
            })?;

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
    // Runs read from logs keep how they were read: their plateaus, missing poses and clock,
    // added to their run's keys.
    let json = recorded::report_with_reads(&with_drift, &c.from_logs) + "\n";
    // Not calibrated (nothing of the robot determined, or no better than nominal held out)
    // and no set-up found either: no robot file is written; the report says why, and so does
    // one line on stderr.
    if !cal.writes_robot() {
        if let Some(p) = &a.json {
            write_all_atomic(&[(p.as_path(), json.as_str())])?;
        }
        say_raw!(a.quiet, "{}", cal.summary);
        eprintln!("calibrate: {}", cal.report.verdict);
        return Ok(1);
    }

    let (calibrated, sidecar, sidecar_text) =
        robot_files(a, &robot, &robot_text, &load_opts, &cal, &c, drift.as_ref())?;
    let svg = match &a.plot {
        Some(_) => Some(crate::calibrate::plot::svg(&cal)?),
        None => None,
    };
    let baseline_sha = baseline.as_ref().map(|b| b.2.as_str());
    let html = html_report(a, &robot, &cal, &c, &map, baseline_sha, drift.as_ref())?;
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
    for (k, read) in c.from_logs.iter().enumerate() {
        for l in read.iter().flat_map(|r| &r.summary) {
            say!(a.quiet, "run {}: {l}", k + 1);
        }
    }
    say_raw!(a.quiet, "{}", cal.summary);
    say!(a.quiet, "wrote {}", a.output.display());
    if let Some(p) = &sidecar {
        say!(
            a.quiet,
            "wrote {} (the effects the URDF names)",
            p.display()
        );
    }
    // The set-up only, with the nominal geometry: a result, told apart from a calibration; its
    // exit code explains itself on stderr, with -q too.
    if cal.setup_only() {
        eprintln!("calibrate: {}", cal.report.verdict);
        return Ok(3);
    }
    Ok(0)
}

/// The run and output flags checked before anything is read (a URDF robot calibrates to a URDF,
/// a DH robot to a DH file): the `--fixture` positions (m).
fn check_runs(a: &CalibrateArgs) -> Result<Vec<Vector3<f64>>, Error> {
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
    let fixtures: Vec<Vector3<f64>> = a.fixture.iter().map(|f| f.m()).collect();
    check_outputs(&[
        Some(a.output.as_path()),
        a.json.as_deref(),
        a.plot.as_deref(),
        a.html.as_deref(),
    ])?;
    let urdf = robot::is_urdf(&a.robot);
    match (urdf, robot::is_urdf(&a.output), robot::is_toml(&a.output)) {
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
    Ok(fixtures)
}

/// The calibration options the flags give (effects, what is known, length offset, resolution,
/// noise, prior), or the usage error of the first bad one.
fn calibrate_options(a: &CalibrateArgs) -> Result<CalibrateOptions, Error> {
    let effects = Effects::parse(&a.effects).map_err(|e| usage(format!("--effects: {e}")))?;
    let mut opts = CalibrateOptions {
        effects,
        fixture_known: a.fixture_known,
        tool_known: a.tool_known,
        length_offset: LengthOffset::parse(a.length_offset.as_deref())
            .map_err(|e| usage(format!("--length-offset: {e}")))?,
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
    if let Some(p) = a.prior {
        opts.prior_length = p.length_mm * MM;
        opts.prior_angle = p.angle_deg * DEG;
        if let Some(s) = p.setup_mm {
            opts.prior_setup = s * MM;
        }
    }
    Ok(opts)
}

/// `--baseline`: the previous calibration report read, with its label and hash, or none.
fn read_baseline(a: &CalibrateArgs) -> Result<Option<(drift::Calibrated, String, String)>, Error> {
    Ok(match &a.baseline {
        Some(path) => {
            let text = read_input(path, "calibration report", crate::files::Kind::Config)?;
            let value: serde_json::Value = serde_json::from_str(&text)
                .map_err(|e| file_err(path, format!("not JSON: {e}")))?;
            Some((
                drift::read_report(&value).map_err(|e| file_err(path, e))?,
                name(path),
                robot::sha256_hex(text.as_bytes()),
            ))
        }
        None => None,
    })
}

/// The calibrated robot file's text rendered from `cal` over the robot file `robot_text`, with
/// a URDF's sidecar file of effects (its path and text) where it has effects.
fn robot_files(
    a: &CalibrateArgs,
    robot: &Robot,
    robot_text: &str,
    load_opts: &LoadOptions,
    cal: &calibrate::Calibration,
    c: &logruns::Campaign,
    drift: Option<&drift::Drift>,
) -> Result<(String, Option<std::path::PathBuf>, Option<String>), Error> {
    let mut header = calibrate::header::lines(robot, cal, &c.hashes, &c.labels);
    if let (Some(d), Some(p)) = (drift, &a.baseline) {
        header.push(format!("since {}: {}", name(p), d.verdict));
    }
    let input = calibrate::files::Input {
        robot,
        text: robot_text,
        path: &a.robot,
        urdf: robot::is_urdf(&a.robot),
        load_opts,
    };
    let f = calibrate::files::render(&input, cal, header, &a.output)?;
    let (sidecar, sidecar_text) = f.sidecar.unzip();
    Ok((f.robot, sidecar, sidecar_text))
}

/// `--html`: the calibration page of `cal` for `robot` and the campaign `c` (MAP `map`, the
/// baseline report's hash and drift where given), rendered; none without the flag.
fn html_report(
    a: &CalibrateArgs,
    robot: &Robot,
    cal: &calibrate::Calibration,
    c: &logruns::Campaign,
    map: &Vector3<f64>,
    baseline_sha: Option<&str>,
    drift: Option<&drift::Drift>,
) -> Result<Option<String>, Error> {
    Ok(match &a.html {
        Some(_) => {
            // The baseline is an input too.
            let effects = match baseline_sha {
                Some(sha) => format!("{}\nbaseline {sha}", a.effects),
                None => a.effects.clone(),
            };
            let hash = calibrate::header::inputs_hash(robot, &c.hashes, &c.fixtures, map, &effects);
            let name = format!("{} [{}]", robot.name, robot.source);
            let mut page = crate::report::calibrate::page(cal, &name, &hash)?;
            if let Some(d) = drift {
                page.sections
                    .push(crate::report::compensate::drift_section(d)?);
            }
            Some(crate::report::render(&page)?)
        }
        None => None,
    })
}

//! `--bar-log` (with `--program`, and/or `--joint-log`) for `calibrate` and `diagnose`: the
//! files of one run → their texts read and parsed, the fixture and MAP checked against the
//! program's header → [`twin::recorded::read`] → one run's [`Measured`] data and how it was
//! read ([`FromLogs`]). Shared by the two subcommands; and `calibrate`'s campaign: every run
//! of its flags read.

use super::args::CalibrateArgs;
use super::common::{file_err, header_xyz, name, program_dialect, read_input};
use super::{usage, Error};
use crate::calibrate::{
    self,
    resync::{self, ResyncError},
};
use crate::dialect::Parsed;
use crate::logs;
use crate::model::MeasurementModel;
use crate::robot::{self, Robot};
use crate::twin::recorded::{self, FromLogs, Input, Refusal};
use crate::twin::{self, Measured};
use crate::units::{fmt_fixed, to_mm};
use nalgebra::Vector3;
use std::path::{Path, PathBuf};

/// A program read back for its logs: the text's hash, the parsed steps (model joints) and the
/// controller mapping they were read with.
pub(super) struct Program {
    pub path: PathBuf,
    pub parsed: Parsed,
    pub sha256: String,
    /// The dialect it was read in (`ngc`, `krl`, ...).
    pub dialect: &'static str,
}

/// Reads a program with its dialect's default controller mapping (the one `edbbgen` writes
/// without a cell's `[controller]` section); a program written for another mapping is refused
/// (calibrate has no cell to take it from).
pub(super) fn read_program(robot: &Robot, path: &Path) -> Result<Program, Error> {
    let text = read_input(path, "program", crate::files::Kind::Program)?;
    let dialect = program_dialect(None, path, &text)?;
    let map = dialect
        .default_map(robot)
        .map_err(|e| file_err(path, format!("controller mapping: {e}")))?;
    let parsed = dialect
        .read(&text, &map)
        .map_err(|e| file_err(path, format!("{} program: {e}", dialect.name)))?;
    if let Some(declared) = parsed.header_value("controller") {
        if declared != map.describe() {
            return Err(file_err(
                path,
                format!(
                    "the program was written for the controller axes \"{declared}\", not the {} default \"{}\": its joint values and logs cannot be read back without that cell",
                    dialect.name,
                    map.describe()
                ),
            ));
        }
    }
    Ok(Program {
        path: path.to_path_buf(),
        parsed,
        sha256: robot::sha256_hex(text.as_bytes()),
        dialect: dialect.name.as_str(),
    })
}

impl Program {
    /// The program as the library takes it.
    pub fn recorded(&self) -> recorded::Program<'_> {
        recorded::Program {
            parsed: &self.parsed,
            name: name(&self.path),
            dialect: self.dialect,
        }
    }
}

/// One run read from logs: the data calibrate and diagnose take, and how they were read.
pub(super) struct LogRun {
    pub measured: Measured,
    pub fixture: Vector3<f64>,
    /// Hash of the inputs (bar log, joint log, program).
    pub sha256: String,
    pub label: String,
    pub from_logs: FromLogs,
}

/// The files of one run from logs, to name the one a refusal is about.
pub(super) struct RunFiles<'a> {
    pub bar: &'a Path,
    pub program: Option<&'a Path>,
    pub joint_log: Option<&'a Path>,
}

impl RunFiles<'_> {
    /// A library refusal as an error naming its file.
    pub fn error(&self, r: Refusal) -> Error {
        let path = match r.input {
            Input::BarLog => Some(self.bar),
            Input::Program => self.program,
            Input::JointLog => self.joint_log,
        };
        file_err(path.unwrap_or(self.bar), r.msg)
    }
}

/// Reads one run from its logs. `fixture`: the flag's (else the program header's); `map`: the
/// MAP the campaign uses (the program's header MAP must agree).
pub(super) fn read_run(
    robot: &Robot,
    bar_path: &Path,
    program: Option<&Program>,
    joint_path: Option<&Path>,
    fixture: Option<Vector3<f64>>,
    map: Vector3<f64>,
) -> Result<LogRun, Error> {
    let fixture = match (fixture, program) {
        (Some(f), _) => f,
        (None, Some(p)) => p
            .parsed
            .header_value("fixture")
            .and_then(header_xyz)
            .ok_or_else(|| {
                file_err(
                    &p.path,
                    "the header states no fixture (fixture: X, Y, Z mm): give --fixture",
                )
            })?,
        (None, None) => {
            return Err(usage(format!(
                "--fixture: required for {} (no --program whose header states it)",
                bar_path.display()
            )))
        }
    };
    if let Some(p) = program {
        if let Some(m) = p.parsed.header_value("MAP").and_then(header_xyz) {
            if (m - map).norm() > 1e-6 {
                return Err(file_err(
                    &p.path,
                    format!(
                        "the program was compiled for the MAP {}, {}, {} mm, the calibration uses {}, {}, {} mm: give --tool",
                        fmt_fixed(to_mm(m.x), 3),
                        fmt_fixed(to_mm(m.y), 3),
                        fmt_fixed(to_mm(m.z), 3),
                        fmt_fixed(to_mm(map.x), 3),
                        fmt_fixed(to_mm(map.y), 3),
                        fmt_fixed(to_mm(map.z), 3)
                    ),
                ));
            }
        }
    }
    if program.is_none() && joint_path.is_none() {
        return Err(usage(format!(
            "--bar-log {}: needs --program (the stop-and-measure program it recorded) or --joint-log",
            bar_path.display()
        )));
    }
    let model = MeasurementModel::new(robot, fixture, map);
    let bar_text = read_input(bar_path, "bar log", crate::files::Kind::Measured)?;
    let bar = logs::parse_bar_log(&bar_text, 10).map_err(|e| file_err(bar_path, e))?;
    let mut sha = robot::sha256_hex(bar_text.as_bytes());
    let joints = match joint_path {
        None => None,
        Some(jp) => {
            let text = read_input(jp, "joint log", crate::files::Kind::Measured)?;
            let joints = logs::parse_joint_log(&text, 10).map_err(|e| file_err(jp, e))?;
            sha = robot::sha256_hex(
                format!("{sha}\n{}", robot::sha256_hex(text.as_bytes())).as_bytes(),
            );
            Some((name(jp), joints))
        }
    };
    if let (None, Some(p)) = (joint_path, program) {
        sha = robot::sha256_hex(format!("{sha}\n{}", p.sha256).as_bytes());
    }
    let files = RunFiles {
        bar: bar_path,
        program: program.map(|p| p.path.as_path()),
        joint_log: joint_path,
    };
    let recorded_program = program.map(Program::recorded);
    let (measured, from_logs) = recorded::read(
        robot,
        &model,
        &name(bar_path),
        &bar,
        recorded_program.as_ref(),
        joints.as_ref().map(|(n, j)| (n.as_str(), j)),
    )
    .map_err(|r| files.error(r))?;
    Ok(LogRun {
        measured,
        fixture,
        sha256: sha,
        label: name(bar_path),
        from_logs,
    })
}

/// A continuous run (one from a joint log) synchronised once more, against the geometry its own
/// data give ([`resync::on_own_geometry`]): `diagnose`'s reading; a stop-and-measure run as read.
pub(super) fn on_own_geometry(
    robot: &Robot,
    run: LogRun,
    map: Vector3<f64>,
    files: &RunFiles,
) -> Result<recorded::Read, Error> {
    let FromLogs {
        extra,
        summary,
        logs,
    } = run.from_logs;
    let Some(logs) = &logs else {
        return Ok((run.measured, extra, summary));
    };
    let model = MeasurementModel::new(robot, run.fixture, map);
    resync::on_own_geometry(&model, robot, &run.measured, run.fixture, &run.label, logs).map_err(
        |e| match e {
            ResyncError::Fit(e) => file_err(files.bar, e),
            ResyncError::Logs { refusal, .. } => files.error(refusal),
        },
    )
}

/// The runs of a campaign as read: per run its readings, the hash of its input, its fixture,
/// its label, its files and, for a run from logs, how it was read.
pub(super) struct Campaign<'a> {
    pub data: Vec<Measured>,
    pub hashes: Vec<String>,
    pub fixtures: Vec<Vector3<f64>>,
    pub labels: Vec<String>,
    pub sources: Vec<RunFiles<'a>>,
    pub from_logs: Vec<Option<FromLogs>>,
}

/// Every run of the flags (`--measured` first, then `--bar-log`) read for `robot` with its
/// `programs`, the flags' `fixtures` (m) and the campaign's MAP `map` (m).
pub(super) fn read_campaign<'a>(
    a: &'a CalibrateArgs,
    robot: &Robot,
    programs: &'a [Program],
    fixtures: &[Vector3<f64>],
    map: Vector3<f64>,
) -> Result<Campaign<'a>, Error> {
    let runs_n = a.measured.len() + a.bar_log.len();
    let fixture_flag = |k: usize| -> Option<Vector3<f64>> {
        match fixtures.len() {
            0 => None,
            1 => Some(fixtures[0]),
            _ => Some(fixtures[k]),
        }
    };
    let program_of = |k: usize| match programs.len() {
        0 => None,
        1 => Some(&programs[0]),
        _ => Some(&programs[k]),
    };
    // As for a measured file: one run alone must carry the robot, a campaign's run may be
    // short.
    let min = if runs_n == 1 { calibrate::MIN_ROWS } else { 1 };
    let mut data: Vec<Measured> = Vec::with_capacity(runs_n);
    let mut hashes: Vec<String> = Vec::with_capacity(runs_n);
    let mut run_fixtures: Vec<Vector3<f64>> = Vec::with_capacity(runs_n);
    let mut labels: Vec<String> = Vec::with_capacity(runs_n);
    let mut sources: Vec<RunFiles> = Vec::with_capacity(runs_n);
    let mut from_logs: Vec<Option<FromLogs>> = Vec::with_capacity(runs_n);
    for (k, path) in a.measured.iter().enumerate() {
        let text = read_input(path, "measured data", crate::files::Kind::Measured)?;
        let m = twin::parse_csv(&text, min).map_err(|e| file_err(path, e))?;
        data.push(m);
        hashes.push(robot::sha256_hex(text.as_bytes()));
        run_fixtures.push(fixture_flag(k).unwrap_or_else(Vector3::zeros));
        labels.push(name(path));
        sources.push(RunFiles {
            bar: path,
            program: None,
            joint_log: None,
        });
        from_logs.push(None);
    }
    for (i, bar) in a.bar_log.iter().enumerate() {
        let k = a.measured.len() + i;
        let joint_log = a.joint_log.get(i).map(|p| p.as_path());
        let run = read_run(robot, bar, program_of(i), joint_log, fixture_flag(k), map)?;
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
        data.push(run.measured);
        hashes.push(run.sha256);
        run_fixtures.push(run.fixture);
        labels.push(run.label);
        sources.push(RunFiles {
            bar,
            program: program_of(i).map(|p| p.path.as_path()),
            joint_log,
        });
        from_logs.push(Some(run.from_logs));
    }
    Ok(Campaign {
        data,
        hashes,
        fixtures: run_fixtures,
        labels,
        sources,
        from_logs,
    })
}

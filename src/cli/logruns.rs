//! `--bar-log` (with `--program`, and/or `--joint-log`) for `calibrate` and `diagnose`: the
//! files of one run → checked inputs → the logs stage ([`crate::logs`]) → one run's
//! [`Measured`] data and what its report says about how they were found.

use super::{usage, Error};
use crate::dialect::Parsed;
use crate::logs::{self, ClockReport, PlateauReport};
use crate::model::MeasurementModel;
use crate::robot::{self, Robot};
use crate::twin::{self, measured::Form, Measured};
use crate::units::{fmt_fixed, to_mm, MM};
use nalgebra::Vector3;
use serde::Serialize;
use std::path::{Path, PathBuf};

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
    let text = super::read_input(path, "program", crate::files::Kind::Program)?;
    let dialect = super::program_dialect(None, path, &text)?;
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

/// The first three numbers of a header value such as "258.000, 1468.000, 708.000 mm ...".
pub(super) fn header_xyz(v: &str) -> Option<Vector3<f64>> {
    let nums: Vec<f64> = v
        .split([',', ' '])
        .filter_map(|w| w.trim().parse::<f64>().ok())
        .take(3)
        .collect();
    (nums.len() == 3).then(|| Vector3::new(nums[0], nums[1], nums[2]) * MM)
}

/// One run read from logs: the data calibrate and diagnose take, and the report's additions.
pub(super) struct LogRun {
    pub measured: Measured,
    pub fixture: Vector3<f64>,
    /// Hash of the inputs (bar log, joint log, program).
    pub sha256: String,
    pub label: String,
    pub extra: RunExtra,
    /// Lines for the summary.
    pub summary: Vec<String>,
    /// A continuous run keeps its logs: synchronised again with a calibrated model
    /// ([`resync`]), the nominal model's errors no longer bias the clock.
    pub logs: Option<Logs>,
}

/// A continuous run's logs: the bar's and the joints (model joints, rad) on their clocks.
pub(super) struct Logs {
    pub bar_path: PathBuf,
    pub joint_path: PathBuf,
    pub bar: logs::BarLog,
    pub t: Vec<f64>,
    pub q: Vec<[f64; 6]>,
}

/// What a run from logs adds to the report's `runs[k]` (DESIGN.md: `plateaus[]`, `missing[]`,
/// `clock`).
#[derive(Clone, Debug, Serialize)]
pub(super) struct RunExtra {
    pub bar_log: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub program: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub joint_log: Option<String>,
    /// "stop_and_measure" or "continuous".
    pub form: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub plateaus: Option<Vec<PlateauReport>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub missing: Option<Vec<usize>>,
    pub clock: ClockReport,
    /// The bar's reading minus the nominal ball-centre distance (mm), over the poses matched
    /// or the samples used (robot errors included: calibrate's `--length-offset free` is what
    /// estimates the bar's zero).
    pub length_zero_mm: f64,
    pub length_zero_std_mm: f64,
    /// Bar samples while unmounted or unmatched, never used.
    pub rows_unused: usize,
    /// A continuous run from a fast bar: consecutive samples averaged into one row (their
    /// residual averaged, the middle sample's pose kept; [`logs::sync::bin`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub samples_per_row: Option<usize>,
}

/// A bar's zero this far from the ball-centre distance is no robot error (m).
pub const ZERO_LIMIT: f64 = 5e-3;

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
    let model = MeasurementModel::new(robot, fixture, map);
    let bar_text = super::read_input(bar_path, "bar log", crate::files::Kind::Measured)?;
    let bar = logs::parse_bar_log(&bar_text, 10).map_err(|e| file_err(bar_path, e))?;
    let mut sha = robot::sha256_hex(bar_text.as_bytes());
    let mut kept: Option<Logs> = None;
    let run = match joint_path {
        None => {
            let p = program.ok_or_else(|| {
                usage(format!(
                    "--bar-log {}: needs --program (the stop-and-measure program it recorded) or --joint-log",
                    bar_path.display()
                ))
            })?;
            sha = robot::sha256_hex(format!("{sha}\n{}", p.sha256).as_bytes());
            stop_and_measure(&model, robot, bar_path, &bar, p)?
        }
        Some(jp) => {
            let text = super::read_input(jp, "joint log", crate::files::Kind::Measured)?;
            let joints = logs::parse_joint_log(&text, 10).map_err(|e| file_err(jp, e))?;
            sha = robot::sha256_hex(
                format!("{sha}\n{}", robot::sha256_hex(text.as_bytes())).as_bytes(),
            );
            // The joint log holds the controller's axis values: the program's mapping, or the
            // model's joints when no program says otherwise.
            let q: Vec<[f64; 6]> = match program {
                Some(p) => joints
                    .q
                    .iter()
                    .map(|c| super::twin_cli::model_joints(&p.parsed.map, c))
                    .collect(),
                None => joints.q.clone(),
            };
            let length =
                |x: &[f64; 6]| model.reached_length(&model.nominal, &robot.effects, x, &[0.0; 6]);
            let read = continuous(&length, bar_path, &bar, jp, &joints.t, &q, "nominal")?;
            kept = Some(Logs {
                bar_path: bar_path.to_path_buf(),
                joint_path: jp.to_path_buf(),
                bar: bar.clone(),
                t: joints.t.clone(),
                q,
            });
            read
        }
    };
    let (measured, mut extra, summary) = run;
    extra.program = program.map(|p| name(&p.path));
    extra.joint_log = joint_path.map(name);
    if extra.length_zero_mm.abs() > to_mm(ZERO_LIMIT) {
        return Err(file_err(
            bar_path,
            format!(
                "the bar reads {} mm from the nominal ball-centre distances: its zero is not the ball-centre distance (calibrate with --length-offset free, or correct the log)",
                fmt_fixed(extra.length_zero_mm, 3)
            ),
        ));
    }
    Ok(LogRun {
        measured,
        fixture,
        sha256: sha,
        label: name(bar_path),
        extra,
        summary,
        logs: kept,
    })
}

/// A continuous run synchronised again, its lengths predicted by `length` (a calibrated
/// model): the run's data, its report additions and summary.
pub(super) fn resync(
    logs: &Logs,
    length: &(dyn Fn(&[f64; 6]) -> f64 + Sync),
    program: Option<&Program>,
) -> Result<Read, Error> {
    let (m, mut extra, summary) = continuous(
        length,
        &logs.bar_path,
        &logs.bar,
        &logs.joint_path,
        &logs.t,
        &logs.q,
        "calibrated",
    )?;
    extra.program = program.map(|p| name(&p.path));
    extra.joint_log = Some(name(&logs.joint_path));
    Ok((m, extra, summary))
}

pub(super) type Read = (Measured, RunExtra, Vec<String>);

fn stop_and_measure(
    model: &MeasurementModel,
    robot: &Robot,
    bar_path: &Path,
    bar: &logs::BarLog,
    p: &Program,
) -> Result<Read, Error> {
    let traj = twin::Trajectory::from_program(robot, model, &p.parsed)
        .map_err(|e| file_err(&p.path, e))?;
    let tpl = twin::logsim::template(&traj, model);
    let instruction = crate::dialect::dwell_instruction(p.dialect);
    if traj.dwells.is_empty() {
        return Err(file_err(
            &p.path,
            format!(
                "the program has no dwell ({instruction}): a bar log alone needs a stop-and-measure program, a dwell after each measurement move (edbbgen writes one with --dwell), or give --joint-log"
            ),
        ));
    }
    if tpl.slots.is_empty() {
        return Err(file_err(
            &p.path,
            format!(
                "the program has no measurement dwell: none of its dwells ({instruction}) follows a move with the bar in place (between a mount pause and the next removal); a bar log alone needs a stop-and-measure program (edbbgen writes one with --dwell), or give --joint-log"
            ),
        ));
    }
    // The measurement poses are the program's dwells; edbbgen's header list, when present, is
    // a check that they are the poses it was compiled for, at this fixture and tool.
    let mut from_dwells = None;
    match logs::measure_list(&p.parsed).map_err(|e| file_err(&p.path, e))? {
        None => {
            let sorted = twin::logsim::measurement_dwells(&traj);
            let mut left_out = String::new();
            if !sorted.settling.is_empty() {
                left_out += &format!(
                    ", {} shorter dwells (under {} s, half the longest) taken as settling, not measured",
                    sorted.settling.len(),
                    fmt_fixed(twin::logsim::SETTLING_SHARE * tpl.dwell, 2)
                );
            }
            if !sorted.off.is_empty() {
                left_out += &format!(
                    ", {} dwells with the bar off (before the first pause, or between a removal pause and the next mount) not measured",
                    sorted.off.len()
                );
            }
            from_dwells = Some(format!(
                "{}: {} measurement poses taken from its dwells ({instruction} after a move, the bar in place){left_out}; no measure list in its header to check them against",
                name(&p.path),
                tpl.slots.len(),
            ));
        }
        Some(list) => {
            if list.len() != tpl.slots.len() {
                return Err(file_err(
                    &p.path,
                    format!(
                        "the header lists {} measurement poses, the program dwells at {} with the bar mounted",
                        list.len(),
                        tpl.slots.len()
                    ),
                ));
            }
            for (k, (l, s)) in list.iter().zip(&tpl.slots).enumerate() {
                if (l - s.length).abs() > 2e-6 {
                    return Err(file_err(
                        &p.path,
                        format!(
                            "pose {}: the header says L {} mm, its joints give {} mm with this fixture and tool: wrong --fixture or --tool?",
                            k + 1,
                            fmt_fixed(to_mm(*l), 3),
                            fmt_fixed(to_mm(s.length), 3)
                        ),
                    ));
                }
            }
        }
    }
    let sm = logs::stop_and_measure(&tpl, bar).map_err(|e| file_err(bar_path, e))?;
    let mut m = Measured {
        form: Form::Static { timed: true },
        std: Some(Vec::new()),
        samples: Some(Vec::new()),
        temp: bar.temp.as_ref().map(|_| Vec::new()),
        ..Measured::default()
    };
    for &(k, j) in &sm.readings {
        let pl = &sm.plateaus[j];
        m.t.push(pl.t - sm.t0);
        m.q.push(tpl.slots[k].q);
        m.length.push(pl.mean);
        if let Some(v) = m.std.as_mut() {
            v.push(pl.std);
        }
        if let Some(v) = m.samples.as_mut() {
            v.push(pl.samples as u32);
        }
        if let (Some(v), Some(temps)) = (m.temp.as_mut(), &bar.temp) {
            let r = &temps[pl.first_row..=pl.last_row];
            v.push(r.iter().sum::<f64>() / r.len() as f64);
        }
    }
    let used: usize = sm
        .readings
        .iter()
        .map(|&(_, j)| sm.plateaus[j].last_row - sm.plateaus[j].first_row + 1)
        .sum();
    let unmatched = sm.report.iter().filter(|r| r.pose.is_none()).count();
    let mut summary: Vec<String> = from_dwells.into_iter().collect();
    summary.push(format!(
        "{}: {} of {} poses matched to plateaus{}{}; clock offset {} s (the program's time, its first pause taken out), drift {} ppm; bar reads nominal + {} mm",
        name(bar_path),
        sm.readings.len(),
        tpl.slots.len(),
        if sm.missing.is_empty() {
            String::new()
        } else {
            format!(
                ", missing: pose {}",
                sm.missing
                    .iter()
                    .map(|k| k.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        },
        if unmatched > 0 {
            format!("; {unmatched} plateaus of no pose (listed, not used)")
        } else {
            String::new()
        },
        match sm.clock.offset_std_s {
            Some(u) => format!(
                "{} +- {}",
                fmt_fixed(sm.clock.offset_s, 3),
                fmt_fixed(u, 3)
            ),
            None => fmt_fixed(sm.clock.offset_s, 3),
        },
        match sm.clock.drift_std_ppm {
            Some(s) => format!(
                "{} +- {}",
                fmt_fixed(sm.clock.drift_ppm, 0),
                fmt_fixed(s, 0)
            ),
            None => fmt_fixed(sm.clock.drift_ppm, 0),
        },
        fmt_fixed(to_mm(sm.zero), 3)
    ));
    let spreads: Vec<f64> = sm
        .readings
        .iter()
        .map(|&(_, j)| sm.plateaus[j].spread)
        .collect();
    if let Some(worst) = spreads.iter().copied().reduce(f64::max) {
        summary.push(format!(
            "plateau spread: median {} um, largest {} um",
            fmt_fixed(median(&spreads) * 1e6, 2),
            fmt_fixed(worst * 1e6, 2)
        ));
    }
    let extra = RunExtra {
        bar_log: name(bar_path),
        program: None,
        joint_log: None,
        form: "stop_and_measure",
        plateaus: Some(sm.report),
        missing: Some(sm.missing),
        clock: sm.clock,
        length_zero_mm: to_mm(sm.zero),
        length_zero_std_mm: to_mm(sm.zero_std),
        rows_unused: bar.len() - used,
        samples_per_row: None,
    };
    Ok((m, extra, summary))
}

fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

fn continuous(
    length: &(dyn Fn(&[f64; 6]) -> f64 + Sync),
    bar_path: &Path,
    bar: &logs::BarLog,
    joint_path: &Path,
    t: &[f64],
    q: &[[f64; 6]],
    which: &str,
) -> Result<Read, Error> {
    let spline = logs::sync::Spline::new(t, q);
    let s = logs::sync::sync(&bar.t, &bar.length, &spline, length)
        .map_err(|e| file_err(joint_path, e))?;
    let t0 = bar.t.first().copied().unwrap_or(0.0);
    let interval = median(&bar.t.windows(2).map(|w| w[1] - w[0]).collect::<Vec<_>>());
    let per_row = logs::sync::samples_per_row(interval);
    let bins = logs::sync::bin(&s, length, per_row);
    let m = Measured {
        t: bins.rows.iter().map(|&k| bar.t[k] - t0).collect(),
        q: bins.q,
        length: bins.length,
        temp: bar
            .temp
            .as_ref()
            .map(|temps| bins.rows.iter().map(|&k| temps[k]).collect()),
        ..Measured::default()
    };
    let clock = ClockReport {
        reference: "joint_log",
        t_ref: "the joint log's time stamps".into(),
        offset_s: s.offset,
        offset_std_s: Some(s.offset_std),
        drift_ppm: s.drift * 1e6,
        drift_std_ppm: Some(s.drift_std * 1e6),
        pauses_s: None,
        pauses_std_s: None,
        timeline_rms_s: None,
        length_rms_um: Some(s.rms * 1e6),
        smoothing_s2: Some(s.smoothing),
        smoothing_std_s2: Some(s.smoothing_std),
        averaging_window_ms: Some((s.smoothing > 0.0).then(|| (24.0 * s.smoothing).sqrt() * 1e3)),
        method: format!("the bar's length against the one the joint log predicts ({which} model): coarse offset search, then offset and drift in steps, then least squares on offset, drift, zero and the bar's smoothing (reading = L + c·L'') over the samples that agree (the bar mounted); uncertainty inflated for the residual's correlation"),
    };
    let smoothing = if s.smoothing > 3.0 * s.smoothing_std && s.smoothing > 0.0 {
        format!(
            "; the bar smooths as a {} ms average (taken out)",
            fmt_fixed((24.0 * s.smoothing).sqrt() * 1e3, 1)
        )
    } else {
        String::new()
    };
    let averaged = if per_row > 1 {
        format!(", averaged {per_row} to a row ({} rows)", m.len())
    } else {
        String::new()
    };
    let summary = vec![format!(
        "{}: {} of {} bar samples synchronised with {}{averaged} ({} s mounted); clock offset {} +- {} ms, drift {} +- {} ppm; bar reads nominal + {} mm",
        name(bar_path),
        s.rows.len(),
        bar.len(),
        name(joint_path),
        fmt_fixed(m.t.last().copied().unwrap_or(0.0) - m.t.first().copied().unwrap_or(0.0), 1),
        fmt_fixed(s.offset * 1e3, 3),
        fmt_fixed(s.offset_std * 1e3, 3),
        fmt_fixed(s.drift * 1e6, 1),
        fmt_fixed(s.drift_std * 1e6, 1),
        fmt_fixed(to_mm(s.zero), 3)
    ) + &smoothing];
    let extra = RunExtra {
        bar_log: name(bar_path),
        program: None,
        joint_log: None,
        form: "continuous",
        plateaus: None,
        missing: None,
        clock,
        length_zero_mm: to_mm(s.zero),
        length_zero_std_mm: to_mm(s.zero_std),
        rows_unused: bar.len() - s.rows.len(),
        samples_per_row: (per_row > 1).then_some(per_row),
    };
    Ok((m, extra, summary))
}

//! A recorded run's logs in (the bar's log, the controller's joint log and/or the program it
//! ran, read back), one run's [`Measured`] data out, with what its report says about how they
//! were found (plateaus, missing poses, the clock) and the summary lines; or a refusal naming
//! the input at fault. The counterpart of [`logsim`], which writes what a real cell leaves.
//!
//! A stop-and-measure run (a bar log and its program): the measurement poses are the program's
//! dwells ([`logsim::measurement_dwells`]), the matcher's template its trajectory's timing
//! ([`logsim::template`]); each matched plateau's mean is a reading. A continuous run (a joint
//! log): the bar synchronised with the joints by the lengths they predict
//! ([`crate::logs::sync`]), first against the nominal model; [`resync`] does it again with a
//! calibrated one.

use super::measured::Form;
use super::{logsim, Measured, Trajectory};
use crate::dialect::{dwell_instruction, Parsed};
use crate::logs::{self, BarLog, ClockReport, JointLog, PlateauReport};
use crate::model::MeasurementModel;
use crate::robot::Robot;
use crate::stats::median;
use crate::units::{fmt_fixed, length_um, to_mm};
use serde::Serialize;

/// The program a bar log recorded, read back.
pub struct Program<'a> {
    pub parsed: &'a Parsed,
    /// Its file name, for the report and the summary.
    pub name: String,
    /// The dialect it was read in (`ngc`, `krl`, ...).
    pub dialect: &'static str,
}

/// The input a refusal is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Input {
    Program,
    BarLog,
    JointLog,
}

/// Why a run cannot be read from its logs, and which input says so.
#[derive(Debug, thiserror::Error)]
#[error("{msg}")]
pub struct Refusal {
    pub input: Input,
    pub msg: String,
}

fn refuse(input: Input, msg: impl std::fmt::Display) -> Refusal {
    Refusal {
        input,
        msg: msg.to_string(),
    }
}

/// A continuous run's logs: the bar's and the joints (model joints, rad) on their clocks, kept
/// to be synchronised again ([`resync`]) once a calibrated model no longer biases the clock.
pub struct Logs {
    pub bar_name: String,
    pub joint_name: String,
    pub program_name: Option<String>,
    pub bar: BarLog,
    pub t: Vec<f64>,
    pub q: Vec<[f64; 6]>,
}

/// What a run from logs adds to the report's `runs[k]` (`plateaus[]`, `missing[]`, `clock`).
#[derive(Clone, Debug, Serialize)]
pub struct RunExtra {
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

/// How a run was read from its logs: the report's additions, the summary lines, and a
/// continuous run's logs.
pub struct FromLogs {
    pub extra: RunExtra,
    pub summary: Vec<String>,
    pub logs: Option<Logs>,
}

/// `report` as JSON text, each of its `runs[k]` with the keys of how run k was read from logs
/// ([`RunExtra`]); `report` as it serialises when no run was.
pub fn report_with_reads(report: &impl Serialize, from_logs: &[Option<FromLogs>]) -> String {
    if from_logs.iter().all(Option::is_none) {
        return serde_json::to_string_pretty(report).unwrap_or_default();
    }
    let mut value = serde_json::to_value(report).unwrap_or_default();
    if let Some(runs) = value.get_mut("runs").and_then(|r| r.as_array_mut()) {
        for (run, read) in runs.iter_mut().zip(from_logs) {
            if let (Some(obj), Some(read)) = (run.as_object_mut(), read) {
                if let Ok(serde_json::Value::Object(add)) = serde_json::to_value(&read.extra) {
                    obj.extend(add);
                }
            }
        }
    }
    serde_json::to_string_pretty(&value).unwrap_or_default()
}

/// A bar's zero this far from the ball-centre distance is no robot error (m).
pub const ZERO_LIMIT: f64 = 5e-3;

/// A run's data, its report additions and its summary lines.
pub type Read = (Measured, RunExtra, Vec<String>);

/// Reads one run from its logs: with a joint log, a continuous run synchronised against the
/// nominal model (`model`: the run's fixture and the campaign's MAP; the joint log in the
/// program's controller mapping, else in model joints); without one, a stop-and-measure run
/// matched to `program`'s dwells. A bar whose zero is off by more than [`ZERO_LIMIT`] is refused.
pub fn read(
    robot: &Robot,
    model: &MeasurementModel,
    bar_name: &str,
    bar: &BarLog,
    program: Option<&Program>,
    joints: Option<(&str, &JointLog)>,
) -> Result<(Measured, FromLogs), Refusal> {
    let mut kept = None;
    let (measured, mut extra, summary) = match joints {
        None => {
            let p = program.ok_or_else(|| {
                refuse(
                    Input::BarLog,
                    "needs a program (the stop-and-measure program it recorded) or a joint log",
                )
            })?;
            stop_and_measure(model, robot, bar_name, bar, p)?
        }
        Some((joint_name, joints)) => {
            // The joint log holds the controller's axis values: the program's mapping, or the
            // model's joints when no program says otherwise.
            let q: Vec<[f64; 6]> = match program {
                Some(p) => joints
                    .q
                    .iter()
                    .map(|c| p.parsed.map.log_joints(c))
                    .collect(),
                None => joints.q.clone(),
            };
            let length =
                |x: &[f64; 6]| model.reached_length(&model.nominal, &robot.effects, x, &[0.0; 6]);
            let read = continuous(&length, bar_name, bar, joint_name, &joints.t, &q, "nominal")?;
            kept = Some(Logs {
                bar_name: bar_name.to_string(),
                joint_name: joint_name.to_string(),
                program_name: program.map(|p| p.name.clone()),
                bar: bar.clone(),
                t: joints.t.clone(),
                q,
            });
            read
        }
    };
    extra.program = program.map(|p| p.name.clone());
    extra.joint_log = joints.map(|(n, _)| n.to_string());
    if extra.length_zero_mm.abs() > to_mm(ZERO_LIMIT) {
        return Err(refuse(
            Input::BarLog,
            format!(
                "the bar reads {} mm from the nominal ball-centre distances: its zero is not the ball-centre distance (calibrate with --length-offset free, or correct the log)",
                fmt_fixed(extra.length_zero_mm, 3)
            ),
        ));
    }
    Ok((
        measured,
        FromLogs {
            extra,
            summary,
            logs: kept,
        },
    ))
}

/// A continuous run synchronised again, its lengths predicted by `length` (a calibrated
/// model): the run's data, its report additions and summary.
pub fn resync(logs: &Logs, length: &(dyn Fn(&[f64; 6]) -> f64 + Sync)) -> Result<Read, Refusal> {
    let (m, mut extra, summary) = continuous(
        length,
        &logs.bar_name,
        &logs.bar,
        &logs.joint_name,
        &logs.t,
        &logs.q,
        "calibrated",
    )?;
    extra.program = logs.program_name.clone();
    extra.joint_log = Some(logs.joint_name.clone());
    Ok((m, extra, summary))
}

fn stop_and_measure(
    model: &MeasurementModel,
    robot: &Robot,
    bar_name: &str,
    bar: &BarLog,
    p: &Program,
) -> Result<Read, Refusal> {
    let traj =
        Trajectory::from_program(robot, model, p.parsed).map_err(|e| refuse(Input::Program, e))?;
    let tpl = logsim::template(&traj, model);
    let instruction = dwell_instruction(p.dialect);
    if traj.dwells.is_empty() {
        return Err(refuse(
            Input::Program,
            format!(
                "the program has no dwell ({instruction}): a bar log alone needs a stop-and-measure program, a dwell after each measurement move (edbbgen writes one with --dwell), or give --joint-log"
            ),
        ));
    }
    if tpl.slots.is_empty() {
        return Err(refuse(
            Input::Program,
            format!(
                "the program has no measurement dwell: none of its dwells ({instruction}) follows a move with the bar in place (between a mount pause and the next removal); a bar log alone needs a stop-and-measure program (edbbgen writes one with --dwell), or give --joint-log"
            ),
        ));
    }
    // The measurement poses are the program's dwells; edbbgen's header list, when present, is
    // a check that they are the poses it was compiled for, at this fixture and tool.
    let from_dwells = check_poses(p, &traj, &tpl, instruction)?;
    let sm = logs::stop_and_measure(&tpl, bar).map_err(|e| refuse(Input::BarLog, e))?;
    let m = readings(&tpl, &sm, bar);
    let used: usize = sm
        .readings
        .iter()
        .map(|&(_, j)| sm.plateaus[j].last_row - sm.plateaus[j].first_row + 1)
        .sum();
    let mut summary: Vec<String> = from_dwells.into_iter().collect();
    summary.push(matched_line(bar_name, &sm, &tpl));
    let spreads: Vec<f64> = sm
        .readings
        .iter()
        .map(|&(_, j)| sm.plateaus[j].spread)
        .collect();
    if let Some(worst) = spreads.iter().copied().reduce(f64::max) {
        summary.push(format!(
            "plateau spread: median {}, largest {}",
            length_um(median(&spreads).unwrap_or(worst) * 1e6),
            length_um(worst * 1e6)
        ));
    }
    let extra = RunExtra {
        bar_log: bar_name.to_string(),
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

/// Checks the dwells against the header's measure list; without one, a note of the poses
/// taken from the dwells (and the dwells left out).
fn check_poses(
    p: &Program,
    traj: &Trajectory,
    tpl: &logs::Template,
    instruction: &str,
) -> Result<Option<String>, Refusal> {
    let mut from_dwells = None;
    match logs::measure_list(p.parsed).map_err(|e| refuse(Input::Program, e))? {
        None => {
            let sorted = logsim::measurement_dwells(traj);
            let mut left_out = String::new();
            if !sorted.settling.is_empty() {
                left_out += &format!(
                    ", {} shorter dwells (under {} s, half the longest) taken as settling, not measured",
                    sorted.settling.len(),
                    fmt_fixed(logsim::SETTLING_SHARE * tpl.dwell, 2)
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
                p.name,
                tpl.slots.len(),
            ));
        }
        Some(list) => {
            if list.len() != tpl.slots.len() {
                return Err(refuse(
                    Input::Program,
                    format!(
                        "the header lists {} measurement poses, the program dwells at {} with the bar mounted",
                        list.len(),
                        tpl.slots.len()
                    ),
                ));
            }
            for (k, (l, s)) in list.iter().zip(&tpl.slots).enumerate() {
                if (l - s.length).abs() > 2e-6 {
                    return Err(refuse(
                        Input::Program,
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
    Ok(from_dwells)
}

/// The matched plateaus as static readings: their time, pose, mean, scatter and samples, and
/// the mean temperature over each where the bar logs one.
fn readings(tpl: &logs::Template, sm: &logs::StopAndMeasure, bar: &BarLog) -> Measured {
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
    m
}

/// The summary's line on the match: the poses matched and missing, the clock and the zero.
fn matched_line(bar_name: &str, sm: &logs::StopAndMeasure, tpl: &logs::Template) -> String {
    let unmatched = sm.report.iter().filter(|r| r.pose.is_none()).count();
    format!(
        "{}: {} of {} poses matched to plateaus{}{}; clock offset {} s (the program's time, its first pause taken out), drift {} ppm; bar reads nominal + {} mm",
        bar_name,
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
    )
}

fn continuous(
    length: &(dyn Fn(&[f64; 6]) -> f64 + Sync),
    bar_name: &str,
    bar: &BarLog,
    joint_name: &str,
    t: &[f64],
    q: &[[f64; 6]],
    which: &str,
) -> Result<Read, Refusal> {
    let spline = logs::sync::Spline::new(t, q);
    let s = logs::sync::sync(&bar.t, &bar.length, &spline, length)
        .map_err(|e| refuse(Input::JointLog, e))?;
    let t0 = bar.t.first().copied().unwrap_or(0.0);
    let interval =
        median(&bar.t.windows(2).map(|w| w[1] - w[0]).collect::<Vec<_>>()).unwrap_or(0.0);
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
        bar_name,
        s.rows.len(),
        bar.len(),
        joint_name,
        fmt_fixed(m.t.last().copied().unwrap_or(0.0) - m.t.first().copied().unwrap_or(0.0), 1),
        fmt_fixed(s.offset * 1e3, 3),
        fmt_fixed(s.offset_std * 1e3, 3),
        fmt_fixed(s.drift * 1e6, 1),
        fmt_fixed(s.drift_std * 1e6, 1),
        fmt_fixed(to_mm(s.zero), 3)
    ) + &smoothing];
    let extra = RunExtra {
        bar_log: bar_name.to_string(),
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

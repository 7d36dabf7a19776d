//! Continuous runs from logs synchronised again against a fitted robot: the runs (their data,
//! fixtures and how each was read from logs) and a fit in; the final fit out, the runs' data,
//! report additions and summaries replaced by those of the last synchronisation.
//!
//! A run from a joint log is first synchronised against the nominal model, whose errors bias
//! the clock (a 20 µs offset costs micrometres where the bar moves fast, a drift off by 1 ppm
//! 100 µs at the ends of a 4-minute run), and a fit from it absorbs part of the clock's error.

use super::{CalibrateError, CalibrateOptions, Calibration, Effects};
use crate::diagnose::Run;
use crate::model::MeasurementModel;
use crate::robot::Robot;
use crate::twin::recorded::{self, FromLogs, Logs, Read, Refusal};
use crate::twin::Measured;
use crate::units::fmt_fixed;
use nalgebra::Vector3;

/// Synchronisations of continuous runs against the calibrated robot, at most; and the clock
/// change (s, anywhere in a run) below which another round would not move a reading by a
/// micrometre at the bar's speeds (up to 1 m/s).
pub const RESYNC_ROUNDS: usize = 5;
pub const RESYNC_TOL: f64 = 1e-6;

/// A failed fit, or a run (by its index) whose logs no longer synchronise.
#[derive(Debug)]
pub enum ResyncError<E> {
    Fit(E),
    Logs { run: usize, refusal: Refusal },
}

/// Fits the campaign (`fit`: a calibration and whatever else the caller's fit states), then
/// synchronises every continuous run again against the calibrated robot whole (its effects
/// too: a compliance moves the bar's length by hundreds of micrometres; each run at its own
/// fixture) and fits again, until the clock moves by less than [`RESYNC_TOL`] anywhere in a
/// run, for at most [`RESYNC_ROUNDS`] rounds (a warning in the report when it has not settled).
/// `data`, `fixtures` and `from_logs` are per run (`from_logs` None for a run not from logs).
pub fn fit_resynchronised<X, E>(
    model: &MeasurementModel,
    data: &mut [Measured],
    fixtures: &[Vector3<f64>],
    from_logs: &mut [Option<FromLogs>],
    fit: impl Fn(&[Run]) -> Result<(Calibration, X), E>,
) -> Result<(Calibration, X), ResyncError<E>> {
    fn runs<'a>(data: &'a [Measured], fixtures: &[Vector3<f64>]) -> Vec<Run<'a>> {
        data.iter()
            .zip(fixtures)
            .map(|(measured, &fixture)| Run { measured, fixture })
            .collect()
    }
    let (mut cal, mut other) = fit(&runs(data, fixtures)).map_err(ResyncError::Fit)?;
    for round in 0..RESYNC_ROUNDS {
        if from_logs
            .iter()
            .all(|r| r.as_ref().is_none_or(|r| r.logs.is_none()))
        {
            break;
        }
        let mut moved: f64 = 0.0;
        for (k, run) in from_logs.iter_mut().enumerate() {
            let Some(FromLogs {
                extra,
                summary,
                logs: Some(logs),
            }) = run
            else {
                continue;
            };
            let mut p = cal.file.params;
            p.fix = cal.estimate.params(k).fix;
            let fx = &cal.file.effects;
            let length = |q: &[f64; 6]| model.reached_length(&p, fx, q, &[0.0; 6]);
            let (m, new, lines) = recorded::resync(logs, &length)
                .map_err(|refusal| ResyncError::Logs { run: k, refusal })?;
            if let (Some(&from), Some(&to)) = (logs.bar.t.first(), logs.bar.t.last()) {
                moved = moved.max(new.clock.moved_from(&extra.clock, from, to));
            }
            data[k] = m;
            *extra = new;
            *summary = lines;
        }
        (cal, other) = fit(&runs(data, fixtures)).map_err(ResyncError::Fit)?;
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
    Ok((cal, other))
}

/// One continuous run synchronised once more, against the geometry its own data give (no
/// effects): what `diagnose` reads, so that the nominal model's errors do not bias the clock.
pub fn on_own_geometry(
    model: &MeasurementModel,
    robot: &Robot,
    measured: &Measured,
    fixture: Vector3<f64>,
    label: &str,
    logs: &Logs,
) -> Result<Read, ResyncError<CalibrateError>> {
    let geometry = CalibrateOptions {
        effects: Effects::None,
        ..Default::default()
    };
    let one = [Run { measured, fixture }];
    let cal = super::run(model, robot, &one, &[label.to_string()], &geometry)
        .map_err(ResyncError::Fit)?;
    let p = cal.estimate.params(0);
    let length = |q: &[f64; 6]| model.length(&p, q);
    recorded::resync(logs, &length).map_err(|refusal| ResyncError::Logs { run: 0, refusal })
}

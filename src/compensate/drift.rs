//! Drift since the last calibration: in = a previous calibration report (`edbbgen.calibrate/1`,
//! its documented keys only: `params` with `value`/`std`, `determined`, `prior`), the nominal
//! robot's model and new runs; out = a calibration that starts from the previous one, and the
//! comparison: which parameters moved beyond their combined uncertainty, how far the MAP moved
//! over the joint space, and a plain verdict.
//!
//! **Why the new fit starts from the baseline.** A routine check measures few poses, which
//! determine fewer parameters than the full calibration did. Held at *nominal*, the others
//! would pull the determined ones by their whole calibrated deviation, and the comparison would
//! flag a drift that is only the nominal model's error. Held at the *baseline's* values, they
//! cost nothing: the fit measures the change since the baseline directly. The report then
//! states deviations from nominal as always (baseline + change); parameters the new data do not
//! determine keep the baseline's values (and say so).
//!
//! **When a parameter moved.** Its change Δ against σ = √(σ_new² + σ_baseline²) (a parameter
//! the baseline did not determine has its prior as σ_baseline): moved when |Δ| > [`THRESHOLD`]·σ.
//! With ~24 parameters the chance that noise alone flags one is about 1 % (Bonferroni).

use crate::calibrate::{self, CalibrateError, CalibrateOptions, Calibration, Report};
use crate::diagnose::Run;
use crate::model::{is_angle, MeasurementModel, Params, FIX, MAP, N_PARAMS, PARAM_NAMES, THETA};
use crate::robot::Robot;
use crate::units::{fmt_fixed, length_um, DEG, MM};
use nalgebra::Vector3;
use serde::Serialize;

use super::offsets::{registered_errors, Um};
use super::round6;

/// A change is flagged when it exceeds this many combined standard uncertainties.
pub const THRESHOLD: f64 = 3.5;

/// The robot parameters of a calibration report (SI; fixtures are the runs', not the robot's).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Calibrated {
    /// Eq. 6 index → (deviation from nominal, its standard uncertainty).
    pub params: Vec<(usize, f64, Option<f64>)>,
    /// The prior of a length (m) and an angle (rad): the uncertainty of an undetermined one.
    pub prior: (f64, f64),
}

impl Calibrated {
    pub fn get(&self, index: usize) -> Option<(f64, Option<f64>)> {
        self.params
            .iter()
            .find(|p| p.0 == index)
            .map(|p| (p.1, p.2))
    }

    fn prior_of(&self, index: usize) -> f64 {
        if is_angle(index) {
            self.prior.1
        } else {
            self.prior.0
        }
    }
}

/// Reads a calibration report's robot parameters.
pub fn read_report(v: &serde_json::Value) -> Result<Calibrated, String> {
    if v.get("schema").and_then(|s| s.as_str()) != Some("edbbgen.calibrate/1") {
        return Err("not a calibration report (schema edbbgen.calibrate/1)".into());
    }
    let params = v
        .get("params")
        .and_then(|p| p.as_object())
        .ok_or("params: missing")?;
    let mut out = Calibrated {
        params: Vec::new(),
        prior: (
            v.pointer("/prior/length_mm")
                .and_then(|x| x.as_f64())
                .unwrap_or(calibrate::DEFAULT_PRIOR_MM)
                * MM,
            v.pointer("/prior/angle_deg")
                .and_then(|x| x.as_f64())
                .unwrap_or(calibrate::DEFAULT_PRIOR_DEG)
                * DEG,
        ),
    };
    for (name, p) in params {
        // Fixture coordinates (x_fix, x_fix[2]) belong to the runs.
        let Some(i) = PARAM_NAMES.iter().position(|n| n == name) else {
            continue;
        };
        if i < FIX + 3 {
            continue;
        }
        let unit = if is_angle(i) { DEG } else { MM };
        let value = p
            .get("value")
            .and_then(|x| x.as_f64())
            .filter(|x| x.is_finite())
            .ok_or(format!("params.{name}.value: not a number"))?;
        let std = p
            .get("std")
            .and_then(|x| x.as_f64())
            .filter(|x| x.is_finite() && *x >= 0.0);
        out.params.push((i, value * unit, std.map(|s| s * unit)));
    }
    out.params.sort_by_key(|p| p.0);
    Ok(out)
}

/// The nominal parameters with the report's deviations applied (the fixture stays).
pub fn geometry(nominal: &Params, cal: &Calibrated) -> Params {
    let mut p = nominal.to_array();
    for &(i, v, _) in &cal.params {
        p[i] += v;
    }
    Params::from_array(&p)
}

/// One parameter's change since the baseline.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Change {
    pub param: String,
    /// mm or deg.
    pub unit: &'static str,
    pub baseline: f64,
    pub now: f64,
    pub change: f64,
    /// The combined standard uncertainty of the change.
    pub std: f64,
    /// |change| / std.
    pub ratio: f64,
    pub moved: bool,
}

/// The comparison with a previous calibration (the report's `drift` key).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Drift {
    pub baseline: String,
    /// Parameters the new data determine, with their change.
    pub changes: Vec<Change>,
    /// The ones that moved beyond `threshold` combined uncertainties, largest ratio first.
    pub moved: Vec<String>,
    /// Parameters the baseline determined that the new data do not: held at the baseline.
    pub held_at_baseline: Vec<String>,
    pub threshold: f64,
    /// How far the MAP moved between the two calibrated robots over random joint poses (µm):
    /// as is, and after a best rigid registration.
    pub map_change_um: Um,
    pub map_change_registered_um: Um,
    /// The new data's residual RMS with the baseline robot (µm): before any refit.
    pub rms_with_baseline_um: f64,
    pub verdict: String,
    /// Per pose, sorted ascending (µm), for the figure.
    #[serde(skip)]
    pub map_change_sorted_um: Vec<f64>,
}

fn unit_of(i: usize) -> (f64, &'static str) {
    if is_angle(i) {
        (DEG, "deg")
    } else {
        (MM, "mm")
    }
}

/// Decimals that show a standard uncertainty with one or two significant digits.
fn decimals(std: f64) -> usize {
    if std > 0.0 {
        // 1.05: an uncertainty of 0.00099 reads 0.001, not 0.0010.
        ((-(1.05 * std).log10()).ceil() as i64).clamp(3, 6) as usize
    } else {
        3
    }
}

/// How one moved parameter reads in the verdict.
fn describe(c: &Change, i: usize) -> String {
    let d = decimals(c.std);
    let amount = format!(
        "{} {} ± {} {}",
        fmt_fixed(c.change, d),
        c.unit,
        fmt_fixed(c.std, d),
        c.unit
    );
    if (THETA..MAP).contains(&i) {
        format!("joint {} zero moved {amount}", i - THETA + 1)
    } else {
        format!("{} changed {amount}", c.param)
    }
}

/// Compares the new calibration `now` (deviations from nominal) with `baseline` over `poses`;
/// `held` are the parameters held at the baseline's values.
pub fn compare(
    model: &MeasurementModel,
    baseline: &Calibrated,
    now: &Calibrated,
    determined: &[usize],
    poses: &[[f64; 6]],
    label: &str,
    rms_with_baseline_um: f64,
) -> Drift {
    let mut changes = Vec::new();
    for &i in determined {
        let (u, unit) = unit_of(i);
        let (b, bs) = baseline.get(i).unwrap_or((0.0, None));
        let bs = bs.unwrap_or_else(|| {
            // Not determined by the baseline: it held the parameter at nominal, uncertain by
            // its prior.
            if baseline.get(i).is_some() {
                0.0
            } else {
                baseline.prior_of(i)
            }
        });
        let (n, ns) = now.get(i).unwrap_or((0.0, None));
        let std = ns.unwrap_or(0.0).hypot(bs);
        let change = n - b;
        let ratio = if std > 0.0 {
            change.abs() / std
        } else {
            f64::INFINITY
        };
        changes.push(Change {
            param: PARAM_NAMES[i].to_string(),
            unit,
            baseline: round6(b / u),
            now: round6(n / u),
            change: round6(change / u),
            std: round6(std / u),
            ratio: (ratio * 100.0).round() / 100.0,
            moved: change != 0.0 && ratio > THRESHOLD,
        });
    }
    let held_at_baseline: Vec<String> = baseline
        .params
        .iter()
        .filter(|p| !determined.contains(&p.0))
        .map(|p| PARAM_NAMES[p.0].to_string())
        .collect();
    let mut order: Vec<(usize, f64)> = changes
        .iter()
        .enumerate()
        .filter(|(_, c)| c.moved)
        .map(|(k, c)| (k, c.ratio))
        .collect();
    order.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let moved: Vec<String> = order
        .iter()
        .map(|&(k, _)| changes[k].param.clone())
        .collect();

    // The MAP of the two calibrated robots over the joint space.
    let pb = geometry(&model.nominal, baseline);
    let pn = geometry(&model.nominal, now);
    let a: Vec<Vector3<f64>> = poses.iter().map(|q| model.map_position(&pb, q)).collect();
    let b: Vec<Vector3<f64>> = poses.iter().map(|q| model.map_position(&pn, q)).collect();
    let mut raw: Vec<f64> = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (y - x).norm() * 1e6)
        .collect();
    let reg = registered_errors(&b, &a);
    let map_change_um: Um = crate::calibrate::predict::spread(&raw).into();
    let map_change_registered_um: Um = crate::calibrate::predict::spread(&reg).into();
    raw.sort_by(f64::total_cmp);

    let spread = format!(
        "the MAP moved {} RMS, {} p95 over the joint space",
        length_um(map_change_um.rms),
        length_um(map_change_um.p95)
    );
    let verdict = if moved.is_empty() {
        format!(
            "unchanged within {}: no parameter moved beyond {} times its combined uncertainty; {spread}",
            length_um(map_change_um.p95),
            fmt_fixed(THRESHOLD, 1)
        )
    } else {
        let list: Vec<String> = order
            .iter()
            .map(|&(k, _)| {
                let i = PARAM_NAMES
                    .iter()
                    .position(|n| *n == changes[k].param)
                    .unwrap_or(0);
                describe(&changes[k], i)
            })
            .collect();
        format!("{}; {spread}", list.join("; "))
    };
    Drift {
        baseline: label.to_string(),
        changes,
        moved,
        held_at_baseline,
        threshold: THRESHOLD,
        map_change_um,
        map_change_registered_um,
        rms_with_baseline_um: (rms_with_baseline_um * 1e3).round() / 1e3,
        verdict,
        map_change_sorted_um: raw,
    }
}

/// The bar's residual RMS (m) of `runs` with the model's geometry `p` (each run's own fixture):
/// what the nominal (or baseline) robot explains before any fit.
pub fn residual_rms(model: &MeasurementModel, p: &Params, runs: &[Run]) -> (f64, Vec<f64>) {
    let mut total = (0.0, 0usize);
    let per_run = runs
        .iter()
        .map(|r| {
            let pr = Params {
                fix: r.fixture,
                ..*p
            };
            let ss: f64 = r
                .measured
                .q
                .iter()
                .zip(&r.measured.length)
                .map(|(q, l)| (l - model.length(&pr, q)).powi(2))
                .sum();
            total.0 += ss;
            total.1 += r.measured.q.len();
            (ss / r.measured.q.len().max(1) as f64).sqrt()
        })
        .collect();
    ((total.0 / total.1.max(1) as f64).sqrt(), per_run)
}

/// A calibration that starts from `baseline`, and its drift since it. The returned
/// calibration is stated like any other (deviations from the nominal `model`); parameters the
/// new data do not determine carry the baseline's values.
pub fn calibrate_against(
    model: &MeasurementModel,
    robot: &Robot,
    runs: &[Run],
    labels: &[String],
    opts: &CalibrateOptions,
    baseline: &Calibrated,
    baseline_label: &str,
) -> Result<(Calibration, Drift), CalibrateError> {
    let start = MeasurementModel {
        nominal: geometry(&model.nominal, baseline),
        ..model.clone()
    };
    let mut cal = calibrate::run(&start, robot, runs, labels, opts)?;
    // The change since the baseline, read from the report the way any report is read.
    let rel = serde_json::to_value(&cal.report)
        .map_err(|e| CalibrateError::Data(e.to_string()))
        .and_then(|v| read_report(&v).map_err(CalibrateError::Data))?;
    let determined: Vec<usize> = rel.params.iter().map(|p| p.0).collect();
    let mut now = baseline.clone();
    for &(i, v, s) in &rel.params {
        let b = baseline.get(i).map_or(0.0, |x| x.0);
        match now.params.iter_mut().find(|p| p.0 == i) {
            Some(p) => *p = (i, b + v, s),
            None => now.params.push((i, v, s)),
        }
    }
    now.params.sort_by_key(|p| p.0);
    let (with_baseline, _) = residual_rms(&start, &start.nominal, runs);
    let poses = calibrate::predict::workspace(robot, opts.workspace_poses, opts.seed);
    let drift = compare(
        model,
        baseline,
        &now,
        &determined,
        &poses,
        baseline_label,
        with_baseline * 1e6,
    );
    // The report as any calibration states it: deviations from nominal, residual before
    // calibration with the nominal robot.
    let (nominal_rms, per_run) = residual_rms(model, &model.nominal, runs);
    rebase_report(
        &mut cal.report,
        baseline,
        &determined,
        nominal_rms,
        &per_run,
    );
    cal.residual_nominal = runs
        .iter()
        .flat_map(|r| {
            let pr = Params {
                fix: r.fixture,
                ..model.nominal
            };
            r.measured
                .q
                .iter()
                .zip(&r.measured.length)
                .map(move |(q, l)| l - model.length(&pr, q))
                .collect::<Vec<_>>()
        })
        .collect();
    // Held out, the refit was judged against the robot it started from, the baseline. When it
    // is no better, nothing measurable moved: the baseline stands and is written again (the
    // drift verdict says "unchanged"), rather than refused as if it were the nominal robot.
    let robot_determined = cal.report.determined.iter().any(|n| {
        PARAM_NAMES
            .iter()
            .position(|p| p == n)
            .is_some_and(|i| i >= FIX + 3)
    });
    let h = cal.report.validation.heldout_rms_um;
    if !cal.report.calibrated && robot_determined && h.calibrated >= h.nominal {
        cal.report.calibrated = true;
        cal.report.verdict = format!(
            "calibrated: the baseline stands; held out, the refit predicts the readings to {} RMS against {} with the baseline robot",
            length_um(h.calibrated),
            length_um(h.nominal)
        );
    }
    cal.summary = calibrate::summary(&cal.report);
    if !drift.held_at_baseline.is_empty() {
        cal.summary += &format!(
            "held at the baseline's values (not at nominal): {}\n",
            drift.held_at_baseline.join(", ")
        );
    }
    cal.summary += &format!(
        "since {}: residual with the baseline robot {}; {}\n",
        baseline_label,
        length_um(drift.rms_with_baseline_um),
        drift.verdict
    );
    Ok((cal, drift))
}

/// Turns a report of a fit relative to the baseline into one relative to nominal.
fn rebase_report(
    report: &mut Report,
    baseline: &Calibrated,
    determined: &[usize],
    nominal_rms: f64,
    per_run: &[f64],
) {
    for (name, entry) in report.params.iter_mut() {
        let Some(i) = PARAM_NAMES.iter().position(|n| n == name) else {
            continue;
        };
        if i < FIX + 3 {
            continue;
        }
        let (u, _) = unit_of(i);
        let b = baseline.get(i).map_or(0.0, |x| x.0) / u;
        if let Some(v) = entry.get_mut("value") {
            if let Some(x) = v.as_f64() {
                *v = round6(x + b).into();
            }
        }
    }
    for &(i, v, s) in &baseline.params {
        if determined.contains(&i) {
            continue;
        }
        let (u, unit) = unit_of(i);
        let mut e = serde_json::Map::new();
        e.insert("value".into(), round6(v / u).into());
        e.insert(
            "std".into(),
            s.map_or(serde_json::Value::Null, |s| round6(s / u).into()),
        );
        report.params.insert(PARAM_NAMES[i].to_string(), e.into());
        if let Some(u_) = report
            .undetermined
            .iter_mut()
            .find(|x| x.param == PARAM_NAMES[i])
        {
            u_.why += &format!(
                "; held at the baseline's value {} {unit}",
                fmt_fixed(v / u, 6)
            );
        }
    }
    report.rms_before_um = (nominal_rms * 1e9).round() / 1e3;
    for (run, rms) in report.runs.iter_mut().zip(per_run) {
        run.rms_before_um = (rms * 1e9).round() / 1e3;
    }
}

/// The parameters a short check program is chosen for: those that moved at the last
/// comparison (a report's `drift.moved`), then the six joint zeros (what a crash, a motor or
/// gearbox exchange and re-mastering move), without repeats. Eq. 6 indices.
pub fn check_parameters(report: Option<&serde_json::Value>) -> Vec<usize> {
    let mut out: Vec<usize> = Vec::new();
    if let Some(moved) = report
        .and_then(|r| r.pointer("/drift/moved"))
        .and_then(|m| m.as_array())
    {
        for m in moved.iter().filter_map(|m| m.as_str()) {
            if let Some(i) = PARAM_NAMES.iter().position(|n| *n == m) {
                if i >= FIX + 3 && !out.contains(&i) {
                    out.push(i);
                }
            }
        }
    }
    for i in THETA..MAP {
        if !out.contains(&i) {
            out.push(i);
        }
    }
    debug_assert!(out.iter().all(|&i| i < N_PARAMS));
    out
}

//! A calibration, the robot it started from and its runs' labels and input hashes in; the
//! comment lines on top of the calibrated robot file out (where it came from, how good it is,
//! what it holds and what it does not).

use super::Calibration;
use crate::robot::{self, Robot};
use crate::units::{fmt_fixed, length_um};
use nalgebra::Vector3;

/// The comment lines on top of the calibrated file: where it came from and how good it is.
pub fn lines(
    robot: &Robot,
    cal: &Calibration,
    hashes: &[String],
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
            &hashes[k][..16],
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
        "residual RMS {} nominal -> {} calibrated; bar noise {} (lag-1 autocorrelation {})",
        length_um(r.rms_before_um),
        length_um(r.rms_after_um),
        length_um(r.noise_um),
        fmt_fixed(r.residual_lag1, 2)
    ));
    h.push(format!(
        "determined ({}): {}",
        r.determined.len(),
        r.determined.join(", ")
    ));
    h.push(format!(
        "validation, held out: {} RMS nominal -> {} calibrated ({} rows)",
        length_um(r.validation.heldout_rms_um.nominal),
        length_um(r.validation.heldout_rms_um.calibrated),
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
        "predicted MAP position uncertainty (1 sigma, after rigid registration): {} RMS where measured, {} RMS and {} p95 over the joint space",
        length_um(p.measured_region_rms),
        length_um(p.workspace_rms),
        length_um(p.workspace_p95)
        ));
    }
    for e in &r.effect_sizes {
        let name = match e.joint {
            Some(j) => format!("{} (joint {j})", e.effect),
            None => e.effect.to_string(),
        };
        h.push(format!(
            "effect {name}: {} RMS over the joint space ({}); {}",
            length_um(e.workspace_rms_um),
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

/// The input hash of a calibration (its page states it): the robot, the runs' data, the
/// fixtures, the tool and the effects option (with a baseline's hash, when there is one).
pub fn inputs_hash(
    robot: &Robot,
    hashes: &[String],
    fixtures: &[Vector3<f64>],
    map: &Vector3<f64>,
    effects: &str,
) -> String {
    let mut s = robot.digest.clone();
    for h in hashes {
        s += "\n";
        s += h;
    }
    for f in fixtures {
        s += &format!("\n{:?}", f.as_slice());
    }
    s += &format!("\n{:?}\n{effects}\n", map.as_slice());
    robot::sha256_hex(s.as_bytes())
}

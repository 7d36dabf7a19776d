//! Figures of a calibration: in = a [`super::Calibration`]; out = [`Figure`]s (drawn by
//! [`crate::plot`]): the residual of every run before and after, and the predicted position
//! uncertainty over the joint space.

use super::Calibration;
use crate::plot::{break_gaps, envelope, run_axis, Figure, Panel, PlotError, Series};
use crate::units::length_um;

/// Pixel columns of a panel: long runs are reduced to a min/max envelope at this width.
const COLUMNS: usize = 900;

/// Measured − model (µm) over time (the reading number for untimed static runs), per run: with the nominal model and the calibrated one.
pub fn residuals(c: &Calibration) -> Figure {
    let mut panels = Vec::new();
    for (k, range) in c.ranges.iter().enumerate() {
        let run = &c.report.runs[k];
        for (colour, (what, r)) in [
            ("nominal", &c.residual_nominal),
            ("calibrated", &c.residual),
        ]
        .into_iter()
        .enumerate()
        {
            let r = &r[range.clone()];
            let (x, x_label) = run_axis(&c.t[range.clone()], c.timed[k]);
            let pts: Vec<(f64, f64)> = x.iter().zip(r).map(|(t, v)| (*t, v * 1e6)).collect();
            let rms = (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt();
            panels.push(Panel {
                title: format!(
                    "run {} ({}), {what} model: RMS {}",
                    k + 1,
                    run.measured,
                    length_um(rms * 1e6)
                ),
                x_label: x_label.into(),
                y_label: "measured − model [µm]".into(),
                series: vec![Series::line(
                    "",
                    colour,
                    break_gaps(&envelope(&pts, COLUMNS), 20.0),
                )],
                ..Panel::default()
            });
        }
    }
    Figure {
        title: "EDBB residual over time, nominal and calibrated model".into(),
        panels,
        columns: 1,
        panel_px: (960, 200),
    }
}

/// The predicted 1σ MAP position uncertainty of the random workspace poses, sorted: the share
/// of the joint space within a given uncertainty.
pub fn uncertainty(c: &Calibration) -> Figure {
    let mut v = c.workspace_std_um.clone();
    v.sort_by(f64::total_cmp);
    let n = v.len().max(1) as f64;
    let pts: Vec<(f64, f64)> = v
        .iter()
        .enumerate()
        .map(|(k, s)| (100.0 * (k + 1) as f64 / n, *s))
        .collect();
    Figure {
        title: String::new(),
        panels: vec![Panel {
            title: format!(
                "predicted MAP position uncertainty over the joint space: RMS {}, p95 {}",
                length_um(c.report.predicted_position_std_um.workspace_rms),
                length_um(c.report.predicted_position_std_um.workspace_p95)
            ),
            x_label: "share of random joint poses [%]".into(),
            y_label: "1σ position uncertainty [µm]".into(),
            series: vec![Series::line("", 2, pts)],
            ..Panel::default()
        }],
        columns: 1,
        panel_px: (960, 260),
    }
}

/// `--plot`: the residuals.
pub fn svg(c: &Calibration) -> Result<String, PlotError> {
    crate::plot::svg(&residuals(c))
}

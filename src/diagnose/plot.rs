//! SVG plot of the residual over time, one panel per diagnosis stage (like the paper's
//! Fig. 12): in = a [`super::Diagnosis`]; out = SVG text, drawn by [`crate::plot`].

use super::Diagnosis;
use crate::plot::{break_gaps, envelope, run_axis, Figure, Panel, PlotError, Series};
use crate::units::length_um;

/// Pixel columns of a panel: long runs are reduced to a min/max envelope at this width.
const COLUMNS: usize = 900;

/// Renders every stage's residual (µm) against time (s), or the reading number for untimed
/// static readings.
pub fn svg(d: &Diagnosis) -> Result<String, PlotError> {
    let (x, x_label) = run_axis(&d.t, d.timed);
    let panels = d
        .stages
        .iter()
        .map(|(label, r)| {
            let pts: Vec<(f64, f64)> = x.iter().zip(r).map(|(t, v)| (*t, v * 1e6)).collect();
            let rms = (r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt() * 1e6;
            Panel {
                title: format!("{label} — RMS {}", length_um(rms)),
                x_label: x_label.into(),
                y_label: "measured − model [µm]".into(),
                series: vec![Series::line(
                    "",
                    0,
                    break_gaps(&envelope(&pts, COLUMNS), 20.0),
                )],
                ..Panel::default()
            }
        })
        .collect();
    crate::plot::svg(&Figure {
        title: "EDBB residual over time, after each diagnosis step".into(),
        panels,
        columns: 1,
        panel_px: (960, 220),
    })
}

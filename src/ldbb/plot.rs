//! The LDBB figures (the paper's Figs. 13–15): in = an [`Analysis`]; out = [`Figure`]s for the
//! HTML report and one SVG for `--plot`, drawn by [`crate::plot`].
//!
//! - Fig. 13 (a): the raw data, the mean of the repeats per load; (b) the load-induced
//!   deflections of Eq. 8, each load against the base load (the apparent loads);
//! - Fig. 14 (a): the compliance-compensated trajectories per load; (b) their average with the
//!   fitted centring sine;
//! - Fig. 15: the kinematic remainder, with the laser-tracker reference when given;
//! - and the compliance along the bar per angle with its ± 1 std band.
//!
//! Every series of a figure has its own palette colour (the report's browser check counts them);
//! black (palette 7) is never data.

use super::{Analysis, SineModel};
use crate::plot::{Figure, Legend, Panel, PlotError, Series};
use crate::units::{length_um, DEG};

const UM: f64 = 1e-6;
/// Width of a single-panel figure and height of every panel (px).
const WIDE: (u32, u32) = (960, 300);

fn curve(angles: &[f64], v: &[f64], scale: f64) -> Vec<(f64, f64)> {
    // Closed around the circle: the first node again at 360°.
    let mut p: Vec<(f64, f64)> = angles
        .iter()
        .zip(v)
        .map(|(a, y)| (a / DEG, y / scale))
        .collect();
    if let (Some(&(_, y0)), Some(_)) = (p.first(), p.last()) {
        p.push((360.0, y0));
    }
    p
}

fn load_label(f: f64) -> String {
    let s = format!("{f}");
    format!("{} N", s.strip_suffix(".0").unwrap_or(&s))
}

fn panel(title: &str, y_label: &str, series: Vec<Series>) -> Panel {
    Panel {
        title: title.into(),
        x_label: "circle angle θ [deg]".into(),
        y_label: y_label.into(),
        series,
        x_range: Some((0.0, 360.0)),
        legend: Legend::Outside,
        ..Panel::default()
    }
}

fn single(p: Panel) -> Figure {
    Figure {
        title: String::new(),
        panels: vec![p],
        columns: 1,
        panel_px: WIDE,
    }
}

/// Fig. 13 (a): the mean of the repeats of each load.
pub fn raw(a: &Analysis) -> Panel {
    let s = (0..a.loads.len())
        .map(|j| Series::line(load_label(a.loads[j]), j, curve(&a.angles, &a.mean[j], UM)))
        .collect();
    panel(
        "Fig. 13 (a): measured deflection, mean of the repeats",
        "deflection [µm]",
        s,
    )
}

/// Fig. 13 (b): Eq. 8, each load's deflection against the base load.
pub fn deflections(a: &Analysis) -> Panel {
    let s = (1..a.loads.len())
        .map(|j| {
            Series::line(
                format!("AL {}", load_label(a.loads[j] - a.loads[0])),
                j - 1,
                curve(&a.angles, &a.deflection[j], UM),
            )
        })
        .collect();
    panel(
        "Fig. 13 (b): load-induced deflection (Eq. 8) at the apparent loads",
        "Δx [µm]",
        s,
    )
}

/// Fig. 14 (a): the compensated trajectories.
pub fn compensated(a: &Analysis) -> Panel {
    let s = (0..a.loads.len())
        .map(|j| {
            Series::line(
                load_label(a.loads[j]),
                j,
                curve(&a.angles, &a.compensated[j], UM),
            )
        })
        .collect();
    panel(
        &format!(
            "Fig. 14 (a): compliance-compensated trajectories (linearity spread {})",
            length_um(a.report.linearity_spread_um)
        ),
        "deflection at zero load [µm]",
        s,
    )
}

/// Fig. 14 (b): their average and the centring sine(s).
pub fn average(a: &Analysis) -> Panel {
    let mut s = vec![Series::line("average", 0, curve(&a.angles, &a.average, UM))];
    let sine = |f: &super::fit::Sine| -> Vec<f64> { a.angles.iter().map(|t| f.eval(*t)).collect() };
    s.push(Series::line(
        format!(
            "sine, b = 1: a {:.3} mm, φ {:.1}°",
            a.sine_linear.a * 1e3,
            a.sine_linear.phi / DEG
        ),
        1,
        curve(&a.angles, &sine(&a.sine_linear), UM),
    ));
    if let Some(n) = &a.sine_nonlinear {
        if a.report.sine_fits.disagree || a.sine_used == SineModel::Nonlinear {
            s.push(Series::line(
                format!(
                    "sine, b free: a {:.3} mm, b {:.3}, φ {:.1}°",
                    n.a * 1e3,
                    n.b,
                    n.phi / DEG
                ),
                2,
                curve(&a.angles, &sine(n), UM),
            ));
        }
    }
    panel(
        "Fig. 14 (b): averaged compensated trajectory and the centring sine (Eq. 9)",
        "deflection [µm]",
        s,
    )
}

/// Fig. 15: the kinematic remainder and the reference.
pub fn kinematic(a: &Analysis) -> Panel {
    let mut s = vec![Series::line(
        "LDBB: compensated − sine",
        0,
        curve(&a.angles, &a.kinematic, UM),
    )];
    if let Some(r) = &a.reference {
        s.push(Series::line(
            "reference (mean removed)",
            1,
            curve(&a.angles, r, UM),
        ));
        s.push(Series::line(
            "reference without its first harmonic (what the LDBB can see)",
            2,
            curve(&a.angles, &super::without_first_harmonic(&a.angles, r), UM),
        ));
    }
    let title = match &a.report.reference {
        Some(r) => format!(
            "Fig. 15: kinematic error along the bar (RMS {}; mean |difference| to the reference {})",
            length_um(a.report.kinematic_error_rms_um),
            length_um(r.mean_abs_difference_um)
        ),
        None => format!(
            "Fig. 15: kinematic error along the bar (RMS {})",
            length_um(a.report.kinematic_error_rms_um)
        ),
    };
    panel(&title, "error [µm]", s)
}

/// The compliance along the bar with its ± 1 std band.
pub fn compliance(a: &Analysis) -> Panel {
    let band = |sign: f64| -> Vec<f64> {
        a.compliance
            .iter()
            .zip(&a.compliance_std)
            .map(|(c, s)| c + sign * if s.is_finite() { *s } else { 0.0 })
            .collect()
    };
    let s = vec![
        Series::line("compliance", 0, curve(&a.angles, &a.compliance, UM)),
        Series::line("± 1 std", 5, curve(&a.angles, &band(1.0), UM)),
        Series::line("", 5, curve(&a.angles, &band(-1.0), UM)),
    ];
    panel("compliance along the bar", "c [µm/N]", s)
}

/// Fig. 13 (a), (b), the compliance, Fig. 14 (a), (b) and Fig. 15 as single-panel figures (id,
/// caption, figure) for the report, in that order.
pub fn figures(a: &Analysis) -> Vec<(&'static str, Figure)> {
    vec![
        ("fig-raw", single(raw(a))),
        ("fig-deflection", single(deflections(a))),
        ("fig-compliance", single(compliance(a))),
        ("fig-compensated", single(compensated(a))),
        ("fig-average", single(average(a))),
        ("fig-kinematic", single(kinematic(a))),
    ]
}

/// `ldbb --plot`: every panel in one SVG, legends in the panels.
pub fn svg(a: &Analysis) -> Result<String, PlotError> {
    let panels = [
        raw(a),
        deflections(a),
        compensated(a),
        average(a),
        kinematic(a),
        compliance(a),
    ]
    .into_iter()
    .map(|p| Panel {
        legend: Legend::UpperRight,
        ..p
    })
    .collect();
    crate::plot::svg(&Figure {
        title: "LDBB loaded circle analysis (Figs. 13–15)".into(),
        panels,
        columns: 1,
        panel_px: (960, 280),
    })
}

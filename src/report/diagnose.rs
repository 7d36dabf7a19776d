//! The diagnosis page: in = the measured data and the [`Diagnosis`]; out = a [`Page`] with the
//! measured and modelled bar length over time (Fig. 11), the residual after each step
//! (Fig. 12), the steps with their parameters and uncertainties, and the verdict — the numbers
//! of the `edbbgen.diagnose/1` report.

use super::{Block, Page, ReportError, Section};
use crate::diagnose::{Diagnosis, Report, Where};
use crate::plot::{break_gaps, Figure, Legend, Panel, Series};
use crate::twin::Measured;
use crate::units::{fmt_fixed, fmt_sig, length_um, to_mm};

const BLUE: usize = 0;
const RED: usize = 1;
const GREEN: usize = 2;

fn where_text(w: &Where) -> String {
    let joints: Vec<String> = w
        .joints_deg
        .iter()
        .enumerate()
        .map(|(j, r)| format!("q{} {}..{}°", j + 1, fmt_fixed(r[0], 1), fmt_fixed(r[1], 1)))
        .collect();
    format!(
        "t {}..{} s, peak {}; {}",
        fmt_fixed(w.t_s[0], 1),
        fmt_fixed(w.t_s[1], 1),
        length_um(w.peak_um),
        joints.join(", ")
    )
}

/// A JSON number or string as table text (parameters are mm / deg already).
fn value_text(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::Number(n) => n
            .as_f64()
            .map(|x| {
                // Small coefficients (thermal expansion, servo lag) keep their digits.
                if x != 0.0 && x.abs() < 1e-3 {
                    format!("{x:.3e}")
                } else {
                    fmt_fixed(x, 4)
                }
            })
            .unwrap_or_else(|| n.to_string()),
        serde_json::Value::Array(a) => a.iter().map(value_text).collect::<Vec<_>>().join(", "),
        serde_json::Value::String(s) => s.clone(),
        serde_json::Value::Null => "—".to_string(),
        other => other.to_string(),
    }
}

/// `inputs_sha256`: the hash of what the diagnosis read (robot file, data, fixture and MAP), for
/// the page's stamp.
pub fn page(
    measured: &Measured,
    d: &Diagnosis,
    robot: &str,
    inputs_sha256: &str,
) -> Result<Page, ReportError> {
    let r = &d.report;
    let fig11 = length_figure(measured, d);
    let fig12 = residual_figure(d);
    let params = param_rows(r);
    let final_model = final_model_rows(r);
    let facts = facts(r, robot);
    let steps: Vec<Vec<String>> = r
        .steps
        .iter()
        .map(|s| {
            vec![
                s.effect.to_string(),
                s.joint.map(|j| j.to_string()).unwrap_or_default(),
                fmt_sig(s.rms_after_um, 3),
                fmt_sig(s.cv_rms_um, 3),
                fmt_fixed(s.bic, 1),
            ]
        })
        .collect();
    let warnings = if r.unexplained {
        vec!["unexplained structure remains above the instrument noise (see 'where')".to_string()]
    } else {
        Vec::new()
    };
    Ok(Page {
        title: format!("edbbgen — diagnosis of {robot}"),
        kind: "diagnose".into(),
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs_sha256: inputs_sha256.to_string(),
        facts,
        warnings,
        sections: vec![
            Section {
                heading: "Measured and modelled bar length (Fig. 11)".into(),
                blocks: vec![Block::figure(
                    "fig-length",
                    "The bar length the EDBB read, the length the nominal model predicts at the recorded joint angles, and the final model's.",
                    &fig11,
                )?],
            },
            Section {
                heading: "Residual after each step (Fig. 12)".into(),
                blocks: vec![Block::figure(
                    "fig-residual",
                    "Measured minus modelled length over time: with the nominal model, after calibrating the geometry, and after each effect the diagnosis named.",
                    &fig12,
                )?],
            },
            Section {
                heading: "Steps".into(),
                blocks: vec![
                    Block::table(
                        &["effect", "joint", "RMS after [µm]", "cross-validated RMS [µm]", "BIC"],
                        steps,
                    ),
                    Block::text(
                        "Parameters of each step with their standard uncertainties (lengths in mm, angles in degrees; geometric parameters are deviations from nominal).",
                    ),
                    Block::table(&["step", "parameter", "value", "std"], params),
                ],
            },
            Section {
                heading: "Final model".into(),
                blocks: vec![
                    Block::text(
                        "The geometry and every named effect fitted together (the geometric step above is the geometry alone, which a missing effect biases). Standard uncertainties from the residual's noise, inflated for its lag-1 correlation. `edbbgen calibrate` turns this into a calibrated robot file, moving only what the data determine.",
                    ),
                    Block::table(&["term", "parameter", "value", "std"], final_model),
                ],
            },
        ],
    })
}

/// Fig. 11: the measured bar length over time and the nominal and final models' lengths.
fn length_figure(measured: &Measured, d: &Diagnosis) -> Figure {
    let (t, x_label) = crate::plot::run_axis(&d.t, d.timed);
    let measured_pts: Vec<(f64, f64)> = t
        .iter()
        .zip(&measured.length)
        .map(|(t, l)| (*t, to_mm(*l)))
        .collect();
    let model_pts = |res: &[f64]| -> Vec<(f64, f64)> {
        t.iter()
            .zip(measured.length.iter().zip(res))
            .map(|(t, (l, e))| (*t, to_mm(l - e)))
            .collect()
    };
    let mut len_series = vec![Series::line(
        "measured",
        BLUE,
        break_gaps(&measured_pts, 20.0),
    )];
    if let Some((_, nominal)) = d.stages.first() {
        len_series.push(Series::line(
            "nominal model",
            RED,
            break_gaps(&model_pts(nominal), 20.0),
        ));
    }
    if d.stages.len() > 1 {
        if let Some((label, last)) = d.stages.last() {
            len_series.push(Series::line(
                format!("final model ({label})"),
                GREEN,
                break_gaps(&model_pts(last), 20.0),
            ));
        }
    }
    Figure {
        title: String::new(),
        panels: vec![Panel {
            title: "bar length over time".into(),
            x_label: x_label.into(),
            y_label: "L [mm]".into(),
            series: len_series,
            legend: Legend::Outside,
            ..Panel::default()
        }],
        columns: 1,
        panel_px: (960, 300),
    }
}

/// Fig. 12: the residual after each step, one panel each.
fn residual_figure(d: &Diagnosis) -> Figure {
    let (t, x_label) = crate::plot::run_axis(&d.t, d.timed);
    Figure {
        title: String::new(),
        panels: d
            .stages
            .iter()
            .enumerate()
            .map(|(k, (label, res))| {
                let pts: Vec<(f64, f64)> = t.iter().zip(res).map(|(t, e)| (*t, e * 1e6)).collect();
                let rms =
                    (res.iter().map(|e| e * e).sum::<f64>() / res.len().max(1) as f64).sqrt() * 1e6;
                Panel {
                    title: format!("{label}: RMS {}", length_um(rms)),
                    x_label: x_label.into(),
                    y_label: "measured − model [µm]".into(),
                    // One colour per step, so every step counts as a series of its own.
                    series: vec![Series::line("", k, break_gaps(&pts, 20.0))],
                    ..Panel::default()
                }
            })
            .collect(),
        columns: 1,
        panel_px: (960, 200),
    }
}

/// Each step's parameters with their standard uncertainties.
fn param_rows(r: &Report) -> Vec<Vec<String>> {
    let mut params: Vec<Vec<String>> = Vec::new();
    for s in &r.steps {
        for (k, v) in &s.params {
            let std = s.std.get(k).map(value_text).unwrap_or_default();
            params.push(vec![
                match s.joint {
                    Some(j) => format!("{} (joint {j})", s.effect),
                    None => s.effect.to_string(),
                },
                k.clone(),
                value_text(v),
                std,
            ]);
        }
    }
    params
}

/// The geometry and every named effect fitted together.
fn final_model_rows(r: &Report) -> Vec<Vec<String>> {
    let mut final_model: Vec<Vec<String>> = r
        .model
        .params
        .iter()
        .map(|(k, v)| {
            vec![
                "geometric".to_string(),
                k.clone(),
                value_text(v),
                r.model.std.get(k).map(value_text).unwrap_or_default(),
            ]
        })
        .collect();
    for e in &r.model.effects {
        for (k, v) in &e.params {
            final_model.push(vec![
                match e.joint {
                    Some(j) => format!("{} (joint {j})", e.effect),
                    None => e.effect.to_string(),
                },
                k.clone(),
                value_text(v),
                e.std.get(k).map(value_text).unwrap_or_default(),
            ]);
        }
    }
    final_model
}

fn facts(r: &Report, robot: &str) -> Vec<(String, String)> {
    let named: Vec<String> = r
        .named_effects
        .iter()
        .map(|e| match e.joint {
            Some(j) => format!("{} (joint {j})", e.effect),
            None => e.effect.to_string(),
        })
        .collect();
    let mut facts = vec![
        ("robot".to_string(), robot.to_string()),
        (
            "data".into(),
            format!("{} rows over {} s", r.rows, fmt_fixed(r.duration_s, 1)),
        ),
        ("bar noise (estimated)".into(), length_um(r.noise_um)),
        ("RMS, nominal model".into(), length_um(r.rms_nominal_um)),
        ("named effects".into(), named.join(", ")),
        ("RMS, final model".into(), length_um(r.rms_final_um)),
        (
            "lag-1 autocorrelation of the final residual".into(),
            fmt_fixed(r.lag1_final, 3),
        ),
        (
            "verdict".into(),
            if r.unexplained {
                "structure above the noise remains that no known effect explains".into()
            } else {
                "residual at the noise level".into()
            },
        ),
    ];
    if let Some(w) = &r.nominal_where {
        facts.push(("nominal model: largest disagreement".into(), where_text(w)));
    }
    if let Some(w) = &r.where_ {
        facts.push(("unexplained: where".into(), where_text(w)));
    }
    facts
}

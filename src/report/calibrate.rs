//! The calibration page: in = a [`Calibration`]; out = a [`Page`] with the residual of every
//! run before and after (Fig. 12's view), the calibrated parameters with their uncertainties,
//! what was held at nominal and why, the effects, and the predicted position uncertainty — the
//! numbers of the `edbbgen.calibrate/1` report.

use super::{Block, Page, ReportError, Section};
use crate::calibrate::{plot, Calibration, Report};
use crate::units::{fmt_fixed, fmt_sig, length_um};

fn num(v: &serde_json::Value) -> String {
    match v {
        serde_json::Value::Number(n) => n
            .as_f64()
            .map(|x| fmt_fixed(x, 6))
            .unwrap_or_else(|| n.to_string()),
        serde_json::Value::Array(a) => a.iter().map(num).collect::<Vec<_>>().join(", "),
        other => other.to_string(),
    }
}

/// The calibration page of `c` for the robot named `robot`, its inputs hashed to `inputs_sha256`.
pub fn page(c: &Calibration, robot: &str, inputs_sha256: &str) -> Result<Page, ReportError> {
    let r = &c.report;
    let effects = effect_rows(r);
    let mut sections = vec![
        Section {
            heading: "Residual before and after (Fig. 12)".into(),
            blocks: vec![Block::figure(
                "fig-residual",
                "Measured minus modelled bar length over time, per run: with the nominal model and with the calibrated one (geometry and effects fitted together).",
                &plot::residuals(c),
            )?],
        },
        Section {
            heading: "Runs".into(),
            blocks: vec![Block::table(
                &[
                    "run",
                    "data",
                    "rows",
                    "fixture given [mm]",
                    "fixture estimated [mm]",
                    "RMS nominal [µm]",
                    "RMS calibrated [µm]",
                ],
                run_rows(r),
            )],
        },
        Section {
            heading: "Calibrated parameters".into(),
            blocks: vec![
                Block::text(
                    "Deviations from nominal of the parameters the data determine (lengths in mm, angles in degrees), with standard uncertainties (GUM Type A: the residual's noise, inflated for its autocorrelation and for what the held-out residual says about model error, through the fit's covariance). A parameter is determined when the data bring its uncertainty below its prior divided by κ.",
                ),
                Block::table(&["parameter", "deviation", "std"], param_rows(r)),
            ],
        },
        Section {
            heading: "Held at nominal".into(),
            blocks: vec![Block::table(&["parameter", "why"], undetermined_rows(r))],
        },
    ];
    sections.push(Section {
        heading: "Candidates, judged on held-out data".into(),
        blocks: vec![
            Block::text("Each effect considered, with the residual RMS of the model with it on blocks of rows held out of the fit; an effect is adopted only when it lowers that clearly."),
            Block::table(&["effect", "form", "held-out RMS [µm]", "adopted"], candidate_rows(r)),
        ],
    });
    if let Some(s) = faults_section(r) {
        sections.push(s);
    }
    if !effects.is_empty() {
        sections.push(effects_section(r, effects));
    }
    sections.push(Section {
        heading: "Predicted position uncertainty".into(),
        blocks: vec![Block::figure(
            "fig-uncertainty",
            "1σ MAP position uncertainty of the calibrated robot at random joint poses within the limits, after a best rigid registration, sorted: noise through the determined parameters combined with the prior uncertainty of the parameters held at nominal.",
            &plot::uncertainty(c),
        )?],
    });
    Ok(Page {
        title: format!("edbbgen — calibration of {robot}"),
        kind: "calibrate".into(),
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs_sha256: inputs_sha256.to_string(),
        facts: facts(r, robot),
        warnings: r.warnings.clone(),
        sections,
    })
}

/// The page's facts (name, value) from the calibration report `r` of the robot named `robot`.
fn facts(r: &Report, robot: &str) -> Vec<(String, String)> {
    let p = &r.predicted_position_std_um;
    let mut facts = vec![
        ("robot".to_string(), robot.to_string()),
        (
            "data".into(),
            format!(
                "{} run{}, {} rows",
                r.runs.len(),
                if r.runs.len() == 1 { "" } else { "s" },
                r.rows
            ),
        ),
        (
            "bar noise (from the residual)".into(),
            format!(
                "{}, lag-1 autocorrelation {}",
                length_um(r.noise_um),
                fmt_fixed(r.residual_lag1, 2)
            ),
        ),
        (
            "RMS, nominal → calibrated".into(),
            format!(
                "{} → {}",
                length_um(r.rms_before_um),
                length_um(r.rms_after_um)
            ),
        ),
        (
            "determined parameters".into(),
            format!("{}", r.determined.len()),
        ),
        (
            "predicted MAP position uncertainty (1σ, registered)".into(),
            format!(
                "{} RMS where measured; {} RMS, {} p95 over the joint space",
                length_um(p.measured_region_rms),
                length_um(p.workspace_rms),
                length_um(p.workspace_p95)
            ),
        ),
        (
            "of which from noise / from parameters held at nominal / from model error".into(),
            format!(
                "{} / {} / {} RMS over the joint space",
                length_um(p.from_noise.workspace_rms),
                length_um(p.from_held.workspace_rms),
                length_um(p.from_model_error.workspace_rms)
            ),
        ),
    ];
    facts.push(("verdict".into(), r.verdict.clone()));
    facts.push((
        "held-out residual, nominal → calibrated".into(),
        format!(
            "{} → {} RMS ({})",
            length_um(r.validation.heldout_rms_um.nominal),
            length_um(r.validation.heldout_rms_um.calibrated),
            r.validation.split
        ),
    ));
    let t = &r.tool;
    facts.push((
        "MAP, given → estimated".into(),
        format!(
            "{}, {}, {} mm → {}, {}, {} mm (moved {} mm)",
            fmt_fixed(t.given_mm[0], 3),
            fmt_fixed(t.given_mm[1], 3),
            fmt_fixed(t.given_mm[2], 3),
            fmt_fixed(t.fitted_mm[0], 3),
            fmt_fixed(t.fitted_mm[1], 3),
            fmt_fixed(t.fitted_mm[2], 3),
            fmt_fixed(t.moved_mm, 3)
        ),
    ));
    if !r.held.is_empty() {
        facts.push(("held at the given value".into(), r.held.join(", ")));
    }
    facts
}

/// The runs table's rows from the calibration report.
fn run_rows(r: &Report) -> Vec<Vec<String>> {
    r.runs
        .iter()
        .enumerate()
        .map(|(k, run)| {
            let f = |v: [f64; 3]| {
                format!(
                    "{}, {}, {}",
                    fmt_fixed(v[0], 3),
                    fmt_fixed(v[1], 3),
                    fmt_fixed(v[2], 3)
                )
            };
            vec![
                format!("{}", k + 1),
                run.measured.clone(),
                run.rows.to_string(),
                f(run.fixture_mm),
                run.fixture_fitted_mm.map(f).unwrap_or_default(),
                fmt_sig(run.rms_before_um, 3),
                fmt_sig(run.rms_after_um, 3),
            ]
        })
        .collect()
}

/// The calibrated parameters' rows (parameter, deviation, std) from the calibration report.
fn param_rows(r: &Report) -> Vec<Vec<String>> {
    r.params
        .iter()
        .map(|(k, v)| {
            vec![
                k.clone(),
                v.get("value").map(num).unwrap_or_default(),
                v.get("std").map(num).unwrap_or_default(),
            ]
        })
        .collect()
}

/// The rows (parameter, why) of the parameters held at nominal, from the calibration report.
fn undetermined_rows(r: &Report) -> Vec<Vec<String>> {
    r.undetermined
        .iter()
        .map(|u| vec![u.param.clone(), u.why.clone()])
        .collect()
}

/// The effects' rows (effect, parameter, value, std) from the calibration report.
fn effect_rows(r: &Report) -> Vec<Vec<String>> {
    let mut effects: Vec<Vec<String>> = Vec::new();
    for e in &r.effects {
        for (k, v) in &e.params {
            effects.push(vec![
                match e.joint {
                    Some(j) => format!("{} (joint {j})", e.effect),
                    None => e.effect.to_string(),
                },
                k.clone(),
                num(v),
                e.std.get(k).map(num).unwrap_or_default(),
            ]);
        }
    }
    effects
}

/// The candidates' rows (effect, form, held-out RMS, adopted) from the calibration report.
fn candidate_rows(r: &Report) -> Vec<Vec<String>> {
    r.candidates
        .iter()
        .map(|c| {
            vec![
                match c.joint {
                    Some(j) => format!("{} (joint {j})", c.effect),
                    None => c.effect.to_string(),
                },
                c.form.clone(),
                fmt_sig(c.heldout_rms_um, 3),
                if c.adopted { "yes" } else { "no" }.to_string(),
            ]
        })
        .collect()
}

/// The section of the segments and outliers found, from the calibration report; none when there
/// are neither.
fn faults_section(r: &Report) -> Option<Section> {
    if r.segments.is_empty() && r.outliers.is_empty() {
        return None;
    }
    let mut blocks = Vec::new();
    if !r.segments.is_empty() {
        let rows: Vec<Vec<String>> = r
            .segments
            .iter()
            .map(|g| {
                vec![
                    g.run.to_string(),
                    format!("{}..{}", g.from_row, g.to_row),
                    match (g.t_from_s, g.t_to_s) {
                        (Some(a), Some(b)) => {
                            format!("{}..{}", fmt_fixed(a, 2), fmt_fixed(b, 2))
                        }
                        _ => String::new(),
                    },
                    g.cause.to_string(),
                    format!(
                        "{}, {}, {}",
                        fmt_fixed(g.fixture_fitted_mm[0], 3),
                        fmt_fixed(g.fixture_fitted_mm[1], 3),
                        fmt_fixed(g.fixture_fitted_mm[2], 3)
                    ),
                    fmt_fixed(g.length_offset_mm, 4),
                ]
            })
            .collect();
        blocks.push(Block::table(
            &[
                "run",
                "rows",
                "t [s]",
                "cause",
                "fixture [mm]",
                "length zero [mm]",
            ],
            rows,
        ));
    }
    if !r.outliers.is_empty() {
        let rows: Vec<Vec<String>> = r
            .outliers
            .iter()
            .map(|o| {
                vec![
                    o.run.to_string(),
                    o.row.to_string(),
                    o.t_s.map(|t| fmt_fixed(t, 3)).unwrap_or_default(),
                    fmt_sig(o.residual_um, 3),
                ]
            })
            .collect();
        blocks.push(Block::table(
            &["run", "row", "t [s]", "residual [µm]"],
            rows,
        ));
    }
    Some(Section {
        heading: "Faults: segments and outliers".into(),
        blocks,
    })
}

/// The section of the effects fitted with the geometry, from the calibration report and the
/// effects' rows.
fn effects_section(r: &Report, effects: Vec<Vec<String>>) -> Section {
    let p = &r.predicted_position_std_um;
    let sizes: Vec<Vec<String>> = r
        .effect_sizes
        .iter()
        .map(|e| {
            vec![
                match e.joint {
                    Some(j) => format!("{} (joint {j})", e.effect),
                    None => e.effect.to_string(),
                },
                fmt_sig(e.workspace_rms_um, 3),
                fmt_sig(e.workspace_p95_um, 3),
                fmt_sig(e.measured_region_rms_um, 3),
                e.at.clone(),
                if e.delivered { "yes" } else { "no" }.to_string(),
                fmt_fixed(p.model_workspace_rms, 2),
                fmt_sig(e.prediction_without_um, 3),
            ]
        })
        .collect();
    let carried = if r.delivered.content == "geometry only" {
        "The robot file was written with the geometry only (--geometry-only): every command evaluates the robot without these effects, and the predicted accuracy includes what they do."
    } else {
        "The calibrated robot file carries them in its [effects] section (a URDF in the sidecar its header names): compensate, simulate and every command that evaluates the robot apply them."
    };
    Section {
            heading: "Effects fitted with the geometry".into(),
            blocks: vec![
                Block::text(carried),
                Block::table(&["effect", "parameter", "value", "std"], effects),
                Block::text(format!(
                    "What each effect does: the MAP displacement it causes, after a best rigid registration, over random poses of the joint space and where measured; the predicted accuracy over the joint space with it applied and without it. A thermal drift is referred to {}.",
                    r.delivered.thermal_reference
                )),
                Block::table(
                    &[
                        "effect",
                        "joint space RMS [µm]",
                        "p95 [µm]",
                        "where measured RMS [µm]",
                        "taken",
                        "in the robot file",
                        "predicted with it [µm]",
                        "predicted without it [µm]",
                    ],
                    sizes,
                ),
            ],
        }
}

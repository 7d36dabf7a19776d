//! The compensation page and the drift section: in = the `edbbgen.compensate/1` report (or a
//! [`Drift`]); out = a [`Page`] (or a [`Section`]) — the accuracy over the joint space with
//! nothing applied, with the mastering offsets only and with full compensation, the targets
//! before and after, the mastering offsets per axis; and for a calibration against a baseline,
//! what moved and how far the MAP moved over the joint space.

use super::{Block, Page, ReportError, Section};
use crate::compensate::drift::Drift;
use crate::compensate::offsets::Mastering;
use crate::compensate::Report;
use crate::plot::{Figure, Panel, Series};
use crate::units::{fmt_fixed, length_um};

/// Sorted per-pose values as a cumulative curve: (share of poses in %, value).
fn cumulative(v: &[f64]) -> Vec<(f64, f64)> {
    let n = v.len().max(1) as f64;
    v.iter()
        .enumerate()
        .map(|(k, s)| (100.0 * (k + 1) as f64 / n, *s))
        .collect()
}

fn accuracy_figure(r: &Report) -> Figure {
    let a = &r.accuracy;
    let mut series = vec![
        Series::line("nothing applied", 0, cumulative(&a.sorted_um.0)),
        Series::line(
            "mastering offsets only (model)",
            1,
            cumulative(&a.sorted_um.1),
        ),
    ];
    if let Some(f) = &a.predicted_full_um {
        series.push(Series::line(
            "full compensation (the calibration's predicted RMS)",
            2,
            vec![(0.0, f.rms), (100.0, f.rms)],
        ));
    }
    Figure {
        title: String::new(),
        panels: vec![Panel {
            title: format!(
                "TCP error over {} random joint poses, registered, sorted",
                a.poses
            ),
            x_label: "share of random joint poses [%]".into(),
            y_label: "TCP position error [µm]".into(),
            series,
            y_log: true,
            legend: crate::plot::Legend::Outside,
            ..Panel::default()
        }],
        columns: 1,
        panel_px: (960, 300),
    }
}

fn targets_figure(t: &crate::compensate::TargetsReport) -> Figure {
    Figure {
        title: String::new(),
        panels: vec![Panel {
            title: format!(
                "{}: the calibrated robot's TCP error at the targets, {} compensated of {}, sorted",
                t.file, t.compensated, t.rows
            ),
            x_label: "share of compensated targets [%]".into(),
            y_label: "TCP position error [µm]".into(),
            series: vec![
                Series::line("at the nominal joints", 0, cumulative(&t.sorted_um.0)),
                Series::line("at the compensated joints", 2, cumulative(&t.sorted_um.1)),
            ],
            y_log: true,
            legend: crate::plot::Legend::Outside,
            ..Panel::default()
        }],
        columns: 1,
        panel_px: (960, 260),
    }
}

pub fn page(r: &Report, robot: &str) -> Result<Page, ReportError> {
    let a = &r.accuracy;
    let facts = facts(r, robot);
    let mut sections = vec![Section {
        heading: "Accuracy over the joint space".into(),
        blocks: vec![
            Block::figure(
                "fig-accuracy",
                "The TCP of the calibrated robot against the nominal robot's at random joint poses within the limits, after a best rigid registration: commanded with the nominal joints (nothing applied) and with the mastering offsets applied; full compensation leaves the calibration's own predicted uncertainty.",
                &accuracy_figure(r),
            )?,
            Block::text(a.how.clone()),
        ],
    }];
    if let Some(t) = &r.targets {
        let mut blocks = vec![Block::figure(
            "fig-targets",
            "Per compensated target: how far the calibrated robot's TCP is from the target at the nominal joints (what a controller with the nominal model does) and at the compensated joints as written.",
            &targets_figure(t),
        )?];
        if !t.not_compensated.is_empty() {
            blocks.push(Block::table(
                &["line", "name", "why not compensated"],
                t.not_compensated
                    .iter()
                    .map(|n| {
                        vec![
                            n.line.to_string(),
                            n.name.clone().unwrap_or_default(),
                            n.status.clone(),
                        ]
                    })
                    .collect(),
            ));
        }
        sections.push(Section {
            heading: "Targets".into(),
            blocks,
        });
    }
    if let Some(m) = &r.mastering {
        sections.push(mastering_section(m));
    }
    Ok(Page {
        title: format!("edbbgen — compensation for {robot}"),
        kind: "compensate".into(),
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs_sha256: String::new(),
        facts,
        warnings: r.notes.clone(),
        sections,
    })
}

/// The page's facts: the robots, the tool point, the accuracy each way, the targets and the
/// program.
fn facts(r: &Report, robot: &str) -> Vec<(String, String)> {
    let a = &r.accuracy;
    let mut facts = vec![
        ("calibrated robot".to_string(), robot.to_string()),
        ("nominal robot".to_string(), r.nominal.clone()),
        (
            "TCP (flange frame)".into(),
            format!(
                "{}, {}, {} mm (nominal); {}, {}, {} mm (calibrated)",
                fmt_fixed(r.tcp_nominal_mm[0], 3),
                fmt_fixed(r.tcp_nominal_mm[1], 3),
                fmt_fixed(r.tcp_nominal_mm[2], 3),
                fmt_fixed(r.tcp_calibrated_mm[0], 3),
                fmt_fixed(r.tcp_calibrated_mm[1], 3),
                fmt_fixed(r.tcp_calibrated_mm[2], 3)
            ),
        ),
        ("controller axes".into(), r.controller.clone()),
        (
            "nothing applied".into(),
            format!(
                "{} RMS, {} p95",
                length_um(a.uncompensated_um.rms),
                length_um(a.uncompensated_um.p95)
            ),
        ),
        (
            "mastering offsets only".into(),
            match &a.predicted_offsets_only_um {
                Some(p) => format!(
                    "{} RMS, {} p95 predicted ({} RMS from the model)",
                    length_um(p.rms),
                    length_um(p.p95),
                    length_um(a.offsets_only_model_um.rms)
                ),
                None => format!(
                    "{} RMS from the model",
                    length_um(a.offsets_only_model_um.rms)
                ),
            },
        ),
        (
            "full compensation".into(),
            match &a.predicted_full_um {
                Some(p) => format!(
                    "{} RMS, {} p95 predicted (the calibration's)",
                    length_um(p.rms),
                    length_um(p.p95)
                ),
                None => "not stated: give --calibration REPORT.json".into(),
            },
        ),
    ];
    if let Some(t) = &r.targets {
        facts.push((
            "targets".into(),
            format!(
                "{}: {} of {} compensated; at the written joints {} max",
                t.file,
                t.compensated,
                t.rows,
                length_um(t.residual_um.max)
            ),
        ));
    }
    if let Some(p) = &r.program {
        facts.push((
            "program".into(),
            format!(
                "{} ({}): {} moves; {} decimals: {} RMS at the printed values",
                p.file,
                p.dialect,
                p.moves,
                p.decimals,
                length_um(p.printed_residual_um.rms)
            ),
        ));
    }
    facts
}

/// The mastering offsets per axis and where the controller keeps them.
fn mastering_section(m: &Mastering) -> Section {
    let rows = m
        .axes
        .iter()
        .zip(&m.instructions)
        .map(|(x, i)| {
            vec![
                x.axis.clone(),
                fmt_fixed(x.joint_delta_deg, 6),
                x.joint_std_deg.map(|v| fmt_fixed(v, 6)).unwrap_or_default(),
                format!("{} {}", fmt_fixed(x.delta, 6), x.units),
                i.clone(),
            ]
        })
        .collect();
    Section {
        heading: "Mastering offsets".into(),
        blocks: vec![
            Block::text(m.convention.clone()),
            Block::table(
                &[
                    "axis",
                    "joint zero Δθ [deg]",
                    "std [deg]",
                    "axis reading change",
                    "where the controller keeps it",
                ],
                rows,
            ),
        ],
    }
}

/// The drift section of a calibration page.
pub fn drift_section(d: &Drift) -> Result<Section, ReportError> {
    let fig = Figure {
        title: String::new(),
        panels: vec![Panel {
            title: format!(
                "MAP change since {} over random joint poses, sorted: RMS {}, p95 {}",
                d.baseline,
                length_um(d.map_change_um.rms),
                length_um(d.map_change_um.p95)
            ),
            x_label: "share of random joint poses [%]".into(),
            y_label: "MAP position change [µm]".into(),
            series: vec![Series::line("", 3, cumulative(&d.map_change_sorted_um))],
            ..Panel::default()
        }],
        columns: 1,
        panel_px: (960, 260),
    };
    let rows = d
        .changes
        .iter()
        .map(|c| {
            vec![
                c.param.clone(),
                format!("{} {}", fmt_fixed(c.baseline, 6), c.unit),
                format!("{} {}", fmt_fixed(c.now, 6), c.unit),
                format!("{} {}", fmt_fixed(c.change, 6), c.unit),
                format!("{} {}", fmt_fixed(c.std, 6), c.unit),
                fmt_fixed(c.ratio, 2),
                if c.moved {
                    "moved".into()
                } else {
                    String::new()
                },
            ]
        })
        .collect();
    let mut blocks = vec![
        Block::text(format!("Verdict: {}.", d.verdict)),
        Block::figure(
            "fig-drift",
            "How far the MAP of the robot calibrated now is from the baseline's, at random joint poses within the limits (not registered).",
            &fig,
        )?,
        Block::text(format!(
            "A parameter moved when its change exceeds {} combined standard uncertainties (the new fit's and the baseline's in quadrature; the prior where the baseline did not determine it). The new data's residual with the baseline robot: {} RMS.",
            fmt_fixed(d.threshold, 1),
            length_um(d.rms_with_baseline_um)
        )),
        Block::table(
            &["parameter", "baseline", "now", "change", "std", "|change| / std", ""],
            rows,
        ),
    ];
    if !d.held_at_baseline.is_empty() {
        blocks.push(Block::text(format!(
            "Not determined by these data, held at the baseline's values: {}.",
            d.held_at_baseline.join(", ")
        )));
    }
    Ok(Section {
        heading: format!("Drift since {}", d.baseline),
        blocks,
    })
}

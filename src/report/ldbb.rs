//! The LDBB page: in = an [`Analysis`]; out = a [`Page`] with the paper's Figs. 13–15, the
//! compliance along the bar, the fits and the stiffnesses — the numbers of the
//! `edbbgen.ldbb/1` report.

use super::{Block, Page, ReportError, Section};
use crate::ldbb::stiffness::Stiffness;
use crate::ldbb::{plot, Analysis, Report, SineModel, SineReport, StiffnessReport};
use crate::units::{fmt_fixed, fmt_sig, length_um};

fn sine_row(name: &str, s: &SineReport) -> Vec<String> {
    let sd = |v: Option<f64>, d: usize| v.map(|x| fmt_fixed(x, d)).unwrap_or_else(|| "-".into());
    vec![
        name.to_string(),
        format!("{} ± {}", fmt_fixed(s.a_mm, 4), sd(s.std.a_mm, 4)),
        if s.model == SineModel::Linear {
            "1 (held)".into()
        } else {
            format!("{} ± {}", fmt_fixed(s.b, 4), sd(s.std.b, 4))
        },
        format!("{} ± {}", fmt_fixed(s.phi_deg, 2), sd(s.std.phi_deg, 2)),
        fmt_sig(s.offset_um, 3),
        fmt_sig(s.rms_um, 3),
    ]
}

/// `source`: what was analysed (file names); `inputs_sha256` the hash of the inputs.
pub fn page(a: &Analysis, source: &str, inputs_sha256: &str) -> Result<Page, ReportError> {
    let r = &a.report;
    let facts = facts(r, source);
    let mut figs = plot::figures(a).into_iter();
    let mut fig = |caption: &str| -> Result<Block, ReportError> {
        let (id, f) = figs.next().expect("one figure per caption");
        Ok(Block::figure(id, caption, &f)?)
    };
    let mut sections = vec![
        Section {
            heading: "Loaded circles (Fig. 13)".into(),
            blocks: vec![
                fig("(a) The LVDT's deflection per load: the mean of the repeats on a common angle grid.")?,
                fig("(b) Eq. 8 with the mechanical base load reference: each load's mean less the lowest load's. 'AL' is the apparent load, the load difference.")?,
            ],
        },
        Section {
            heading: "Compliance along the bar".into(),
            blocks: vec![fig(
                "The least-squares slope of the load means against the load, per angle, with its standard uncertainty (the larger of the repeatability and the scatter about the line, pooled over ±5°).",
            )?],
        },
        Section {
            heading: "Compensated trajectories and the centring sine (Fig. 14)".into(),
            blocks: vec![
                fig("(a) Each load's mean less compliance × load: the trajectory extrapolated to zero load. Their spread measures how far the compliance is from linear in the load.")?,
                fig("(b) Their average and the fitted centring sine a·sin(bθ − φ) + offset (Eq. 9); the nonlinear fit is drawn when it disagrees with the linear one or is the one used.")?,
                Block::table(
                    &["fit", "a [mm]", "b", "φ [deg]", "offset [µm]", "RMS about it [µm]"],
                    std::iter::once(sine_row("linear (b = 1)", &r.sine_fits.linear))
                        .chain(r.sine_fits.nonlinear.iter().map(|n| sine_row("nonlinear (b free)", n)))
                        .collect(),
                ),
                Block::text("Uncertainties are one standard deviation from the residual, inflated for its correlation along the circle. A centring offset produces b = 1; the bar cannot tell it from the first harmonic of the kinematic error."),
            ],
        },
        Section {
            heading: "Kinematic error (Fig. 15)".into(),
            blocks: vec![fig(
                "The averaged compensated trajectory less the sine: the robot's kinematic error along the bar without its mean and first harmonic; with the laser-tracker reference (mean removed, and without its first harmonic) when given.",
            )?],
        },
    ];
    if let (Some(st), Some(sr)) = (&a.stiffness, &r.stiffness) {
        sections.push(stiffness_section(st, sr));
    }
    Ok(Page {
        title: "edbbgen — LDBB loaded circle analysis".into(),
        kind: "ldbb".into(),
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs_sha256: inputs_sha256.to_string(),
        facts,
        warnings: r.warnings.clone(),
        sections,
    })
}

/// The page's facts: the data, the loads, the noise, the compliance, the sine, the error.
fn facts(r: &Report, source: &str) -> Vec<(String, String)> {
    let mut facts = vec![
        ("data".to_string(), source.to_string()),
        (
            "loads".into(),
            format!(
                "{} N, {} repeat(s) each, {} rows",
                r.loads_n
                    .iter()
                    .map(|f| fmt_fixed(*f, 0))
                    .collect::<Vec<_>>()
                    .join(", "),
                r.repeats,
                r.rows
            ),
        ),
        ("angle grid".into(), format!("{} deg", r.grid_step_deg)),
        (
            "LVDT noise (robust, per sample)".into(),
            length_um(r.noise_um),
        ),
        (
            "compliance along the bar".into(),
            format!("RMS {}/N", length_um(r.compliance_rms_um_per_n)),
        ),
        ("linearity spread".into(), length_um(r.linearity_spread_um)),
        (
            "centring sine".into(),
            format!(
                "a {} mm, b {}, φ {}° ({})",
                fmt_fixed(r.sine_fit.a_mm, 4),
                fmt_fixed(r.sine_fit.b, 4),
                fmt_fixed(r.sine_fit.phi_deg, 2),
                if r.sine_fit.model == SineModel::Linear {
                    "linear fit, b = 1"
                } else {
                    "nonlinear fit, b free"
                }
            ),
        ),
        (
            "kinematic error along the bar".into(),
            format!("RMS {}", length_um(r.kinematic_error_rms_um)),
        ),
    ];
    if let Some(rf) = &r.reference {
        facts.push((
            "against the reference".into(),
            format!(
                "mean |difference| {} (RMS {}; {} without the first harmonic)",
                length_um(rf.mean_abs_difference_um),
                length_um(rf.rms_difference_um),
                length_um(rf.mean_abs_difference_first_harmonic_removed_um)
            ),
        ));
    }
    facts
}

/// The joint stiffnesses and the combinations the circle determines.
fn stiffness_section(st: &Stiffness, sr: &StiffnessReport) -> Section {
    let rows: Vec<Vec<String>> = (0..6)
        .map(|i| {
            vec![
                (i + 1).to_string(),
                st.stiffness_nm_per_rad[i]
                    .map(|k| format!("{k:.4e}"))
                    .unwrap_or_else(|| "-".into()),
                st.std_nm_per_rad[i]
                    .map(|k| format!("{k:.2e}"))
                    .unwrap_or_else(|| "-".into()),
                st.why[i].clone().unwrap_or_default(),
            ]
        })
        .collect();
    let combos: Vec<Vec<String>> = sr
        .combinations
        .iter()
        .map(|c| {
            let terms: Vec<String> = c
                .joints
                .iter()
                .zip(&c.weights)
                .map(|(j, w)| format!("{}/k{j}", fmt_fixed(*w, 3)))
                .collect();
            vec![
                terms.join(" + "),
                format!("{:.4e} ± {:.2e}", c.compliance_rad_per_nm, c.std_rad_per_nm),
                c.effective_stiffness_nm_per_rad
                    .map(|k| format!("{k:.4e}"))
                    .unwrap_or_else(|| "-".into()),
            ]
        })
        .collect();
    let mut blocks = vec![
        Block::text(format!(
            "c(θ) = uᵀ Jₚ K⁻¹ Jₚᵀ u with Jₚ the tool ball's positional Jacobian at the {} joint angles and u the bar direction. A stiffness is given where the circle determines it (relative standard uncertainty ≤ {} %); the fit leaves {}/N RMS.",
            if sr.joint_angles == "recorded" { "recorded" } else { "IK" },
            fmt_fixed(sr.relative_std_limit * 100.0, 0),
            length_um(sr.fit_rms_um_per_n)
        )),
        Block::table(&["joint", "stiffness [N·m/rad]", "std", "why not determined"], rows),
    ];
    if !combos.is_empty() {
        blocks.push(Block::text(
            "Combinations the circle determines where single joints are not:",
        ));
        blocks.push(Block::table(
            &[
                "combination",
                "value [rad/(N·m)]",
                "effective stiffness [N·m/rad]",
            ],
            combos,
        ));
    }
    Section {
        heading: "Joint stiffness".into(),
        blocks,
    }
}

//! The calibration report's parts: in = the converged fit, its held-out score and its
//! uncertainty; out = the warnings, the per-run lines, the parameters left undetermined and
//! why, the segments, outliers and candidates, the tool point and the verdict.

use super::delivered::{self, EffectSize, FileModel};
use super::steps::{Fit, HeldOutScore};
use super::uncertainty::{confounding, Uncertainty};
use super::{
    predict, prior, round, CalibrateOptions, CandidateReport, Delivered, Effects, OutlierReport,
    Predicted, RunReport, SegmentReport, SetupReport, ToolReport, Undetermined, FLAG_SIGMAS,
    STEEL_EXPANSION, WRITE_SHARE,
};
use crate::diagnose::fit::{self, accumulate, model_cols, score, structural, Known};
use crate::diagnose::{self, Basis, Estimate, Param, Problem};
use crate::model::{MeasurementModel, Status, MAP};
use crate::robot::effects::ThermalState;
use crate::robot::Robot;
use crate::twin::effects::Effect;
use crate::units::{fmt_fixed, length_um, DEG, MM};
use nalgebra::Vector3;

/// What the residual says, and every warning of the report in order.
pub(super) struct Diagnostics {
    pub warnings: Vec<String>,
    /// One reading's noise (m; 0 when the data cannot tell it), [`Diagnostics::noise`] says
    /// how it was found.
    pub noise_hf: f64,
    pub noise: crate::diagnose::noise::Noise,
    pub rms_after: f64,
    /// Structure clearly above the noise is left in the residual.
    pub structure: bool,
}

pub(super) fn diagnostics(
    model: &MeasurementModel,
    problem: &Problem,
    known: &Known,
    f: &Fit,
    u: &Uncertainty,
    opts: &CalibrateOptions,
) -> Diagnostics {
    let (est, free) = (&f.est, &f.free);
    let mut warnings = f.warnings.clone();
    // An effect the data cannot tell from the geometry makes the geometry uncertain: say which.
    if let Some(w) = confounding(
        &f.fitted,
        free,
        est,
        u.sigma_eff,
        model,
        &u.calibrated,
        &u.space,
    ) {
        warnings.push(w);
    }
    let live = fit::kept_values(&f.fitted.residual, &problem.weight);
    let neighbours = crate::diagnose::noise::Neighbours::new(problem);
    let noise = crate::diagnose::noise::reading_noise(
        problem,
        &neighbours,
        &f.fitted.residual,
        opts.noise,
        false,
    );
    let noise_hf = noise.or(0.0);
    let rms_after = fit::rms(&live);
    // Structure above the noise: the residual clearly larger than the noise, or a lag-1
    // correlation white noise of this length would not show (5 standard errors).
    let kept_rows = problem.kept().max(1);
    let rho_limit = (5.0 / (kept_rows as f64).sqrt()).max(0.1);
    let structure = (noise.known() && rms_after > 1.25 * noise_hf) || f.rho > rho_limit;
    if !noise.known() {
        warnings.push(format!(
            "the reading noise is {}: whether the residual (RMS {}) holds more than noise is not decided",
            noise.source.describe(noise.within_deg),
            length_um(rms_after * 1e6)
        ));
    }
    if structure {
        let hint = match opts.effects {
            Effects::None => "; fit the effects with --effects auto",
            _ => "",
        };
        warnings.push(format!(
            "structure above the noise is left in the residual (RMS {} against {} of reading noise ({}), lag-1 autocorrelation {}): the model misses an effect, and the geometry absorbs part of it{hint}",
            length_um(rms_after * 1e6),
            length_um(noise_hf * 1e6),
            noise.source.describe(noise.within_deg),
            fmt_fixed(f.rho, 2)
        ));
    }
    // A uniform expansion is a scale the geometry absorbs: a thermal drift the model leaves
    // out need not show in the residual. The temperature log says it is there all the same.
    let thermal_fitted = est.effects.iter().any(|t| t.effect == Effect::ThermalDrift);
    if let (false, Some(dt)) = (thermal_fitted, problem.temperature_change()) {
        let reach = u
            .region
            .iter()
            .map(|q| model.map_position(&u.calibrated, q).norm())
            .fold(0.0f64, f64::max);
        let growth = STEEL_EXPANSION * dt * reach;
        if growth > noise_hf {
            let hint = match opts.effects {
                Effects::Auto => "",
                _ => "; fit the effects with --effects auto",
            };
            warnings.push(format!(
                "the logged temperature changed by {} K during the runs: about {} of thermal growth at the MAP's {} mm reach (steel, {} per K), which the model leaves to the geometry{hint}",
                fmt_fixed(dt, 2),
                length_um(growth * 1e6),
                fmt_fixed(reach * 1e3, 0),
                STEEL_EXPANSION
            ));
        }
    }
    if let Some(w) = extrapolated(problem, est, u) {
        warnings.push(w);
    }
    if opts.fixture_known {
        if let Some(w) = fixture_check(problem, est, free) {
            warnings.push(w);
        }
    }
    warnings.extend(flagged(problem, known, f, opts));
    Diagnostics {
        warnings,
        noise_hf,
        noise,
        rms_after,
        structure,
    }
}

/// A parameter that moved by several prior sigmas: the prior (or the given value) was off. A
/// segment's own fixture or zero is a step (reported as one); a free length zero has no given
/// value.
fn flagged(problem: &Problem, known: &Known, f: &Fit, opts: &CalibrateOptions) -> Vec<String> {
    let mut out = Vec::new();
    for q in &f.free {
        let flagged = match *q {
            Param::Fixture { group, .. } => problem.fix_groups[group].given,
            Param::Offset { group } => problem.off_groups[group].given && known.offset,
            Param::Shared(_) => true,
        };
        let dev = f.est.get(*q) - f.nominal.get(*q);
        let p = prior(opts, *q);
        if flagged && dev.abs() > FLAG_SIGMAS * p {
            let (u, unit) = if q.is_angle() {
                (DEG, "deg")
            } else {
                (MM, "mm")
            };
            let check = match q {
                Param::Shared(i) if crate::model::is_map(*i) => "check --tool",
                Param::Fixture { .. } => "check --fixture",
                Param::Offset { .. } => "check the bar's zero (--length-offset)",
                _ => "check the robot file, or widen --prior if such deviations are expected",
            };
            out.push(format!(
                "{} moved by {} {unit} from its {} value, more than {} prior sigmas ({} {unit}): {check}",
                problem.param_name(*q),
                fmt_fixed(dev / u, 4),
                if q.is_setup() { "given" } else { "nominal" },
                fmt_fixed(FLAG_SIGMAS, 0),
                fmt_fixed(p / u, 4)
            ));
        }
    }
    out
}

/// With the fixture held (`--fixture-known`): does estimating it explain clearly more (BIC,
/// and a tenth of the residual)? Then the given position is probably off, and the geometry
/// absorbs it.
/// and a tenth of the residual)? Then the given position is probably off, and the geometry
/// absorbs it.
fn fixture_check(problem: &Problem, est: &Estimate, free: &[Param]) -> Option<String> {
    let (_, with_fixture) = structural(problem, &Known::default(), est);
    let extra: Vec<Param> = with_fixture
        .iter()
        .filter(|q| matches!(q, Param::Fixture { .. }) && !free.contains(q))
        .copied()
        .collect();
    if extra.is_empty() {
        return None;
    }
    let mut cols = model_cols(est, free);
    let base = cols.len();
    cols.extend(extra.iter().map(|&q| fit::Col::Geo(q)));
    let st = accumulate(problem, est, &cols, 1);
    let sel0: Vec<usize> = (0..base).collect();
    let sel1: Vec<usize> = (0..cols.len()).collect();
    let (rss0, _, bic0, _) = score(&st, &sel0);
    let (rss1, _, bic1, _) = score(&st, &sel1);
    let n = problem.kept().max(1) as f64;
    (bic1 < bic0 - 10.0 && rss1 < 0.9 * rss0).then(|| {
        format!(
            "the fixture position looks off: estimating it lowers the residual from {} to {} RMS; check --fixture, or leave out --fixture-known",
            length_um((rss0 / n).sqrt() * 1e6),
            length_um((rss1 / n).sqrt() * 1e6)
        )
    })
}

/// The standard uncertainty (mm) of a free parameter, None for one held.
fn std_of(free: &[Param], var: &[f64], q: Param) -> Option<f64> {
    free.iter()
        .position(|x| *x == q)
        .map(|a| round(var[a].max(0.0).sqrt() / MM, 6))
}

/// One line per run: its fixture as given and fitted, its zero and residuals.
/// The joints' measured ranges (rad), over the rows the fit kept.
pub(super) fn joint_ranges(problem: &Problem) -> [[f64; 2]; 6] {
    let mut r = [[f64::INFINITY, f64::NEG_INFINITY]; 6];
    for (q, w) in problem.m.q.iter().zip(&problem.weight) {
        if *w > 0.0 {
            for (r, q) in r.iter_mut().zip(q) {
                r[0] = r[0].min(*q);
                r[1] = r[1].max(*q);
            }
        }
    }
    r
}

/// A cyclic error's form beyond the joint range the data reached rests on a bound, not on the
/// data: say so when that bound is most of the prediction over the joint space.
fn extrapolated(problem: &Problem, est: &Estimate, u: &Uncertainty) -> Option<String> {
    let m = u.predicted.from_effect_model;
    if !(m.workspace_rms > 1.0 && m.workspace_rms > 3.0 * m.measured_region_rms) {
        return None;
    }
    let ranges = joint_ranges(problem);
    let joints: Vec<String> = est
        .effects
        .iter()
        .filter_map(|t| match t.effect {
            Effect::CyclicError(j) => Some(format!(
                "joint {} measured over {}..{} deg",
                j + 1,
                fmt_fixed(ranges[j][0] / DEG, 1),
                fmt_fixed(ranges[j][1] / DEG, 1)
            )),
            _ => None,
        })
        .collect();
    Some(format!(
        "a cyclic error is extrapolated beyond the range measured ({}): harmonics of the next orders, as large as those fitted, that the data cannot exclude put {} RMS into the prediction over the joint space ({} where measured); measure the joint over more of its turn to bound them",
        joints.join(", "),
        length_um(m.workspace_rms),
        length_um(m.measured_region_rms)
    ))
}

pub(super) fn runs(
    problem: &Problem,
    f: &Fit,
    var: &[f64],
    labels: &[String],
    residual_nominal: &[f64],
) -> Vec<RunReport> {
    let (est, free, residual) = (&f.est, &f.free, &f.fitted.residual);
    let mut out = Vec::with_capacity(problem.runs());
    for (r, range) in problem.ranges.iter().enumerate() {
        let fixture_fitted = free
            .iter()
            .any(|q| matches!(q, Param::Fixture { group, .. } if *group == r));
        let kept_r: Vec<usize> = range.clone().filter(|&k| problem.weight[k] > 0.0).collect();
        let rms_kept = |v: &[f64]| -> f64 {
            (kept_r.iter().map(|&k| v[k] * v[k]).sum::<f64>() / kept_r.len().max(1) as f64).sqrt()
        };
        let fixture_mm: [f64; 3] = problem.fixtures[r].map(|v| round(v / MM, 6)).into();
        out.push(RunReport {
            measured: labels.get(r).cloned().unwrap_or_default(),
            fixture_mm,
            rows: range.len(),
            rms_before_um: round(rms_kept(residual_nominal) * 1e6, 3),
            rms_after_um: round(rms_kept(residual) * 1e6, 3),
            fixture_fitted_mm: fixture_fitted
                .then(|| est.fixtures[r].map(|v| round(v / MM, 6)).into()),
            fixture_std_mm: fixture_fitted.then(|| {
                [0, 1, 2].map(|axis| std_of(free, var, Param::Fixture { group: r, axis }))
            }),
            fixture_moved_mm: fixture_fitted
                .then(|| round((est.fixtures[r] - problem.fixtures[r]).norm() / MM, 6)),
            length_offset_mm: round(est.offsets[r] / MM, 6),
            length_offset_std_mm: std_of(free, var, Param::Offset { group: r }),
            form: problem.forms[r].name(),
            rows_used: kept_r.len(),
        });
    }
    out
}

/// The parameters not moved: held by assumption (names), or undetermined with the reason.
pub(super) fn undetermined(
    problem: &Problem,
    f: &Fit,
    status: &[(Param, Status)],
    opts: &CalibrateOptions,
) -> (Vec<Undetermined>, Vec<String>) {
    let mut undetermined = Vec::new();
    let mut held = Vec::new();
    for (q, st) in status {
        if f.free.contains(q) {
            continue;
        }
        let name = problem.param_name(*q);
        let unit = |q: &Param| {
            if q.is_angle() {
                (DEG, "deg")
            } else {
                (MM, "mm")
            }
        };
        let why = match st {
            Status::Known => {
                held.push(name);
                continue;
            }
            Status::Dependent { on } => format!("dependent on {}", on.join(", ")),
            Status::Negligible => {
                "no influence on the bar length at the recorded poses".to_string()
            }
            Status::Identifiable => match f.weak.iter().find(|(w, _)| w == q) {
                Some((_, sd)) if *sd < 1e3 * prior(opts, *q) => {
                    let (u, name) = unit(q);
                    format!(
                        "not determined by these data: its standard uncertainty would be {} {name}, more than the prior {} {name} / {}",
                        fmt_fixed(sd / u, 4),
                        fmt_fixed(prior(opts, *q) / u, 4),
                        fmt_fixed(opts.kappa, 1)
                    )
                }
                Some(_) => {
                    "not determined by these data: they do not constrain it (its uncertainty would exceed a thousand priors)".to_string()
                }
                None => "not determined by these data".to_string(),
            },
        };
        undetermined.push(Undetermined { param: name, why });
    }
    (undetermined, held)
}

/// The segments of every split run.
pub(super) fn segments(problem: &Problem, est: &Estimate) -> Vec<SegmentReport> {
    let mut segments = Vec::new();
    for (r, range) in problem.ranges.iter().enumerate() {
        let mut cuts: Vec<usize> = problem
            .fix_groups
            .iter()
            .chain(&problem.off_groups)
            .filter(|g| g.run == r && !g.given && !g.rows.is_empty())
            .map(|g| g.rows.start)
            .collect();
        if cuts.is_empty() {
            continue;
        }
        cuts.push(range.start);
        cuts.push(range.end);
        cuts.sort_unstable();
        cuts.dedup();
        let timed = problem.forms[r].timed();
        for w in cuts.windows(2) {
            let (a, b) = (w[0], w[1]);
            if a >= b {
                continue;
            }
            let starts =
                |groups: &[fit::Group]| groups.iter().any(|g| g.rows.start == a && !g.given);
            let cause = match (
                a == range.start,
                starts(&problem.fix_groups),
                starts(&problem.off_groups),
            ) {
                (true, _, _) => "run start",
                (false, true, true) => "fixture moved and length zero changed",
                (false, true, false) => "fixture moved",
                _ => "length zero changed",
            };
            segments.push(SegmentReport {
                run: r + 1,
                from_row: a - range.start + 1,
                to_row: b - range.start,
                t_from_s: timed.then(|| round(problem.m.t[a], 3)),
                t_to_s: timed.then(|| round(problem.m.t[b - 1], 3)),
                cause,
                fixture_fitted_mm: est.fixtures[problem.fixture_group_of(a)]
                    .map(|v| round(v / MM, 6))
                    .into(),
                length_offset_mm: round(est.offsets[problem.offset_group_of(a)] / MM, 6),
            });
        }
    }
    segments
}

/// The rows dropped as outliers.
pub(super) fn outliers(problem: &Problem, residual: &[f64]) -> Vec<OutlierReport> {
    (0..problem.rows())
        .filter(|&k| problem.weight[k] <= 0.0 && problem.base_weight[k] > 0.0)
        .map(|k| {
            let r = problem.run_of(k);
            OutlierReport {
                run: r + 1,
                row: k - problem.ranges[r].start + 1,
                t_s: problem.forms[r].timed().then(|| round(problem.m.t[k], 3)),
                residual_um: round(residual[k] * 1e6, 3),
            }
        })
        .collect()
}

/// Every effect considered, with its held-out score; an effect the user listed is adopted.
pub(super) fn candidates(
    f: &Fit,
    opts: &CalibrateOptions,
    heldout_cal: f64,
) -> Vec<CandidateReport> {
    let est = &f.est;
    let mut candidates: Vec<CandidateReport> = f
        .candidates
        .iter()
        .map(|c| CandidateReport {
            effect: c.effect.name(),
            joint: c.effect.joint(),
            heldout_rms_um: round(c.heldout_rms * 1e6, 3),
            adopted: c.adopted && est.effects.iter().any(|t| t.effect == c.effect)
                || c.effect == Effect::Geometric,
            form: if c.effect == Effect::Geometric {
                "geometry".into()
            } else {
                diagnose::form_name(c.effect, c.basis)
            },
        })
        .collect();
    if let Effects::List(v) = &opts.effects {
        for e in v {
            let b = est
                .effects
                .iter()
                .find(|t| t.effect == *e)
                .map_or(Basis::Standard, |t| t.basis);
            candidates.push(CandidateReport {
                effect: e.name(),
                joint: e.joint(),
                heldout_rms_um: round(heldout_cal * 1e6, 3),
                adopted: true,
                form: diagnose::form_name(*e, b),
            });
        }
    }
    candidates
}

/// The verdict: something of the robot determined, better than nominal held out, and a
/// predicted uncertainty well under the priors'.
pub(super) fn verdict(
    problem: &Problem,
    f: &Fit,
    held_out: &HeldOutScore,
    u: &Uncertainty,
    opts: &CalibrateOptions,
    residual_structure: bool,
) -> (bool, String) {
    let (heldout_cal, heldout_nom) = (held_out.calibrated, held_out.nominal);
    let robot_determined = f.free.iter().any(|q| !q.is_setup());
    if !robot_determined {
        let closest = f
            .weak
            .iter()
            .filter(|(q, _)| !q.is_setup())
            .min_by(|a, b| (a.1 / prior(opts, a.0)).total_cmp(&(b.1 / prior(opts, b.0))));
        let detail = match closest {
            Some((q, sd)) if sd.is_finite() && *sd < 1e3 * prior(opts, *q) => format!(
                " (the best seen, {}, would have {} prior sigmas of uncertainty)",
                problem.param_name(*q),
                fmt_fixed(sd / prior(opts, *q), 2)
            ),
            _ => String::new(),
        };
        (
            false,
            format!(
                "not calibrated: no parameter of the robot is determined by these data{detail}; measure more poses over a wider range of every joint, or check the set-up (--tool, --fixture, --length-offset)"
            ),
        )
    } else if heldout_cal >= heldout_nom {
        let effects_hint = match (&opts.effects, residual_structure) {
            (Effects::Auto, _) | (_, false) => "",
            _ => ", fit the effects (--effects auto)",
        };
        (
            false,
            format!(
                "not calibrated: held out, the calibrated robot predicts the readings no better than the nominal one ({} against {} RMS); the data show no deviation the geometry explains: check the set-up (--tool, --fixture, --length-offset){effects_hint} or measure over a wider range",
                length_um(heldout_cal * 1e6),
                length_um(heldout_nom * 1e6)
            ),
        )
    } else if u.space_rms >= WRITE_SHARE * u.nominal_prior_rms * 1e6 {
        (
            false,
            format!(
                "not calibrated: its predicted position uncertainty over the joint space ({} RMS, mostly from the parameters these data cannot determine) is not under half of what the priors say of the nominal robot ({}); measure over a wider range of every joint",
                length_um(u.space_rms),
                length_um(u.nominal_prior_rms * 1e6)
            ),
        )
    } else {
        (
            true,
            format!(
                "calibrated: held out, the calibrated robot predicts the readings to {} RMS against {} for the nominal one",
                length_um(heldout_cal * 1e6),
                length_um(heldout_nom * 1e6)
            ),
        )
    }
}

/// The set-up found with the nominal geometry, when the robot itself is not calibrated: the
/// tool point, each run's fixture (first segment) and length zero with their standard
/// uncertainties, and how close the data put the true geometry to the nominal one. Delivered
/// (written into the robot file with the nominal geometry) when the data determine the tool
/// point or a whole fixture; a length zero alone is no robot's property.
pub(super) fn setup(
    model: &MeasurementModel,
    problem: &Problem,
    f: &Fit,
    held_out: &HeldOutScore,
    u: &Uncertainty,
    robot_determined: bool,
) -> SetupReport {
    let (e, fitted) = &held_out.setup;
    let free = &fitted.free;
    // Type A of the set-up-only fit: its residual holds what the nominal geometry leaves,
    // counted as the independent readings it is worth.
    let kept = fit::kept_values(&fitted.residual, &problem.weight);
    let dof = kept.len().saturating_sub(free.len()).max(1) as f64;
    let s2 = fitted.rss / dof * fit::correlation_time(&kept);
    let cov = fit::inverse(&fitted.normal) * s2;
    let var: Vec<f64> = (0..cov.nrows()).map(|k| cov[(k, k)]).collect();
    let tool_std = [0, 1, 2].map(|a| std_of(free, &var, Param::Shared(MAP + a)));
    let runs = problem.runs();
    let whole_fixture =
        |r: usize| (0..3).all(|axis| free.contains(&Param::Fixture { group: r, axis }));
    let delivered = tool_std.iter().any(Option::is_some) || (0..runs).any(whole_fixture);
    // The geometry: the calibrated one's distance from the nominal (same tool point) over the
    // joint space after a best rigid registration, plus twice its predicted uncertainty.
    let within = robot_determined.then(|| {
        let mut cal = f.est.params(0);
        cal.map = e.params(0).map;
        let nom = e.params(0);
        let a: Vec<Vector3<f64>> = u
            .space
            .iter()
            .map(|q| model.map_position(&cal, q))
            .collect();
        let b: Vec<Vector3<f64>> = u
            .space
            .iter()
            .map(|q| model.map_position(&nom, q))
            .collect();
        let d = predict::register(&a, &b).0;
        round(d * 1e6 + 2.0 * u.space_rms, 3)
    });
    SetupReport {
        delivered,
        tool_mm: [0, 1, 2].map(|a| round(e.p[MAP + a] / MM, 6)),
        tool_std_mm: tool_std,
        fixtures_mm: (0..runs)
            .map(|r| e.fixtures[r].map(|v| round(v / MM, 6)).into())
            .collect(),
        fixtures_std_mm: (0..runs)
            .map(|r| [0, 1, 2].map(|axis| std_of(free, &var, Param::Fixture { group: r, axis })))
            .collect(),
        length_offsets_mm: (0..runs).map(|r| round(e.offsets[r] / MM, 6)).collect(),
        length_offsets_std_mm: (0..runs)
            .map(|r| std_of(free, &var, Param::Offset { group: r }))
            .collect(),
        heldout_rms_um: round(held_out.nominal * 1e6, 3),
        geometry_within_um: within,
    }
}

/// The tool point as given and as fitted.
pub(super) fn tool(f: &Fit, var: &[f64]) -> ToolReport {
    let tool_std = [0, 1, 2].map(|a| std_of(&f.free, var, Param::Shared(MAP + a)));
    let map_given = Vector3::new(f.nominal.p[MAP], f.nominal.p[MAP + 1], f.nominal.p[MAP + 2]);
    let map_fitted = Vector3::new(f.est.p[MAP], f.est.p[MAP + 1], f.est.p[MAP + 2]);
    ToolReport {
        given_mm: map_given.map(|v| round(v / MM, 6)).into(),
        fitted_mm: map_fitted.map(|v| round(v / MM, 6)).into(),
        std_mm: tool_std,
        moved_mm: round((map_fitted - map_given).norm() / MM, 6),
    }
}

/// Poses of the recorded motion the servo lag is sized along.
const MOTION_ROWS: usize = 2000;

/// Each adopted effect's size over the joint space, the prediction of what the written files
/// deliver (an effect they leave out adds its size, pose by pose), the per-pose prediction
/// (µm) and what is delivered.
pub(super) fn delivered(
    model: &MeasurementModel,
    robot: &Robot,
    problem: &Problem,
    f: &Fit,
    u: &Uncertainty,
    file: &FileModel,
    opts: &CalibrateOptions,
) -> (Vec<EffectSize>, Predicted, Vec<f64>, Delivered) {
    let adopted: Vec<Effect> = f.est.effects.iter().map(|t| t.effect).collect();
    // A drift is sized where the runs ended (a lag) or at the logged temperature farthest
    // from the reference.
    let drift = match &file.effects.thermal {
        Some(crate::robot::effects::Thermal::Lag { .. }) => (
            ThermalState::Elapsed(problem.span()),
            format!(
                "the end of the runs (t = {} s)",
                fmt_fixed(problem.span(), 0)
            ),
        ),
        Some(crate::robot::effects::Thermal::Temperature { reference_c, .. }) => {
            let far = problem
                .m
                .temp
                .iter()
                .flatten()
                .copied()
                .max_by(|a, b| (a - reference_c).abs().total_cmp(&(b - reference_c).abs()))
                .unwrap_or(*reference_c);
            (
                ThermalState::Temperature(far),
                format!(
                    "{} C, the logged temperature farthest from the reference",
                    fmt_fixed(far, 2)
                ),
            )
        }
        None => (ThermalState::Reference, String::new()),
    };
    let moving: Vec<usize> = (0..problem.rows())
        .filter(|&k| problem.weight[k] > 0.0 && problem.velocity(k).iter().any(|v| *v != 0.0))
        .collect();
    let stride = moving.len().div_ceil(MOTION_ROWS).max(1);
    let motion: Vec<([f64; 6], [f64; 6])> = moving
        .iter()
        .step_by(stride)
        .map(|&k| (problem.m.q[k], problem.velocity(k)))
        .collect();
    let mut sizes = delivered::sizes(
        model,
        robot,
        file,
        &adopted,
        &u.space,
        &u.region,
        drift,
        &motion,
        opts.write_effects,
    );
    // The model's own per-pose uncertainty (µm); an effect left out adds its size.
    let mut space_std = u.space_std.clone();
    let mut not_delivered = Vec::new();
    for (effect, per_pose, size) in sizes.iter_mut() {
        let without: Vec<f64> = u
            .space_std
            .iter()
            .zip(per_pose.iter())
            .map(|(a, b)| a.hypot(b * 1e6))
            .collect();
        if size.acts_on == "pose" {
            size.prediction_without_um = round(predict::spread(&without).rms, 3);
        } else {
            size.prediction_without_um = u.predicted.workspace_rms;
        }
        if !opts.write_effects {
            let name = match effect.joint() {
                Some(j) => format!("{} (joint {j})", effect.name()),
                None => effect.name().to_string(),
            };
            not_delivered.push(format!(
                "{name}: left out of the robot file (--geometry-only); {} RMS over the joint space ({})",
                length_um(size.workspace_rms_um),
                size.at
            ));
            if size.acts_on == "pose" {
                for (s, b) in space_std.iter_mut().zip(per_pose.iter()) {
                    *s = s.hypot(b * 1e6);
                }
            }
        }
    }
    let mut predicted = u.predicted;
    if !opts.write_effects && !sizes.is_empty() {
        let space = predict::spread(&space_std);
        predicted.workspace_rms = round(space.rms, 3);
        predicted.workspace_p95 = round(space.p95, 3);
        // Where measured: the model's own, and each effect's RMS there, root-sum-squared.
        let region_ms = sizes
            .iter()
            .filter(|s| s.2.acts_on == "pose")
            .map(|s| s.2.measured_region_rms_um.powi(2))
            .sum::<f64>();
        predicted.measured_region_rms = round(
            (predicted.measured_region_rms.powi(2) + region_ms).sqrt(),
            3,
        );
    }
    let zero_shifts = (0..6)
        .filter(|_| opts.write_effects)
        .filter_map(|j| {
            let d = file.params.dh[j].theta - f.est.params(0).dh[j].theta;
            (d != 0.0).then(|| super::ZeroShift {
                param: format!("theta{}", j + 1),
                shift_deg: round(d / DEG, 9),
            })
        })
        .collect();
    let delivered = Delivered {
        content: if opts.write_effects || adopted.is_empty() {
            "geometry and effects"
        } else {
            "geometry only"
        },
        not_delivered,
        thermal_reference: file.reference.clone(),
        zero_shifts,
    };
    (
        sizes.into_iter().map(|s| s.2).collect(),
        predicted,
        space_std,
        delivered,
    )
}

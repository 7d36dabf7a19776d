//! Diagnosis: in = measurement model + measured EDBB data; out = where simulation and
//! measurement disagree, the calibrated geometry, the effects that explain what remains, and
//! the `edbbgen.diagnose/1` report (DESIGN.md). No file I/O.
//!
//! Method. The fit ([`fit`]) turns every effect of the library into regressors linear in its
//! few parameters, so one pass over the rows gives the normal equations of the geometry and of
//! every candidate at once, per contiguous time block. A candidate is accepted only when it
//! lowers both the BIC and the cross-validated error clearly and explains a good part of the
//! excess over the noise; the accepted model is refitted jointly (geometry and effects, the
//! effects applied exactly), and the loop repeats until the residual is at the noise level and
//! white, or nothing helps. `calibrate` runs the same loop on a campaign of runs to name the
//! effects it fits with the geometry.

pub mod fit;
pub mod plot;

pub use fit::{Basis, Estimate, Fitted, Param, Problem, Run, Term};

use crate::model::{MeasurementModel, N_PARAMS};
use crate::twin::effects::Effect;
use crate::twin::Measured;
use crate::units::{fmt_fixed, to_deg, DEG, MM};
use fit::{accumulate, effect_cols, lag1, model_cols, noise_estimate, rms, score, solve};
use rayon::prelude::*;
use serde::Serialize;

#[derive(Clone, Debug)]
pub struct DiagnoseOptions {
    /// Contiguous time blocks for cross-validation.
    pub folds: usize,
    /// At most this many effects after the geometry.
    pub max_effects: usize,
    /// The robot's link masses (its file's inertials; empty when it has none): joint
    /// compliance is then also tried with the gravity torques they give.
    pub masses: Vec<crate::robot::PointMass>,
}

impl Default for DiagnoseOptions {
    fn default() -> Self {
        DiagnoseOptions {
            folds: 8,
            max_effects: 3,
            masses: Vec::new(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DiagnoseError {
    #[error("{0}")]
    Data(String),
}

/// Where a residual is largest: time span, joint ranges, peak.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct Where {
    pub t_s: [f64; 2],
    pub joints_deg: Vec<[f64; 2]>,
    pub peak_um: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct StepReport {
    pub effect: &'static str,
    pub joint: Option<usize>,
    pub rms_after_um: f64,
    pub params: serde_json::Map<String, serde_json::Value>,
    /// Standard uncertainties of `params` (same keys, same units).
    pub std: serde_json::Map<String, serde_json::Value>,
    pub bic: f64,
    pub cv_rms_um: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct NamedEffect {
    pub effect: &'static str,
    pub joint: Option<usize>,
}

/// One effect of a fitted model with its parameters and their standard uncertainties.
#[derive(Clone, Debug, Serialize)]
pub struct EffectReport {
    pub effect: &'static str,
    pub joint: Option<usize>,
    pub params: serde_json::Map<String, serde_json::Value>,
    pub std: serde_json::Map<String, serde_json::Value>,
}

/// The final model of a diagnosis: the joint fit of the geometry and the named effects.
#[derive(Clone, Debug, Serialize)]
pub struct ModelReport {
    /// Deviations from nominal of the fitted geometry (mm for lengths, deg for angles).
    pub params: serde_json::Map<String, serde_json::Value>,
    /// Their standard uncertainties (same keys, same units).
    pub std: serde_json::Map<String, serde_json::Value>,
    pub effects: Vec<EffectReport>,
}

/// The `edbbgen.diagnose/1` report (DESIGN.md); keys after `steps` are additions.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub rms_nominal_um: f64,
    pub named_effects: Vec<NamedEffect>,
    pub unexplained: bool,
    #[serde(rename = "where")]
    pub where_: Option<Where>,
    pub rms_final_um: f64,
    pub steps: Vec<StepReport>,
    pub rows: usize,
    pub duration_s: f64,
    /// Noise of the bar estimated from the high-frequency part of the residual.
    pub noise_um: f64,
    /// Lag-1 autocorrelation of the final residual (white ≈ 0).
    pub lag1_final: f64,
    /// Where the nominal model and the measurement disagree most.
    pub nominal_where: Option<Where>,
    /// The final joint fit: geometry and every named effect together (the `geometric` step
    /// holds the geometry-only fit, which a missing effect biases).
    pub model: ModelReport,
}

/// The report plus the residual after each stage (for the plot) and a human summary.
#[derive(Clone, Debug)]
pub struct Diagnosis {
    pub report: Report,
    pub t: Vec<f64>,
    /// (stage label, residual in metres per row).
    pub stages: Vec<(String, Vec<f64>)>,
    pub summary: String,
}

/// Noise of the residual in the GUM's sense: (σ per row, lag-1 autocorrelation ρ, the factor
/// (1 + ρ)/(1 − ρ) by which correlated rows inflate a variance). σ² = rᵀr / (n − p); a
/// lag-1-correlated residual carries fewer independent rows than it has.
pub fn noise_variance(residual: &[f64], coefficients: usize) -> (f64, f64, f64) {
    let n = residual.len();
    let rr: f64 = residual.iter().map(|v| v * v).sum();
    let sigma = (rr / (n.saturating_sub(coefficients)).max(1) as f64).sqrt();
    let rho = lag1(residual).clamp(0.0, 0.99);
    (sigma, rho, (1.0 + rho) / (1.0 - rho))
}

/// An effect's parameters in report units, with standard uncertainties from the diagonal of
/// the coefficient covariance `var` (same order as the coefficients).
pub fn effect_report(
    e: Effect,
    basis: Basis,
    coef: &[f64],
    var: &[f64],
    temp_log: bool,
) -> EffectReport {
    let sd = |k: usize| var.get(k).map_or(0.0, |v| v.max(0.0).sqrt());
    let mut params = serde_json::Map::new();
    let mut std = serde_json::Map::new();
    match e {
        Effect::CyclicError(_) => {
            let pick = |f: &dyn Fn(usize) -> f64, off: usize| -> Vec<f64> {
                (0..3).map(|h| round(to_deg(f(2 * h + off)), 6)).collect()
            };
            params.insert("cos_deg".into(), pick(&|k| coef[k], 0).into());
            params.insert("sin_deg".into(), pick(&|k| coef[k], 1).into());
            std.insert("cos_deg".into(), pick(&sd, 0).into());
            std.insert("sin_deg".into(), pick(&sd, 1).into());
        }
        Effect::Backlash(_) => {
            params.insert("play_deg".into(), round(to_deg(coef[0]), 6).into());
            std.insert("play_deg".into(), round(to_deg(sd(0)), 6).into());
        }
        Effect::ServoLag => {
            params.insert("tau_s".into(), round(coef[0], 6).into());
            std.insert("tau_s".into(), round(sd(0), 6).into());
        }
        Effect::ThermalDrift => {
            let key = if temp_log {
                "alpha_per_k"
            } else {
                "scale_poly_t"
            };
            let v: Vec<f64> = coef.iter().map(|c| round(*c, 12)).collect();
            let s: Vec<f64> = (0..coef.len()).map(|k| round(sd(k), 12)).collect();
            params.insert(key.into(), v.into());
            std.insert(key.into(), s.into());
        }
        Effect::JointCompliance if basis == Basis::KnownMasses => {
            // Compliance c = 1/k per joint; a stiffness only where c is clearly positive.
            let k: Vec<Option<f64>> = (0..6)
                .map(|j| (coef[j] > 3.0 * sd(j)).then(|| round(1.0 / coef[j], 0)))
                .collect();
            let ks: Vec<Option<f64>> = (0..6)
                .map(|j| (coef[j] > 3.0 * sd(j)).then(|| round(sd(j) / (coef[j] * coef[j]), 0)))
                .collect();
            params.insert("masses".into(), "robot file inertials".into());
            params.insert(
                "stiffness_nm_per_rad".into(),
                serde_json::to_value(k).unwrap_or_default(),
            );
            std.insert(
                "stiffness_nm_per_rad".into(),
                serde_json::to_value(ks).unwrap_or_default(),
            );
        }
        Effect::JointCompliance => {
            let used = coef.iter().filter(|c| **c != 0.0).count();
            params.insert("masses".into(), "unknown: general gravity basis".into());
            params.insert("basis_terms".into(), used.into());
        }
        Effect::Geometric => {}
    }
    EffectReport {
        effect: e.name(),
        joint: e.joint(),
        params,
        std,
    }
}

/// Deviations from nominal of the free geometry (mm, deg) and their standard uncertainties
/// from the diagonal `var` (SI², same order as `free`).
pub fn geometry_report(
    problem: &Problem,
    est: &Estimate,
    free: &[Param],
    var: &[f64],
) -> (
    serde_json::Map<String, serde_json::Value>,
    serde_json::Map<String, serde_json::Value>,
) {
    let nominal = Estimate::nominal(problem);
    let mut params = serde_json::Map::new();
    let mut std = serde_json::Map::new();
    for (k, q) in free.iter().enumerate() {
        let unit = if q.is_angle() { DEG } else { MM };
        let name = q.name(problem.runs());
        let dev = (est.get(*q) - nominal.get(*q)) / unit;
        params.insert(name.clone(), round(dev, 6).into());
        std.insert(name, round(var[k].max(0.0).sqrt() / unit, 6).into());
    }
    (params, std)
}

/// Every effect of the estimate with its parameters, their variances `var` following the
/// effects' coefficients in order.
pub fn effects_report(problem: &Problem, est: &Estimate, var: &[f64]) -> Vec<EffectReport> {
    let mut k = 0;
    est.effects
        .iter()
        .map(|t| {
            let n = t.coef.len();
            let r = effect_report(
                t.effect,
                t.basis,
                &t.coef,
                &var[k..k + n],
                problem.m.temp.is_some(),
            );
            k += n;
            r
        })
        .collect()
}

/// The report of a fitted model: geometry and effects with standard uncertainties from the
/// residual's noise (correlation-inflated) and the pseudo-inverse of the normal matrix.
pub fn model_report(problem: &Problem, est: &Estimate, fitted: &Fitted) -> ModelReport {
    let (sigma, _, inflate) = noise_variance(&fitted.residual, fitted.coefficients());
    let cov = fit::inverse(&fitted.normal) * (sigma * sigma * inflate);
    let var: Vec<f64> = (0..cov.nrows()).map(|k| cov[(k, k)]).collect();
    let g = fitted.free.len();
    let (params, std) = geometry_report(problem, est, &fitted.free, &var[..g]);
    let effects = effects_report(problem, est, &var[g..]);
    ModelReport {
        params,
        std,
        effects,
    }
}

/// The time span and joint ranges of the largest residual cluster (1 s moving RMS).
fn locate(m: &Measured, r: &[f64]) -> Option<Where> {
    let n = r.len();
    if n == 0 {
        return None;
    }
    let dt = (m.t[n - 1] - m.t[0]) / (n.max(2) - 1) as f64;
    let w = ((1.0 / dt.max(1e-6)) as usize).clamp(1, n);
    let mut pre = vec![0.0; n + 1];
    for k in 0..n {
        pre[k + 1] = pre[k] + r[k] * r[k];
    }
    let mov: Vec<f64> = (0..n)
        .map(|k| {
            let (a, b) = (k.saturating_sub(w / 2), (k + w / 2 + 1).min(n));
            ((pre[b] - pre[a]) / (b - a) as f64).sqrt()
        })
        .collect();
    let (peak_k, peak) =
        mov.iter().enumerate().fold(
            (0, 0.0),
            |(bk, bv), (k, v)| if *v > bv { (k, *v) } else { (bk, bv) },
        );
    let half = 0.5 * peak;
    let mut a = peak_k;
    while a > 0 && mov[a - 1] >= half {
        a -= 1;
    }
    let mut b = peak_k;
    while b + 1 < n && mov[b + 1] >= half {
        b += 1;
    }
    let joints_deg = (0..6)
        .map(|j| {
            let (lo, hi) = m.q[a..=b].iter().fold((f64::MAX, f64::MIN), |(lo, hi), q| {
                (lo.min(q[j]), hi.max(q[j]))
            });
            [round(to_deg(lo), 3), round(to_deg(hi), 3)]
        })
        .collect();
    let peak_abs = r[a..=b].iter().fold(0.0f64, |mx, v| mx.max(v.abs()));
    Some(Where {
        t_s: [round(m.t[a], 3), round(m.t[b], 3)],
        joints_deg,
        peak_um: round(peak_abs * 1e6, 3),
    })
}

fn round(v: f64, d: i32) -> f64 {
    let s = 10f64.powi(d);
    let r = (v * s).round() / s;
    if r == 0.0 {
        0.0
    } else {
        r
    }
}

// ---- the loop -----------------------------------------------------------------------------

/// The candidates tried after the geometry (joint compliance with known masses too, when the
/// robot file gives them).
fn candidates(masses_known: bool) -> Vec<(Effect, Basis)> {
    let mut c = Vec::new();
    if masses_known {
        c.push((Effect::JointCompliance, Basis::KnownMasses));
    }
    c.extend([
        (Effect::JointCompliance, Basis::Standard),
        (Effect::ThermalDrift, Basis::Standard),
        (Effect::ServoLag, Basis::Standard),
    ]);
    c.extend((0..6).map(|j| (Effect::CyclicError(j), Basis::Standard)));
    c.extend((0..6).map(|j| (Effect::Backlash(j), Basis::Standard)));
    c
}

/// A diagnosis with its final model: the estimate and the joint fit of the geometry and the
/// named effects.
pub struct Selected {
    pub estimate: Estimate,
    pub fitted: Fitted,
    pub diagnosis: Diagnosis,
}

/// Runs the diagnosis of one recorded run: the fixture and the MAP are free where the data
/// determine them (calibration absorbs them).
pub fn run(
    model: &MeasurementModel,
    m: &Measured,
    opts: &DiagnoseOptions,
) -> Result<Diagnosis, DiagnoseError> {
    if m.len() < N_PARAMS + 2 {
        return Err(DiagnoseError::Data(format!(
            "{} rows: at least {} are needed",
            m.len(),
            N_PARAMS + 2
        )));
    }
    let problem = Problem::new(
        model,
        &[Run {
            measured: m,
            fixture: model.nominal.fix,
        }],
    )
    .with_masses(&opts.masses);
    let (_, free) = fit::structural(&problem, true, true);
    Ok(select(&problem, &free, opts).diagnosis)
}

/// The diagnosis of a prepared problem whose free geometry is `free`: the geometry first, then
/// one effect at a time while one clearly helps; every accepted model is refitted jointly.
pub fn select(problem: &Problem, free: &[Param], opts: &DiagnoseOptions) -> Selected {
    let m = &problem.m;
    let folds = opts.folds.clamp(2, 20).min(m.len() / fit::CHUNK).max(2);
    let mut s = Estimate::nominal(problem);
    let nominal_res = accumulate(problem, &s, &[], 1).residual;
    let rms_nominal = rms(&nominal_res);
    let mut stages = vec![("nominal".to_string(), nominal_res.clone())];

    // Calibration: the geometric fit.
    let st = fit::refit_stats(problem, &mut s, free);
    let mut residual = st.residual.clone();
    let (x_var, bic0, cv0) = {
        let sel: Vec<usize> = (0..st.c).collect();
        let (_, var, _) = solve(&st.n[0], &st.b[0], &sel);
        let (_, _, bic, cv) = score(&st, &sel);
        (var, bic, cv)
    };
    let n = m.len() as f64;
    let sigma2 = st.rr[0] / (n - free.len() as f64).max(1.0);
    let var: Vec<f64> = x_var.iter().map(|v| v * sigma2).collect();
    let (params, std) = geometry_report(problem, &s, free, &var);
    let mut steps = vec![StepReport {
        effect: "geometric",
        joint: None,
        rms_after_um: round(rms(&residual) * 1e6, 3),
        params,
        std,
        bic: round(bic0, 1),
        cv_rms_um: round((cv0 / n).sqrt() * 1e6, 3),
    }];
    stages.push(("geometric".to_string(), residual.clone()));
    let mut named = vec![NamedEffect {
        effect: "geometric",
        joint: None,
    }];

    let mut noise = noise_estimate(&residual);
    for _ in 0..opts.max_effects {
        noise = noise.min(noise_estimate(&residual));
        let r_now = rms(&residual);
        if r_now <= 1.5 * noise && lag1(&residual) < 0.2 {
            break;
        }
        // One pass: the current model's columns plus every candidate's.
        let base_cols = model_cols(problem, &s, free);
        let mut cols = base_cols.clone();
        let mut groups = Vec::new();
        for (e, basis) in candidates(!problem.masses.is_empty()) {
            if s.effects.iter().any(|t| t.effect == e) {
                continue;
            }
            let ec = effect_cols(e, basis, problem.thermal_terms);
            groups.push(((e, basis), cols.len()..cols.len() + ec.len()));
            cols.extend(ec);
        }
        let st = accumulate(problem, &s, &cols, folds);
        let base_sel: Vec<usize> = (0..base_cols.len()).collect();
        let (rss0, _, bic0, cv0) = score(&st, &base_sel);
        let excess = (rss0 - n * noise * noise).max(0.0);
        let scored: Vec<((Effect, Basis), f64, f64, f64)> = groups
            .par_iter()
            .map(|(e, range)| {
                let sel: Vec<usize> = base_sel.iter().copied().chain(range.clone()).collect();
                let (rss, _, bic, cv) = score(&st, &sel);
                (*e, rss, bic, cv)
            })
            .collect();
        let best = scored
            .iter()
            .filter(|(_, rss, bic, cv)| {
                *bic < bic0 - 10.0 && *cv < 0.95 * cv0 && rss0 - rss >= 0.6 * excess
            })
            .min_by(|a, b| a.2.total_cmp(&b.2));
        let Some(&((e, basis), _, _, cv)) = best else {
            break;
        };
        // The linearised score judged the forms at a geometry that still absorbs the effect;
        // an effect with two forms (joint compliance with and without known masses) is
        // refitted in both and the better BIC kept, so the small model wins where it is right.
        let forms: Vec<Basis> = if e == Effect::JointCompliance && !problem.masses.is_empty() {
            vec![Basis::KnownMasses, Basis::Standard]
        } else {
            vec![basis]
        };
        let mut chosen: Option<(Estimate, fit::Stats, f64, Basis)> = None;
        for b in forms {
            let mut trial = s.clone();
            trial.add_effect(e, b, problem.thermal_terms);
            let st = fit::refit_stats(problem, &mut trial, free);
            let k = model_cols(problem, &trial, free).len() as f64;
            let bic = n * (st.rr[0] / n).max(1e-300).ln() + k * n.ln();
            if chosen.as_ref().is_none_or(|c| bic < c.2 - 10.0) {
                chosen = Some((trial, st, bic, b));
            }
        }
        let Some((trial, st, bic, basis)) = chosen else {
            break;
        };
        s = trial;
        residual = st.residual.clone();
        let coef = s.effects.last().map(|x| x.coef.clone()).unwrap_or_default();
        let step = effect_report(e, basis, &coef, &[], m.temp.is_some());
        let label = match e.joint() {
            Some(j) => format!("+{} (joint {j})", e.name()),
            None => format!("+{}", e.name()),
        };
        steps.push(StepReport {
            effect: e.name(),
            joint: e.joint(),
            rms_after_um: round(rms(&residual) * 1e6, 3),
            params: step.params,
            std: serde_json::Map::new(),
            bic: round(bic, 1),
            cv_rms_um: round((cv / n).sqrt() * 1e6, 3),
        });
        named.push(NamedEffect {
            effect: e.name(),
            joint: e.joint(),
        });
        stages.push((label, residual.clone()));
    }
    // The final model: the joint fit's normal matrix at the estimate.
    let cols = model_cols(problem, &s, free);
    let st = accumulate(problem, &s, &cols, 1);
    let (normal, _, rss, _) = st.total();
    let fitted = Fitted {
        free: free.to_vec(),
        normal,
        residual: st.residual,
        rss,
    };
    noise = noise.min(noise_estimate(&residual));
    let rms_final = rms(&residual);
    let l1 = lag1(&residual);
    let unexplained = rms_final > 2.0 * noise || l1 > 0.5;
    let where_ = if unexplained {
        locate(m, &residual)
    } else {
        None
    };
    let report = Report {
        schema: "edbbgen.diagnose/1",
        rms_nominal_um: round(rms_nominal * 1e6, 3),
        named_effects: named,
        unexplained,
        where_,
        rms_final_um: round(rms_final * 1e6, 3),
        steps,
        rows: m.len(),
        duration_s: round(m.t[m.len() - 1] - m.t[0], 3),
        noise_um: round(noise * 1e6, 3),
        lag1_final: round(l1, 4),
        nominal_where: locate(m, &nominal_res),
        model: model_report(problem, &s, &fitted),
    };
    let summary = summary(&report);
    Selected {
        estimate: s,
        fitted,
        diagnosis: Diagnosis {
            report,
            t: m.t.clone(),
            stages,
            summary,
        },
    }
}

fn summary(r: &Report) -> String {
    let mut s = format!(
        "{} rows over {} s; bar noise ~{} um\n",
        r.rows,
        fmt_fixed(r.duration_s, 1),
        fmt_fixed(r.noise_um, 2)
    );
    s += &format!("nominal model: RMS {} um", fmt_fixed(r.rms_nominal_um, 2));
    if let Some(w) = &r.nominal_where {
        s += &format!(
            ", largest at t {}..{} s (peak {} um)",
            fmt_fixed(w.t_s[0], 1),
            fmt_fixed(w.t_s[1], 1),
            fmt_fixed(w.peak_um, 1)
        );
    }
    s.push('\n');
    for st in &r.steps {
        let name = match st.joint {
            Some(j) => format!("{} (joint {j})", st.effect),
            None => st.effect.to_string(),
        };
        s += &format!("  + {name:<24} RMS {} um\n", fmt_fixed(st.rms_after_um, 3));
    }
    if r.unexplained {
        s += "UNEXPLAINED structure remains";
        if let Some(w) = &r.where_ {
            s += &format!(
                " at t {}..{} s, joints {}",
                fmt_fixed(w.t_s[0], 1),
                fmt_fixed(w.t_s[1], 1),
                w.joints_deg
                    .iter()
                    .enumerate()
                    .map(|(j, r)| format!(
                        "q{} {}..{}",
                        j + 1,
                        fmt_fixed(r[0], 1),
                        fmt_fixed(r[1], 1)
                    ))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        s.push('\n');
    } else {
        s += &format!(
            "residual at the noise level: RMS {} um, lag-1 autocorrelation {}\n",
            fmt_fixed(r.rms_final_um, 3),
            fmt_fixed(r.lag1_final, 3)
        );
    }
    s
}

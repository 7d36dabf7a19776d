//! The loaded double ball bar (LDBB, Sections 2.2, 3.2 and 4.2 of the paper): in = loaded
//! circle data ([`data::Loaded`]), the [`setup::Setup`], optionally the robot and a laser-
//! tracker reference; out = an [`Analysis`]: the compliance along the bar per angle, the
//! compensated trajectories, the centring sine and the kinematic remainder, the stiffnesses the
//! circle determines, and the `edbbgen.ldbb/1` report.
//!
//! The steps, in the paper's order:
//! 1. every run onto one angle grid ([`resample`]); the repeats of a load averaged per angle;
//! 2. Eq. 8 with the mechanical base load reference: each load's deflection relative to the
//!    lowest load. Compliance comes from differences between loads, never from an unloaded
//!    run: the least-squares slope of the load means against the load, per angle, with its
//!    standard uncertainty;
//! 3. the compliance-compensated trajectories (each load's mean less compliance × load, i.e.
//!    extrapolated to zero load), their spread (the linearity of the compliance) and average;
//! 4. the centring sine of Eq. 9 on the average ([`fit`]): linear least squares with b = 1
//!    (no initial guess), then the paper's nonlinear fit with b free;
//! 5. the kinematic remainder: average minus sine, compared with the reference if given;
//! 6. with a robot: joint stiffnesses from c(θ) = uᵀJₚK⁻¹Jₚᵀu ([`stiffness`]).
//!
//! What the bar cannot tell apart: a translation of the whole circle against the table ball
//! (the centring error) and the first harmonic of the robot's kinematic error along the bar are
//! the same signal. The sine takes both; the kinematic remainder has no mean and no first
//! harmonic. Joint angles are in the data's frame, angles follow the setup's convention
//! ([`setup`]). Nothing here reads or writes files.

pub mod data;
pub mod fit;
pub mod kin;
pub mod plot;
pub mod program;
pub mod resample;
pub mod setup;
pub mod sim;
pub mod stiffness;

use crate::robot::Robot;
use crate::units::{fmt_sig, length_um, DEG};
use data::{Loaded, Reference};
use fit::Sine;
use serde::Serialize;
use setup::Setup;
use std::f64::consts::TAU;

const UM: f64 = 1e-6;

/// Which sine the kinematic remainder subtracts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SineModel {
    /// b = 1: the first harmonic, what a centring offset produces (default).
    Linear,
    /// The paper's Eq. 9 with b free.
    Nonlinear,
}

/// Where the nonlinear fit starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SineStart {
    /// From the linear fit (needs no guess).
    Linear,
    /// The paper's guess: a = 0.8 mm, b = 1, φ = 22.5°.
    Paper,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Options {
    /// Angle grid step (rad); 360° must be a whole number of steps.
    pub grid_step: f64,
    pub sine: SineModel,
    pub start: SineStart,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            grid_step: DEG,
            sine: SineModel::Linear,
            start: SineStart::Linear,
        }
    }
}

/// Bad data: one line naming the row (line, column) or the load and run.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LdbbError {
    #[error(
        "line {line}, column 2 (load_n): load {load} N is not one of the setup's loads ({loads})"
    )]
    UnknownLoad {
        line: usize,
        load: String,
        loads: String,
    },
    #[error("line {line}, column 1 (run): run {run} of load {load} N, but the setup asks for {repeats} repeat(s)")]
    ExtraRun {
        line: usize,
        run: usize,
        load: String,
        repeats: usize,
    },
    #[error("load {load} N: no rows (the setup lists it in loads.loads_n)")]
    MissingLoad { load: String },
    #[error(
        "load {load} N: run(s) {missing} missing; the setup asks for {repeats} repeats per load"
    )]
    MissingRun {
        load: String,
        missing: String,
        repeats: usize,
    },
    #[error("load {load} N, run {run}: the angles do not cover the circle: no sample between {from} and {to} deg ({samples} samples; the grid step is {step} deg)")]
    Coverage {
        load: String,
        run: usize,
        from: String,
        to: String,
        samples: usize,
        step: String,
    },
    #[error("{0}")]
    Options(String),
    #[error("robot: {0}")]
    Robot(String),
}

/// One recorded circle on the grid.
#[derive(Clone, Debug)]
pub struct Run {
    pub load: f64,
    pub run: usize,
    pub rows: usize,
    pub grid: resample::RunGrid,
}

/// Everything the analysis found (SI: m, rad, N; compliances m/N).
#[derive(Clone, Debug)]
pub struct Analysis {
    /// Grid angles (rad), k·step.
    pub angles: Vec<f64>,
    pub loads: Vec<f64>,
    pub runs: Vec<Run>,
    /// Per load: the mean of its repeats per angle, and their standard deviation.
    pub mean: Vec<Vec<f64>>,
    pub repeat_std: Vec<Vec<f64>>,
    /// Eq. 8: per load, its mean less the base (lowest) load's; the base's is zero.
    pub deflection: Vec<Vec<f64>>,
    pub compliance: Vec<f64>,
    pub compliance_std: Vec<f64>,
    /// Per load: mean − compliance × load (the trajectory extrapolated to zero load).
    pub compensated: Vec<Vec<f64>>,
    /// Max − min over the loads of the compensated trajectories, per angle.
    pub spread: Vec<f64>,
    pub average: Vec<f64>,
    pub sine_linear: Sine,
    pub sine_nonlinear: Option<Sine>,
    pub sine_used: SineModel,
    pub kinematic: Vec<f64>,
    /// The reference on the grid (mean removed), when given.
    pub reference: Option<Vec<f64>>,
    pub stiffness: Option<stiffness::Stiffness>,
    pub report: Report,
    pub warnings: Vec<String>,
}

impl Analysis {
    pub fn sine(&self) -> &Sine {
        match (self.sine_used, &self.sine_nonlinear) {
            (SineModel::Nonlinear, Some(s)) => s,
            _ => &self.sine_linear,
        }
    }
}

// ---- the report (edbbgen.ldbb/1) -----------------------------------------------------------

/// Rounds for the report: the numbers stay readable and their bytes stable.
fn r(x: f64, decimals: i32) -> f64 {
    let k = 10f64.powi(decimals);
    let v = (x * k).round() / k;
    if v == 0.0 {
        0.0
    } else {
        v
    }
}

/// Rounds to `digits` significant digits (for stiffnesses and compliances in rad/(N·m)).
fn sig(x: f64, digits: i32) -> f64 {
    if x == 0.0 || !x.is_finite() {
        return x;
    }
    let e = x.abs().log10().floor() as i32;
    r(x, digits - 1 - e)
}

#[derive(Clone, Debug, Serialize)]
pub struct ComplianceReport {
    pub angle_deg: Vec<f64>,
    pub um_per_n: Vec<f64>,
    pub std_um_per_n: Vec<Option<f64>>,
}

#[derive(Clone, Debug, Serialize)]
pub struct SineReport {
    pub a_mm: f64,
    pub b: f64,
    pub phi_deg: f64,
    pub offset_um: f64,
    pub model: SineModel,
    pub std: SineStd,
    pub rms_um: f64,
    pub converged: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct SineStd {
    pub a_mm: Option<f64>,
    pub b: Option<f64>,
    pub phi_deg: Option<f64>,
    pub offset_um: Option<f64>,
}

fn opt(x: f64, d: i32) -> Option<f64> {
    x.is_finite().then(|| r(x, d))
}

impl SineReport {
    fn of(s: &Sine, model: SineModel) -> Self {
        SineReport {
            a_mm: r(s.a * 1e3, 5),
            b: r(s.b, 5),
            phi_deg: r(s.phi / DEG, 3),
            offset_um: r(s.offset / UM, 3),
            model,
            std: SineStd {
                a_mm: opt(s.std_a * 1e3, 5),
                b: opt(s.std_b, 5),
                phi_deg: opt(s.std_phi / DEG, 3),
                offset_um: opt(s.std_offset / UM, 3),
            },
            rms_um: r(s.rms / UM, 3),
            converged: s.converged,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct SineFits {
    pub linear: SineReport,
    pub nonlinear: Option<SineReport>,
    /// Where the nonlinear fit started.
    pub nonlinear_start: SineStart,
    pub disagree: bool,
}

#[derive(Clone, Debug, Serialize)]
pub struct Curve {
    pub angle_deg: Vec<f64>,
    pub um: Vec<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct ReferenceReport {
    pub mean_abs_difference_um: f64,
    pub rms_difference_um: f64,
    /// The same after removing the first harmonic from both (the part the LDBB cannot see).
    pub mean_abs_difference_first_harmonic_removed_um: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct LoadReport {
    pub load_n: f64,
    /// Mean of the repeats per angle, µm.
    pub mean_um: Vec<f64>,
    /// Eq. 8: mean less the base load's mean, µm (zero for the base).
    pub deflection_um: Vec<f64>,
    /// Compliance compensated: mean − compliance × load, µm.
    pub compensated_um: Vec<f64>,
    /// Largest standard deviation of the repeats over the circle, µm.
    pub max_repeat_std_um: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct StiffnessReport {
    pub std_nm_per_rad: Vec<Option<f64>>,
    pub why: Vec<Option<String>>,
    pub combinations: Vec<stiffness::Combination>,
    pub singular_values: Vec<f64>,
    pub fit_rms_um_per_n: f64,
    pub relative_std_limit: f64,
    /// Where the joint angles came from: "recorded" or "ik".
    pub joint_angles: &'static str,
}

/// `ldbb --json`: DESIGN.md's keys first, in its order, then the extensions.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub compliance: ComplianceReport,
    pub sine_fit: SineReport,
    pub kinematic_error: Curve,
    pub stiffness_nm_per_rad: Vec<Option<f64>>,
    pub linearity_spread_um: f64,
    pub reference: Option<ReferenceReport>,
    // ---- extensions ----
    pub grid_step_deg: f64,
    pub rows: usize,
    pub loads_n: Vec<f64>,
    pub repeats: usize,
    pub noise_um: f64,
    pub outliers: usize,
    pub compliance_rms_um_per_n: f64,
    pub kinematic_error_rms_um: f64,
    pub sine_fits: SineFits,
    pub stiffness: Option<StiffnessReport>,
    pub loads: Vec<LoadReport>,
    pub warnings: Vec<String>,
}

// ---- the analysis --------------------------------------------------------------------------

fn load_text(f: f64) -> String {
    let s = format!("{f}");
    s.strip_suffix(".0").map(str::to_string).unwrap_or(s)
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// Removes the least-squares mean and first harmonic of a curve on the uniform grid.
pub fn without_first_harmonic(angles: &[f64], v: &[f64]) -> Vec<f64> {
    match fit::sine_linear(angles, v) {
        Some(s) => v.iter().zip(angles).map(|(y, t)| y - s.eval(*t)).collect(),
        None => v.to_vec(),
    }
}

/// Runs the whole analysis. `robot` enables the stiffness identification (with the setup's
/// tool); `reference` the comparison with a laser tracker.
pub fn run(
    loaded: &Loaded,
    setup: &Setup,
    robot: Option<&Robot>,
    reference: Option<&Reference>,
    opts: &Options,
) -> Result<Analysis, LdbbError> {
    let angles = grid_angles(opts)?;
    let nodes = angles.len();
    let loads = setup.loads.clone();
    let nl = loads.len();

    // ---- group the rows by load and run -------------------------------------------------
    let groups = group_rows(loaded, setup)?;

    // ---- 1. every run onto the grid ----------------------------------------------------------
    let runs = grid_runs(loaded, &groups, &loads, nodes, opts)?;
    let nr = setup.repeats;
    let (mean, repeat_std) = repeat_means(&runs, nl, nr, nodes);

    // ---- 2. Eq. 8 and the compliance per angle ---------------------------------------------
    let deflection: Vec<Vec<f64>> = (0..nl)
        .map(|j| (0..nodes).map(|k| mean[j][k] - mean[0][k]).collect())
        .collect();
    let (compliance, compliance_std) =
        compliance_per_angle(&loads, &mean, &repeat_std, nr, nodes, opts);

    // ---- 3. compensated trajectories, their spread and average ------------------------------
    let compensated: Vec<Vec<f64>> = (0..nl)
        .map(|j| {
            (0..nodes)
                .map(|k| mean[j][k] - compliance[k] * loads[j])
                .collect()
        })
        .collect();
    let spread: Vec<f64> = (0..nodes)
        .map(|k| {
            let v = (0..nl).map(|j| compensated[j][k]);
            v.clone().fold(f64::NEG_INFINITY, f64::max) - v.fold(f64::INFINITY, f64::min)
        })
        .collect();
    let average: Vec<f64> = (0..nodes)
        .map(|k| (0..nl).map(|j| compensated[j][k]).sum::<f64>() / nl as f64)
        .collect();

    // ---- 4. the centring sine (Eq. 9) ----------------------------------------------------------
    let mut warnings = setup.warnings();
    let (lin, nonlin, disagree) = centring_sine(&angles, &average, opts, &mut warnings)?;
    let sine_used = match (&nonlin, opts.sine) {
        (Some(_), SineModel::Nonlinear) => SineModel::Nonlinear,
        _ => SineModel::Linear,
    };
    let used = match (sine_used, &nonlin) {
        (SineModel::Nonlinear, Some(n)) => n.clone(),
        _ => lin.clone(),
    };

    // ---- 5. the kinematic remainder and the reference ------------------------------------------
    let kinematic: Vec<f64> = (0..nodes)
        .map(|k| average[k] - used.eval(angles[k]))
        .collect();
    let (reference_grid, reference_report) = compare_reference(reference, &angles, &kinematic)?;

    // ---- 6. stiffness -----------------------------------------------------------------------
    let stiff = match robot {
        None => None,
        Some(robot) => Some(stiffness_of(
            robot,
            setup,
            &runs,
            &angles,
            &mean,
            &compliance,
            &mut warnings,
        )?),
    };

    // ---- report -----------------------------------------------------------------------------
    let (outliers, noise) = data_warnings(&runs, &compliance, &mut warnings);
    let deg: Vec<f64> = angles.iter().map(|a| r(a / DEG, 6)).collect();
    let report = Report {
        schema: "edbbgen.ldbb/1",
        compliance: ComplianceReport {
            angle_deg: deg.clone(),
            um_per_n: compliance.iter().map(|c| r(c / UM, 6)).collect(),
            std_um_per_n: compliance_std.iter().map(|s| opt(s / UM, 6)).collect(),
        },
        sine_fit: SineReport::of(&used, sine_used),
        kinematic_error: Curve {
            angle_deg: deg.clone(),
            um: curve_um(&kinematic),
        },
        stiffness_nm_per_rad: match &stiff {
            Some((s, _)) => s
                .stiffness_nm_per_rad
                .iter()
                .map(|k| k.map(|v| sig(v, 4)))
                .collect(),
            None => vec![None; 6],
        },
        linearity_spread_um: r(spread.iter().cloned().fold(0.0, f64::max) / UM, 3),
        reference: reference_report,
        grid_step_deg: r(opts.grid_step / DEG, 9),
        rows: loaded.samples.len(),
        loads_n: loads.clone(),
        repeats: nr,
        noise_um: r(noise / UM, 3),
        outliers,
        compliance_rms_um_per_n: r(rms(&compliance) / UM, 6),
        kinematic_error_rms_um: r(rms(&kinematic) / UM, 3),
        sine_fits: SineFits {
            linear: SineReport::of(&lin, SineModel::Linear),
            nonlinear: nonlin
                .as_ref()
                .map(|n| SineReport::of(n, SineModel::Nonlinear)),
            nonlinear_start: opts.start,
            disagree,
        },
        stiffness: stiff
            .as_ref()
            .map(|(s, recorded)| stiffness_report(s, *recorded)),
        loads: load_reports(&loads, &mean, &deflection, &compensated, &repeat_std),
        warnings: warnings.clone(),
    };
    Ok(Analysis {
        angles,
        loads,
        runs,
        mean,
        repeat_std,
        deflection,
        compliance,
        compliance_std,
        compensated,
        spread,
        average,
        sine_linear: lin,
        sine_nonlinear: nonlin,
        sine_used,
        kinematic,
        reference: reference_grid,
        stiffness: stiff.map(|s| s.0),
        report,
        warnings,
    })
}

/// A curve (m) in µm, rounded for the report.
fn curve_um(v: &[f64]) -> Vec<f64> {
    v.iter().map(|x| r(x / UM, 4)).collect::<Vec<_>>()
}

/// The report's per-load section from the loads and their mean, deflection, compensated and
/// repeat-deviation curves (m).
fn load_reports(
    loads: &[f64],
    mean: &[Vec<f64>],
    deflection: &[Vec<f64>],
    compensated: &[Vec<f64>],
    repeat_std: &[Vec<f64>],
) -> Vec<LoadReport> {
    (0..loads.len())
        .map(|j| LoadReport {
            load_n: loads[j],
            mean_um: curve_um(&mean[j]),
            deflection_um: curve_um(&deflection[j]),
            compensated_um: curve_um(&compensated[j]),
            max_repeat_std_um: r(repeat_std[j].iter().cloned().fold(0.0, f64::max) / UM, 3),
        })
        .collect()
}

/// The grid angles (rad) of `opts`' grid step, or the error when it does not divide the circle.
fn grid_angles(opts: &Options) -> Result<Vec<f64>, LdbbError> {
    let bad_step = || {
        LdbbError::Options(format!(
            "--grid-step: {} deg must divide 360 deg into at least 12 steps",
            opts.grid_step / DEG
        ))
    };
    if !opts.grid_step.is_finite() || opts.grid_step <= 0.0 {
        return Err(bad_step());
    }
    let nodes = (TAU / opts.grid_step).round() as usize;
    if nodes < 12 || (nodes as f64 * opts.grid_step - TAU).abs() > 1e-9 {
        return Err(bad_step());
    }
    Ok((0..nodes).map(|k| k as f64 * TAU / nodes as f64).collect())
}

/// The rows of `loaded` grouped by load and run (indices per run per load of `setup`), or the
/// error naming a load or run that the setup does not have or that has no rows.
fn group_rows(loaded: &Loaded, setup: &Setup) -> Result<Vec<Vec<Vec<usize>>>, LdbbError> {
    let loads = &setup.loads;
    let nl = loads.len();
    let loads_list = loads
        .iter()
        .map(|f| load_text(*f))
        .collect::<Vec<_>>()
        .join(", ");

    let mut groups: Vec<Vec<Vec<usize>>> = vec![vec![Vec::new(); setup.repeats]; nl];
    for (k, s) in loaded.samples.iter().enumerate() {
        let j = loads
            .iter()
            .position(|&f| (f - s.load).abs() <= 1e-6 * f.max(1.0))
            .ok_or_else(|| LdbbError::UnknownLoad {
                line: s.line,
                load: load_text(s.load),
                loads: loads_list.clone(),
            })?;
        if s.run > setup.repeats {
            return Err(LdbbError::ExtraRun {
                line: s.line,
                run: s.run,
                load: load_text(loads[j]),
                repeats: setup.repeats,
            });
        }
        groups[j][s.run - 1].push(k);
    }
    for (j, g) in groups.iter().enumerate() {
        if g.iter().all(|r| r.is_empty()) {
            return Err(LdbbError::MissingLoad {
                load: load_text(loads[j]),
            });
        }
        let missing: Vec<String> = (0..setup.repeats)
            .filter(|&r| g[r].is_empty())
            .map(|r| (r + 1).to_string())
            .collect();
        if !missing.is_empty() {
            return Err(LdbbError::MissingRun {
                load: load_text(loads[j]),
                missing: missing.join(", "),
                repeats: setup.repeats,
            });
        }
    }
    Ok(groups)
}

/// Every run of the `groups` onto the grid of `nodes` angles, runs in load order, or the error
/// naming a run that leaves a gap in the circle.
fn grid_runs(
    loaded: &Loaded,
    groups: &[Vec<Vec<usize>>],
    loads: &[f64],
    nodes: usize,
    opts: &Options,
) -> Result<Vec<Run>, LdbbError> {
    let mut runs = Vec::new();
    for (j, g) in groups.iter().enumerate() {
        for (r, idx) in g.iter().enumerate() {
            let ang: Vec<f64> = idx.iter().map(|&k| loaded.samples[k].angle).collect();
            let val: Vec<f64> = idx.iter().map(|&k| loaded.samples[k].deflection).collect();
            let q: Option<Vec<[f64; 6]>> = idx
                .iter()
                .map(|&k| loaded.samples[k].q)
                .collect::<Option<Vec<_>>>();
            let grid = resample::run(&ang, &val, q.as_deref(), nodes).map_err(|gap| {
                LdbbError::Coverage {
                    load: load_text(loads[j]),
                    run: r + 1,
                    from: format!("{:.2}", gap.from / DEG),
                    to: format!("{:.2}", gap.to / DEG),
                    samples: gap.samples,
                    step: format!("{}", opts.grid_step / DEG),
                }
            })?;
            runs.push(Run {
                load: loads[j],
                run: r + 1,
                rows: idx.len(),
                grid,
            });
        }
    }
    Ok(runs)
}

/// Per load (of `nl`, `nr` repeats each): the mean of its runs per angle and their standard deviation.
fn repeat_means(
    runs: &[Run],
    nl: usize,
    nr: usize,
    nodes: usize,
) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let run_of = |j: usize, r: usize| &runs[j * nr + r].grid;
    let mut mean = vec![vec![0.0; nodes]; nl];
    let mut repeat_std = vec![vec![0.0; nodes]; nl];
    for j in 0..nl {
        for k in 0..nodes {
            let v: Vec<f64> = (0..nr).map(|r| run_of(j, r).y[k]).collect();
            let m = v.iter().sum::<f64>() / nr as f64;
            mean[j][k] = m;
            repeat_std[j][k] = if nr > 1 {
                (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (nr - 1) as f64).sqrt()
            } else {
                0.0
            };
        }
    }
    (mean, repeat_std)
}

/// The sum of squared deviations of the loads from their mean (N²).
fn load_sxx(loads: &[f64]) -> f64 {
    let nl = loads.len();
    let fm = loads.iter().sum::<f64>() / nl as f64;
    let sxx: f64 = loads.iter().map(|f| (f - fm).powi(2)).sum();
    sxx
}

/// The compliance per angle (the slope of the load means over the loads) and its standard
/// uncertainty, from the per-load means and repeat deviations of `nr` repeats.
fn compliance_per_angle(
    loads: &[f64],
    mean: &[Vec<f64>],
    repeat_std: &[Vec<f64>],
    nr: usize,
    nodes: usize,
    opts: &Options,
) -> (Vec<f64>, Vec<f64>) {
    let nl = loads.len();
    let sxx = load_sxx(loads);
    let mut compliance = vec![0.0; nodes];
    let mut lack = vec![0.0; nodes];
    for k in 0..nodes {
        let y: Vec<f64> = (0..nl).map(|j| mean[j][k]).collect();
        let (slope, _, rss) = fit::line(loads, &y);
        compliance[k] = slope;
        lack[k] = if nl > 2 {
            rss / (nl - 2) as f64
        } else {
            f64::NAN
        };
    }
    // Its uncertainty: the larger of the repeatability of the load means and the scatter
    // about the line (nonlinearity), each pooled over ±5° where it changes slowly.
    let half = ((5.0 * DEG / opts.grid_step).round() as usize).max(1);
    let rep_var: Vec<f64> = (0..nodes)
        .map(|k| (0..nl).map(|j| repeat_std[j][k].powi(2)).sum::<f64>() / nl as f64 / nr as f64)
        .collect();
    let rep_var = fit::smooth(&rep_var, half);
    let lack = if nl > 2 {
        fit::smooth(&lack, half)
    } else {
        lack
    };
    let compliance_std: Vec<f64> = (0..nodes)
        .map(|k| {
            let v = match (nr > 1, nl > 2) {
                (true, true) => rep_var[k].max(lack[k]),
                (true, false) => rep_var[k],
                (false, true) => lack[k],
                (false, false) => f64::NAN,
            };
            (v / sxx).sqrt()
        })
        .collect();
    (compliance, compliance_std)
}

/// Eq. 9 fitted to the `average` trajectory: the linear sine, the nonlinear one (b free) and
/// whether they disagree; their warnings go into `warnings`.
fn centring_sine(
    angles: &[f64],
    average: &[f64],
    opts: &Options,
    warnings: &mut Vec<String>,
) -> Result<(Sine, Option<Sine>, bool), LdbbError> {
    let lin = fit::sine_linear(angles, average)
        .ok_or_else(|| LdbbError::Options("the sine fit failed (degenerate data)".into()))?;
    let start = match opts.start {
        SineStart::Linear => [lin.a, 1.0, lin.phi, lin.offset],
        SineStart::Paper => [0.8e-3, 1.0, 22.5 * DEG, lin.offset],
    };
    let nonlin = fit::sine_nonlinear(angles, average, start);
    let mut disagree = false;
    if let Some(n) = &nonlin {
        let dphi =
            ((n.phi - lin.phi + std::f64::consts::PI).rem_euclid(TAU) - std::f64::consts::PI).abs();
        if !n.converged {
            warnings.push("the nonlinear sine fit (b free) did not converge".into());
            disagree = true;
        } else if (n.a - lin.a).abs() > (0.005e-3f64).max(0.05 * lin.a)
            || dphi > 2.0 * DEG
            || (n.b - 1.0).abs() > 0.01
        {
            disagree = true;
        }
        if disagree {
            warnings.push(format!(
                "the nonlinear sine fit (b free, started from the {} guess) disagrees with the linear one (b = 1): a {:.4} vs {:.4} mm, b {:.4}, phi {:.2} vs {:.2} deg; a centring offset gives b = 1, b != 1 absorbs part of the kinematic error (the kinematic remainder uses the {} fit)",
                match opts.start { SineStart::Linear => "linear fit's", SineStart::Paper => "paper's" },
                n.a * 1e3,
                lin.a * 1e3,
                n.b,
                n.phi / DEG,
                lin.phi / DEG,
                match opts.sine { SineModel::Linear => "linear", SineModel::Nonlinear => "nonlinear" },
            ));
        }
    } else if opts.sine == SineModel::Nonlinear {
        warnings.push("the nonlinear sine fit failed; the linear fit is used".into());
    }
    Ok((lin, nonlin, disagree))
}

/// The `reference` on the grid (mean removed) and its comparison with the `kinematic` remainder,
/// or none without a reference; the error when it does not cover the circle.
fn compare_reference(
    reference: Option<&Reference>,
    angles: &[f64],
    kinematic: &[f64],
) -> Result<(Option<Vec<f64>>, Option<ReferenceReport>), LdbbError> {
    let nodes = angles.len();
    Ok(match reference {
        None => (None, None),
        Some(rf) => {
            let g = resample::run(&rf.angle, &rf.error, None, nodes).map_err(|gap| {
                LdbbError::Options(format!(
                    "reference: the angles do not cover the circle: no sample between {:.2} and {:.2} deg",
                    gap.from / DEG,
                    gap.to / DEG
                ))
            })?;
            let mr = g.y.iter().sum::<f64>() / nodes as f64;
            let mk = kinematic.iter().sum::<f64>() / nodes as f64;
            let refc: Vec<f64> = g.y.iter().map(|v| v - mr).collect();
            let diff: Vec<f64> = (0..nodes).map(|k| (kinematic[k] - mk) - refc[k]).collect();
            let h1 = without_first_harmonic(angles, &diff);
            let mad = |v: &[f64]| v.iter().map(|x| x.abs()).sum::<f64>() / v.len() as f64;
            (
                Some(refc),
                Some(ReferenceReport {
                    mean_abs_difference_um: r(mad(&diff) / UM, 3),
                    rms_difference_um: r(rms(&diff) / UM, 3),
                    mean_abs_difference_first_harmonic_removed_um: r(mad(&h1) / UM, 3),
                }),
            )
        }
    })
}

/// The joint stiffnesses of `robot` from the compliance per angle, the per-load means and the
/// runs (their recorded joint angles, else inverse kinematics), and whether the angles were
/// recorded; a warning goes into `warnings` when the recorded poses are off the setup's circle.
fn stiffness_of(
    robot: &Robot,
    setup: &Setup,
    runs: &[Run],
    angles: &[f64],
    mean: &[Vec<f64>],
    compliance: &[f64],
    warnings: &mut Vec<String>,
) -> Result<(stiffness::Stiffness, bool), LdbbError> {
    let nodes = angles.len();
    let loads = &setup.loads;
    let (nl, nr) = (loads.len(), setup.repeats);
    let sxx = load_sxx(loads);
    let run_of = |j: usize, r: usize| &runs[j * nr + r].grid;
    let (map, orientation) = setup.tool().map_err(LdbbError::Robot)?;
    let arm = kin::Arm { robot, map };
    let recorded = runs.iter().all(|r| r.grid.q.is_some());
    let q: Vec<[f64; 6]> = if recorded {
        (0..nodes)
            .map(|k| {
                let mut s = [0.0; 6];
                for r in runs {
                    let qk = r.grid.q.as_ref().map_or([0.0; 6], |q| q[k]);
                    for i in 0..6 {
                        s[i] += qk[i] / runs.len() as f64;
                    }
                }
                s
            })
            .collect()
    } else {
        let ik = kin::CircleIk::new(arm.clone(), orientation, setup).map_err(LdbbError::Robot)?;
        angles
            .iter()
            .map(|&t| {
                ik.at(setup, t).ok_or_else(|| {
                    LdbbError::Robot(format!("no IK at circle angle {:.2} deg", t / DEG))
                })
            })
            .collect::<Result<_, _>>()?
    };
    // The bar direction from the recorded pose to the table ball; how far the recorded
    // poses are from the setup's circle tells whether robot and setup belong together.
    let mut worst = 0.0f64;
    let rows: Vec<[f64; 6]> = (0..nodes)
        .map(|k| {
            let p = arm.map_position(&q[k]);
            worst = worst.max((p - setup.circle.point(angles[k])).norm());
            arm.compliance_row(&q[k], &(p - setup.table_ball).normalize())
        })
        .collect();
    if worst > 1e-3 {
        warnings.push(format!(
                    "the recorded joint angles put the tool ball up to {:.1} mm off the setup's circle: check the robot file, end_link and [tool] of the setup",
                    worst * 1e3
                ));
    }
    // The covariance of the compliance over the angles, from whole run curves: each
    // run's deviation from its load's mean, scaled so that Σ e eᵀ = Cov(c).
    let mut c_err = Vec::new();
    if nr > 1 {
        let scale = 1.0 / (sxx * (nr * nl * (nr - 1)) as f64).sqrt();
        for j in 0..nl {
            for r in 0..nr {
                c_err.push(
                    (0..nodes)
                        .map(|k| (run_of(j, r).y[k] - mean[j][k]) * scale)
                        .collect::<Vec<f64>>(),
                );
            }
        }
    }
    // The compliance of the lower and of the upper half of the loads (they share the
    // middle load when the count is odd).
    let half_c = |js: std::ops::Range<usize>| -> Vec<f64> {
        (0..nodes)
            .map(|k| {
                let y: Vec<f64> = js.clone().map(|j| mean[j][k]).collect();
                fit::line(&loads[js.clone()], &y).0
            })
            .collect()
    };
    let levels = (nl >= 3).then(|| (half_c(0..nl.div_ceil(2)), half_c(nl / 2..nl)));
    Ok((
        stiffness::identify(
            &rows,
            compliance,
            &c_err,
            levels.as_ref().map(|(a, b)| (a.as_slice(), b.as_slice())),
        ),
        recorded,
    ))
}

/// The runs' outlier count and median noise (m); warnings go into `warnings` for outliers and
/// for angles whose compliance is not positive.
fn data_warnings(runs: &[Run], compliance: &[f64], warnings: &mut Vec<String>) -> (usize, f64) {
    let nodes = compliance.len();
    let outliers: usize = runs.iter().map(|r| r.grid.outliers).sum();
    if outliers > 0 {
        warnings.push(format!(
            "{outliers} sample(s) more than 8 robust standard deviations off their run's curve were left out"
        ));
    }
    let mut noises: Vec<f64> = runs.iter().map(|r| r.grid.noise).collect();
    noises.sort_by(f64::total_cmp);
    let noise = noises[noises.len() / 2];
    let negative = compliance.iter().filter(|c| **c <= 0.0).count();
    if negative > 0 {
        warnings.push(format!(
            "the compliance along the bar is not positive at {negative} of {nodes} angles: check the sign of deflection_um (positive = longer) and the load order"
        ));
    }
    (outliers, noise)
}

/// The report's stiffness section from the identified stiffness `s`, rounded; `recorded` says
/// where the joint angles came from.
fn stiffness_report(s: &stiffness::Stiffness, recorded: bool) -> StiffnessReport {
    StiffnessReport {
        std_nm_per_rad: s
            .std_nm_per_rad
            .iter()
            .map(|v| v.map(|x| sig(x, 3)))
            .collect(),
        why: s.why.to_vec(),
        combinations: s
            .combinations
            .iter()
            .map(|c| stiffness::Combination {
                joints: c.joints.clone(),
                weights: c.weights.iter().map(|w| r(*w, 4)).collect(),
                compliance_rad_per_nm: sig(c.compliance_rad_per_nm, 4),
                std_rad_per_nm: sig(c.std_rad_per_nm, 3),
                effective_stiffness_nm_per_rad: c.effective_stiffness_nm_per_rad.map(|v| sig(v, 4)),
            })
            .collect(),
        singular_values: s.singular_values.iter().map(|v| sig(*v, 4)).collect(),
        fit_rms_um_per_n: sig(s.fit_rms_um_per_n, 3),
        relative_std_limit: s.relative_std_limit,
        joint_angles: if recorded { "recorded" } else { "ik" },
    }
}

/// A few lines for the terminal.
pub fn summary(a: &Analysis) -> String {
    let r = &a.report;
    let (cmin, cmax) = a
        .compliance
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), c| {
            (lo.min(*c), hi.max(*c))
        });
    let mut s = format!(
        "{} rows: {} loads x {} repeats; compliance along the bar {}..{} µm/N (RMS {}); linearity spread {}\n",
        r.rows,
        a.loads.len(),
        r.repeats,
        fmt_sig(cmin / UM, 3),
        fmt_sig(cmax / UM, 3),
        fmt_sig(r.compliance_rms_um_per_n, 3),
        length_um(r.linearity_spread_um)
    );
    let sf = &r.sine_fit;
    s += &format!(
        "centring sine ({}): a {:.4} mm, b {:.4}, phi {:.2} deg; kinematic error RMS {}",
        match sf.model {
            SineModel::Linear => "linear, b = 1",
            SineModel::Nonlinear => "nonlinear, b free",
        },
        sf.a_mm,
        sf.b,
        sf.phi_deg,
        length_um(r.kinematic_error_rms_um)
    );
    if let Some(rf) = &r.reference {
        s += &format!(
            "; reference: mean |difference| {}",
            length_um(rf.mean_abs_difference_um)
        );
    }
    s.push('\n');
    if let Some(st) = &a.stiffness {
        let k: Vec<String> = (0..6)
            .map(|i| match st.stiffness_nm_per_rad[i] {
                Some(v) => format!("k{} {:.3e}", i + 1, v),
                None => format!("k{} -", i + 1),
            })
            .collect();
        s += &format!("stiffness [N*m/rad]: {}", k.join(", "));
        if !st.combinations.is_empty() {
            s += &format!(
                " (+{} combination(s), see the report)",
                st.combinations.len()
            );
        }
        s.push('\n');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use data::Sample;
    use rand::{Rng, SeedableRng};

    /// A synthetic recording, no robot: reading = kinematic(θ) + compliance(θ)·F + centring
    /// sine + the run's offset + noise, at random angles from each run's own origin.
    fn synthetic(
        loads: &[f64],
        repeats: usize,
        drop: Option<(usize, usize)>,
    ) -> (Loaded, Vec<f64>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let c = |t: f64| 0.4e-6 + 0.1e-6 * (2.0 * t).cos();
        let k = |t: f64| 8e-6 * (3.0 * t + 0.5).sin() + 4e-6 * (2.0 * t).cos();
        let sine = |t: f64| 0.28e-3 * (t - 0.7).sin();
        let mut samples = Vec::new();
        for (j, &f) in loads.iter().enumerate() {
            for r in 1..=repeats {
                if drop == Some((j, r)) {
                    continue;
                }
                let start = rng.random_range(0.0..TAU);
                let off = rng.random_range(-3e-6..3e-6);
                for i in 0..1800 {
                    let t = start + TAU * (i as f64 + rng.random_range(0.0..0.7)) / 1800.0;
                    samples.push(Sample {
                        run: r,
                        load: f,
                        angle: t,
                        q: None,
                        deflection: k(t)
                            + c(t) * f
                            + sine(t)
                            + off
                            + rng.random_range(-1.5e-6..1.5e-6),
                        line: samples.len() + 2,
                    });
                }
            }
        }
        let grid: Vec<f64> = (0..360).map(|i| i as f64 * DEG).collect();
        (Loaded { samples }, grid.iter().map(|&t| k(t)).collect())
    }

    #[test]
    fn recovers_compliance_sine_and_kinematic_error_without_a_robot() {
        let mut setup = setup::tests_support::paper_setup();
        setup.robot = None;
        let (loaded, k) = synthetic(&setup.loads, 3, None);
        let a = run(&loaded, &setup, None, None, &Options::default()).unwrap();
        for (i, t) in a.angles.iter().enumerate() {
            let c = 0.4e-6 + 0.1e-6 * (2.0 * t).cos();
            assert!(
                (a.compliance[i] - c).abs() < 0.01e-6,
                "{i}: {}",
                a.compliance[i]
            );
            assert!((a.kinematic[i] - k[i]).abs() < 1.5e-6, "{i}");
        }
        assert!((a.sine_linear.a - 0.28e-3).abs() < 1e-6);
        assert!((a.sine_linear.phi - 0.7).abs() < 0.01);
        // The stated std of the compliance matches its actual error within a factor 2.
        let err: Vec<f64> = (0..360)
            .map(|i| a.compliance[i] - (0.4e-6 + 0.1e-6 * (2.0 * a.angles[i]).cos()))
            .collect();
        let sd = a.compliance_std.iter().sum::<f64>() / 360.0;
        assert!(
            rms(&err) / sd > 0.3 && rms(&err) / sd < 2.0,
            "{} vs {sd}",
            rms(&err)
        );
        // Linear compliance: the compensated loads differ only by the runs' offsets (±3 µm,
        // 1 µm per load mean) and noise.
        assert!(
            a.report.linearity_spread_um < 6.0,
            "{}",
            a.report.linearity_spread_um
        );
        assert!(a.stiffness.is_none() && a.report.stiffness_nm_per_rad == vec![None; 6]);
    }

    #[test]
    fn the_nonlinear_sine_on_request_and_from_the_papers_guess() {
        let mut setup = setup::tests_support::paper_setup();
        setup.robot = None;
        let (loaded, _) = synthetic(&setup.loads, 3, None);
        let opts = |sine, start| Options {
            sine,
            start,
            ..Options::default()
        };
        let a = run(
            &loaded,
            &setup,
            None,
            None,
            &opts(SineModel::Nonlinear, SineStart::Linear),
        )
        .unwrap();
        let n = a.sine_nonlinear.clone().unwrap();
        assert_eq!(a.report.sine_fit.model, SineModel::Nonlinear);
        assert_eq!(a.report.sine_fit.b, r(n.b, 5));
        assert!((a.kinematic[10] - (a.average[10] - n.eval(a.angles[10]))).abs() < 1e-15);
        // The paper's guess (a = 0.8 mm, φ = 22.5°) reaches the same minimum here.
        let p = run(
            &loaded,
            &setup,
            None,
            None,
            &opts(SineModel::Nonlinear, SineStart::Paper),
        )
        .unwrap();
        let m = p.sine_nonlinear.unwrap();
        assert!(
            (m.a - n.a).abs() < 1e-9 && (m.b - n.b).abs() < 1e-6,
            "{m:?} {n:?}"
        );
        assert_eq!(p.report.sine_fits.nonlinear_start, SineStart::Paper);
    }

    #[test]
    fn structural_errors_name_the_load_and_run() {
        let mut setup = setup::tests_support::paper_setup();
        setup.robot = None;
        let (loaded, _) = synthetic(&setup.loads, 3, Some((2, 2)));
        let e = run(&loaded, &setup, None, None, &Options::default()).unwrap_err();
        assert_eq!(
            e.to_string(),
            "load 375 N: run(s) 2 missing; the setup asks for 3 repeats per load"
        );
        let (mut loaded, _) = synthetic(&setup.loads, 3, None);
        loaded.samples[10].load = 300.0;
        let e = run(&loaded, &setup, None, None, &Options::default()).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("line 12, column 2 (load_n): load 300 N is not one of"),
            "{e}"
        );
        let (mut loaded, _) = synthetic(&setup.loads, 3, None);
        let first = loaded.samples[0].clone();
        loaded.samples.retain(|s| {
            !(s.load == first.load
                && s.run == first.run
                && (s.angle - first.angle).rem_euclid(TAU) > 3.0
                && (s.angle - first.angle).rem_euclid(TAU) < 3.3)
        });
        let e = run(&loaded, &setup, None, None, &Options::default()).unwrap_err();
        assert!(
            e.to_string().contains("the angles do not cover the circle"),
            "{e}"
        );
        let bad = Options {
            grid_step: 7.0 * DEG,
            ..Options::default()
        };
        let (loaded, _) = synthetic(&setup.loads, 3, None);
        assert!(matches!(
            run(&loaded, &setup, None, None, &bad),
            Err(LdbbError::Options(_))
        ));
    }
}

//! What a calibration delivers: in = the fitted estimate (geometry and the effects adopted,
//! with their variances) and the problem it was fitted to; out = the robot file's model (the
//! physical geometry and the effects in the form `robot::effects` reads), each effect's size
//! over the joint space, and the prediction of what the written files deliver.
//!
//! The geometry written is the physical one. The fit takes a cyclic error's harmonics about
//! their mean over the joint's measured range (so that the joint's zero stays separable); the
//! file takes them about zero (their mean over a turn), and the constant between the two goes
//! to the joint's zero, θ. The fit already splits a backlash about the centre of its play and
//! refers a thermal drift to the start of the runs; both are written as they are.

use super::predict;
use crate::diagnose::fit::growth_per_link;
use crate::diagnose::{Basis, Estimate, Problem, Term};
use crate::model::{MeasurementModel, Params};
use crate::robot::effects::{
    Backlash, Compliance, ComplianceForm, Cyclic, Effects, MomentTerm, ServoLag, Thermal,
    ThermalState, G,
};
use crate::robot::Robot;
use crate::twin::effects::Effect;
use nalgebra::Vector3;
use serde::Serialize;

/// The calibrated model as the robot file holds it.
#[derive(Clone, Debug, PartialEq)]
pub struct FileModel {
    /// The physical geometry (run 1's fixture, the calibrated tool point).
    pub params: Params,
    pub effects: Effects,
    /// What a thermal drift is referred to, in words.
    pub reference: String,
}

fn sd(var: &[f64], k: usize) -> f64 {
    var.get(k).map_or(0.0, |v| v.max(0.0).sqrt())
}

/// The robot file's model of an estimate; `var` holds the variances of the effects'
/// coefficients in the order of `est.effects`.
pub fn file_model(problem: &Problem, est: &Estimate, var: &[f64]) -> FileModel {
    let mut params = est.params(0);
    let mut effects = Effects::default();
    let mut reference = String::from("none (no thermal drift)");
    let mut k = 0;
    for t in &est.effects {
        let v = &var[k.min(var.len())..(k + t.coef.len()).min(var.len())];
        k += t.coef.len();
        add_term(problem, t, v, &mut params, &mut effects, &mut reference);
    }
    FileModel {
        params,
        effects,
        reference,
    }
}

fn add_term(
    problem: &Problem,
    t: &Term,
    var: &[f64],
    params: &mut Params,
    effects: &mut Effects,
    reference: &mut String,
) {
    let c = &t.coef;
    match t.effect {
        Effect::CyclicError(j) => {
            let orders = t.basis.orders();
            let mut shift = 0.0;
            for (n, &h) in orders.iter().enumerate() {
                let (ms, mc) = problem.harmonic_mean(j, h);
                shift += c[2 * n] * mc + c[2 * n + 1] * ms;
            }
            params.dh[j].theta -= shift;
            effects.cyclic.push(Cyclic {
                joint: j,
                cos: (0..orders.len()).map(|n| c[2 * n]).collect(),
                sin: (0..orders.len()).map(|n| c[2 * n + 1]).collect(),
                cos_std: (0..orders.len()).map(|n| sd(var, 2 * n)).collect(),
                sin_std: (0..orders.len()).map(|n| sd(var, 2 * n + 1)).collect(),
                orders,
            });
        }
        Effect::Backlash(j) => effects.backlash.push(Backlash {
            joint: j,
            play: c[0].max(0.0),
            play_std: sd(var, 0),
        }),
        Effect::ServoLag => {
            effects.servo_lag = Some(ServoLag {
                tau: c[0],
                tau_std: sd(var, 0),
                second_order: c.get(1).copied().unwrap_or(0.0),
                second_order_std: sd(var, 1),
            })
        }
        Effect::ThermalDrift if !t.basis.is_lag() => {
            let reference_c = problem.first_temperature(0).unwrap_or(0.0);
            *reference = format!(
                "the temperature at the start of the runs ({} C, the first temp_c of run 1)",
                crate::units::fmt_fixed(reference_c, 2)
            );
            let std: Vec<f64> = (0..c.len()).map(|k| sd(var, k)).collect();
            effects.thermal = Some(Thermal::Temperature {
                alpha: growth_per_link(t.basis, c),
                alpha_std: growth_per_link(t.basis, &std),
                reference_c,
            });
        }
        Effect::ThermalDrift => {
            *reference = "the start of each run (t = 0 s of its first reading)".into();
            let n = c.len() - 1;
            let std: Vec<f64> = (0..c.len()).map(|k| sd(var, k)).collect();
            effects.thermal = Some(Thermal::Lag {
                scale: growth_per_link(t.basis, &c[..n]),
                scale_std: growth_per_link(t.basis, &std[..n]),
                time_constant: c[n],
                time_constant_std: sd(var, n),
            });
        }
        Effect::JointCompliance if t.basis == Basis::KnownMasses => {
            effects.compliance = Some(Compliance {
                form: ComplianceForm::KnownMasses {
                    compliance: std::array::from_fn(|j| c[j]),
                    std: std::array::from_fn(|j| sd(var, j)),
                    masses: problem.masses.clone(),
                },
                gravity: [0.0, 0.0, -G],
            })
        }
        Effect::JointCompliance => {
            // The general basis in the fit's column order: joint j, link i > j, mass then the
            // three first moments.
            let mut terms = Vec::with_capacity(c.len());
            let mut n = 0;
            for j in 0..6 {
                for link in j + 1..=6 {
                    for moment in 0..4 {
                        terms.push(MomentTerm {
                            joint: j,
                            link,
                            moment,
                            value: c[n],
                            std: sd(var, n),
                        });
                        n += 1;
                    }
                }
            }
            effects.compliance = Some(Compliance {
                form: ComplianceForm::LinkMoments { terms },
                gravity: [0.0, 0.0, -G],
            })
        }
        Effect::Geometric => {}
    }
}

/// An effect's size: the MAP displacement it causes, after a best rigid registration.
#[derive(Clone, Debug, Serialize)]
pub struct EffectSize {
    pub effect: &'static str,
    pub joint: Option<usize>,
    /// RMS and 95th percentile over random poses of the whole joint space, RMS over the
    /// recorded poses (µm).
    pub workspace_rms_um: f64,
    pub workspace_p95_um: f64,
    pub measured_region_rms_um: f64,
    /// Where the size is taken: one flank of a play, the end of the runs for a drift, along
    /// the recorded motion for a servo lag.
    pub at: String,
    /// Poses (`pose`) or motion only (`motion`: a servo lag moves no pose).
    pub acts_on: &'static str,
    /// In the written robot file, and so applied by `compensate` and the twin.
    pub delivered: bool,
    /// The predicted workspace RMS (µm) were this effect not applied.
    pub prediction_without_um: f64,
}

/// The displacement of each pose (m) a model change makes, after the best rigid registration
/// over the poses: `with` and `without` the change.
fn registered_change(with: &[Vector3<f64>], without: &[Vector3<f64>]) -> Vec<f64> {
    let (_, _, r, t) = predict::register(with, without);
    with.iter()
        .zip(without)
        .map(|(a, b)| (r * a + t - b).norm())
        .collect()
}

/// One effect alone, as a robot file model.
fn only(effects: &Effects, effect: Effect) -> Effects {
    let mut e = Effects::default();
    match effect {
        Effect::CyclicError(j) => {
            e.cyclic = effects
                .cyclic
                .iter()
                .filter(|c| c.joint == j)
                .cloned()
                .collect()
        }
        Effect::Backlash(j) => {
            e.backlash = effects
                .backlash
                .iter()
                .filter(|b| b.joint == j)
                .cloned()
                .collect()
        }
        Effect::JointCompliance => e.compliance = effects.compliance.clone(),
        Effect::ThermalDrift => e.thermal = effects.thermal.clone(),
        Effect::ServoLag => e.servo_lag = effects.servo_lag.clone(),
        Effect::Geometric => {}
    }
    e
}

/// Every effect's size over the poses of the joint space (`space`) and of the measured region
/// (`region`); `state` is the thermal state a drift is sized at, `motion` the recorded
/// joint velocities (rad/s) a servo lag is sized along.
#[allow(clippy::too_many_arguments)]
pub fn sizes(
    model: &MeasurementModel,
    robot: &Robot,
    file: &FileModel,
    adopted: &[Effect],
    space: &[[f64; 6]],
    region: &[[f64; 6]],
    drift_state: (ThermalState, String),
    motion: &[([f64; 6], [f64; 6])],
    delivered: bool,
) -> Vec<(Effect, Vec<f64>, EffectSize)> {
    let p = &file.params;
    let geometry = |q: &[f64; 6]| model.map_position(p, q);
    let mut out = Vec::new();
    for &effect in adopted {
        let e = only(&file.effects, effect);
        // A backlash moves a pose by half the play against the direction it came from: half
        // the poses from below, half from above (one flank everywhere would be a constant
        // joint offset, which a registration removes for joint 1).
        let approach_of = |k: usize| -> [f64; 6] {
            let mut a = [0.0; 6];
            for b in &e.backlash {
                a[b.joint] = if k % 2 == 0 { 1.0 } else { -1.0 };
            }
            a
        };
        let (state, at, acts_on) = match effect {
            Effect::Backlash(_) => (
                ThermalState::Reference,
                "against the centre of the play, half the poses approached from each side"
                    .to_string(),
                "pose",
            ),
            Effect::ThermalDrift => (drift_state.0, drift_state.1.clone(), "pose"),
            Effect::ServoLag => (
                ThermalState::Reference,
                "along the recorded motion (continuous measuring)".to_string(),
                "motion",
            ),
            _ => (ThermalState::Reference, "at every pose".to_string(), "pose"),
        };
        let moved = |k: usize, q: &[f64; 6]| -> Vector3<f64> {
            let load = e.load(&robot.base, &p.dh, &robot.flange, q, &approach_of(k));
            let mut ps = *p;
            ps.dh = e.at_state(&p.dh, state);
            model.map_position(&ps, &load)
        };
        let per = |poses: &[[f64; 6]]| -> Vec<f64> {
            let a: Vec<Vector3<f64>> = poses.iter().enumerate().map(|(k, q)| moved(k, q)).collect();
            let b: Vec<Vector3<f64>> = poses.iter().map(geometry).collect();
            registered_change(&a, &b)
        };
        let (space_m, region_m) = if effect == Effect::ServoLag {
            // A pose is not moved; along the motion the axes are late by τ·q̇ (less the
            // second-order term), which moves the MAP by the position Jacobian times that.
            let Some(l) = &e.servo_lag else { continue };
            let along: Vec<f64> = motion
                .iter()
                .map(|(q, v)| {
                    let late: [f64; 6] = std::array::from_fn(|j| q[j] - l.tau * v[j]);
                    (model.map_position(p, &late) - geometry(q)).norm()
                })
                .collect();
            (along.clone(), along)
        } else {
            (per(space), per(region))
        };
        let s = predict::spread(&space_m.iter().map(|v| v * 1e6).collect::<Vec<_>>());
        let r = predict::spread(&region_m.iter().map(|v| v * 1e6).collect::<Vec<_>>());
        out.push((
            effect,
            space_m,
            EffectSize {
                effect: effect.name(),
                joint: effect.joint(),
                workspace_rms_um: super::round(s.rms, 3),
                workspace_p95_um: super::round(s.p95, 3),
                measured_region_rms_um: super::round(r.rms, 3),
                at,
                acts_on,
                delivered,
                prediction_without_um: 0.0,
            },
        ));
    }
    out
}

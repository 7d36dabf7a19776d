//! The calibrated robot's effects as a compensation applies them: the robot, the tool point and
//! the state asked for (a changed payload, the thermal state, how targets are approached) in;
//! the robot's effects with the payload added and one note per effect out, or why that state
//! does not apply to this robot.

use super::targets::Approach;
use crate::robot::effects::{ComplianceForm, Thermal};
use crate::robot::{Frame, PointMass, Robot};
use crate::units::{fmt_fixed, DEG, MM};
use nalgebra::Vector3;

/// The state a compensation is asked for, as the command line states it.
pub struct Setup<'a> {
    /// A changed payload: its mass (kg) and centre (m, flange frame; None: the tool point).
    pub payload: Option<(f64, Option<Vector3<f64>>)>,
    pub approach: Approach,
    /// The approach as given (for the note).
    pub approach_flag: &'a str,
    /// A program is compensated (else targets).
    pub program: bool,
    pub temperature: Option<f64>,
    pub elapsed: Option<f64>,
}

/// A state that does not apply: to the flags, or to the calibrated robot.
#[derive(Debug)]
pub enum SetupError {
    Flag(String),
    Robot(String),
}

/// The calibrated robot's effects as this compensation applies them: a changed payload
/// (`--payload`) added to a compliance with a mass model, and one note per effect saying how
/// it is applied (and the thermal state, the approach convention, what is not applied).
pub fn effects(calibrated: &mut Robot, tcp: &Frame, s: &Setup) -> Result<Vec<String>, SetupError> {
    let mut notes = Vec::new();
    let e = &mut calibrated.effects;
    if let Some((mass, centre)) = s.payload {
        let centre = centre.unwrap_or(tcp.t);
        match e.compliance.as_mut().map(|c| &mut c.form) {
            Some(ComplianceForm::KnownMasses { masses, .. }) => {
                masses.push(PointMass {
                    frame: 6,
                    com: calibrated.flange.apply(&centre),
                    mass,
                });
                notes.push(format!(
                    "joint compliance: the robot file's masses plus a payload of {} kg at {}, {}, {} mm in the flange frame (--payload)",
                    fmt_fixed(mass, 3),
                    fmt_fixed(centre.x / MM, 1),
                    fmt_fixed(centre.y / MM, 1),
                    fmt_fixed(centre.z / MM, 1)
                ));
            }
            Some(ComplianceForm::LinkMoments { .. }) => {
                return Err(SetupError::Robot(
                    "--payload: its joint compliance was identified without a mass model (form link_moments), for the payload carried during the calibration; a changed payload needs a new calibration with it".into(),
                ))
            }
            None => {
                return Err(SetupError::Robot(
                    "--payload: the robot has no joint compliance (no [effects.joint_compliance]) for a payload to act on".into(),
                ))
            }
        }
    } else if let Some(c) = &e.compliance {
        notes.push(match c.form {
            ComplianceForm::KnownMasses { .. } => "joint compliance: applied to every target with the robot file's masses and gravity as calibrated (--payload adds a changed payload)".to_string(),
            ComplianceForm::LinkMoments { .. } => "joint compliance: applied to every target for the payload and gravity of the calibration (identified without a mass model: a changed payload needs a new calibration)".to_string(),
        });
    }
    let e = &calibrated.effects;
    for c in &e.cyclic {
        notes.push(format!(
            "cyclic error of joint {}: applied to every target (harmonic orders {:?})",
            c.joint + 1,
            c.orders
        ));
    }
    for b in &e.backlash {
        notes.push(format!(
            "backlash of joint {} ({} deg play): applied by each target's approach ({}); a joint whose approach is not known is taken at the centre of the play",
            b.joint + 1,
            fmt_fixed(b.play / DEG, 5),
            if s.program {
                format!(
                    "the direction of the program's move into it; into the first move {}",
                    match s.approach {
                        Approach::Positive => "from below (--approach positive)",
                        Approach::Negative => "from above (--approach negative)",
                        _ => "not known: the centre of the play, up to half of it off (--approach positive or negative says where the robot comes from)",
                    }
                )
            } else {
                format!("the targets' approach column, else --approach {}", s.approach_flag)
            }
        ));
    }
    match (&e.thermal, s.temperature, s.elapsed) {
        (Some(_), None, None) => notes.push(
            "thermal drift: compensated at the reference state of the calibration (--temperature or --elapsed for another)".into(),
        ),
        (Some(Thermal::Temperature { reference_c, .. }), Some(c), _) => notes.push(format!(
            "thermal drift: compensated at {} C ({} K from the reference)",
            fmt_fixed(c, 2),
            fmt_fixed(c - reference_c, 2)
        )),
        (Some(Thermal::Lag { .. }), None, Some(t)) => notes.push(format!(
            "thermal drift: compensated at {} s after the reference state",
            fmt_fixed(t, 1)
        )),
        (Some(_), _, _) => {
            return Err(SetupError::Flag(
                "--temperature applies to a drift referred to a logged temperature, --elapsed to a warm-up lag: the robot's [effects.thermal_drift] form is the other".into(),
            ))
        }
        (None, Some(_), _) | (None, _, Some(_)) => {
            return Err(SetupError::Flag(
                "--temperature/--elapsed: the calibrated robot has no thermal drift".into(),
            ))
        }
        (None, None, None) => {}
    }
    if let Some(l) = &e.servo_lag {
        notes.push(format!(
            "servo lag ({} ms): moves no pose, so no target is changed for it; it matters where the robot measures while moving",
            fmt_fixed(l.tau * 1e3, 2)
        ));
    }
    Ok(notes)
}

/// The calibration report's predicted accuracy (RMS, p95, µm) where it states one; notes say
/// what it does not cover (another tool point given with `tcp_given`) or that it is missing.
pub fn predicted_accuracy(
    report_json: Option<&serde_json::Value>,
    tcp_given: bool,
    notes: &mut Vec<String>,
) -> Option<(f64, f64)> {
    let predicted = report_json.and_then(|v| {
        Some((
            v.pointer("/predicted_position_std_um/workspace_rms")?
                .as_f64()?,
            v.pointer("/predicted_position_std_um/workspace_p95")?
                .as_f64()?,
        ))
    });
    if predicted.is_some() && tcp_given {
        notes.push("the calibration's predicted uncertainty is the MAP's: at another TCP the flange's orientation uncertainty adds, times their distance".into());
    }
    if predicted.is_none() {
        notes.push("the calibration's predicted accuracy is not known here: give --calibration REPORT.json".into());
    }
    predicted
}

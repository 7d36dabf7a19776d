//! The effects library: in = joint angles, time, effect parameters; out = the load-side joint
//! angles (or link lengths) of the real robot. Names are DESIGN.md's, exactly. The same physical
//! models serve the simulator (truth) and the diagnosis (as regressors).

use crate::model::{MeasurementModel, Params};
use crate::robot::kinematics::chain_frames;
use crate::robot::PointMass;
use crate::twin::truth::Cyclic;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Standard gravity, m/s².
pub const G: f64 = 9.80665;
/// A joint that moves less than this between two samples (rad) keeps its last motion
/// direction (the approach direction the fit's screening uses for backlash; 1e-6 rad: far
/// above the CSV's 1e-6° quantisation of the recorded angles).
pub const MOTION_DEADBAND: f64 = 1e-6;

/// Backlash as a play (hysteresis) operator of full width `play` (rad): the load-side angle
/// stays where it was until the motor, `play`/2 away on either side, pushes it. Returns the
/// new load angle. Sampled at the bar's rate it is exact wherever the motor moves
/// monotonically between two samples.
pub fn play(load: f64, motor: f64, play: f64) -> f64 {
    let h = 0.5 * play.max(0.0);
    load.clamp(motor - h, motor + h)
}

/// One effect of the library, with its joint (0-based) where it belongs to one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub enum Effect {
    Geometric,
    JointCompliance,
    ThermalDrift,
    CyclicError(usize),
    Backlash(usize),
    ServoLag,
}

impl Effect {
    /// The name reports use (DESIGN.md).
    pub fn name(&self) -> &'static str {
        match self {
            Effect::Geometric => "geometric",
            Effect::JointCompliance => "joint_compliance",
            Effect::ThermalDrift => "thermal_drift",
            Effect::CyclicError(_) => "cyclic_error",
            Effect::Backlash(_) => "backlash",
            Effect::ServoLag => "servo_lag",
        }
    }

    /// 1-based joint for reports, or None.
    pub fn joint(&self) -> Option<usize> {
        match self {
            Effect::CyclicError(j) | Effect::Backlash(j) => Some(j + 1),
            _ => None,
        }
    }
}

/// Cyclic transmission error of one joint (rad), a few harmonics of its angle.
pub fn cyclic(c: &Cyclic, q: f64) -> f64 {
    (0..3)
        .map(|h| {
            let (s, co) = ((h + 1) as f64 * q).sin_cos();
            c.cos[h] * co + c.sin[h] * s
        })
        .sum()
}

/// Gravity torque about each joint axis (N·m) from point masses, at configuration q.
/// Gravity is −z of the robot base frame; a positive torque turns the joint positively.
pub fn gravity_torques(
    model: &MeasurementModel,
    p: &Params,
    q: &[f64; 6],
    masses: &[PointMass],
) -> [f64; 6] {
    let frames = chain_frames(&model.base, &p.dh, &model.flange, q);
    let mut tau = [0.0; 6];
    for m in masses {
        let k = m.frame.min(6);
        let pos = frames[k].apply(&m.com);
        let f = Vector3::new(0.0, 0.0, -G * m.mass);
        // Joint j (0-based) turns about z of frame j and moves frames j+1.. only.
        for j in 0..k {
            let z = frames[j].r.column(2);
            tau[j] += z.dot(&(pos - frames[j].t).cross(&f));
        }
    }
    tau
}

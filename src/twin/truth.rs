//! The real robot of a simulation (`TRUTH.toml`): in = TOML text in user units (mm, deg, µm);
//! out = [`Truth`] in SI.
//!
//! ```toml
//! noise_um = 0.5            # bar noise, standard deviation (default 0.5)
//! resolution_um = 0.1       # bar resolution (default 0.1)
//! [geometric]               # deviations from nominal, report names: mm for lengths, deg for angles
//! a2 = 0.15
//! theta3 = 0.01
//! [joint_compliance]        # deflection = gravity torque / stiffness
//! stiffness_nm_per_rad = [1e7, 2e6, 2e6, 5e5, 5e5, 5e5]
//! masses_kg = [0, 60, 40, 20, 8, 3]   # lumped at DH frame origins 1..6 (default: URDF inertials)
//! [thermal_drift]           # a_i, d_i scale by 1 + alpha * dT(t), dT = rise * (1 - exp(-t/tc))
//! alpha_per_k = 11.5e-6
//! rise_k = 3.0
//! time_constant_s = 600
//! temp_log = true           # write a temp_c column
//! [cyclic_error]            # load angle += sum_h cos_h cos(h q) + sin_h sin(h q), h = 1..3
//! joint = 2
//! cos_deg = [0.002, 0.0, 0.001]
//! sin_deg = [0.0, 0.001, 0.0]
//! [backlash]                # play operator: the load stays until the motor, play/2 away, pushes it
//! joint = 3
//! play_deg = 0.01
//! [servo_lag]               # the axes follow the logged setpoints with this delay
//! tau_s = 0.004
//! [fixture_slip]            # not a library effect: a disturbance for testing `unexplained`
//! at_s = 30.0
//! shift_mm = [0.03, 0.0, 0.0]
//! ```

use crate::model::{is_angle, MeasurementModel, N_PARAMS, PARAM_NAMES};
use crate::robot::{PointMass, Robot};
use crate::units::{DEG, MM};
use nalgebra::Vector3;
use serde::Deserialize;
use std::collections::BTreeMap;

pub const AMBIENT_C: f64 = 20.0;
const UM: f64 = 1e-6;

#[derive(Clone, Debug, PartialEq)]
pub struct Compliance {
    /// Joint stiffness, N·m/rad.
    pub stiffness: [f64; 6],
    /// Point masses; empty = the robot's URDF inertials.
    pub masses: Vec<PointMass>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Thermal {
    /// Linear expansion coefficient, 1/K.
    pub alpha: f64,
    /// Temperature rise at the end of the warm-up, K.
    pub rise: f64,
    pub time_constant: f64,
    pub temp_log: bool,
}

impl Thermal {
    /// Temperature above ambient at time t (s from the start of recording).
    pub fn delta(&self, t: f64) -> f64 {
        self.rise * (1.0 - (-t / self.time_constant).exp())
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Cyclic {
    /// 0-based joint index.
    pub joint: usize,
    /// Harmonics 1..3, radians.
    pub cos: [f64; 3],
    pub sin: [f64; 3],
}

#[derive(Clone, Debug, PartialEq)]
pub struct Backlash {
    pub joint: usize,
    /// Full play, radians.
    pub play: f64,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Slip {
    pub at_s: f64,
    pub shift: Vector3<f64>,
}

/// The real robot: SI units, 0-based joints.
#[derive(Clone, Debug, PartialEq)]
pub struct Truth {
    /// Bar noise σ (m) and resolution (m).
    pub noise: f64,
    pub resolution: f64,
    /// Deviations from nominal in Eq. 6 order (m, rad).
    pub geometric: [f64; N_PARAMS],
    pub compliance: Option<Compliance>,
    pub thermal: Option<Thermal>,
    pub cyclic: Option<Cyclic>,
    pub backlash: Option<Backlash>,
    /// Servo delay, s.
    pub servo_lag: Option<f64>,
    pub fixture_slip: Option<Slip>,
}

impl Default for Truth {
    fn default() -> Self {
        Truth {
            noise: 0.5 * UM,
            resolution: 0.1 * UM,
            geometric: [0.0; N_PARAMS],
            compliance: None,
            thermal: None,
            cyclic: None,
            backlash: None,
            servo_lag: None,
            fixture_slip: None,
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Spec {
    noise_um: Option<f64>,
    resolution_um: Option<f64>,
    #[serde(default)]
    geometric: BTreeMap<String, f64>,
    joint_compliance: Option<ComplianceSpec>,
    thermal_drift: Option<ThermalSpec>,
    cyclic_error: Option<CyclicSpec>,
    backlash: Option<BacklashSpec>,
    servo_lag: Option<ServoSpec>,
    fixture_slip: Option<SlipSpec>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ComplianceSpec {
    stiffness_nm_per_rad: [f64; 6],
    masses_kg: Option<[f64; 6]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ThermalSpec {
    alpha_per_k: Option<f64>,
    rise_k: f64,
    time_constant_s: Option<f64>,
    #[serde(default)]
    temp_log: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CyclicSpec {
    joint: usize,
    #[serde(default)]
    cos_deg: Vec<f64>,
    #[serde(default)]
    sin_deg: Vec<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BacklashSpec {
    joint: usize,
    play_deg: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ServoSpec {
    tau_s: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SlipSpec {
    at_s: f64,
    shift_mm: [f64; 3],
}

fn joint(section: &str, j: usize) -> Result<usize, String> {
    if (1..=6).contains(&j) {
        Ok(j - 1)
    } else {
        Err(format!("{section}.joint: {j} is not a joint number 1..6"))
    }
}

fn harmonics(key: &str, v: &[f64]) -> Result<[f64; 3], String> {
    if v.len() > 3 {
        return Err(format!(
            "cyclic_error.{key}: at most 3 harmonics, {} given",
            v.len()
        ));
    }
    Ok(std::array::from_fn(|h| {
        v.get(h).copied().unwrap_or(0.0) * DEG
    }))
}

impl Truth {
    /// Parses TRUTH.toml; errors are one line naming the line/key.
    pub fn from_toml(text: &str) -> Result<Truth, String> {
        let spec: Spec =
            toml::from_str(text).map_err(|e| crate::robot::dh::toml_error(text, &e))?;
        let mut t = Truth {
            noise: spec.noise_um.unwrap_or(0.5) * UM,
            resolution: spec.resolution_um.unwrap_or(0.1) * UM,
            ..Truth::default()
        };
        if !(t.noise >= 0.0 && t.resolution >= 0.0) {
            return Err("noise_um and resolution_um must be >= 0".into());
        }
        for (name, v) in &spec.geometric {
            let k = PARAM_NAMES.iter().position(|n| n == name).ok_or_else(|| {
                format!("geometric.{name}: not a parameter name (x_fix, alpha1, a2, d3, theta4, x_map, ...)")
            })?;
            t.geometric[k] = v * if is_angle(k) { DEG } else { MM };
        }
        if let Some(c) = spec.joint_compliance {
            if c.stiffness_nm_per_rad
                .iter()
                .any(|k| k.is_nan() || *k <= 0.0)
            {
                return Err("joint_compliance.stiffness_nm_per_rad: must all be > 0".into());
            }
            t.compliance = Some(Compliance {
                stiffness: c.stiffness_nm_per_rad,
                masses: c.masses_kg.map(|m| lumped_masses(&m)).unwrap_or_default(),
            });
        }
        if let Some(th) = spec.thermal_drift {
            let tc = th.time_constant_s.unwrap_or(600.0);
            if tc.is_nan() || tc <= 0.0 {
                return Err("thermal_drift.time_constant_s: must be > 0".into());
            }
            t.thermal = Some(Thermal {
                alpha: th.alpha_per_k.unwrap_or(11.5e-6),
                rise: th.rise_k,
                time_constant: tc,
                temp_log: th.temp_log,
            });
        }
        if let Some(c) = spec.cyclic_error {
            t.cyclic = Some(Cyclic {
                joint: joint("cyclic_error", c.joint)?,
                cos: harmonics("cos_deg", &c.cos_deg)?,
                sin: harmonics("sin_deg", &c.sin_deg)?,
            });
        }
        if let Some(b) = spec.backlash {
            t.backlash = Some(Backlash {
                joint: joint("backlash", b.joint)?,
                play: b.play_deg * DEG,
            });
        }
        if let Some(s) = spec.servo_lag {
            if !(s.tau_s.is_finite() && s.tau_s.abs() < 1.0) {
                return Err("servo_lag.tau_s: must be below 1 s".into());
            }
            t.servo_lag = Some(s.tau_s);
        }
        if let Some(s) = spec.fixture_slip {
            t.fixture_slip = Some(Slip {
                at_s: s.at_s,
                shift: Vector3::from(s.shift_mm) * MM,
            });
        }
        Ok(t)
    }

    /// The masses joint compliance acts on: the truth's own, else the robot's URDF inertials,
    /// else a generic 130 kg-class arm lumped at the DH frame origins.
    pub fn compliance_masses(&self, robot: &Robot) -> Vec<PointMass> {
        match &self.compliance {
            Some(c) if !c.masses.is_empty() => c.masses.clone(),
            _ if !robot.masses.is_empty() => robot.masses.clone(),
            _ => lumped_masses(&DEFAULT_MASSES_KG),
        }
    }

    /// The true geometric parameters.
    pub fn params(&self, model: &MeasurementModel) -> crate::model::Params {
        let mut p = model.nominal.to_array();
        for k in 0..N_PARAMS {
            p[k] += self.geometric[k];
        }
        crate::model::Params::from_array(&p)
    }
}

/// Lumped masses of a generic large arm at DH frames 1..6 (kg).
pub const DEFAULT_MASSES_KG: [f64; 6] = [0.0, 80.0, 50.0, 25.0, 8.0, 3.0];

fn lumped_masses(m: &[f64; 6]) -> Vec<PointMass> {
    (0..6)
        .filter(|&i| m[i] > 0.0)
        .map(|i| PointMass {
            frame: i + 1,
            com: Vector3::zeros(),
            mass: m[i],
        })
        .collect()
}

//! The effects a calibrated robot carries beside its geometry: in = the `[effects]` table of a
//! `.dh.toml` (or of the sidecar file a calibrated URDF names), in the units its keys name;
//! out = [`Effects`] in SI, how they move the robot (the load-side joints a command reaches,
//! the link lengths at a thermal state), their inverse (the command that reaches given
//! load-side joints), and the table written back.
//!
//! The model, per joint j with the commanded (motor-side) angle q_j:
//!
//! ```text
//! load_j = q_j + Σ_h (cos_h·cos(h·q_j) + sin_h·sin(h·q_j))     cyclic error: zero mean over a turn
//!              − play_j/2 · approach_j                         backlash: the geometry is the play's centre
//!              + Σ_terms c · g_term(q)                         gravity compliance (at the reference geometry)
//! a_i, d_i → a_i, d_i · (1 + s_i·(1 − exp(−t/τ)))              thermal drift, t from the reference state
//!          or a_i, d_i · (1 + α_i·(T − T_ref))                 ... referred to a logged temperature
//! ```
//!
//! `approach_j` is +1 when the joint last moved in the positive direction into the pose, −1 in
//! the negative one, 0 when unknown (the centre of the play). The servo lag belongs to motion:
//! it delays a moving axis and leaves a pose where it is, so [`Effects::load`] has no term for
//! it; the twin applies it along a trajectory.

use super::kinematics::{chain_frames, Frame};
use super::{Dh, PointMass};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// The version of the section; a file without the section is geometry only.
pub const SCHEMA: &str = "edbbgen.effects/1";
/// The comment a calibrated URDF names its sidecar file with: `<!-- edbbgen effects: FILE -->`.
pub const SIDECAR_MARK: &str = "edbbgen effects:";
/// Standard gravity (m/s²), the direction the calibration assumes: −z of the robot base.
pub const G: f64 = 9.80665;

const DEG: f64 = std::f64::consts::PI / 180.0;

/// A cyclic (transmission) error of one joint: harmonics of its own angle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cyclic {
    /// 0-based.
    pub joint: usize,
    /// Harmonic orders, ascending; `cos`, `sin` (rad) and their standard uncertainties per order.
    pub orders: Vec<usize>,
    pub cos: Vec<f64>,
    pub sin: Vec<f64>,
    pub cos_std: Vec<f64>,
    pub sin_std: Vec<f64>,
}

/// Backlash of one joint: the full play (rad) around the geometry's joint zero.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Backlash {
    pub joint: usize,
    pub play: f64,
    pub play_std: f64,
}

/// One term of a gravity compliance identified without a mass model: joint `joint`'s
/// compliance times the mass (`moment` 0) or the first moment along axis `moment` − 1 of DH
/// frame `link`'s (1..=6) axes of everything rigid with that frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MomentTerm {
    pub joint: usize,
    pub link: usize,
    pub moment: usize,
    /// rad·kg/(N·m) for a mass, rad·kg·m/(N·m) for a first moment.
    pub value: f64,
    pub std: f64,
}

/// How a gravity compliance was identified.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ComplianceForm {
    /// A compliance per joint (rad/(N·m)) times the gravity torque of point masses: a payload
    /// is one more mass, so a changed payload can be evaluated.
    KnownMasses {
        compliance: [f64; 6],
        std: [f64; 6],
        masses: Vec<PointMass>,
    },
    /// The general gravity basis (no mass model): valid for the payload carried during the
    /// calibration only.
    LinkMoments { terms: Vec<MomentTerm> },
}

/// Joint deflection under gravity.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Compliance {
    pub form: ComplianceForm,
    /// Gravity in the robot base frame (m/s²) as it was during the calibration.
    pub gravity: [f64; 3],
}

/// Thermal growth of the links, per link (DH row i scales its `a` and `d`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Thermal {
    /// 1 + scale_i·(1 − exp(−t/τ)), t (s) since the reference state (the start of the runs).
    Lag {
        scale: [f64; 6],
        scale_std: [f64; 6],
        time_constant: f64,
        time_constant_std: f64,
    },
    /// 1 + α_i·(T − T_ref) for a temperature T (°C) as the runs logged it.
    Temperature {
        alpha: [f64; 6],
        alpha_std: [f64; 6],
        reference_c: f64,
    },
}

/// The axes follow their setpoints late by τ (s), with a second-order term c₂ (s²):
/// x = s(t − τ) + c₂·s̈.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ServoLag {
    pub tau: f64,
    pub tau_std: f64,
    pub second_order: f64,
    pub second_order_std: f64,
}

/// Every effect a robot file carries; the default is none (geometry only).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Effects {
    pub cyclic: Vec<Cyclic>,
    pub backlash: Vec<Backlash>,
    pub compliance: Option<Compliance>,
    pub thermal: Option<Thermal>,
    pub servo_lag: Option<ServoLag>,
}

/// The thermal state a robot is evaluated at.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum ThermalState {
    /// The state the file's geometry describes.
    #[default]
    Reference,
    /// Seconds since the reference state (a lag drift).
    Elapsed(f64),
    /// A temperature (°C; a drift referred to a logged temperature).
    Temperature(f64),
}

/// Torque about joint j per unit mass at frame i's origin (comp 0) or per unit first moment
/// along frame i's axis comp − 1 (comp 1..=3), under gravity `g` (base frame).
pub fn gravity_basis(fr: &[Frame; 8], g: &Vector3<f64>, j: usize, i: usize, comp: usize) -> f64 {
    let z = fr[j].r.column(2);
    let arm = if comp == 0 {
        fr[i].t - fr[j].t
    } else {
        fr[i].r.column(comp - 1).into_owned()
    };
    z.dot(&arm.cross(g))
}

/// Gravity torques about every joint axis (N·m) of point masses, from the chain's frames.
pub fn gravity_torques(fr: &[Frame; 8], masses: &[PointMass], g: &Vector3<f64>) -> [f64; 6] {
    let mut tau = [0.0; 6];
    for m in masses {
        let k = m.frame.min(6);
        let pos = fr[k].apply(&m.com);
        let f = g * m.mass;
        // Joint j (0-based) turns about z of frame j and moves frames j+1.. only.
        for (j, t) in tau.iter_mut().enumerate().take(k) {
            let z = fr[j].r.column(2);
            *t += z.dot(&(pos - fr[j].t).cross(&f));
        }
    }
    tau
}

impl Effects {
    /// No effect: the robot is its geometry.
    pub fn is_empty(&self) -> bool {
        *self == Effects::default()
    }

    /// Effects that move a robot standing still (all but the servo lag).
    pub fn act_on_poses(&self) -> bool {
        !(self.cyclic.is_empty()
            && self.backlash.is_empty()
            && self.compliance.is_none()
            && self.thermal.is_none())
    }

    /// The joints with a backlash.
    pub fn backlash_joints(&self) -> impl Iterator<Item = usize> + '_ {
        self.backlash.iter().map(|b| b.joint)
    }

    /// The load-side joint angles the commanded angles `q` reach: cyclic errors, backlash by
    /// each joint's `approach` (+1, −1, 0 = the centre of the play) and gravity compliance at
    /// the reference geometry (`base`, `dh`, `flange`).
    pub fn load(
        &self,
        base: &Frame,
        dh: &[Dh; 6],
        flange: &Frame,
        q: &[f64; 6],
        approach: &[f64; 6],
    ) -> [f64; 6] {
        let mut out = *q;
        for c in &self.cyclic {
            out[c.joint] += cyclic_value(c, q[c.joint]);
        }
        for b in &self.backlash {
            out[b.joint] -= 0.5 * b.play * side(approach[b.joint]);
        }
        if let Some(c) = &self.compliance {
            let fr = chain_frames(base, dh, flange, q);
            let g = Vector3::from(c.gravity);
            match &c.form {
                ComplianceForm::KnownMasses {
                    compliance, masses, ..
                } => {
                    let tau = gravity_torques(&fr, masses, &g);
                    for j in 0..6 {
                        out[j] += compliance[j] * tau[j];
                    }
                }
                ComplianceForm::LinkMoments { terms } => {
                    for t in terms {
                        out[t.joint] += t.value * gravity_basis(&fr, &g, t.joint, t.link, t.moment);
                    }
                }
            }
        }
        out
    }

    /// The commanded angles whose load side is `target` (the inverse of [`Effects::load`]):
    /// q = target − e(q) by fixed-point iteration. The corrections change by far less than
    /// the joint angle does (their derivatives are of the order of a harmonic's amplitude
    /// times its order, or a compliance times a torque's derivative: 1e-3 at most), so each
    /// iteration gains three digits or more.
    pub fn command(
        &self,
        base: &Frame,
        dh: &[Dh; 6],
        flange: &Frame,
        target: &[f64; 6],
        approach: &[f64; 6],
    ) -> [f64; 6] {
        let mut q = *target;
        for _ in 0..30 {
            let load = self.load(base, dh, flange, &q, approach);
            let next: [f64; 6] = std::array::from_fn(|j| q[j] + (target[j] - load[j]));
            let step = (0..6).map(|j| (next[j] - q[j]).abs()).fold(0.0, f64::max);
            q = next;
            if step < 1e-15 {
                break;
            }
        }
        q
    }

    /// The geometry at a thermal state: the file's geometry is the reference state.
    pub fn at_state(&self, dh: &[Dh; 6], state: ThermalState) -> [Dh; 6] {
        let growth = self.growth(state);
        std::array::from_fn(|i| Dh {
            a: dh[i].a * (1.0 + growth[i]),
            d: dh[i].d * (1.0 + growth[i]),
            ..dh[i]
        })
    }

    /// Each link's relative growth at a thermal state.
    pub fn growth(&self, state: ThermalState) -> [f64; 6] {
        match (&self.thermal, state) {
            (
                Some(Thermal::Lag {
                    scale,
                    time_constant,
                    ..
                }),
                ThermalState::Elapsed(t),
            ) => {
                let f = 1.0 - (-t.max(0.0) / time_constant).exp();
                scale.map(|s| s * f)
            }
            (
                Some(Thermal::Temperature {
                    alpha, reference_c, ..
                }),
                ThermalState::Temperature(c),
            ) => alpha.map(|a| a * (c - reference_c)),
            _ => [0.0; 6],
        }
    }
}

/// +1, −1, or 0 for an approach that is not known (the centre of the play).
fn side(approach: f64) -> f64 {
    if approach > 0.0 {
        1.0
    } else if approach < 0.0 {
        -1.0
    } else {
        0.0
    }
}

impl Effects {
    /// The same effects referred to another description of the same chain (`to`: base
    /// transform, DH table, flange transform; `from` the one they were identified in), whose
    /// DH frames may sit differently on the same links (a calibrated URDF loads to a DH table
    /// whose common normals may point the other way). Each link's frame in `to` is a fixed
    /// rigid motion T of its frame in `from` (T = F_from⁻¹·F_to, the same at every q): a mass
    /// stays, its centre c becomes T⁻¹·c, and a mass m with first moment M (the compliance's
    /// general terms are both, times a compliance) becomes m and Rᵀ(M − m·t).
    pub fn reframed(
        &self,
        from: (&Frame, &[Dh; 6], &Frame),
        to: (&Frame, &[Dh; 6], &Frame),
    ) -> Effects {
        let mut out = self.clone();
        let Some(c) = out.compliance.as_mut() else {
            return out;
        };
        let zero = [0.0; 6];
        let fa = chain_frames(from.0, from.1, from.2, &zero);
        let fb = chain_frames(to.0, to.1, to.2, &zero);
        let t: [Frame; 8] = std::array::from_fn(|i| fa[i].inverse().mul(&fb[i]));
        match &mut c.form {
            ComplianceForm::KnownMasses { masses, .. } => {
                for m in masses.iter_mut() {
                    let k = m.frame.min(6);
                    m.com = t[k].inverse().apply(&m.com);
                }
            }
            ComplianceForm::LinkMoments { terms } => {
                let value = |terms: &[MomentTerm], j: usize, l: usize, m: usize| {
                    terms
                        .iter()
                        .find(|x| x.joint == j && x.link == l && x.moment == m)
                        .map_or((0.0, 0.0), |x| (x.value, x.std))
                };
                let old = terms.clone();
                for x in terms.iter_mut().filter(|x| x.moment > 0) {
                    let tr = &t[x.link];
                    let (vm, _) = value(&old, x.joint, x.link, 0);
                    let v = Vector3::from_fn(|a, _| value(&old, x.joint, x.link, a + 1).0);
                    let s = Vector3::from_fn(|a, _| value(&old, x.joint, x.link, a + 1).1);
                    let moved = tr.r.transpose() * (v - tr.t * vm);
                    x.value = moved[x.moment - 1];
                    // Standard uncertainties through the rotation (the mass term's share
                    // neglected: its translation is a millimetre at most).
                    let r = tr.r.transpose();
                    x.std = (0..3)
                        .map(|a| (r[(x.moment - 1, a)] * s[a]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                }
            }
        }
        out
    }
}

impl super::Robot {
    /// The pose of a point of the flange frame (the MAP, a TCP) in the base frame when the
    /// robot is commanded `q`: its effects applied (each joint coming from `approach`) to the
    /// geometry at a thermal `state`. Without effects, [`super::Robot::point`].
    pub fn reached_point(
        &self,
        q: &[f64; 6],
        p_flange: &Vector3<f64>,
        approach: &[f64; 6],
        state: ThermalState,
    ) -> Vector3<f64> {
        let load = self
            .effects
            .load(&self.base, &self.dh, &self.flange, q, approach);
        let dh = self.effects.at_state(&self.dh, state);
        super::kinematics::flange_pose(&self.base, &dh, &self.flange, &load).apply(p_flange)
    }
}

/// A cyclic error's value (rad) at the joint's commanded angle.
pub fn cyclic_value(c: &Cyclic, q: f64) -> f64 {
    c.orders
        .iter()
        .zip(c.cos.iter().zip(&c.sin))
        .map(|(&h, (a, b))| {
            let (s, co) = (h as f64 * q).sin_cos();
            a * co + b * s
        })
        .sum()
}

// ---- the file form -------------------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileEffects {
    schema: String,
    #[serde(default)]
    cyclic_error: Vec<FileCyclic>,
    #[serde(default)]
    backlash: Vec<FileBacklash>,
    #[serde(default)]
    joint_compliance: Option<FileCompliance>,
    #[serde(default)]
    thermal_drift: Option<FileThermal>,
    #[serde(default)]
    servo_lag: Option<FileServo>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileCyclic {
    joint: usize,
    orders: Vec<usize>,
    cos_deg: Vec<f64>,
    sin_deg: Vec<f64>,
    #[serde(default)]
    cos_std_deg: Option<Vec<f64>>,
    #[serde(default)]
    sin_std_deg: Option<Vec<f64>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileBacklash {
    joint: usize,
    play_deg: f64,
    #[serde(default)]
    play_std_deg: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileMass {
    frame: usize,
    mass_kg: f64,
    com_mm: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileTerm {
    joint: usize,
    link: usize,
    moment: String,
    value: f64,
    #[serde(default)]
    std: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileCompliance {
    form: String,
    gravity_mps2: [f64; 3],
    /// For people: where the payload comes from.
    #[serde(default)]
    #[allow(dead_code)]
    payload: Option<String>,
    #[serde(default)]
    compliance_rad_per_nm: Option<[f64; 6]>,
    #[serde(default)]
    compliance_std_rad_per_nm: Option<[f64; 6]>,
    #[serde(default)]
    masses: Vec<FileMass>,
    #[serde(default)]
    terms: Vec<FileTerm>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileThermal {
    form: String,
    #[serde(default)]
    scale: Option<[f64; 6]>,
    #[serde(default)]
    scale_std: Option<[f64; 6]>,
    #[serde(default)]
    time_constant_s: Option<f64>,
    #[serde(default)]
    time_constant_std_s: Option<f64>,
    #[serde(default)]
    alpha_per_k: Option<[f64; 6]>,
    #[serde(default)]
    alpha_std_per_k: Option<[f64; 6]>,
    #[serde(default)]
    reference_temp_c: Option<f64>,
    /// For people: what the reference state is.
    #[serde(default)]
    #[allow(dead_code)]
    reference: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileServo {
    tau_s: f64,
    #[serde(default)]
    tau_std_s: f64,
    #[serde(default)]
    second_order_s2: f64,
    #[serde(default)]
    second_order_std_s2: f64,
}

const MOMENTS: [&str; 4] = ["mass", "x", "y", "z"];

fn joint_index(j: usize, what: &str) -> Result<usize, String> {
    if (1..=6).contains(&j) {
        Ok(j - 1)
    } else {
        Err(format!("{what}: joint {j} (expected 1..6)"))
    }
}

fn finite(v: &[f64], what: &str) -> Result<(), String> {
    match v.iter().find(|x| !x.is_finite()) {
        Some(x) => Err(format!("{what}: {x} is not a number")),
        None => Ok(()),
    }
}

/// Reads an `[effects]` table (the TOML value of the key `effects`). Errors name the key.
pub fn from_toml(value: toml::Value) -> Result<Effects, String> {
    let f: FileEffects = value
        .try_into()
        .map_err(|e: toml::de::Error| format!("effects: {}", e.message().trim()))?;
    if f.schema != SCHEMA {
        return Err(format!(
            "effects.schema: \"{}\" is not a version this edbbgen reads (\"{SCHEMA}\")",
            f.schema
        ));
    }
    let mut out = Effects::default();
    for c in f.cyclic_error {
        out.cyclic.push(cyclic(c, &out.cyclic)?);
    }
    for b in f.backlash {
        let joint = joint_index(b.joint, "effects.backlash")?;
        if !(b.play_deg.is_finite() && b.play_deg >= 0.0) {
            return Err(format!(
                "effects.backlash (joint {}): play_deg {} is not a play (>= 0)",
                b.joint, b.play_deg
            ));
        }
        if out.backlash.iter().any(|x| x.joint == joint) {
            return Err(format!(
                "effects.backlash: joint {} is given twice",
                b.joint
            ));
        }
        out.backlash.push(Backlash {
            joint,
            play: b.play_deg * DEG,
            play_std: b.play_std_deg * DEG,
        });
    }
    if let Some(c) = f.joint_compliance {
        out.compliance = Some(compliance(c)?);
    }
    if let Some(t) = f.thermal_drift {
        out.thermal = Some(thermal(t)?);
    }
    if let Some(s) = f.servo_lag {
        finite(&[s.tau_s, s.second_order_s2], "effects.servo_lag")?;
        out.servo_lag = Some(ServoLag {
            tau: s.tau_s,
            tau_std: s.tau_std_s,
            second_order: s.second_order_s2,
            second_order_std: s.second_order_std_s2,
        });
    }
    Ok(out)
}

/// One joint's cyclic error, checked (`known`: the joints read before it).
fn cyclic(c: FileCyclic, known: &[Cyclic]) -> Result<Cyclic, String> {
    let joint = joint_index(c.joint, "effects.cyclic_error")?;
    let n = c.orders.len();
    let zeros = vec![0.0; n];
    let cos_std = c.cos_std_deg.unwrap_or_else(|| zeros.clone());
    let sin_std = c.sin_std_deg.unwrap_or(zeros);
    if n == 0
        || c.cos_deg.len() != n
        || c.sin_deg.len() != n
        || cos_std.len() != n
        || sin_std.len() != n
    {
        return Err(format!(
            "effects.cyclic_error (joint {}): orders, cos_deg, sin_deg (and their std) need one value per order",
            c.joint
        ));
    }
    if c.orders.contains(&0) || c.orders.windows(2).any(|w| w[0] >= w[1]) {
        return Err(format!(
            "effects.cyclic_error (joint {}): orders must be ascending and at least 1",
            c.joint
        ));
    }
    if known.iter().any(|x| x.joint == joint) {
        return Err(format!(
            "effects.cyclic_error: joint {} is given twice",
            c.joint
        ));
    }
    for v in [&c.cos_deg, &c.sin_deg, &cos_std, &sin_std] {
        finite(v, "effects.cyclic_error")?;
    }
    Ok(Cyclic {
        joint,
        orders: c.orders,
        cos: c.cos_deg.iter().map(|v| v * DEG).collect(),
        sin: c.sin_deg.iter().map(|v| v * DEG).collect(),
        cos_std: cos_std.iter().map(|v| v * DEG).collect(),
        sin_std: sin_std.iter().map(|v| v * DEG).collect(),
    })
}

/// The joint compliance, checked: known masses or link moments.
fn compliance(c: FileCompliance) -> Result<Compliance, String> {
    finite(&c.gravity_mps2, "effects.joint_compliance.gravity_mps2")?;
    let form = match c.form.as_str() {
        "known_masses" => known_masses(&c)?,
        "link_moments" => link_moments(&c)?,
        other => {
            return Err(format!(
                "effects.joint_compliance.form: \"{other}\" (expected \"known_masses\" or \"link_moments\")"
            ))
        }
    };
    Ok(Compliance {
        form,
        gravity: c.gravity_mps2,
    })
}

fn known_masses(c: &FileCompliance) -> Result<ComplianceForm, String> {
    let compliance = c
        .compliance_rad_per_nm
        .ok_or("effects.joint_compliance: form \"known_masses\" needs compliance_rad_per_nm")?;
    finite(
        &compliance,
        "effects.joint_compliance.compliance_rad_per_nm",
    )?;
    let mut masses = Vec::with_capacity(c.masses.len());
    for m in &c.masses {
        if m.frame > 6 || !(m.mass_kg.is_finite() && m.mass_kg >= 0.0) {
            return Err(format!(
                "effects.joint_compliance.masses: frame {} (0..6), mass {} kg (>= 0)",
                m.frame, m.mass_kg
            ));
        }
        finite(&m.com_mm, "effects.joint_compliance.masses.com_mm")?;
        masses.push(PointMass {
            frame: m.frame,
            com: Vector3::from(m.com_mm) * 1e-3,
            mass: m.mass_kg,
        });
    }
    Ok(ComplianceForm::KnownMasses {
        compliance,
        std: c.compliance_std_rad_per_nm.unwrap_or([0.0; 6]),
        masses,
    })
}

fn link_moments(c: &FileCompliance) -> Result<ComplianceForm, String> {
    let mut terms = Vec::with_capacity(c.terms.len());
    for t in &c.terms {
        let joint = joint_index(t.joint, "effects.joint_compliance.terms")?;
        let moment = MOMENTS.iter().position(|m| *m == t.moment).ok_or_else(|| {
            format!(
                "effects.joint_compliance.terms: moment \"{}\" (expected mass, x, y or z)",
                t.moment
            )
        })?;
        if t.link <= joint || t.link > 6 {
            return Err(format!(
                "effects.joint_compliance.terms: link {} of joint {} (a link after the joint, up to 6)",
                t.link, t.joint
            ));
        }
        finite(&[t.value, t.std], "effects.joint_compliance.terms")?;
        terms.push(MomentTerm {
            joint,
            link: t.link,
            moment,
            value: t.value,
            std: t.std,
        });
    }
    Ok(ComplianceForm::LinkMoments { terms })
}

/// The thermal drift, checked: a lag or a temperature coefficient.
fn thermal(t: FileThermal) -> Result<Thermal, String> {
    Ok(match t.form.as_str() {
        "lag" => {
            let (Some(scale), Some(tau)) = (t.scale, t.time_constant_s) else {
                return Err(
                    "effects.thermal_drift: form \"lag\" needs scale and time_constant_s".into(),
                );
            };
            finite(&scale, "effects.thermal_drift.scale")?;
            if !(tau.is_finite() && tau > 0.0) {
                return Err(format!(
                    "effects.thermal_drift.time_constant_s: {tau} (expected > 0)"
                ));
            }
            Thermal::Lag {
                scale,
                scale_std: t.scale_std.unwrap_or([0.0; 6]),
                time_constant: tau,
                time_constant_std: t.time_constant_std_s.unwrap_or(0.0),
            }
        }
        "temperature" => {
            let (Some(alpha), Some(reference_c)) = (t.alpha_per_k, t.reference_temp_c) else {
                return Err("effects.thermal_drift: form \"temperature\" needs alpha_per_k and reference_temp_c".into());
            };
            finite(&alpha, "effects.thermal_drift.alpha_per_k")?;
            finite(&[reference_c], "effects.thermal_drift.reference_temp_c")?;
            Thermal::Temperature {
                alpha,
                alpha_std: t.alpha_std_per_k.unwrap_or([0.0; 6]),
                reference_c,
            }
        }
        other => {
            return Err(format!(
                "effects.thermal_drift.form: \"{other}\" (expected \"lag\" or \"temperature\")"
            ))
        }
    })
}

/// A number as TOML writes it: the shortest text that reads back to the same f64.
fn num(v: f64) -> String {
    let v = if v == 0.0 { 0.0 } else { v };
    let s = format!("{v:?}");
    if s.contains('.') || s.contains('e') || s.contains("inf") || s.contains("NaN") {
        s
    } else {
        format!("{s}.0")
    }
}

fn list(v: impl IntoIterator<Item = f64>) -> String {
    let items: Vec<String> = v.into_iter().map(num).collect();
    format!("[{}]", items.join(", "))
}

/// The `[effects]` table as text (every number exact), with comments that say what each
/// effect means and the state it refers to; empty for no effects. `reference` says what the
/// reference state of a thermal drift is.
pub fn to_toml(e: &Effects, reference: &str) -> String {
    if e.is_empty() {
        return String::new();
    }
    let mut s = String::new();
    s += "# Effects calibrated with the geometry above; the geometry is the physical one: a\n";
    s +=
        "# cyclic error has zero mean over a turn (its constant part is in theta), a backlash is\n";
    s += "# split about the centre of its play, a thermal drift is zero at its reference state.\n";
    s += "# Commanded angle q (the controller's), load-side angle the arm reaches:\n";
    s += "#   load = q + sum_h cos_h cos(h q) + sin_h sin(h q)  - play/2 * approach  + compliance * gravity torque\n";
    s += "# Standard uncertainties beside each value (*_std*).\n";
    s += "[effects]\n";
    s += &format!("schema = \"{SCHEMA}\"\n");
    for c in &e.cyclic {
        s += "\n[[effects.cyclic_error]]\n";
        s += &format!("joint = {}\n", c.joint + 1);
        s += &format!(
            "orders = [{}]\n",
            c.orders
                .iter()
                .map(|h| h.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
        s += &format!("cos_deg = {}\n", list(c.cos.iter().map(|v| v / DEG)));
        s += &format!("sin_deg = {}\n", list(c.sin.iter().map(|v| v / DEG)));
        s += &format!(
            "cos_std_deg = {}\n",
            list(c.cos_std.iter().map(|v| v / DEG))
        );
        s += &format!(
            "sin_std_deg = {}\n",
            list(c.sin_std.iter().map(|v| v / DEG))
        );
    }
    for b in &e.backlash {
        s += "\n[[effects.backlash]]\n";
        s += "# the arm rests on one flank: load = q - play/2 when it came from below (moving +), + play/2 from above\n";
        s += &format!("joint = {}\n", b.joint + 1);
        s += &format!("play_deg = {}\n", num(b.play / DEG));
        s += &format!("play_std_deg = {}\n", num(b.play_std / DEG));
    }
    if let Some(c) = &e.compliance {
        s += "\n[effects.joint_compliance]\n";
        match &c.form {
            ComplianceForm::KnownMasses {
                compliance,
                std,
                masses,
            } => {
                s += "# deflection of joint j = compliance_j * gravity torque of the masses (a payload is one more mass on frame 6)\n";
                s += "form = \"known_masses\"\n";
                s += &format!("gravity_mps2 = {}\n", list(c.gravity));
                s += "payload = \"the masses below\"\n";
                s += &format!("compliance_rad_per_nm = {}\n", list(*compliance));
                s += &format!("compliance_std_rad_per_nm = {}\n", list(*std));
                for m in masses {
                    s += "\n[[effects.joint_compliance.masses]]\n";
                    s += &format!("frame = {}\n", m.frame);
                    s += &format!("mass_kg = {}\n", num(m.mass));
                    s += &format!("com_mm = {}\n", list(m.com.iter().map(|v| v * 1e3)));
                }
            }
            ComplianceForm::LinkMoments { terms } => {
                s += "# deflection of joint j = sum of value * gravity torque per unit mass (moment = mass, at DH frame\n";
                s += "# `link`'s origin) or per unit first moment (moment = x, y, z: along that frame's axis), i.e.\n";
                s += "# compliance_j times the mass (kg) or first moment (kg m) of everything rigid with the link:\n";
                s += "# rad kg/(N m) or rad kg m/(N m). No mass model: valid for the payload of the calibration.\n";
                s += "form = \"link_moments\"\n";
                s += &format!("gravity_mps2 = {}\n", list(c.gravity));
                s += "payload = \"as carried during the calibration\"\n";
                for t in terms {
                    s += "\n[[effects.joint_compliance.terms]]\n";
                    s += &format!(
                        "joint = {}\nlink = {}\nmoment = \"{}\"\nvalue = {}\nstd = {}\n",
                        t.joint + 1,
                        t.link,
                        MOMENTS[t.moment],
                        num(t.value),
                        num(t.std)
                    );
                }
            }
        }
    }
    if let Some(t) = &e.thermal {
        s += "\n[effects.thermal_drift]\n";
        match t {
            Thermal::Lag {
                scale,
                scale_std,
                time_constant,
                time_constant_std,
            } => {
                s += "# a_i and d_i of DH row i grow by the factor 1 + scale_i (1 - exp(-t / time_constant)), t from the reference state\n";
                s += "form = \"lag\"\n";
                s += &format!("reference = \"{}\"\n", reference.replace('"', "'"));
                s += &format!("scale = {}\n", list(*scale));
                s += &format!("scale_std = {}\n", list(*scale_std));
                s += &format!("time_constant_s = {}\n", num(*time_constant));
                s += &format!("time_constant_std_s = {}\n", num(*time_constant_std));
            }
            Thermal::Temperature {
                alpha,
                alpha_std,
                reference_c,
            } => {
                s += "# a_i and d_i of DH row i grow by the factor 1 + alpha_i (T - reference_temp_c)\n";
                s += "form = \"temperature\"\n";
                s += &format!("reference = \"{}\"\n", reference.replace('"', "'"));
                s += &format!("reference_temp_c = {}\n", num(*reference_c));
                s += &format!("alpha_per_k = {}\n", list(*alpha));
                s += &format!("alpha_std_per_k = {}\n", list(*alpha_std));
            }
        }
    }
    if let Some(l) = &e.servo_lag {
        s += "\n[effects.servo_lag]\n";
        s += "# motion only: a moving axis is late by tau_s (x = setpoint(t - tau) + second_order * setpoint''); a pose is not moved\n";
        s += &format!("tau_s = {}\n", num(l.tau));
        s += &format!("tau_std_s = {}\n", num(l.tau_std));
        s += &format!("second_order_s2 = {}\n", num(l.second_order));
        s += &format!("second_order_std_s2 = {}\n", num(l.second_order_std));
    }
    s
}

/// The file a URDF's comment names as its effects sidecar, if any.
pub fn sidecar_name(urdf_text: &str) -> Option<String> {
    let at = urdf_text.find(SIDECAR_MARK)?;
    let rest = &urdf_text[at + SIDECAR_MARK.len()..];
    let end = rest.find("-->")?.min(rest.find('\n').unwrap_or(usize::MAX));
    let name = rest[..end].trim();
    (!name.is_empty()).then(|| name.to_string())
}

/// Reads a sidecar file's text: a TOML document whose one table is `[effects]`.
pub fn from_sidecar(text: &str) -> Result<Effects, String> {
    let doc: toml::Table = toml::from_str(text).map_err(|e| e.message().trim().to_string())?;
    if let Some(k) = doc.keys().find(|k| *k != "effects") {
        return Err(format!("{k}: unknown key (a sidecar holds only [effects])"));
    }
    match doc.get("effects") {
        Some(v) => from_toml(v.clone()),
        None => Err("no [effects] table".into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Effects {
        Effects {
            cyclic: vec![Cyclic {
                joint: 1,
                orders: vec![1, 3],
                cos: vec![3e-5, -1.1e-5],
                sin: vec![2e-5, 0.7e-5],
                cos_std: vec![1e-7, 1e-7],
                sin_std: vec![1e-7, 1e-7],
            }],
            backlash: vec![Backlash {
                joint: 0,
                play: 2e-4,
                play_std: 1e-6,
            }],
            compliance: Some(Compliance {
                form: ComplianceForm::LinkMoments {
                    terms: vec![
                        MomentTerm {
                            joint: 1,
                            link: 3,
                            moment: 0,
                            value: 2.5e-5,
                            std: 1e-7,
                        },
                        MomentTerm {
                            joint: 2,
                            link: 6,
                            moment: 3,
                            value: -1.5e-6,
                            std: 1e-8,
                        },
                    ],
                },
                gravity: [0.0, 0.0, -G],
            }),
            thermal: Some(Thermal::Lag {
                scale: [0.0, 3e-5, 3e-5, 0.0, 0.0, 0.0],
                scale_std: [0.0; 6],
                time_constant: 600.0,
                time_constant_std: 12.0,
            }),
            servo_lag: Some(ServoLag {
                tau: 0.004,
                tau_std: 1e-5,
                second_order: -1e-6,
                second_order_std: 0.0,
            }),
        }
    }

    fn nj_like() -> [Dh; 6] {
        let d = |alpha: f64, a: f64, d: f64, theta: f64| Dh {
            alpha: alpha * DEG,
            a,
            d,
            theta: theta * DEG,
        };
        [
            d(-90.0, 0.4, 0.55, 0.0),
            d(-180.0, 0.86, 0.0, -90.0),
            d(-90.0, -0.21, 0.0, 180.0),
            d(90.0, 0.0, 0.762, 0.0),
            d(90.0, 0.0, 0.0, 0.0),
            d(0.0, 0.0, 0.21, 0.0),
        ]
    }

    #[test]
    fn the_table_reads_back_exactly() {
        let e = sample();
        let text = to_toml(&e, "the start of the runs");
        let doc: toml::Table = toml::from_str(&text).unwrap();
        let back = from_toml(doc["effects"].clone()).unwrap();
        // Degrees in the file: the round trip through the unit is within an ulp or two.
        let close = |a: f64, b: f64| (a - b).abs() <= 4.0 * f64::EPSILON * a.abs().max(b.abs());
        assert_eq!(back.cyclic[0].orders, vec![1, 3]);
        for (a, b) in back.cyclic[0].cos.iter().zip(&e.cyclic[0].cos) {
            assert!(close(*a, *b), "{a} {b}");
        }
        assert!(close(back.backlash[0].play, e.backlash[0].play));
        assert_eq!(back.compliance, e.compliance);
        assert_eq!(back.thermal, e.thermal);
        assert_eq!(back.servo_lag, e.servo_lag);
        assert!(from_toml(toml::Value::Table(Default::default())).is_err());
    }

    #[test]
    fn bad_tables_name_their_key() {
        for (bad, needle) in [
            ("schema = \"edbbgen.effects/9\"", "effects.schema"),
            ("schema = \"edbbgen.effects/1\"\n[[cyclic_error]]\njoint = 7\norders = [1]\ncos_deg = [0.0]\nsin_deg = [0.0]", "joint 7"),
            ("schema = \"edbbgen.effects/1\"\n[[cyclic_error]]\njoint = 2\norders = [1, 2]\ncos_deg = [0.0]\nsin_deg = [0.0]", "one value per order"),
            ("schema = \"edbbgen.effects/1\"\n[[backlash]]\njoint = 1\nplay_deg = -1.0", "play_deg"),
            ("schema = \"edbbgen.effects/1\"\n[thermal_drift]\nform = \"lag\"", "time_constant_s"),
            ("schema = \"edbbgen.effects/1\"\ncolour = 3", "colour"),
        ] {
            let v: toml::Value = toml::from_str::<toml::Table>(bad).unwrap().into();
            let e = from_toml(v).unwrap_err();
            assert!(e.contains(needle), "{bad}: {e}");
        }
    }

    #[test]
    fn command_inverts_load_on_every_term() {
        let e = sample();
        let dh = nj_like();
        let (base, flange) = (Frame::IDENTITY, Frame::IDENTITY);
        for (k, approach) in [[1.0; 6], [-1.0; 6], [0.0; 6]].iter().enumerate() {
            let target = [0.3, -0.4 + 0.1 * k as f64, 0.7, 1.2, -0.5, 2.0];
            let q = e.command(&base, &dh, &flange, &target, approach);
            let back = e.load(&base, &dh, &flange, &q, approach);
            for j in 0..6 {
                assert!(
                    (back[j] - target[j]).abs() < 1e-15,
                    "{j}: {back:?} {target:?}"
                );
            }
            // The backlash acts on joint 1 only, by half the play against the approach.
            let plain = Effects {
                backlash: e.backlash.clone(),
                ..Effects::default()
            };
            let b = plain.load(&base, &dh, &flange, &target, approach);
            assert!((b[0] - target[0] + 0.5 * 2e-4 * approach[0]).abs() < 1e-15);
        }
    }

    #[test]
    fn the_general_gravity_basis_is_the_point_mass_torque() {
        // A point mass m at c in frame 3 is the mass term m plus first moments m·c: the two
        // forms of compliance agree (independent of how the fit parametrises it).
        let dh = nj_like();
        let q = [0.2, -0.3, 0.5, 0.1, 0.7, -0.2];
        let fr = chain_frames(&Frame::IDENTITY, &dh, &Frame::IDENTITY, &q);
        let g = Vector3::new(0.0, 0.0, -G);
        let (m, c) = (42.0, Vector3::new(0.1, -0.05, 0.3));
        let tau = gravity_torques(
            &fr,
            &[PointMass {
                frame: 3,
                com: c,
                mass: m,
            }],
            &g,
        );
        for j in 0..3 {
            let basis = m * gravity_basis(&fr, &g, j, 3, 0)
                + (0..3)
                    .map(|a| m * c[a] * gravity_basis(&fr, &g, j, 3, a + 1))
                    .sum::<f64>();
            assert!((basis - tau[j]).abs() < 1e-9 * tau[j].abs().max(1.0), "{j}");
        }
        assert_eq!(tau[3], 0.0);
    }

    #[test]
    fn reframed_compliance_deflects_alike_on_a_chain_described_otherwise() {
        // The same chain with two DH rows described with the common normal the other way
        // (α, a negated, θ turned by π, and the next row's θ by π): FK is the same, frames
        // 3 and 4 turned by a half turn about z. Row 4 is both: its two half turns cancel.
        let a = nj_like();
        let mut b = a;
        b[2].alpha = -a[2].alpha;
        b[2].a = -a[2].a;
        b[2].theta = a[2].theta + std::f64::consts::PI;
        b[3].alpha = -a[3].alpha;
        b[3].a = -a[3].a;
        b[4].theta = a[4].theta + std::f64::consts::PI;
        let id = Frame::IDENTITY;
        let q = [0.3, -0.2, 0.6, 1.1, -0.4, 0.9];
        let fk = |dh: &[Dh; 6]| chain_frames(&id, dh, &id, &q)[6].t;
        assert!((fk(&a) - fk(&b)).norm() < 1e-12);
        let e = sample();
        let known = Effects {
            compliance: Some(Compliance {
                form: ComplianceForm::KnownMasses {
                    compliance: [0.0, 2e-7, 3e-7, 1e-7, 0.0, 0.0],
                    std: [0.0; 6],
                    masses: vec![PointMass {
                        frame: 3,
                        com: Vector3::new(0.1, 0.2, -0.05),
                        mass: 30.0,
                    }],
                },
                gravity: [0.0, 0.0, -G],
            }),
            ..Effects::default()
        };
        for fx in [e, known] {
            let moved = fx.reframed((&id, &a, &id), (&id, &b, &id));
            for q in [q, [1.0, 0.4, -0.7, -2.0, 1.2, 0.1]] {
                let x = fx.load(&id, &a, &id, &q, &[1.0; 6]);
                let y = moved.load(&id, &b, &id, &q, &[1.0; 6]);
                for j in 0..6 {
                    assert!((x[j] - y[j]).abs() < 1e-15, "{j}: {x:?} {y:?}");
                }
            }
        }
    }

    #[test]
    fn a_lag_drift_is_zero_at_its_reference_and_grows_to_its_scale() {
        let e = sample();
        let dh = nj_like();
        assert_eq!(e.at_state(&dh, ThermalState::Reference), dh);
        assert_eq!(e.at_state(&dh, ThermalState::Elapsed(0.0)), dh);
        let late = e.at_state(&dh, ThermalState::Elapsed(1e7));
        assert!((late[1].a / dh[1].a - 1.0 - 3e-5).abs() < 1e-12);
        assert_eq!(late[0], dh[0]);
        // A temperature state does not move a lag drift.
        assert_eq!(e.at_state(&dh, ThermalState::Temperature(30.0)), dh);
    }

    #[test]
    fn the_sidecar_is_named_in_a_comment_and_holds_only_effects() {
        let urdf = "<?xml version=\"1.0\"?>\n<!-- edbbgen effects: arm.cal.effects.toml -->\n<robot name=\"r\"/>";
        assert_eq!(sidecar_name(urdf).as_deref(), Some("arm.cal.effects.toml"));
        assert_eq!(sidecar_name("<robot/>"), None);
        let block =
            "<!-- edbbgen calibration\n     edbbgen effects: a.effects.toml\n     warning: x\n-->";
        assert_eq!(sidecar_name(block).as_deref(), Some("a.effects.toml"));
        let text = to_toml(&sample(), "start");
        assert_eq!(from_sidecar(&text).unwrap().servo_lag, sample().servo_lag);
        assert!(from_sidecar("[other]\nx = 1").is_err());
    }
}

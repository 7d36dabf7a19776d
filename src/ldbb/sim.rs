//! The LDBB simulator (`simulate-ldbb`): in = robot, setup, a truth (`LDBB_TRUTH.toml`) and a
//! seed; out = loaded-circle data in the DESIGN.md contract and, optionally, the laser-tracker
//! reference. For tests and the worked example; the analysis never calls it.
//!
//! ```toml
//! noise_um = 1.0                  # LVDT noise, standard deviation per sample
//! run_offset_um = 3.0             # each recorded circle's LVDT offset, standard deviation
//! lt_noise_um = 0.5               # laser-tracker noise (the reference)
//! stiffness_nm_per_rad = [8.0e6, 5.0e6, 4.0e6, 1.2e6, 1.0e6, 6.0e5]
//! centring_offset_mm = [0.3, 0.0, 0.0]   # table ball against the circle centre (base frame)
//! [geometric]                     # perturbed joint origins: deviations of the DH parameters
//! theta2 = 0.01                   # (report names, mm / deg) and of the tool ball (x_map, ...)
//! [nonlinearity]                  # gear hardening: stiffness k·(1 + |τ|/τh); 0 = linear
//! hardening_torque_nm = [0.0, 3000.0, 2000.0, 0.0, 0.0, 0.0]
//! [gravity]                       # point masses at DH frames 1..6 (kg): gravity torques set
//! masses_kg = [0.0, 400.0, 250.0, 60.0, 20.0, 10.0]   # the gears' operating point
//! ```
//!
//! The physics: the robot drives its joints to the nominal IK of the circle (the recorded
//! angles). The gears wind up by Δqᵢ = gᵢ(τᵢ) under the torques τ = Jₚᵀ·F·u + τ_gravity, with
//! gᵢ(τ) = τ/kᵢ, or with hardening gᵢ(τ) = (τh/kᵢ)·sign(τ)·ln(1 + |τ|/τh). The true tool ball
//! is the perturbed robot's forward kinematics at q + Δq; u points from the table ball to it
//! (solved to a fixed point). The table ball is where the centring put it: at the real
//! (unloaded) robot's circle centre, as the operator finds it with the robot, plus the
//! centring offset. The LVDT reads |tool ball − table ball| − L plus the run's offset and noise.
//! Each run samples the circle at its own random start angle with jittered spacing.

use super::data::{Loaded, Reference, Sample};
use super::kin::{Arm, CircleIk};
use super::setup::Setup;
use crate::model::{is_angle, N_PARAMS, PARAM_NAMES};
use crate::robot::kinematics::chain_frames;
use crate::robot::{Dh, PointMass, Robot};
use crate::units::{DEG, MM};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::Deserialize;
use std::collections::BTreeMap;

const UM: f64 = 1e-6;

/// The real robot and instrument of a simulation (SI).
#[derive(Clone, Debug, PartialEq)]
pub struct Truth {
    pub noise: f64,
    pub run_offset: f64,
    pub lt_noise: f64,
    pub stiffness: [f64; 6],
    /// Torque at which a joint's stiffness has doubled (N·m); None = linear.
    pub hardening: [Option<f64>; 6],
    pub centring_offset: Vector3<f64>,
    /// Deviations in Eq. 6 order (the fixture entries stay zero).
    pub geometric: [f64; N_PARAMS],
    pub masses: Vec<PointMass>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TruthT {
    noise_um: Option<f64>,
    run_offset_um: Option<f64>,
    lt_noise_um: Option<f64>,
    stiffness_nm_per_rad: [f64; 6],
    centring_offset_mm: Option<[f64; 3]>,
    #[serde(default)]
    geometric: BTreeMap<String, f64>,
    nonlinearity: Option<NonlinT>,
    gravity: Option<GravityT>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct NonlinT {
    hardening_torque_nm: [f64; 6],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GravityT {
    masses_kg: [f64; 6],
}

impl Truth {
    pub fn from_toml(text: &str) -> Result<Truth, String> {
        let t: TruthT = toml::from_str(text).map_err(|e| crate::robot::dh::toml_error(text, &e))?;
        let nonneg = |k: &str, v: Option<f64>, d: f64| -> Result<f64, String> {
            let v = v.unwrap_or(d);
            if v.is_finite() && v >= 0.0 {
                Ok(v * UM)
            } else {
                Err(format!("{k}: {v} must be a number >= 0"))
            }
        };
        if t.stiffness_nm_per_rad
            .iter()
            .any(|k| !(k.is_finite() && *k > 0.0))
        {
            return Err("stiffness_nm_per_rad: every stiffness must be > 0".into());
        }
        let mut geometric = [0.0; N_PARAMS];
        for (name, v) in &t.geometric {
            let k = PARAM_NAMES
                .iter()
                .position(|n| n == name)
                .filter(|&k| !crate::model::is_fixture(k))
                .ok_or_else(|| {
                    format!("geometric.{name}: not a joint-origin or tool parameter (alpha1..6, a1..6, d1..6, theta1..6, x_map, y_map, z_map; the table ball is centring_offset_mm)")
                })?;
            if !v.is_finite() {
                return Err(format!("geometric.{name}: not finite"));
            }
            geometric[k] = v * if is_angle(k) { DEG } else { MM };
        }
        let mut hardening = [None; 6];
        if let Some(n) = &t.nonlinearity {
            for i in 0..6 {
                let h = n.hardening_torque_nm[i];
                if !(h.is_finite() && h >= 0.0) {
                    return Err(format!(
                        "nonlinearity.hardening_torque_nm: joint {}: {h} must be >= 0 (0 = linear)",
                        i + 1
                    ));
                }
                hardening[i] = (h > 0.0).then_some(h);
            }
        }
        let c = t.centring_offset_mm.unwrap_or([0.0; 3]);
        if !c.iter().all(|v| v.is_finite()) {
            return Err("centring_offset_mm: not finite".into());
        }
        let masses = match &t.gravity {
            Some(g) => {
                if g.masses_kg.iter().any(|m| !(m.is_finite() && *m >= 0.0)) {
                    return Err("gravity.masses_kg: masses must be >= 0".into());
                }
                (0..6)
                    .filter(|&i| g.masses_kg[i] > 0.0)
                    .map(|i| PointMass {
                        frame: i + 1,
                        com: Vector3::zeros(),
                        mass: g.masses_kg[i],
                    })
                    .collect()
            }
            None => Vec::new(),
        };
        Ok(Truth {
            noise: nonneg("noise_um", t.noise_um, 1.0)?,
            run_offset: nonneg("run_offset_um", t.run_offset_um, 0.0)?,
            lt_noise: nonneg("lt_noise_um", t.lt_noise_um, 0.5)?,
            stiffness: t.stiffness_nm_per_rad,
            hardening,
            centring_offset: Vector3::from(c) * MM,
            geometric,
            masses,
        })
    }

    /// Gear wind-up of joint i under torque τ.
    pub fn windup(&self, i: usize, tau: f64) -> f64 {
        match self.hardening[i] {
            None => tau / self.stiffness[i],
            Some(h) => h / self.stiffness[i] * tau.signum() * (tau.abs() / h).ln_1p(),
        }
    }
}

/// The true robot: perturbed DH table and tool ball.
struct Real<'a> {
    robot: &'a Robot,
    dh: [Dh; 6],
    map: Vector3<f64>,
    lt: Vector3<f64>,
    truth: &'a Truth,
}

impl Real<'_> {
    fn new<'a>(
        robot: &'a Robot,
        map: Vector3<f64>,
        lt: Vector3<f64>,
        truth: &'a Truth,
    ) -> Real<'a> {
        let g = &truth.geometric;
        let dh = std::array::from_fn(|i| Dh {
            alpha: robot.dh[i].alpha + g[crate::model::ALPHA + i],
            a: robot.dh[i].a + g[crate::model::A + i],
            d: robot.dh[i].d + g[crate::model::D + i],
            theta: robot.dh[i].theta + g[crate::model::THETA + i],
        });
        let dm = Vector3::new(
            g[crate::model::MAP],
            g[crate::model::MAP + 1],
            g[crate::model::MAP + 2],
        );
        Real {
            robot,
            dh,
            map: map + dm,
            lt: lt + dm,
            truth,
        }
    }

    /// Gravity torques at the load-side angles q (N·m).
    fn gravity(&self, q: &[f64; 6]) -> [f64; 6] {
        let f = chain_frames(&self.robot.base, &self.dh, &self.robot.flange, q);
        let mut tau = [0.0; 6];
        for m in &self.truth.masses {
            let k = m.frame.min(6);
            let pos = f[k].apply(&m.com);
            let force = Vector3::new(0.0, 0.0, -crate::twin::effects::G * m.mass);
            for j in 0..k {
                tau[j] += f[j].r.column(2).dot(&(pos - f[j].t).cross(&force));
            }
        }
        tau
    }

    /// Tool ball and LT point under a load `load` (N) pushing the tool ball away from `table`,
    /// with the joints commanded to `q`.
    fn deflected(
        &self,
        q: &[f64; 6],
        load: f64,
        table: &Vector3<f64>,
    ) -> (Vector3<f64>, Vector3<f64>) {
        let mut ql = *q;
        let mut out = (Vector3::zeros(), Vector3::zeros());
        for _ in 0..4 {
            let f = chain_frames(&self.robot.base, &self.dh, &self.robot.flange, &ql);
            let p = f[7].apply(&self.map);
            out = (p, f[7].apply(&self.lt));
            let u = (p - table).normalize();
            let g = self.gravity(&ql);
            let next: [f64; 6] = std::array::from_fn(|i| {
                let jp = f[i].r.column(2).cross(&(p - f[i].t));
                let tau = jp.dot(&(u * load)) + g[i];
                q[i] + self.truth.windup(i, tau)
            });
            if (0..6).all(|i| (next[i] - ql[i]).abs() < 1e-13) {
                break;
            }
            ql = next;
        }
        out
    }
}

/// Simulated data and the truth it came from (for tests: the noise-free pieces).
pub struct Simulated {
    pub loaded: Loaded,
    /// Laser-tracker reference at `samples_per_circle` angles from 0.
    pub reference: Reference,
}

/// Simulates every load and repeat of the setup.
pub fn simulate(
    robot: &Robot,
    setup: &Setup,
    truth: &Truth,
    seed: u64,
) -> Result<Simulated, String> {
    let (map, orientation) = setup.tool()?;
    let lt = setup.lt_map_offset.unwrap_or(map);
    let arm = Arm { robot, map };
    let ik = CircleIk::new(arm.clone(), orientation, setup)?;
    let real = Real::new(robot, map, lt, truth);
    // Centring with the real robot: commanded to the circle centre, it stands here (unloaded).
    let centre_q = arm
        .ik(&setup.circle.centre, &orientation, &ik.nodes[0])
        .ok_or("the circle centre is out of reach with the setup's tool orientation")?;
    let centre_real = real
        .deflected(&centre_q, 0.0, &(setup.circle.centre - Vector3::z()))
        .0;
    let table = setup.table_ball + (centre_real - setup.circle.centre) + truth.centring_offset;

    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n = setup.circle.samples_per_circle;
    // Draw every random number in a fixed order first; the physics then runs in parallel.
    let mut plan: Vec<(usize, f64, f64, f64)> = Vec::new(); // (run, load, angle, noise)
    let mut offsets = Vec::new();
    for &load in &setup.loads {
        for run in 1..=setup.repeats {
            let start = rng.random_range(0.0..std::f64::consts::TAU);
            let off = truth.run_offset * normal(&mut rng);
            offsets.push(off);
            for k in 0..n {
                let jitter = rng.random_range(-0.3..0.3);
                let angle = start + std::f64::consts::TAU * (k as f64 + jitter) / n as f64;
                plan.push((run, load, angle, off + truth.noise * normal(&mut rng)));
            }
        }
    }
    let samples: Result<Vec<Sample>, String> = plan
        .par_iter()
        .enumerate()
        .map(|(k, &(run, load, angle, extra))| {
            let q = ik
                .at(setup, angle)
                .ok_or_else(|| format!("no IK at circle angle {:.3} deg", angle / DEG))?;
            let (p, _) = real.deflected(&q, load, &table);
            let reading = (p - table).norm() - setup.bar_length + extra;
            Ok(Sample {
                run,
                load,
                angle: angle.rem_euclid(std::f64::consts::TAU),
                q: Some(q),
                deflection: reading,
                line: k + 2,
            })
        })
        .collect();
    // The laser tracker: the LT point's unloaded deviation from its nominal path along the
    // bar, centred like the circle (the real robot's translation at the centre removed).
    let lt_centre = real.deflected(&centre_q, 0.0, &table).1;
    let lt_centre_nominal =
        chain_frames(&robot.base, &robot.dh, &robot.flange, &centre_q)[7].apply(&lt);
    let shift = lt_centre - lt_centre_nominal;
    let noise: Vec<f64> = (0..n).map(|_| truth.lt_noise * normal(&mut rng)).collect();
    let reference: Result<Vec<(f64, f64)>, String> = (0..n)
        .into_par_iter()
        .map(|k| {
            let angle = std::f64::consts::TAU * k as f64 / n as f64;
            let q = ik
                .at(setup, angle)
                .ok_or_else(|| format!("no IK at circle angle {:.3} deg", angle / DEG))?;
            let (_, plt) = real.deflected(&q, 0.0, &table);
            let nominal = chain_frames(&robot.base, &robot.dh, &robot.flange, &q)[7].apply(&lt);
            let u = setup.bar_direction(angle);
            Ok((angle, u.dot(&(plt - nominal - shift)) + noise[k]))
        })
        .collect();
    let reference = reference?;
    Ok(Simulated {
        loaded: Loaded { samples: samples? },
        reference: Reference {
            angle: reference.iter().map(|r| r.0).collect(),
            error: reference.iter().map(|r| r.1).collect(),
        },
    })
}

/// A standard normal draw (Box–Muller; deterministic for a seeded generator).
fn normal(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// The noise-free truth of a simulation on the analysis grid, for tests: per node, the true
/// compliance along the bar (least-squares slope over the setup's loads, m/N) and the true
/// unloaded reading (m), with the tool ball on the nominal circle.
pub fn truth_on_grid(
    robot: &Robot,
    setup: &Setup,
    truth: &Truth,
    angles: &[f64],
) -> Result<(Vec<f64>, Vec<f64>), String> {
    let clean = Truth {
        noise: 0.0,
        run_offset: 0.0,
        lt_noise: 0.0,
        ..truth.clone()
    };
    let (map, orientation) = setup.tool()?;
    let arm = Arm { robot, map };
    let ik = CircleIk::new(arm.clone(), orientation, setup)?;
    let real = Real::new(robot, map, setup.lt_map_offset.unwrap_or(map), &clean);
    let centre_q = arm
        .ik(&setup.circle.centre, &orientation, &ik.nodes[0])
        .ok_or("centre out of reach")?;
    let centre_real = real
        .deflected(&centre_q, 0.0, &(setup.circle.centre - Vector3::z()))
        .0;
    let table = setup.table_ball + (centre_real - setup.circle.centre) + truth.centring_offset;
    let mut c = Vec::new();
    let mut y0 = Vec::new();
    for &t in angles {
        let q = ik.at(setup, t).ok_or("IK")?;
        let read = |f: f64| (real.deflected(&q, f, &table).0 - table).norm() - setup.bar_length;
        let ys: Vec<f64> = setup.loads.iter().map(|&f| read(f)).collect();
        c.push(super::fit::line(&setup.loads, &ys).0);
        y0.push(read(0.0));
    }
    Ok((c, y0))
}

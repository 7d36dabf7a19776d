//! Digital twin: in = robot, measurement model, a parsed program and a [`Truth`] (the real
//! robot's errors and effects); out = what the EDBB and the joint encoders would record
//! ([`Measured`], the CSV contract of DESIGN.md). No file I/O.
//!
//! The virtual robot runs the program on a [`trajectory::Trajectory`] (velocity-limited
//! synchronous joint moves, blends, dwells); the recorded joint angles are the controller's
//! encoder readings (motor side), the bar reads the true MAP distance of the perturbed robot
//! plus Gaussian noise, quantised to the instrument's resolution.

pub mod circle;
pub mod effects;
pub mod logsim;
pub mod measured;
pub mod recorded;
pub mod trajectory;
pub mod truth;

pub use effects::{gravity_torques, Effect};
pub use measured::{parse_csv, CsvError, Measured};
pub use trajectory::{Dwell, Trajectory};
pub use truth::Truth;

use crate::dialect::Parsed;
use crate::model::{MeasurementModel, Params, A, D, N_PARAMS};
use crate::robot::effects::{Effects as RobotEffects, ThermalState};
use crate::robot::{Dh, Frame, Robot};
use rand::{Rng, SeedableRng};

/// Steps of the motion between two samples a play operator follows (the motor may turn
/// between samples: where it does, the load is pushed to within (step/2)² of the turn's
/// curvature of where a continuous operator would leave it).
const PLAY_STEPS: usize = 32;

#[derive(Clone, Debug)]
pub struct SimOptions {
    /// Sample rate of the bar (Hz).
    pub rate: f64,
    pub seed: u64,
}

impl Default for SimOptions {
    fn default() -> Self {
        SimOptions {
            rate: 50.0,
            seed: 1,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SimError {
    #[error("program line {line}: {msg}")]
    Program { line: usize, msg: String },
    #[error("{0}")]
    Empty(String),
}

/// Runs `program` on the true robot and records what the bar and the encoders see.
pub fn simulate(
    robot: &Robot,
    model: &MeasurementModel,
    program: &Parsed,
    truth: &Truth,
    opts: &SimOptions,
) -> Result<Measured, SimError> {
    let traj = Trajectory::from_program(robot, model, program)?;
    // Sample times: every window with the bar in place, on one clock (gaps between sections).
    let times: Vec<f64> = traj
        .windows
        .iter()
        .flat_map(|&(a, b)| {
            let n = ((b - a) * opts.rate).floor() as usize + 1;
            (0..n).map(move |k| a + k as f64 / opts.rate)
        })
        .collect();
    let (t0, t1) = (
        traj.windows.first().map_or(0.0, |w| w.0),
        traj.windows.last().map_or(0.0, |w| w.1),
    );
    if times.len() < 3 || t1 - t0 < 2.0 / opts.rate {
        return Err(SimError::Empty(
            "the program records nothing: no motion between the M0 that mounts the bar and the one that removes it".into(),
        ));
    }
    let n = times.len();
    let mut sampler = Sampler::new(robot, model, &traj, truth, t0, opts.seed);
    let mut out = Measured {
        t: Vec::with_capacity(n),
        q: Vec::with_capacity(n),
        length: Vec::with_capacity(n),
        temp: truth
            .thermal
            .as_ref()
            .filter(|th| th.temp_log)
            .map(|_| Vec::with_capacity(n)),
        ..Measured::default()
    };
    for &ts in &times {
        let t = ts - t0;
        let (q, l) = sampler.sample(ts, t);
        out.t.push(t);
        out.q.push(q);
        out.length.push(l);
        if let Some(temps) = out.temp.as_mut() {
            temps.push(sampler.temperature(t));
        }
    }
    Ok(out)
}

/// The real robot sampled along a trajectory, one bar reading after another: the state the
/// effects carry between samples (the backlash's load side, which follows the motor through a
/// play operator along the motion between samples) and the noise stream.
pub struct Sampler<'a> {
    model: &'a MeasurementModel,
    traj: &'a Trajectory,
    truth: &'a Truth,
    truep: [f64; N_PARAMS],
    masses: Vec<crate::robot::PointMass>,
    t0: f64,
    /// The backlash joint's load-side angle at the previous sample.
    load_b: Option<f64>,
    /// The robot file's own effects (a calibrated robot) and its reference geometry: the
    /// robot the truth's deviations are added to.
    effects: RobotEffects,
    reference: (Frame, [Dh; 6], Frame),
    /// Per backlash of the robot file: the load-side angle at the previous sample.
    load_file: Vec<Option<f64>>,
    /// Program time of the previous sample.
    prev_ts: Option<f64>,
    rng: rand_chacha::ChaCha8Rng,
}

impl<'a> Sampler<'a> {
    /// A sampler whose first reading is at program time `t0` (backlash rests against the flank
    /// of the joint's first motion after it); noise from `seed`.
    pub fn new(
        robot: &Robot,
        model: &'a MeasurementModel,
        traj: &'a Trajectory,
        truth: &'a Truth,
        t0: f64,
        seed: u64,
    ) -> Self {
        let nominal = model.nominal.to_array();
        let mut truep = nominal;
        for k in 0..N_PARAMS {
            truep[k] += truth.geometric[k];
        }
        Sampler {
            model,
            traj,
            truth,
            truep,
            masses: truth.compliance_masses(robot),
            t0,
            load_b: None,
            effects: robot.effects.clone(),
            reference: (robot.base, robot.dh, robot.flange),
            load_file: vec![None; robot.effects.backlash.len()],
            prev_ts: None,
            rng: rand_chacha::ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// The bar's reading and the logged joints at program time `ts`; `t` is the time since
    /// the recording started (thermal drift, fixture slip).
    pub fn sample(&mut self, ts: f64, t: f64) -> ([f64; 6], f64) {
        let truth = self.truth;
        let setpoint = self.traj.position(ts);
        // Servo lag: the axes follow the logged setpoints with a delay (the truth's and the
        // robot file's, in series; the file's with its second-order term).
        let lag =
            truth.servo_lag.unwrap_or(0.0) + self.effects.servo_lag.as_ref().map_or(0.0, |l| l.tau);
        let mut motor = match (truth.servo_lag, &self.effects.servo_lag) {
            (None, None) => setpoint,
            _ => self.traj.position(ts - lag),
        };
        if let Some(l) = self
            .effects
            .servo_lag
            .as_ref()
            .filter(|l| l.second_order != 0.0)
        {
            let h = 1e-3;
            let (a, b) = (
                self.traj.position(ts - lag - h),
                self.traj.position(ts - lag + h),
            );
            for j in 0..6 {
                motor[j] += l.second_order * (a[j] - 2.0 * motor[j] + b[j]) / (h * h);
            }
        }
        let mut load = motor;
        // The robot file's effects: cyclic errors and compliance on the motor angles, its
        // backlash through a play operator of its own along the motion.
        if self.effects.act_on_poses() {
            let (b, dh, f) = &self.reference;
            load = self.effects.load(b, dh, f, &motor, &[0.0; 6]);
            for (k, bl) in self.effects.backlash.iter().enumerate() {
                let j = bl.joint;
                let x = motor[j];
                let y = match (self.load_file[k], self.prev_ts) {
                    (Some(mut y), Some(tp)) => {
                        for i in 1..=PLAY_STEPS {
                            let ti = tp + (ts - tp) * i as f64 / PLAY_STEPS as f64;
                            y = effects::play(y, self.traj.position(ti - lag)[j], bl.play);
                        }
                        y
                    }
                    (Some(y), None) => effects::play(y, x, bl.play),
                    (None, _) => x - 0.5 * bl.play * self.traj.first_direction(j, self.t0),
                };
                self.load_file[k] = Some(y);
                load[j] += y - x;
            }
        }
        if let Some(b) = &truth.backlash {
            let x = motor[b.joint];
            let y = match (self.load_b, self.prev_ts) {
                // The play follows the motor through the motion since the last sample (it
                // may have turned between samples): 8 steps along the trajectory.
                (Some(mut y), Some(tp)) => {
                    for i in 1..=PLAY_STEPS {
                        let ti = tp + (ts - tp) * i as f64 / PLAY_STEPS as f64;
                        let xi = self.traj.position(ti - lag)[b.joint];
                        y = effects::play(y, xi, b.play);
                    }
                    y
                }
                (Some(y), None) => effects::play(y, x, b.play),
                // The load rests against the flank of the joint's first motion.
                (None, _) => x - 0.5 * b.play * self.traj.first_direction(b.joint, self.t0),
            };
            self.load_b = Some(y);
            load[b.joint] = y;
        }
        self.prev_ts = Some(ts);
        if let Some(c) = &truth.cyclic {
            load[c.joint] += effects::cyclic(c, motor[c.joint]);
        }
        if let Some(c) = &truth.compliance {
            let tau = gravity_torques(
                self.model,
                &Params::from_array(&self.truep),
                &motor,
                &self.masses,
            );
            for j in 0..6 {
                load[j] += tau[j] / c.stiffness[j];
            }
        }
        let mut p = self.truep;
        // The robot file's thermal drift: a lag from the recording's start (its reference
        // state), one referred to a temperature at the temperature the twin logs.
        if self.effects.thermal.is_some() {
            let state = match self.effects.thermal {
                Some(crate::robot::effects::Thermal::Temperature { .. }) => {
                    ThermalState::Temperature(self.file_temperature(t))
                }
                _ => ThermalState::Elapsed(t),
            };
            let g = self.effects.growth(state);
            for i in 0..6 {
                p[A + i] *= 1.0 + g[i];
                p[D + i] *= 1.0 + g[i];
            }
        }
        if let Some(th) = &truth.thermal {
            let s = 1.0 + th.alpha * th.delta(t);
            for i in 0..6 {
                p[A + i] *= s;
                p[D + i] *= s;
            }
        }
        if let Some(sl) = &truth.fixture_slip {
            if t >= sl.at_s {
                for i in 0..3 {
                    p[i] += sl.shift[i];
                }
            }
        }
        let l =
            self.model.length(&Params::from_array(&p), &load) + truth.noise * gauss(&mut self.rng);
        let l = if truth.resolution > 0.0 {
            (l / truth.resolution).round() * truth.resolution
        } else {
            l
        };
        // Encoders see the motor side; with servo lag the controller logs its setpoints.
        let logged = if truth.servo_lag.is_some() || self.effects.servo_lag.is_some() {
            setpoint
        } else {
            motor
        };
        (logged, l)
    }

    /// The temperature a robot file's drift referred to a temperature sees: the twin's log
    /// when the truth has a drift, else the file's reference (no growth).
    fn file_temperature(&self, t: f64) -> f64 {
        match (&self.truth.thermal, &self.effects.thermal) {
            (Some(_), _) => self.temperature(t),
            (None, Some(crate::robot::effects::Thermal::Temperature { reference_c, .. })) => {
                *reference_c
            }
            _ => truth::AMBIENT_C,
        }
    }

    /// The temperature the log's `temp_c` column holds at time t (°C).
    pub fn temperature(&self, t: f64) -> f64 {
        self.truth
            .thermal
            .as_ref()
            .map_or(truth::AMBIENT_C, |th| truth::AMBIENT_C + th.delta(t))
    }
}

/// A standard normal sample (Box-Muller): the crate has no rand_distr.
pub fn gauss(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

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
pub mod measured;
pub mod trajectory;
pub mod truth;

pub use effects::{gravity_torques, Effect};
pub use measured::{parse_csv, CsvError, Measured};
pub use trajectory::Trajectory;
pub use truth::Truth;

use crate::dialect::Parsed;
use crate::model::{MeasurementModel, Params, A, D, N_PARAMS};
use crate::robot::Robot;
use rand::{Rng, SeedableRng};

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
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed);
    let nominal = model.nominal.to_array();
    let mut truep = nominal;
    for k in 0..N_PARAMS {
        truep[k] += truth.geometric[k];
    }
    let masses = truth.compliance_masses(robot);
    // Backlash: the load side rests against the flank of its joint's first motion, then
    // follows the motor through a play operator.
    let mut load_b: Option<f64> = None;
    let mut prev_ts: Option<f64> = None;
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
        let setpoint = traj.position(ts);
        // Servo lag: the axes follow the logged setpoints with a delay.
        let motor = match truth.servo_lag {
            Some(tau) => traj.position(ts - tau),
            None => setpoint,
        };
        let mut load = motor;
        if let Some(b) = &truth.backlash {
            let x = motor[b.joint];
            let y = match (load_b, prev_ts) {
                // The play follows the motor through the motion since the last sample (it
                // may have turned between samples): 8 steps along the trajectory.
                (Some(mut y), Some(tp)) => {
                    for i in 1..=8 {
                        let ti = tp + (ts - tp) * i as f64 / 8.0;
                        let xi = traj.position(ti - truth.servo_lag.unwrap_or(0.0))[b.joint];
                        y = effects::play(y, xi, b.play);
                    }
                    y
                }
                (Some(y), None) => effects::play(y, x, b.play),
                (None, _) => x - 0.5 * b.play * traj.first_direction(b.joint, t0),
            };
            load_b = Some(y);
            load[b.joint] = y;
        }
        prev_ts = Some(ts);
        if let Some(c) = &truth.cyclic {
            load[c.joint] += effects::cyclic(c, motor[c.joint]);
        }
        if let Some(c) = &truth.compliance {
            let tau = gravity_torques(model, &Params::from_array(&truep), &motor, &masses);
            for j in 0..6 {
                load[j] += tau[j] / c.stiffness[j];
            }
        }
        let mut p = truep;
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
        let l = model.length(&Params::from_array(&p), &load) + truth.noise * gauss(&mut rng);
        let l = if truth.resolution > 0.0 {
            (l / truth.resolution).round() * truth.resolution
        } else {
            l
        };
        out.t.push(t);
        // Encoders see the motor side; with servo lag the controller logs its setpoints.
        out.q.push(if truth.servo_lag.is_some() {
            setpoint
        } else {
            motor
        });
        out.length.push(l);
        if let (Some(temps), Some(th)) = (out.temp.as_mut(), &truth.thermal) {
            temps.push(truth::AMBIENT_C + th.delta(t));
        }
    }
    Ok(out)
}

/// A standard normal sample (Box-Muller): the crate has no rand_distr.
pub fn gauss(rng: &mut impl Rng) -> f64 {
    let u1: f64 = rng.random_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

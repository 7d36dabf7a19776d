//! A second simulator of bar readings, written for the tests and kept apart from `src/twin`:
//! its own forward kinematics (4 × 4 matrices of the DH table), its own trajectories (a random
//! walk of waypoints on the bar's shell, joined by cubic Hermite splines, with dwells), and its
//! own formulas for the physics of each effect:
//!
//! - joint compliance: point masses fixed in the link frames and a payload, their gravity
//!   torques from cross products of this module's frames, deflection τ/k evaluated at the
//!   deflected pose (one fixed-point iteration);
//! - thermal drift: every link's translation grows by α·ΔT(t), the temperature a first-order
//!   lag that starts part-way warm: ΔT(t) = R − (R − T₀)·exp(−t/τ);
//! - cyclic error: Σ A_h sin(h·q + φ_h) over a set of harmonic orders of one joint's angle;
//! - backlash: a play operator started at a random point inside the play;
//! - servo lag: the axes follow the logged setpoints through a first-order servo loop
//!   (x' = (s − x)/τ, integrated at 2 kHz), not a pure delay;
//! - a fixture that slides to a new place over 0.2 s once during the run;
//! - the fixture's and the tool's true positions off the given ones; bar noise and resolution;
//!   zero jumps, a drifting zero and outliers; joint readings quantised to 0.1°; static poses.
//!
//! Nothing here calls the library's effects, its measurement model or its trajectories; the
//! library is used only to read the robot file's numbers.

#![allow(dead_code)]

use nalgebra::{Matrix3, Matrix4, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

pub const DEG: f64 = PI / 180.0;
const GRAVITY: f64 = 9.81;

/// A serial arm by its standard DH table (alpha, a, d, theta per joint; SI), with limits and
/// axis speeds.
#[derive(Clone, Debug)]
pub struct Arm {
    pub dh: [[f64; 4]; 6],
    pub lo: [f64; 6],
    pub hi: [f64; 6],
    pub speed: [f64; 6],
}

fn rot_z(t: f64) -> Matrix4<f64> {
    let (s, c) = t.sin_cos();
    Matrix4::new(
        c, -s, 0.0, 0.0, s, c, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
    )
}

fn rot_x(t: f64) -> Matrix4<f64> {
    let (s, c) = t.sin_cos();
    Matrix4::new(
        1.0, 0.0, 0.0, 0.0, 0.0, c, -s, 0.0, 0.0, s, c, 0.0, 0.0, 0.0, 0.0, 1.0,
    )
}

fn shift(x: f64, y: f64, z: f64) -> Matrix4<f64> {
    let mut m = Matrix4::identity();
    m[(0, 3)] = x;
    m[(1, 3)] = y;
    m[(2, 3)] = z;
    m
}

fn origin(m: &Matrix4<f64>) -> Vector3<f64> {
    Vector3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)])
}

fn apply(m: &Matrix4<f64>, p: &Vector3<f64>) -> Vector3<f64> {
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    r * p + origin(m)
}

impl Arm {
    /// The numbers of a `.dh.toml` robot (read by the library's loader: data only).
    pub fn from_file(path: &std::path::Path) -> Arm {
        let r = edbbgen::robot::load(path, &Default::default()).expect("robot");
        let (lo, hi) = r.limits();
        Arm {
            dh: std::array::from_fn(|i| [r.dh[i].alpha, r.dh[i].a, r.dh[i].d, r.dh[i].theta]),
            lo,
            hi,
            speed: std::array::from_fn(|i| r.joints[i].max_speed),
        }
    }

    /// Frames 0..6 (base to flange) at q, every link's translation scaled by `grow`.
    pub fn frames(&self, q: &[f64; 6], grow: f64) -> [Matrix4<f64>; 7] {
        self.frames_grown(q, &[grow; 6])
    }

    /// Frames 0..6 at q, link i's translation scaled by `grow[i]`.
    pub fn frames_grown(&self, q: &[f64; 6], grow: &[f64; 6]) -> [Matrix4<f64>; 7] {
        let mut f = [Matrix4::identity(); 7];
        for i in 0..6 {
            let [alpha, a, d, theta] = self.dh[i];
            f[i + 1] = f[i]
                * rot_z(theta + q[i])
                * shift(0.0, 0.0, d * grow[i])
                * shift(a * grow[i], 0.0, 0.0)
                * rot_x(alpha);
        }
        f
    }

    /// The tool point (flange frame) in the base frame.
    pub fn point(&self, q: &[f64; 6], tool: &Vector3<f64>) -> Vector3<f64> {
        apply(&self.frames(q, 1.0)[6], tool)
    }

    /// This arm with every DH entry moved by `err` ([alpha, a, d, theta] per joint).
    pub fn perturbed(&self, err: &[[f64; 4]; 6]) -> Arm {
        let mut a = self.clone();
        for i in 0..6 {
            for k in 0..4 {
                a.dh[i][k] += err[i][k];
            }
        }
        a
    }
}

/// Random DH errors: lengths up to ±`mm`, angles up to ±`deg`.
pub fn dh_errors(rng: &mut ChaCha8Rng, mm: f64, deg: f64) -> [[f64; 4]; 6] {
    std::array::from_fn(|_| {
        [
            rng.random_range(-deg..deg) * DEG,
            rng.random_range(-mm..mm) * 1e-3,
            rng.random_range(-mm..mm) * 1e-3,
            rng.random_range(-deg..deg) * DEG,
        ]
    })
}

/// A random unit vector.
pub fn direction(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}

/// Box–Muller.
pub fn normal(rng: &mut ChaCha8Rng) -> f64 {
    let u: f64 = rng.random_range(1e-300..1.0);
    let v: f64 = rng.random();
    (-2.0 * u.ln()).sqrt() * (2.0 * PI * v).cos()
}

// ---- trajectories -------------------------------------------------------------------------

/// A joint trajectory: knots (time, position, velocity, acceleration) joined by quintic
/// Hermite splines: continuous accelerations, as a jerk-limited controller moves.
#[derive(Clone, Debug)]
pub struct Path {
    pub t: Vec<f64>,
    pub q: Vec<[f64; 6]>,
    pub v: Vec<[f64; 6]>,
    pub a: Vec<[f64; 6]>,
}

impl Path {
    pub fn duration(&self) -> f64 {
        *self.t.last().unwrap_or(&0.0)
    }

    pub fn at(&self, t: f64) -> [f64; 6] {
        let t = t.clamp(0.0, self.duration());
        if self.t.len() < 2 {
            return self.q[0];
        }
        let k = self
            .t
            .partition_point(|&x| x <= t)
            .clamp(1, self.t.len() - 1);
        let (t0, t1) = (self.t[k - 1], self.t[k]);
        let h = t1 - t0;
        let s = (t - t0) / h;
        let (s2, s3, s4, s5) = (s * s, s * s * s, s.powi(4), s.powi(5));
        let h0 = 1.0 - 10.0 * s3 + 15.0 * s4 - 6.0 * s5;
        let h1 = s - 6.0 * s3 + 8.0 * s4 - 3.0 * s5;
        let h2 = 0.5 * s2 - 1.5 * s3 + 1.5 * s4 - 0.5 * s5;
        let h3 = 0.5 * s3 - s4 + 0.5 * s5;
        let h4 = -4.0 * s3 + 7.0 * s4 - 3.0 * s5;
        let h5 = 10.0 * s3 - 15.0 * s4 + 6.0 * s5;
        std::array::from_fn(|j| {
            h0 * self.q[k - 1][j]
                + h1 * h * self.v[k - 1][j]
                + h2 * h * h * self.a[k - 1][j]
                + h3 * h * h * self.a[k][j]
                + h4 * h * self.v[k][j]
                + h5 * self.q[k][j]
        })
    }
}

/// Solves joint 1 so that the tool point is `len` from `fix` (joint 1 turns about the base z
/// axis, as in every DH table here); the solution nearest `near`, within the limits.
fn solve_q1(
    arm: &Arm,
    q: &[f64; 6],
    tool: &Vector3<f64>,
    fix: &Vector3<f64>,
    len: f64,
    near: f64,
) -> Option<f64> {
    let mut q0 = *q;
    q0[0] = 0.0;
    let p = arm.point(&q0, tool);
    // |Rz(φ) p − F|² = C − 2 (c·cos φ + s·sin φ), C = |p|² + |F|² − 2 F_z p_z.
    let c0 = p.norm_squared() + fix.norm_squared() - 2.0 * fix.z * p.z;
    let (a, b) = (fix.x * p.x + fix.y * p.y, fix.y * p.x - fix.x * p.y);
    let r = a.hypot(b);
    let cosd = (c0 - len * len) / (2.0 * r);
    if r < 1e-9 || cosd.abs() > 1.0 {
        return None;
    }
    let beta = b.atan2(a);
    let d = cosd.acos();
    let mut best: Option<f64> = None;
    for base in [beta + d, beta - d] {
        for turn in -2..=2 {
            let phi = base + turn as f64 * 2.0 * PI;
            if phi >= arm.lo[0]
                && phi <= arm.hi[0]
                && best.is_none_or(|x| (phi - near).abs() < (x - near).abs())
            {
                best = Some(phi);
            }
        }
    }
    best
}

/// Options of a continuous recording.
#[derive(Clone, Debug)]
pub struct Walk {
    pub fixture: Vector3<f64>,
    pub tool: Vector3<f64>,
    /// Bar range (m).
    pub len: (f64, f64),
    pub duration: f64,
    /// Share of the axis speeds used.
    pub speed: f64,
    pub seed: u64,
}

/// A random walk on the bar's shell: waypoints a joint step apart (joints 2-6 random within
/// their limits, joint 1 solved for a random bar length), joined by splines with the axis
/// speeds respected, and now and then a dwell; the bar stays within its range along the way.
pub fn walk(arm: &Arm, w: &Walk) -> Path {
    let mut rng = ChaCha8Rng::seed_from_u64(w.seed ^ 0x07e3_5111u64);
    let margin = 5.0 * DEG;
    let lo: [f64; 6] = std::array::from_fn(|j| (arm.lo[j] + margin).max(-PI));
    let hi: [f64; 6] = std::array::from_fn(|j| (arm.hi[j] - margin).min(PI));
    let len_of = |q: &[f64; 6]| (arm.point(q, &w.tool) - w.fixture).norm();
    // The first waypoint: anywhere on the shell.
    let mut q = loop {
        let mut q: [f64; 6] = std::array::from_fn(|j| rng.random_range(lo[j]..hi[j]));
        let l = rng.random_range(w.len.0..w.len.1);
        if let Some(q1) = solve_q1(arm, &q, &w.tool, &w.fixture, l, 0.0) {
            q[0] = q1;
            break q;
        }
    };
    let mut path = Path {
        t: vec![0.0],
        q: vec![q],
        v: vec![[0.0; 6]],
        a: vec![[0.0; 6]],
    };
    let mut tries = 0;
    while path.duration() < w.duration {
        tries += 1;
        assert!(tries < 200_000, "the walk finds no way on the shell");
        // A step of up to 30° on joints 2-6, a new bar length, joint 1 solved near its last.
        let mut n = q;
        for j in 1..6 {
            n[j] = (q[j] + rng.random_range(-30.0..30.0) * DEG).clamp(lo[j], hi[j]);
        }
        let l = rng.random_range(w.len.0..w.len.1);
        let Some(q1) = solve_q1(arm, &n, &w.tool, &w.fixture, l, q[0]) else {
            continue;
        };
        n[0] = q1;
        if (n[0] - q[0]).abs() > 60.0 * DEG {
            continue;
        }
        // The move's time: its slowest axis at the speed share, at least 0.4 s.
        let dt = (0..6)
            .map(|j| (n[j] - q[j]).abs() / (w.speed * arm.speed[j]))
            .fold(0.4, f64::max)
            * 1.5;
        // Pass through the previous knot (the mean of its secants, the change of them as its
        // acceleration), unless the robot rested there; now and then stop after this move.
        let stop = rng.random_range(0.0..1.0) < 0.15;
        let mut trial = path.clone();
        let t0 = trial.duration();
        let k = trial.t.len() - 1;
        trial.t.push(t0 + dt);
        trial.q.push(n);
        trial.v.push([0.0; 6]);
        trial.a.push([0.0; 6]);
        if k > 0 && !path_stopped(&path) {
            let prev = trial.q[k - 1];
            let tp = trial.t[k] - trial.t[k - 1];
            let here = trial.q[k];
            trial.v[k] =
                std::array::from_fn(|j| 0.5 * ((here[j] - prev[j]) / tp + (n[j] - here[j]) / dt));
            trial.a[k] = std::array::from_fn(|j| {
                ((n[j] - here[j]) / dt - (here[j] - prev[j]) / tp) / (0.5 * (tp + dt))
            });
        }
        // The bar within its range (20 mm of slack) all along the new move and the one before.
        let from = trial.t[k.saturating_sub(1)];
        let ok = (0..=80).all(|s| {
            let t = from + (t0 + dt - from) * s as f64 / 80.0;
            let l = len_of(&trial.at(t));
            l > w.len.0 - 0.02 && l < w.len.1 + 0.02
        });
        if !ok {
            continue;
        }
        path = trial;
        q = n;
        if stop {
            let t1 = path.duration() + rng.random_range(0.5..2.0);
            path.t.push(t1);
            path.q.push(q);
            path.v.push([0.0; 6]);
            path.a.push([0.0; 6]);
        }
    }
    path
}

/// A path that stops at every knot in turn (a stop-and-go program: quintic moves with zero
/// velocity and acceleration at both ends follow the straight joint line between knots), each
/// move timed by its slowest axis at `speed` of the axis speeds (at least 0.5 s), with
/// `dwell` seconds at every knot.
pub fn through(arm: &Arm, knots: &[[f64; 6]], speed: f64, dwell: f64) -> Path {
    through_dwelling(arm, knots, speed, &vec![dwell; knots.len()])
}

/// [`through`] with a dwell of its own at each knot (`dwell[k]` seconds after arriving at
/// knot k).
pub fn through_dwelling(arm: &Arm, knots: &[[f64; 6]], speed: f64, dwell: &[f64]) -> Path {
    let mut path = Path {
        t: vec![0.0],
        q: vec![knots[0]],
        v: vec![[0.0; 6]],
        a: vec![[0.0; 6]],
    };
    if dwell.first().is_some_and(|d| *d > 0.0) {
        path.t.push(dwell[0]);
        path.q.push(knots[0]);
        path.v.push([0.0; 6]);
        path.a.push([0.0; 6]);
    }
    for (k, w) in knots.windows(2).enumerate() {
        let dt = (0..6)
            .map(|j| (w[1][j] - w[0][j]).abs() / (speed * arm.speed[j]))
            .fold(0.5, f64::max)
            * 1.875; // a quintic's peak speed is 1.875 times its mean
        for (t, q) in [(dt, w[1]), (dwell[k + 1], w[1])] {
            if t > 0.0 {
                let t0 = path.duration();
                path.t.push(t0 + t);
                path.q.push(q);
                path.v.push([0.0; 6]);
                path.a.push([0.0; 6]);
            }
        }
    }
    path
}

/// True when the path ends at rest (its last two knots equal).
fn path_stopped(p: &Path) -> bool {
    let n = p.q.len();
    n < 2 || p.q[n - 1] == p.q[n - 2]
}

// ---- the real robot -----------------------------------------------------------------------

/// A point mass: link frame index (1..6), position in that frame (m), mass (kg).
pub type Mass = (usize, Vector3<f64>, f64);

/// A cyclic error's harmonic: order, amplitude (rad), phase (rad).
pub type Harmonic = (usize, f64, f64);

/// What the real robot does besides its geometry; each effect in this module's own formulas.
#[derive(Clone, Debug, Default)]
pub struct Physics {
    /// Point masses (kg) fixed in link frames (frame index 1..6, position in that frame), and
    /// the joint stiffnesses (N·m/rad).
    pub compliance: Option<(Vec<Mass>, [f64; 6])>,
    /// α (1/K), final rise R (K), starting rise T₀ (K), τ (s).
    pub thermal: Option<(f64, f64, f64, f64)>,
    /// The links (0-based) the thermal drift grows; empty: every link.
    pub thermal_links: Vec<usize>,
    /// Joint, and (order, amplitude rad, phase rad) per harmonic.
    pub cyclic: Option<(usize, Vec<Harmonic>)>,
    /// Joint, full play (rad).
    pub backlash: Option<(usize, f64)>,
    /// First-order servo loop time constant (s).
    pub servo: Option<f64>,
    /// At time t (s) the fixture slides by this (m) over 0.2 s.
    pub slip: Option<(f64, Vector3<f64>)>,
    /// Gross reading errors: (sample index, error in m), e.g. a bar that caught.
    pub spikes: Vec<(usize, f64)>,
}

/// The truth of a simulation: the real geometry, tool and fixture, and the physics.
#[derive(Clone, Debug)]
pub struct Truth {
    pub arm: Arm,
    pub tool: Vector3<f64>,
    pub fixture: Vector3<f64>,
    pub physics: Physics,
    /// Bar noise σ and resolution (m).
    pub noise: f64,
    pub resolution: f64,
}

impl Truth {
    /// Gravity torques about every joint axis at q (gravity −z of the base).
    fn torques(&self, q: &[f64; 6], masses: &[(usize, Vector3<f64>, f64)]) -> [f64; 6] {
        let f = self.arm.frames(q, 1.0);
        let mut tau = [0.0; 6];
        for (frame, at, m) in masses {
            let p = apply(&f[*frame], at);
            let force = Vector3::new(0.0, 0.0, -GRAVITY * m);
            for j in 0..*frame {
                let z = Vector3::new(f[j][(0, 2)], f[j][(1, 2)], f[j][(2, 2)]);
                tau[j] += z.dot(&(p - origin(&f[j])).cross(&force));
            }
        }
        tau
    }

    /// Load-side joint angles from the motor side ones (cyclic error, compliance; backlash is
    /// applied by the caller, which keeps its state).
    fn load(&self, motor: &[f64; 6]) -> [f64; 6] {
        let mut q = *motor;
        if let Some((j, harmonics)) = &self.physics.cyclic {
            q[*j] += harmonics
                .iter()
                .map(|(h, a, phi)| a * (*h as f64 * motor[*j] + phi).sin())
                .sum::<f64>();
        }
        if let Some((masses, k)) = &self.physics.compliance {
            // Deflection at the deflected pose: one fixed-point step from the undeflected one.
            let mut d = q;
            for _ in 0..2 {
                let tau = self.torques(&d, masses);
                d = std::array::from_fn(|j| q[j] + tau[j] / k[j]);
            }
            q = d;
        }
        q
    }

    fn grow(&self, t: f64) -> f64 {
        match self.physics.thermal {
            Some((alpha, rise, start, tau)) => {
                1.0 + alpha * (rise - (rise - start) * (-t / tau).exp())
            }
            None => 1.0,
        }
    }

    /// Each link's growth factor at time t: the drift's on the links it grows, 1 elsewhere.
    fn grow_links(&self, t: f64) -> [f64; 6] {
        let g = self.grow(t);
        let links = &self.physics.thermal_links;
        std::array::from_fn(|i| {
            if links.is_empty() || links.contains(&i) {
                g
            } else {
                1.0
            }
        })
    }

    /// The true tool point when the controller commands `motor` and stands still: the
    /// backlash joint's load side at `play_load` (where the play operator left it), the
    /// other effects on the motor angles, the links as at time t of a recording.
    pub fn reached(&self, motor: &[f64; 6], play_load: Option<f64>, t: f64) -> Vector3<f64> {
        let mut m = *motor;
        if let (Some((j, _)), Some(y)) = (self.physics.backlash, play_load) {
            m[j] = y;
        }
        let load = self.load(&m);
        apply(
            &self.arm.frames_grown(&load, &self.grow_links(t))[6],
            &self.tool,
        )
    }

    fn fixture_at(&self, t: f64) -> Vector3<f64> {
        match self.physics.slip {
            Some((at, d)) => self.fixture + d * ((t - at) / 0.2).clamp(0.0, 1.0),
            None => self.fixture,
        }
    }

    /// The true tool point at joint angles q (geometry only): what a calibrated robot file
    /// should reproduce.
    pub fn point(&self, q: &[f64; 6]) -> Vector3<f64> {
        self.arm.point(q, &self.tool)
    }

    /// The robot a DH table can hold: a cyclic error's mean over the range `(lo, hi)` its
    /// joint was measured in moved into the joint's zero (by quadrature here). Over a joint
    /// that turns far less than a turn only the zero plus that mean is observable, and it is
    /// the best constant for the real robot there.
    pub fn effective(&self, lo: [f64; 6], hi: [f64; 6]) -> Truth {
        let mut t = self.clone();
        if let Some((j, harmonics)) = &self.physics.cyclic {
            let (lo, hi) = (lo[*j], hi[*j]);
            let n = 20_000;
            let mean = (0..n)
                .map(|i| {
                    let q = lo + (hi - lo) * (i as f64 + 0.5) / n as f64;
                    harmonics
                        .iter()
                        .map(|(h, a, phi)| a * (*h as f64 * q + phi).sin())
                        .sum::<f64>()
                })
                .sum::<f64>()
                / n as f64;
            t.arm.dh[*j][3] += mean;
        }
        t
    }

    /// The true tool point at joint angles q with the links as they were at time t (s) of a
    /// recording: a thermal drift's robot at the start of the recording is what the
    /// calibration describes (it cannot know the temperature before the data began).
    pub fn point_at(&self, q: &[f64; 6], t: f64) -> Vector3<f64> {
        apply(
            &self.arm.frames_grown(q, &self.grow_links(t))[6],
            &self.tool,
        )
    }
}

/// A recording: times, logged joint angles and bar readings (SI).
#[derive(Clone, Debug, Default)]
pub struct Recording {
    pub t: Vec<f64>,
    pub q: Vec<[f64; 6]>,
    pub length: Vec<f64>,
}

impl Recording {
    /// The measured-data CSV (continuous form), written by this module.
    pub fn csv(&self) -> String {
        let mut s = String::from("t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm\n");
        for k in 0..self.t.len() {
            s += &format!("{:.3}", self.t[k]);
            for j in 0..6 {
                s += &format!(",{:.6}", self.q[k][j] / DEG);
            }
            s += &format!(",{:.5}\n", self.length[k] * 1e3);
        }
        s
    }
}

/// Runs `path` on the true robot at `rate` Hz: the controller logs the setpoints, the axes
/// follow (servo loop, backlash, cyclic error, compliance), the links grow, the fixture may
/// slide, and the bar reads the distance with noise and resolution.
pub fn record(truth: &Truth, path: &Path, rate: f64, seed: u64) -> Recording {
    record_from(truth, path, rate, seed, 0.0)
}

/// [`record`] of a path that starts `t0` seconds into the robot's day (its thermal state);
/// the recording's times still start at 0.
pub fn record_from(truth: &Truth, path: &Path, rate: f64, seed: u64, t0: f64) -> Recording {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0xba5e);
    let n = (path.duration() * rate).floor() as usize;
    let mut out = Recording::default();
    // The drives between bar samples, at 2 kHz: the servo loop's state and the backlash's
    // load angle (started anywhere inside the play; it stays unless the motor, b/2 away on
    // either side, pushes it).
    let inner = 2000.0;
    let per_sample = (inner / rate).round().max(1.0) as usize;
    let mut x = path.at(0.0);
    let mut play: Option<f64> = None;
    let step = |x: &mut [f64; 6], play: &mut Option<f64>, s: [f64; 6], rng: &mut ChaCha8Rng| {
        match truth.physics.servo {
            Some(tau) => {
                let a = 1.0 - (-1.0 / (inner * tau)).exp();
                for j in 0..6 {
                    x[j] += a * (s[j] - x[j]);
                }
            }
            None => *x = s,
        }
        if let Some((j, b)) = truth.physics.backlash {
            let y = play.unwrap_or(x[j] + rng.random_range(-0.5..0.5) * b);
            *play = Some(y.clamp(x[j] - 0.5 * b, x[j] + 0.5 * b));
        }
    };
    step(&mut x, &mut play, path.at(0.0), &mut rng);
    for k in 0..n {
        let t = k as f64 / rate;
        let set = path.at(t);
        // Whole inner steps, counted (a time summed in floating point would drift and give
        // some samples an extra step).
        if k > 0 {
            for i in 1..=per_sample {
                let ti = ((k - 1) * per_sample + i) as f64 / (per_sample as f64 * rate);
                step(&mut x, &mut play, path.at(ti), &mut rng);
            }
        }
        let mut motor = x;
        if let (Some((j, _)), Some(y)) = (truth.physics.backlash, play) {
            motor[j] = y;
        }
        let load = truth.load(&motor);
        let f = truth.arm.frames_grown(&load, &truth.grow_links(t0 + t));
        let p = apply(&f[6], &truth.tool);
        let mut l = (p - truth.fixture_at(t0 + t)).norm() + truth.noise * normal(&mut rng);
        if let Some((_, e)) = truth.physics.spikes.iter().find(|(i, _)| *i == k) {
            l += e;
        }
        let l = (l / truth.resolution).round() * truth.resolution;
        out.t.push(t);
        out.q.push(set);
        out.length.push(l);
    }
    out
}

// ---- static readings ----------------------------------------------------------------------

/// A static campaign: one reading per pose, in the order taken, of a draw-wire (or a bar)
/// whose zero is unknown, jumps and drifts; joints logged to a resolution.
#[derive(Clone, Debug)]
pub struct Static {
    pub poses: usize,
    /// Joint readings quantised to this (rad; 0: exact).
    pub joint_step: f64,
    /// Length readings quantised to this (m).
    pub length_step: f64,
    /// Reading noise (m).
    pub noise: f64,
    /// The instrument's zero: reading − distance (m).
    pub zero: f64,
    /// Zero jumps: (first row affected, 0-based; jump in m).
    pub jumps: Vec<(usize, f64)>,
    /// A drifting zero: (first row, rows, total change in m), linear over the rows.
    pub drift: Option<(usize, usize, f64)>,
    /// Outliers: (row, error in m).
    pub outliers: Vec<(usize, f64)>,
    /// Poses keep the tool point above this height and within this distance of the anchor.
    pub min_z: f64,
    pub max_len: f64,
    pub seed: u64,
}

/// What a static campaign recorded.
#[derive(Clone, Debug, Default)]
pub struct StaticRecording {
    /// The joint angles as logged (quantised) and as they were.
    pub q_logged: Vec<[f64; 6]>,
    pub q_true: Vec<[f64; 6]>,
    pub length: Vec<f64>,
}

impl StaticRecording {
    /// The measured-data CSV in the static form (no `t_s`), written by this module.
    pub fn csv(&self) -> String {
        let mut s = String::from("q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm\n");
        for k in 0..self.length.len() {
            for j in 0..6 {
                s += &format!("{:.4},", self.q_logged[k][j] / DEG);
            }
            s += &format!("{:.5}\n", self.length[k] * 1e3);
        }
        s
    }
}

/// The zero of the instrument at row k.
fn zero_at(c: &Static, k: usize) -> f64 {
    let mut z = c.zero;
    for (r, j) in &c.jumps {
        if k >= *r {
            z += j;
        }
    }
    if let Some((from, rows, total)) = c.drift {
        z += total * ((k as f64 - from as f64) / rows as f64).clamp(0.0, 1.0);
    }
    z
}

/// Random poses within the limits (the tool point above `min_z`, within `max_len` of the
/// anchor) and the readings of the instrument at each.
pub fn static_readings(truth: &Truth, c: &Static) -> StaticRecording {
    let mut rng = ChaCha8Rng::seed_from_u64(c.seed ^ 0x57a7);
    let mut out = StaticRecording::default();
    while out.length.len() < c.poses {
        let q: [f64; 6] =
            std::array::from_fn(|j| rng.random_range(truth.arm.lo[j]..truth.arm.hi[j]));
        let p = truth.point(&q);
        let d = (p - truth.fixture).norm();
        if p.z < c.min_z || d > c.max_len {
            continue;
        }
        let k = out.length.len();
        let mut l = d + zero_at(c, k) + c.noise * normal(&mut rng);
        if let Some((_, e)) = c.outliers.iter().find(|(r, _)| *r == k) {
            l += e;
        }
        let quant = |v: f64, step: f64| {
            if step > 0.0 {
                (v / step).round() * step
            } else {
                v
            }
        };
        out.q_true.push(q);
        out.q_logged.push(q.map(|v| quant(v, c.joint_step)));
        out.length.push(quant(l, c.length_step));
    }
    out
}

/// The floor the readings' resolution puts under any model's residual (m): the RMS over the
/// poses of the length error that uniform joint rounding of `joint_step` causes (∂L/∂q by
/// central differences of this module's kinematics), with the length's own rounding and noise.
pub fn resolution_floor(truth: &Truth, poses: &[[f64; 6]], c: &Static) -> f64 {
    let h = 1e-6;
    let len = |q: &[f64; 6]| (truth.point(q) - truth.fixture).norm();
    let ms: f64 = poses
        .iter()
        .map(|q| {
            (0..6)
                .map(|j| {
                    let (mut a, mut b) = (*q, *q);
                    a[j] += h;
                    b[j] -= h;
                    ((len(&a) - len(&b)) / (2.0 * h)).powi(2)
                })
                .sum::<f64>()
        })
        .sum::<f64>()
        / poses.len().max(1) as f64;
    let q = c.joint_step * c.joint_step / 12.0;
    (ms * q + c.length_step * c.length_step / 12.0 + c.noise * c.noise).sqrt()
}

// ---- logs on two clocks -------------------------------------------------------------------

/// How a continuous run is logged by two devices that share no clock: the controller logs its
/// joints at `joint_rate` on its clock (the reference here), the bar its readings at
/// `bar_rate` on a clock that runs `drift` fast (t_bar = offset + (1 + drift)·t_joint) and
/// averages the distance over `window` seconds before each sample (0: instantaneous).
#[derive(Clone, Debug)]
pub struct Clocks {
    pub joint_rate: f64,
    pub bar_rate: f64,
    pub offset: f64,
    pub drift: f64,
    pub window: f64,
    /// Joint-clock seconds the bar starts after the joint log (negative: before), and how
    /// long before the joint log's end it stops.
    pub bar_start: f64,
    pub bar_stop: f64,
    /// The controller logs its setpoints (true) or the axes' actual positions (false).
    pub setpoints: bool,
}

/// The two log files of a continuous run, as the devices write them.
#[derive(Clone, Debug, Default)]
pub struct TwoLogs {
    /// `t_s,length_mm`, the bar's clock.
    pub bar: String,
    /// `t_s,q1_deg,...,q6_deg`, the controller's clock.
    pub joints: String,
    pub bar_rows: usize,
    pub joint_rows: usize,
}

/// Runs `path` on the true robot (servo loop, backlash, cyclic error, compliance, links
/// growing) integrated at 10 kHz and logs it on two clocks: the joints as the controller
/// logs them, the bar's distances (noise, resolution, its averaging window) at the bar
/// clock's own regular ticks. Between the physics steps the distance is interpolated
/// linearly (0.1 ms: under 0.1 µm at the accelerations here).
pub fn record_logs(truth: &Truth, path: &Path, c: &Clocks, seed: u64) -> TwoLogs {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x2c10c);
    let inner = 10_000.0;
    let n = (path.duration() * inner).floor() as usize;
    // The true distance and the axes' positions at every physics step.
    let mut dist = Vec::with_capacity(n + 1);
    let mut actual = Vec::with_capacity(n + 1);
    let mut x = path.at(0.0);
    let mut play: Option<f64> = None;
    for i in 0..=n {
        let t = i as f64 / inner;
        let s = path.at(t);
        match truth.physics.servo {
            Some(tau) if i > 0 => {
                let a = 1.0 - (-1.0 / (inner * tau)).exp();
                for j in 0..6 {
                    x[j] += a * (s[j] - x[j]);
                }
            }
            _ => x = s,
        }
        let mut motor = x;
        if let Some((j, b)) = truth.physics.backlash {
            let y = play.unwrap_or(x[j] + rng.random_range(-0.5..0.5) * b);
            let y = y.clamp(x[j] - 0.5 * b, x[j] + 0.5 * b);
            play = Some(y);
            motor[j] = y;
        }
        let load = truth.load(&motor);
        let f = truth.arm.frames_grown(&load, &truth.grow_links(t));
        dist.push((apply(&f[6], &truth.tool) - truth.fixture_at(t)).norm());
        actual.push(x);
    }
    let at = |v: &[f64], t: f64| {
        let u = (t * inner).clamp(0.0, n as f64);
        let i = (u.floor() as usize).min(n.saturating_sub(1));
        let f = u - i as f64;
        v[i] * (1.0 - f) + v[(i + 1).min(n)] * f
    };
    let mut out = TwoLogs {
        bar: String::from("t_s,length_mm\n"),
        joints: String::from("t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n"),
        ..TwoLogs::default()
    };
    // The controller's log: its clock is the reference.
    let dur = path.duration();
    let mut k = 0;
    loop {
        let t = k as f64 / c.joint_rate;
        if t > dur {
            break;
        }
        let q = if c.setpoints {
            path.at(t)
        } else {
            let i = ((t * inner).round() as usize).min(n);
            actual[i]
        };
        out.joints += &format!("{:.4}", t);
        for v in q {
            out.joints += &format!(",{:.8}", v / DEG);
        }
        out.joints += "\n";
        out.joint_rows += 1;
        k += 1;
    }
    // The bar's log: regular ticks of its own clock, from bar_start to dur − bar_stop.
    let a = 1.0 + c.drift;
    let u0 = c.offset + a * c.bar_start;
    let u1 = c.offset + a * (dur - c.bar_stop);
    let first = (u0 * c.bar_rate).ceil() as i64;
    let last = (u1 * c.bar_rate).floor() as i64;
    let avg = (c.window * inner).round().max(1.0) as usize;
    for k in first..=last {
        let u = k as f64 / c.bar_rate;
        let t = (u - c.offset) / a;
        let l = if avg <= 1 {
            at(&dist, t)
        } else {
            (0..avg)
                .map(|i| at(&dist, t - i as f64 / inner))
                .sum::<f64>()
                / avg as f64
        };
        let l = l + truth.noise * normal(&mut rng);
        let l = (l / truth.resolution).round() * truth.resolution;
        out.bar += &format!("{:.4},{:.5}\n", u, l * 1e3);
        out.bar_rows += 1;
    }
    out
}

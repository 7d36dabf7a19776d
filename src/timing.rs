//! Move times with acceleration: in = joint moves (rad), the joints' maximum speeds (rad/s) and
//! accelerations (rad/s²), which corners blend; out = each move's duration and the program's.
//!
//! A joint-space move a → b runs every joint on one profile s(t) ∈ [0, 1] (synchronous
//! interpolation, as PTP / MoveAbsJ / movej and a CNC kernel's joint-space lines do): the path
//! speed ṡ is limited by the joint that needs the longest at its speed (Eq. 7's time T₇ = 1/ṡ)
//! and the path acceleration s̈ by the joint that needs the longest at its acceleration
//! (T_a² = max |Δqᵢ|/aᵢ = 1/s̈). The profile is a trapezoid: T = T₇ + T_a²/T₇ when the move
//! reaches its cruise (T₇ ≥ T_a), else a triangle, T = 2·T_a. Eq. 7 (T₇ alone) is the limit of
//! infinite acceleration.
//!
//! A blended corner overlaps the two moves (the superposition of the first move's deceleration
//! and the next one's acceleration, LinuxCNC's parabolic blend): the time saved is the shorter
//! of the first move's final ramp and either move's time at its cruise speed (LinuxCNC limits a
//! blend to half of each segment). A controller may scale the acceleration of moves that blend
//! ([`crate::dialect::Corner::blend_acceleration`]: LinuxCNC halves it so that the two
//! superposed moves together stay within the limits).

use serde::{Deserialize, Serialize};

/// The joints' limits a move time depends on (SI).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    /// Maximum joint speeds (rad/s).
    pub speed: [f64; 6],
    /// Maximum joint accelerations (rad/s²).
    pub accel: [f64; 6],
}

impl Limits {
    pub fn of(robot: &crate::robot::Robot) -> Self {
        Limits {
            speed: robot.max_speeds(),
            accel: robot.max_accelerations(),
        }
    }
}

/// Eq. 7: the time of the slowest joint at its maximum speed (no acceleration).
#[inline]
pub fn eq7(a: &[f64; 6], b: &[f64; 6], speed: &[f64; 6]) -> f64 {
    let mut t = 0.0_f64;
    for i in 0..6 {
        t = t.max((a[i] - b[i]).abs() / speed[i]);
    }
    t
}

/// T_a: the square root of the longest time-squared any joint needs at its acceleration,
/// max √(|Δqᵢ|/aᵢ) (a triangle profile takes 2·T_a).
#[inline]
pub fn accel_time(a: &[f64; 6], b: &[f64; 6], accel: &[f64; 6]) -> f64 {
    let mut t2 = 0.0_f64;
    for i in 0..6 {
        t2 = t2.max((a[i] - b[i]).abs() / accel[i]);
    }
    t2.sqrt()
}

/// The synchronous trapezoid's duration from T₇ (time at the cruise speed over the whole
/// move) and T_a (see [`accel_time`]).
#[inline]
pub fn trapezoid(t7: f64, ta: f64) -> f64 {
    if t7 <= 0.0 && ta <= 0.0 {
        0.0
    } else if t7 >= ta {
        t7 + ta * ta / t7
    } else {
        2.0 * ta
    }
}

/// The shortest duration of the move a → b at the joints' speeds and accelerations scaled by
/// `accel_scale` (1 for a move between exact stops).
pub fn move_time(a: &[f64; 6], b: &[f64; 6], lim: &Limits, accel_scale: f64) -> f64 {
    let t7 = eq7(a, b, &lim.speed);
    let ta = accel_time(a, b, &lim.accel) / accel_scale.sqrt();
    trapezoid(t7, ta)
}

/// The duration of a move whose cruise speed makes it take `cruise` s without ramps (a G93 F,
/// a speed percentage): the controller's ramps at the (scaled) accelerations come on top; a
/// move too short to reach that speed takes its triangle.
pub fn with_ramps(a: &[f64; 6], b: &[f64; 6], cruise: f64, lim: &Limits, accel_scale: f64) -> f64 {
    let ta = accel_time(a, b, &lim.accel) / accel_scale.sqrt();
    trapezoid(cruise, ta)
}

/// The cruise time of a move whose whole time (ramps included) is `total`: T = T₇ + T_a²/T₇
/// solved for T₇ (a move too short for a cruise runs its triangle at T_a). How a whole-move
/// time word (RAPID `\T`, URScript `t`) is read.
pub fn cruise_of(total: f64, ta: f64) -> f64 {
    let disc = total * total - 4.0 * ta * ta;
    if disc <= 0.0 {
        ta
    } else {
        (total + disc.sqrt()) / 2.0
    }
}

/// The time two moves overlap at a blended corner (superposed ramps): the shorter of the first
/// move's final ramp and either move's time at its cruise speed (a blend takes at most half of
/// each move). `t7`/`ta` are each move's cruise time and acceleration time as in [`trapezoid`].
pub fn overlap(t7_in: f64, ta_in: f64, t7_out: f64, ta_out: f64) -> f64 {
    // The speed actually reached (its time over the whole move): the cruise, or the triangle's peak.
    let cruise_in = t7_in.max(ta_in);
    let cruise_out = t7_out.max(ta_out);
    // The first move's ramp from that speed to rest: (1/cruise) / (1/ta²).
    let ramp_in = if cruise_in > 0.0 {
        ta_in * ta_in / cruise_in
    } else {
        0.0
    };
    ramp_in.min(cruise_in).min(cruise_out)
}

/// One move of a program as [`program`] times it: its cruise time (the time at its cruise
/// speed over the whole move, [`eq7`] or what the program commands), its acceleration time
/// `ta` (at the acceleration its blends allow, see [`accel_time`]), its own duration (ramps
/// included) and the time it overlaps the next move (0 unless the corner between them blends).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MoveTiming {
    pub cruise: f64,
    pub ta: f64,
    pub duration: f64,
    pub overlap_next: f64,
}

impl MoveTiming {
    /// The path profile s(t) ∈ [0, 1] this timing states: the synchronous trapezoid's phases
    /// (ramps of the trapezoid's length, a cruise at 1/cruise, or the triangle when the move is
    /// too short for a cruise), each ramp shaped as a cycloidal speed ramp
    /// v(u) = V·(u − sin(2πu)/2π): the same duration, distance and cruise speed as the
    /// trapezoid's straight ramp, the speed monotone (never above the cruise's), the
    /// acceleration continuous (zero at rest and at the cruise, a finite jerk, as a jerk-limited
    /// controller runs its ramps) with its mean over the ramp at the path acceleration and its
    /// peak twice that. Returns (s, ds/dt) at time t after the move's start; 0 before, 1 after.
    /// Its duration is exactly [`MoveTiming::duration`].
    pub fn profile(&self, t: f64) -> (f64, f64) {
        let d = self.duration;
        if d <= 0.0 || t >= d {
            return (1.0, 0.0);
        }
        if t <= 0.0 {
            return (0.0, 0.0);
        }
        let (v, ramp) = if self.cruise >= self.ta {
            (1.0 / self.cruise, self.ta * self.ta / self.cruise)
        } else {
            (1.0 / self.ta, self.ta)
        };
        // Distance and speed of a cycloidal ramp from rest, `r` s into it.
        let up = |r: f64| -> (f64, f64) {
            let u = r / ramp;
            let w = std::f64::consts::TAU * u;
            (
                v * ramp
                    * (0.5 * u * u
                        + (w.cos() - 1.0) / (std::f64::consts::TAU * std::f64::consts::TAU)),
                v * (u - w.sin() / std::f64::consts::TAU),
            )
        };
        if t < ramp {
            up(t)
        } else if t <= d - ramp {
            (0.5 * v * ramp + v * (t - ramp), v)
        } else {
            let (s, ds) = up(d - t);
            (1.0 - s, ds)
        }
    }
}

/// A program's moves timed together: `poses[k]` reached from `poses[k-1]` in `cruise[k]` s
/// without ramps (`cruise[0]` is ignored: the approach), `blended[k]` when the corner at pose k
/// blends into the next move. Returns each move's timing (the first, the approach's start,
/// all 0): its ramps at the acceleration its blends allow, and the overlap of each blended
/// corner with the move after it.
pub fn moves(
    poses: &[[f64; 6]],
    cruise: &[f64],
    blended: &[bool],
    lim: &Limits,
    blend_acceleration: f64,
) -> Vec<MoveTiming> {
    let n = poses.len();
    let mut out = vec![MoveTiming::default(); n];
    for k in 1..n {
        let blends = blended[k] || blended[k - 1];
        let scale = if blends { blend_acceleration } else { 1.0 };
        let ta = accel_time(&poses[k - 1], &poses[k], &lim.accel) / scale.sqrt();
        out[k] = MoveTiming {
            cruise: cruise[k],
            ta,
            duration: trapezoid(cruise[k], ta),
            overlap_next: 0.0,
        };
    }
    for k in 1..n.saturating_sub(1) {
        if blended[k] {
            let (a, b) = (out[k], out[k + 1]);
            out[k].overlap_next = overlap(a.cruise, a.ta, b.cruise, b.ta);
        }
    }
    out
}

/// [`moves`] as each move's own duration (0 for the first) and the program's total, the
/// overlaps of blended corners taken off.
pub fn program(
    poses: &[[f64; 6]],
    cruise: &[f64],
    blended: &[bool],
    lim: &Limits,
    blend_acceleration: f64,
) -> (Vec<f64>, f64) {
    let m = moves(poses, cruise, blended, lim, blend_acceleration);
    // Summed as before the split (all durations, then the overlaps): the same bits.
    let mut total: f64 = m.iter().map(|m| m.duration).sum();
    for mt in &m {
        if mt.overlap_next != 0.0 {
            total -= mt.overlap_next;
        }
    }
    (m.iter().map(|m| m.duration).collect(), total)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The trapezoid against a direct integration of the profile (independent: a time-stepped
    /// bang-coast-bang on one joint).
    #[test]
    fn trapezoid_matches_a_stepped_integration() {
        for &(d, v, acc) in &[
            (1.0, 2.0, 4.0),
            (1.0, 2.0, 1.0),
            (0.3, 1.5, 20.0),
            (2.0, 0.5, 0.3),
        ] {
            let lim = Limits {
                speed: [v; 6],
                accel: [acc; 6],
            };
            let a = [0.0; 6];
            let mut b = [0.0; 6];
            b[2] = d;
            let t = move_time(&a, &b, &lim, 1.0);
            // Step: accelerate while the stopping distance allows, coast at v, brake.
            let dt = 1e-6;
            let (mut x, mut s, mut time) = (0.0f64, 0.0f64, 0.0f64);
            while x < d {
                let stop = s * s / (2.0 * acc);
                let acc_now = if d - x <= stop {
                    -acc
                } else if s < v {
                    acc
                } else {
                    0.0
                };
                s = (s + acc_now * dt).clamp(1e-9, v);
                x += s * dt;
                time += dt;
            }
            assert!(
                (t - time).abs() < 2e-3 * t.max(1.0),
                "{d} {v} {acc}: {t} vs {time}"
            );
        }
    }

    #[test]
    fn slowest_joint_leads_and_eq7_is_the_limit() {
        let lim = Limits {
            speed: [1.0, 2.0, 1.0, 1.0, 1.0, 1.0],
            accel: [1e9; 6],
        };
        let a = [0.0; 6];
        let b = [0.5, 2.0, 0.0, 0.0, 0.0, 0.0];
        assert!((move_time(&a, &b, &lim, 1.0) - 1.0).abs() < 1e-6);
        assert_eq!(move_time(&a, &a, &lim, 1.0), 0.0);
        // Halving the acceleration lengthens the ramps.
        let lim = Limits {
            speed: [1.0; 6],
            accel: [2.0; 6],
        };
        let b = [2.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert!((move_time(&a, &b, &lim, 1.0) - 2.5).abs() < 1e-12);
        assert!((move_time(&a, &b, &lim, 0.5) - 3.0).abs() < 1e-12);
    }

    #[test]
    fn blends_take_the_overlap_off() {
        let lim = Limits {
            speed: [1.0; 6],
            accel: [2.0; 6],
        };
        let poses = [
            [0.0; 6],
            [2.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [2.0, 2.0, 0.0, 0.0, 0.0, 0.0],
        ];
        let cruise = [0.0, 2.0, 2.0];
        let (t, total) = program(&poses, &cruise, &[false; 3], &lim, 1.0);
        assert_eq!(t, vec![0.0, 2.5, 2.5]);
        assert!((total - 5.0).abs() < 1e-12);
        // Blended at pose 1: each move at half acceleration (3 s), the 1 s ramp overlapped.
        let (t, total) = program(&poses, &cruise, &[false, true, false], &lim, 0.5);
        assert_eq!(t, vec![0.0, 3.0, 3.0]);
        assert!((total - 5.0).abs() < 1e-12);
    }

    /// The profile a twin runs: it takes the move's duration, reaches s = 1, never exceeds the
    /// cruise speed, and its speed is the derivative of its distance (central differences) with
    /// no jump in distance or speed, for a trapezoid and a triangle.
    #[test]
    fn the_profile_takes_the_stated_time_within_the_cruise_speed() {
        for &(cruise, ta) in &[(2.0, 1.0), (0.5, 1.0), (1.0, 1.0), (3.0, 0.2)] {
            let m = MoveTiming {
                cruise,
                ta,
                duration: trapezoid(cruise, ta),
                overlap_next: 0.0,
            };
            let vmax = 1.0 / cruise.max(ta);
            assert_eq!(m.profile(m.duration), (1.0, 0.0));
            assert!((m.profile(m.duration * (1.0 - 1e-12)).0 - 1.0).abs() < 1e-9);
            let h = 1e-6;
            let mut prev = m.profile(0.0);
            let n = 2000;
            for k in 1..n {
                let t = m.duration * k as f64 / n as f64;
                let (s, v) = m.profile(t);
                assert!(
                    v <= vmax * (1.0 + 1e-12) && v >= 0.0,
                    "{cruise} {ta} {t}: {v}"
                );
                let fd = (m.profile(t + h).0 - m.profile(t - h).0) / (2.0 * h);
                assert!(
                    (fd - v).abs() < 1e-5 * vmax.max(1.0),
                    "{cruise} {ta} {t}: {fd} vs {v}"
                );
                assert!(s >= prev.0 && (s - prev.0) <= vmax * m.duration / n as f64 * 1.0001);
                prev = (s, v);
            }
        }
    }
}

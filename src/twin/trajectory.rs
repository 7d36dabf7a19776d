//! Timing of a parsed program: in = the program's steps; out = the joint trajectory q(t) the
//! virtual controller follows and the recording window.
//!
//! - Each move is a synchronous joint-space line with a cycloidal speed profile
//!   s(u) = u − sin(2πu)/2π (smooth acceleration, zero speed at both ends; peak speed twice the
//!   mean). Its duration is the commanded one, read the dialect's way ([`crate::dialect::Timing`]: G93 60/F s,
//!   RAPID `\T`, URScript `t`, a speed percentage of the axes, G0: the slowest axis at its
//!   maximum speed), stretched where needed so the peak speed stays within every joint's limit
//!   (the controller is velocity-limited).
//! - Blends (G64 P mm): the next move starts while the previous one still runs — the
//!   controller superposes the two (overlapping blend). The overlap is the time in which the
//!   MAP is within the blend distance of the corner (straight-line MAP distance along the move),
//!   at most half of either move. The superposed trajectory stays smooth (C²).
//! - G4 dwells stand still; an M0 pause ends any blend. The bar is mounted at the first M0,
//!   removed at the second, mounted again at the third (programs in sections), and so on: the
//!   recording windows are the intervals with the bar in place (the whole program when it has
//!   no M0).

use super::SimError;
use crate::dialect::{Parsed, Step};
use crate::model::MeasurementModel;
use crate::robot::Robot;
use std::f64::consts::TAU;

#[derive(Clone, Debug)]
struct Seg {
    t0: f64,
    dur: f64,
    delta: [f64; 6],
}

#[derive(Clone, Debug)]
pub struct Trajectory {
    start: [f64; 6],
    segs: Vec<Seg>,
    /// Sum of the deltas of segments 0..k (k = index), so `prefix[k]` = start + done moves.
    prefix: Vec<[f64; 6]>,
    /// End times of the segments (non-decreasing).
    ends: Vec<f64>,
    /// Recording windows [start, end] (s, program time): the intervals with the bar in place.
    pub windows: Vec<(f64, f64)>,
    /// Program times of the pauses (M0), in order; a pause takes no program time.
    pub pauses: Vec<f64>,
    /// The dwells (G4 and its kin), in order: where the robot stands still for a set time.
    pub dwells: Vec<Dwell>,
}

/// A dwell of the program: program times [from, to], the pose it stands at (rad), and the
/// program line.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dwell {
    pub from: f64,
    pub to: f64,
    pub q: [f64; 6],
    pub line: usize,
}

fn profile(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u - (TAU * u).sin() / TAU
}

fn profile_rate(u: f64) -> f64 {
    if !(0.0..=1.0).contains(&u) {
        return 0.0;
    }
    1.0 - (TAU * u).cos()
}

impl Trajectory {
    pub fn from_program(
        robot: &Robot,
        model: &MeasurementModel,
        program: &Parsed,
    ) -> Result<Trajectory, SimError> {
        let vmax = robot.max_speeds();
        let mut start: Option<[f64; 6]> = None;
        let mut cur = [0.0; 6];
        let mut cur_axes = [0.0; 6];
        let mut segs: Vec<Seg> = Vec::new();
        let mut t_end = 0.0f64;
        // Blend distance (m) of the corner at the end of the last segment, if it may blend.
        let mut pending_blend: Option<f64> = None;
        let mut pauses: Vec<f64> = Vec::new();
        let mut dwells: Vec<Dwell> = Vec::new();
        for l in &program.lines {
            match &l.step {
                step @ Step::Move {
                    target,
                    axes,
                    blend,
                    ..
                } => {
                    let target: [f64; 6] = target.map(f64::to_radians);
                    let Some(_) = start else {
                        start = Some(target);
                        cur = target;
                        cur_axes = *axes;
                        continue;
                    };
                    let delta: [f64; 6] = std::array::from_fn(|i| target[i] - cur[i]);
                    // Eq. 7: the slowest axis at its maximum speed.
                    let eq7 = (0..6).map(|i| delta[i].abs() / vmax[i]).fold(0.0, f64::max);
                    if eq7 == 0.0 {
                        continue;
                    }
                    // A move whose speed is left to the controller runs at the axes' maximum.
                    let commanded = program.duration(&cur_axes, step, &vmax).unwrap_or(eq7);
                    if !(commanded.is_finite() && commanded > 0.0) {
                        return Err(SimError::Program {
                            line: l.line,
                            msg: "move without a usable feed".into(),
                        });
                    }
                    // Cycloidal profile: peak speed = 2 × mean.
                    let dur = commanded.max(2.0 * eq7);
                    let mut t0 = t_end;
                    if let (Some(b), Some(prev)) = (pending_blend, segs.last()) {
                        let w_prev = blend_time(model, prev, &cur, b, true);
                        let seg = Seg {
                            t0: 0.0,
                            dur,
                            delta,
                        };
                        let w_next = blend_time(model, &seg, &cur, b, false);
                        t0 -= w_prev.min(w_next).min(0.5 * prev.dur).min(0.5 * dur);
                    }
                    segs.push(Seg { t0, dur, delta });
                    t_end = t_end.max(t0 + dur);
                    cur = target;
                    cur_axes = *axes;
                    pending_blend = blend.filter(|b| *b > 0.0).map(|b| b * 1e-3);
                }
                Step::Dwell(s) => {
                    let from = t_end;
                    t_end += s.max(0.0);
                    pending_blend = None;
                    if start.is_some() {
                        dwells.push(Dwell {
                            from,
                            to: t_end,
                            q: cur,
                            line: l.line,
                        });
                    }
                }
                Step::Pause => {
                    pauses.push(t_end);
                    pending_blend = None;
                }
                Step::End => break,
            }
        }
        let start = start.ok_or_else(|| SimError::Empty("the program has no moves".into()))?;
        let mut prefix = Vec::with_capacity(segs.len() + 1);
        let mut acc = start;
        prefix.push(acc);
        for s in &segs {
            for i in 0..6 {
                acc[i] += s.delta[i];
            }
            prefix.push(acc);
        }
        // Segments end in order (overlaps are at most half a move).
        let mut ends: Vec<f64> = segs.iter().map(|s| s.t0 + s.dur).collect();
        for k in 1..ends.len() {
            ends[k] = ends[k].max(ends[k - 1]);
        }
        // The bar goes in at the first M0, out at the next, in again at the third (a program in
        // sections), and so on; without any M0 it is in place for the whole program.
        let windows: Vec<(f64, f64)> = if pauses.is_empty() {
            vec![(0.0, t_end)]
        } else {
            pauses
                .chunks(2)
                .map(|p| (p[0], p.get(1).copied().unwrap_or(t_end)))
                .filter(|(a, b)| b > a)
                .collect()
        };
        Ok(Trajectory {
            start,
            segs,
            prefix,
            ends,
            windows,
            pauses,
            dwells,
        })
    }

    /// Setpoint at program time t (rad).
    pub fn position(&self, t: f64) -> [f64; 6] {
        let done = self.ends.partition_point(|&e| e <= t);
        let mut q = self.prefix[done];
        for s in self.segs[done..].iter().take_while(|s| s.t0 < t) {
            let f = profile((t - s.t0) / s.dur);
            for i in 0..6 {
                q[i] += s.delta[i] * f;
            }
        }
        q
    }

    /// Joint speeds at program time t (rad/s).
    pub fn velocity(&self, t: f64) -> [f64; 6] {
        let done = self.ends.partition_point(|&e| e <= t);
        let mut v = [0.0; 6];
        for s in self.segs[done..].iter().take_while(|s| s.t0 < t) {
            let f = profile_rate((t - s.t0) / s.dur) / s.dur;
            for i in 0..6 {
                v[i] += s.delta[i] * f;
            }
        }
        v
    }

    /// Direction (±1) of joint j's first motion after time t (+1 if it never moves).
    pub fn first_direction(&self, j: usize, t: f64) -> f64 {
        self.segs
            .iter()
            .filter(|s| s.t0 + s.dur > t && s.delta[j] != 0.0)
            .map(|s| s.delta[j].signum())
            .next()
            .unwrap_or(1.0)
    }

    /// The start configuration (rad).
    pub fn start(&self) -> [f64; 6] {
        self.start
    }

    /// The program's end (s): the last move or dwell.
    pub fn end(&self) -> f64 {
        let moves = self.ends.last().copied().unwrap_or(0.0);
        let dwells = self.dwells.last().map_or(0.0, |d| d.to);
        let pauses = self.pauses.last().copied().unwrap_or(0.0);
        moves.max(dwells).max(pauses)
    }

    /// The recording window (index into `windows`) that holds program time t, if any.
    pub fn window_at(&self, t: f64) -> Option<usize> {
        self.windows
            .iter()
            .position(|&(a, b)| t >= a - 1e-9 && t <= b + 1e-9)
    }
}

/// Time before the end (`at_end`) or after the start of `seg` during which the MAP is within
/// `blend` metres of that end, along the straight MAP chord of the move.
fn blend_time(
    model: &MeasurementModel,
    seg: &Seg,
    corner: &[f64; 6],
    blend: f64,
    at_end: bool,
) -> f64 {
    let other: [f64; 6] = std::array::from_fn(|i| {
        if at_end {
            corner[i] - seg.delta[i]
        } else {
            corner[i] + seg.delta[i]
        }
    });
    let d = (model.map_position(&model.nominal, corner)
        - model.map_position(&model.nominal, &other))
    .norm();
    if d <= blend {
        return 0.5 * seg.dur;
    }
    // Profile fraction f = blend / d reached at u: profile is symmetric, so the time from
    // the near end equals the time from the start to reach fraction f.
    let f = blend / d;
    let (mut lo, mut hi) = (0.0, 0.5);
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if profile(mid) < f {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi) * seg.dur
}

//! Timing of a parsed program: in = the program's steps and how its dialect times them
//! ([`crate::dialect::ProgramTiming`]); out = the joint trajectory q(t) the virtual controller
//! follows and the recording window.
//!
//! - The moves are timed by the model the program states its times with
//!   ([`crate::timing::moves`], as the compiler's header and `verify` time them): each move a
//!   synchronous joint-space line on the trapezoid's phases (ramps as long as the trapezoid's
//!   at the joints' accelerations, scaled by the dialect's blend acceleration on moves that
//!   blend; a cruise at the commanded speed, read the dialect's way
//!   ([`crate::dialect::Timing`]: G93 60/F s, RAPID `\T` and URScript `t` whole-move times, a
//!   speed percentage of the axes, G0: the slowest axis at its maximum speed), never faster
//!   than the slowest axis at its maximum: the controller is velocity-limited). The moves take
//!   exactly the stated times. Each ramp is a cycloidal speed ramp
//!   ([`crate::timing::MoveTiming::profile`]): the trapezoid's distance and time, the speed
//!   within the cruise's, the acceleration continuous (a finite jerk, as industrial
//!   controllers ramp) with its mean at the joint's acceleration and its peak twice that — a
//!   straight trapezoid would meet the acceleration limit exactly, but its acceleration steps
//!   and a robot at an exact stop then turns on a parabola, which no jerk-limited arm does.
//! - Blends: the next move starts while the previous one still runs, the two superposed
//!   (LinuxCNC's parabolic blend), overlapping by [`crate::timing::overlap`]. A corner blends
//!   when the program writes a blend there, the next line is a move and the bar is in place on
//!   both moves (as `verify` counts it).
//! - G4 dwells stand still; an M0 pause ends any blend. The bar is mounted at the first M0,
//!   removed at the second, mounted again at the third (programs in sections), and so on: the
//!   recording windows are the intervals with the bar in place (the whole program when it has
//!   no M0).

use super::SimError;
use crate::dialect::{MoveTime, Parsed, Step, Timing};
use crate::model::MeasurementModel;
use crate::robot::Robot;
use crate::timing::{self, Limits, MoveTiming};

#[derive(Clone, Debug)]
struct Seg {
    t0: f64,
    timing: MoveTiming,
    delta: [f64; 6],
}

impl Seg {
    fn end(&self) -> f64 {
        self.t0 + self.timing.duration
    }
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

/// A program step as the timeline needs it.
enum Event {
    /// Index into the moves (0: the approach's target, where the program starts).
    Move(usize),
    Dwell(f64, usize),
    Pause,
}

impl Trajectory {
    /// The program's trajectory on the robot's joint speeds and accelerations and the timing
    /// of the dialect the program was read in (`program.timing`). `_model` is not used: the
    /// blends overlap by the timing model, not by a MAP distance (kept for the callers).
    pub fn from_program(
        robot: &Robot,
        _model: &MeasurementModel,
        program: &Parsed,
    ) -> Result<Trajectory, SimError> {
        let lim = Limits::of(robot);
        // The moves: targets (rad), cruise times, a blend written at the end, the bar in place.
        let mut poses: Vec<[f64; 6]> = Vec::new();
        let mut cruise: Vec<f64> = Vec::new();
        let mut blend_written: Vec<bool> = Vec::new();
        let mut mounted_at: Vec<bool> = Vec::new();
        let mut flows_on: Vec<bool> = Vec::new();
        let mut events: Vec<Event> = Vec::new();
        let any_pause = program.lines.iter().any(|l| matches!(l.step, Step::Pause));
        let mut mounted = !any_pause;
        let mut cur_axes = [0.0; 6];
        for (k, l) in program.lines.iter().enumerate() {
            match &l.step {
                Step::Move {
                    target,
                    axes,
                    blend,
                    timing: word,
                    ..
                } => {
                    let target: [f64; 6] = target.map(f64::to_radians);
                    let c = match poses.last() {
                        None => 0.0,
                        Some(cur) => {
                            move_cruise(program, &lim, l, word, (cur, &cur_axes), &target)?
                        }
                    };
                    events.push(Event::Move(poses.len()));
                    poses.push(target);
                    cruise.push(c);
                    blend_written.push(blend.is_some());
                    mounted_at.push(mounted);
                    flows_on.push(matches!(
                        program.lines.get(k + 1).map(|n| &n.step),
                        Some(Step::Move { .. })
                    ));
                    cur_axes = *axes;
                }
                Step::Dwell(s) => events.push(Event::Dwell(*s, l.line)),
                Step::Pause => {
                    mounted = !mounted;
                    events.push(Event::Pause);
                }
                Step::End => break,
            }
        }
        let Some(&start) = poses.first() else {
            return Err(SimError::Empty("the program has no moves".into()));
        };
        // The corners that blend, as `verify` counts them.
        let blended = blended_corners(&blend_written, &mounted_at, &flows_on);
        let timings = timing::moves(
            &poses,
            &cruise,
            &blended,
            &lim,
            program.timing.blend_acceleration,
        );
        let (segs, t_end, pauses, dwells) = place_events(&events, &poses, &blended, &timings);
        let mut prefix = Vec::with_capacity(segs.len() + 1);
        let mut acc = start;
        prefix.push(acc);
        for s in &segs {
            for i in 0..6 {
                acc[i] += s.delta[i];
            }
            prefix.push(acc);
        }
        // Segments end in order (a blend overlaps at most the next move's cruise).
        let mut ends: Vec<f64> = segs.iter().map(Seg::end).collect();
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
            let (f, _) = s.timing.profile(t - s.t0);
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
            let (_, f) = s.timing.profile(t - s.t0);
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
            .filter(|s| s.end() > t && s.delta[j] != 0.0)
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
/// A move's cruise time (s) from `cur` (the controller axes `cur_axes`) to `target` (rad), as
/// the controller runs it: the commanded time, never above an axis's maximum speed.
fn move_cruise(
    program: &Parsed,
    lim: &Limits,
    l: &crate::dialect::Line,
    word: &Timing,
    (cur, cur_axes): (&[f64; 6], &[f64; 6]),
    target: &[f64; 6],
) -> Result<f64, SimError> {
    let vmax = lim.speed;
    let step = &l.step;
    let eq7 = timing::eq7(cur, target, &vmax);
    // A move whose speed is left to the controller runs at the axes' maximum; a standstill
    // takes no time.
    let commanded = program.duration(cur_axes, step, &vmax).unwrap_or(eq7);
    if eq7 > 0.0 && !(commanded.is_finite() && commanded > 0.0) {
        return Err(SimError::Program {
            line: l.line,
            msg: "move without a usable feed".into(),
        });
    }
    // A whole-move time word (RAPID `\T`, URScript `t`) states the ramps too: its cruise is
    // what leaves them room (as `verify`).
    let c = match (program.timing.move_time, word) {
        (MoveTime::Total, Timing::Duration(_)) => {
            timing::cruise_of(commanded, timing::accel_time(cur, target, &lim.accel))
        }
        _ => commanded,
    };
    // The controller never runs an axis above its maximum speed.
    Ok(if eq7 > 0.0 { c.max(eq7) } else { 0.0 })
}

/// The corners that blend: a blend written, into a move that follows directly, the bar in
/// place on both.
fn blended_corners(blend_written: &[bool], mounted_at: &[bool], flows_on: &[bool]) -> Vec<bool> {
    let n = blend_written.len();
    (0..n)
        .map(|j| {
            blend_written[j]
                && mounted_at[j]
                && flows_on[j]
                && j > 0
                && j + 1 < n
                && mounted_at[j + 1]
        })
        .collect()
}

/// The moves and dwells on the program's clock: the segments, the end time, the pauses and
/// the dwells (those after the first move).
fn place_events(
    events: &[Event],
    poses: &[[f64; 6]],
    blended: &[bool],
    timings: &[MoveTiming],
) -> (Vec<Seg>, f64, Vec<f64>, Vec<Dwell>) {
    let n = poses.len();
    let start = poses[0];
    let mut segs: Vec<Seg> = Vec::with_capacity(n);
    let mut t_end = 0.0f64;
    let mut pauses: Vec<f64> = Vec::new();
    let mut dwells: Vec<Dwell> = Vec::new();
    // The program's time starts at the first move (the approach's target).
    let mut started = false;
    let mut last_q = start;
    for e in events {
        match *e {
            Event::Move(0) => started = true,
            Event::Move(k) => {
                let overlap = if blended[k - 1] {
                    timings[k - 1].overlap_next
                } else {
                    0.0
                };
                let seg = Seg {
                    t0: t_end - overlap,
                    timing: timings[k],
                    delta: std::array::from_fn(|i| poses[k][i] - poses[k - 1][i]),
                };
                t_end = t_end.max(seg.end());
                segs.push(seg);
                last_q = poses[k];
            }
            Event::Dwell(s, line) => {
                let from = t_end;
                t_end += s.max(0.0);
                if started {
                    dwells.push(Dwell {
                        from,
                        to: t_end,
                        q: last_q,
                        line,
                    });
                }
            }
            Event::Pause => pauses.push(t_end),
        }
    }
    (segs, t_end, pauses, dwells)
}

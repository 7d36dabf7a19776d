//! The logs a real cell leaves: in = a program's trajectory, the true robot and
//! [`LogOptions`] (the clocks, the operator, the log's flaws); out = the bar's own log and the
//! controller's joint log, each on its own clock, the synchronous recording of the same bar
//! samples (the reference a perfectly synchronised system would give), and the truth the
//! tests check a match against.
//!
//! Time. The controller's clock t_c is the program's time with every pause lasting what the
//! operator takes (`pause`, uniform) and every controller stop (`holds`: the robot halts in a
//! move made with the bar) its length. The bar's clock is t_bar = offset + (1 + drift)·t_c;
//! it samples at its own rate from `lead` seconds before the program to `tail` after it. The
//! joint log samples the controller's clock at its rate.
//!
//! The bar. Mounted at a random moment of each mount pause, removed at a random moment of each
//! removal pause; while mounted it reads the true ball-centre distance plus `zero` (a bar whose
//! zero is not the ball-centre distance), noise and resolution ([`super::Sampler`]). While
//! unmounted (`handling`) it reads what a bar in someone's hands reads: moved between random
//! lengths, lying still on the bench for a few seconds (plateaus that belong to no pose), or
//! out of range (no samples). Flaws: `gaps` random stretches without samples, `dropout`
//! single samples lost, the plateaus of the `missing` poses lost (a gap over the whole
//! standstill), a decaying 15 Hz vibration on the plateaus of the `vibration` poses.

use super::{SimError, Trajectory, Truth};
use crate::logs::{BarLog, JointLog};
use crate::model::MeasurementModel;
use crate::robot::Robot;
use crate::twin::Measured;
use rand::{Rng, SeedableRng};

/// How the logs are recorded (SI; documented defaults in [`Default`]).
#[derive(Clone, Debug, PartialEq)]
pub struct LogOptions {
    /// Sample rates of the bar and of the joint log (Hz).
    pub bar_rate: f64,
    pub joint_rate: f64,
    /// t_bar = offset + (1 + drift)·t_c (s, dimensionless).
    pub offset: f64,
    pub drift: f64,
    /// The operator's pause lengths (s): uniform in [min, max].
    pub pause: (f64, f64),
    /// Logging starts this long before the program (its first move) and ends this long after
    /// it (s).
    pub lead: f64,
    pub tail: f64,
    /// The bar's reading minus the ball-centre distance (m).
    pub zero: f64,
    /// Random gaps in the bar log, and their lengths (s).
    pub gaps: usize,
    pub gap_len: (f64, f64),
    /// Probability that a bar sample is lost.
    pub dropout: f64,
    /// Poses (1-based, in dwell order) whose plateau the bar log loses.
    pub missing: Vec<usize>,
    /// The controller's moves take this many times their program time (its acceleration ramps,
    /// a speed override); dwells and pauses are exact.
    pub move_scale: f64,
    /// Controller stops in moves made with the bar, and their lengths (s).
    pub holds: usize,
    pub hold_len: (f64, f64),
    /// Poses (1-based) whose plateau a vibration disturbs, and its amplitude (m).
    pub vibration: Vec<usize>,
    pub vibration_amp: f64,
    /// Readings while the bar is unmounted (handled, on the bench); otherwise none.
    pub handling: bool,
    /// The lengths a handled bar takes (m).
    pub bar_range: (f64, f64),
    pub seed: u64,
}

impl Default for LogOptions {
    fn default() -> Self {
        LogOptions {
            bar_rate: 50.0,
            joint_rate: 100.0,
            offset: 0.0,
            drift: 0.0,
            pause: (5.0, 20.0),
            lead: 3.0,
            tail: 3.0,
            zero: 0.0,
            gaps: 0,
            gap_len: (0.5, 3.0),
            dropout: 0.0,
            missing: Vec::new(),
            move_scale: 1.0,
            holds: 0,
            hold_len: (0.5, 3.0),
            vibration: Vec::new(),
            vibration_amp: 10e-6,
            handling: true,
            bar_range: (0.300, 0.520),
            seed: 1,
        }
    }
}

/// The simulated logs and their truth.
#[derive(Clone, Debug)]
pub struct Logs {
    pub bar: BarLog,
    /// The controller's joint log (model joints, rad; the CLI writes the controller's axes).
    pub joints: JointLog,
    /// The bar's mounted samples with the joints the controller logged at their instants:
    /// what a synchronous recording would hold (t from the bar log's first sample).
    pub synchronous: Measured,
    pub truth: LogTruth,
}

/// What the simulation knows and a matcher must find.
#[derive(Clone, Debug, PartialEq)]
pub struct LogTruth {
    /// Per measurement dwell of the program (the bar mounted), in order: the standstill with
    /// the bar mounted, on the bar clock.
    pub standstills: Vec<(f64, f64)>,
    /// Whether the log holds that standstill whole (no `missing`, no gap over any of it).
    pub intact: Vec<bool>,
    /// The controller's stops (bar clock).
    pub holds: Vec<(f64, f64)>,
    /// The bar's mount intervals (bar clock).
    pub mounted: Vec<(f64, f64)>,
}

/// A stop of the robot on the controller's clock: at program time `at`, for `len` seconds.
#[derive(Clone, Copy, Debug)]
struct Stop {
    at: f64,
    len: f64,
}

/// Program time ↔ controller time: the stops inserted, the moves taking `scale` times their
/// program time (a controller's acceleration ramps or speed override), the dwells exact.
/// Knots (program, real), both non-decreasing; a stop is two knots at one program time.
struct Clock {
    knots: Vec<(f64, f64)>,
}

impl Clock {
    fn new(stops: &[Stop], dwells: &[(f64, f64)], end: f64, scale: f64) -> Clock {
        let mut cuts: Vec<f64> = vec![0.0, end];
        cuts.extend(stops.iter().map(|s| s.at));
        for d in dwells {
            cuts.push(d.0);
            cuts.push(d.1);
        }
        cuts.sort_by(f64::total_cmp);
        cuts.dedup();
        let in_dwell = |a: f64, b: f64| {
            let m = 0.5 * (a + b);
            dwells.iter().any(|d| m > d.0 && m < d.1)
        };
        let mut knots = vec![(cuts[0], cuts[0])];
        for w in cuts.windows(2) {
            let (a, b) = (w[0], w[1]);
            for s in stops.iter().filter(|s| s.at == a) {
                let r = knots.last().map_or(0.0, |k| k.1);
                knots.push((a, r + s.len));
            }
            let r = knots.last().map_or(0.0, |k| k.1);
            let slope = if in_dwell(a, b) { 1.0 } else { scale };
            knots.push((b, r + slope * (b - a)));
        }
        let last = *cuts.last().unwrap_or(&0.0);
        for s in stops.iter().filter(|s| s.at == last) {
            let r = knots.last().map_or(0.0, |k| k.1);
            knots.push((last, r + s.len));
        }
        Clock { knots }
    }

    /// Controller time at which program time `tp` is reached (before a stop at `tp`).
    fn real(&self, tp: f64) -> f64 {
        let k = &self.knots;
        if tp <= k[0].0 {
            return k[0].1 - (k[0].0 - tp);
        }
        for w in k.windows(2) {
            if tp <= w[1].0 && w[1].0 > w[0].0 {
                return w[0].1 + (tp - w[0].0) / (w[1].0 - w[0].0) * (w[1].1 - w[0].1);
            }
        }
        let l = k[k.len() - 1];
        l.1 + (tp - l.0)
    }

    /// Controller time at which program time `tp` is left (after a stop at `tp`).
    fn real_after(&self, tp: f64) -> f64 {
        let stand: f64 = self
            .knots
            .windows(2)
            .filter(|w| w[0].0 == tp && w[1].0 == tp)
            .map(|w| w[1].1 - w[0].1)
            .sum();
        self.real(tp) + stand
    }

    /// Program time at controller time `tc` (standing during a stop).
    fn program(&self, tc: f64) -> f64 {
        let k = &self.knots;
        if tc <= k[0].1 {
            return k[0].0 - (k[0].1 - tc);
        }
        for w in k.windows(2) {
            if tc <= w[1].1 {
                if w[1].0 == w[0].0 || w[1].1 == w[0].1 {
                    return w[0].0;
                }
                return w[0].0 + (tc - w[0].1) / (w[1].1 - w[0].1) * (w[1].0 - w[0].0);
            }
        }
        let l = k[k.len() - 1];
        l.0 + (tc - l.1)
    }
}

fn uniform(rng: &mut impl Rng, (a, b): (f64, f64)) -> f64 {
    if b > a {
        rng.random_range(a..b)
    } else {
        a
    }
}

/// Runs the program's trajectory as a real cell would log it.
pub fn simulate_logs(
    robot: &Robot,
    model: &MeasurementModel,
    traj: &Trajectory,
    truth: &Truth,
    opts: &LogOptions,
) -> Result<Logs, SimError> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed ^ 0x6c6f_6773);
    let end = traj.end();
    // Pauses: their lengths and the moment the operator mounts or removes the bar; controller
    // stops inside moves made with the bar.
    let (stops, toggles, holds_at) = pauses_and_holds(&mut rng, traj, opts);
    let dwell_spans: Vec<(f64, f64)> = traj.dwells.iter().map(|d| (d.from, d.to)).collect();
    let clock = Clock::new(&stops, &dwell_spans, end, opts.move_scale);
    // Real-time start of each original stop.
    let stop_start = |k: usize| clock.real(stops[k].at);
    let mounted_real = mount_intervals(&stops, &toggles, stop_start);
    let real_end = clock.real_after(end);
    let a = 1.0 + opts.drift;
    let to_bar = |tc: f64| opts.offset + a * tc;
    let standstill = standstills(traj, &clock, &mounted_real);
    // Bar log gaps: random ones, and the missing poses' standstills (a little wider).
    let t_first = -opts.lead;
    let t_last = real_end + opts.tail;
    let mut gaps: Vec<(f64, f64)> = Vec::new();
    for _ in 0..opts.gaps {
        let len = uniform(&mut rng, opts.gap_len);
        let at = rng.random_range(t_first..t_last);
        gaps.push((at, at + len));
    }
    for &k in &opts.missing {
        if let Some(&(x, y)) = standstill.get(k.wrapping_sub(1)) {
            gaps.push((x - 0.1, y + 0.1));
        }
    }
    let intact: Vec<bool> = standstill
        .iter()
        .map(|&(x, y)| !gaps.iter().any(|&(a, b)| a < y && b > x))
        .collect();
    // Handling while unmounted: segments (kind, from, to, length at from, length at to).
    let junk = if opts.handling {
        handling(&mut rng, t_first, t_last, opts.bar_range)
    } else {
        Vec::new()
    };
    let vib: Vec<(f64, f64)> = opts
        .vibration
        .iter()
        .filter_map(|&k| standstill.get(k.wrapping_sub(1)).copied())
        .collect();
    let mut sampler = super::Sampler::new(robot, model, traj, truth, 0.0, opts.seed);
    let temp_log = truth.thermal.as_ref().is_some_and(|th| th.temp_log);
    let scene = BarScene {
        clock: &clock,
        mounted: &mounted_real,
        gaps: &gaps,
        junk: &junk,
        vib: &vib,
    };
    let (bar, sync) = sample_bar(
        &scene,
        &mut sampler,
        &mut rng,
        opts,
        (t_first, t_last),
        temp_log,
    );
    // The controller's joint log.
    let nj = ((t_last - t_first) * opts.joint_rate).floor() as usize + 1;
    let mut joints = JointLog::default();
    for k in 0..nj {
        let tc = t_first + k as f64 / opts.joint_rate;
        joints.t.push(tc);
        joints.q.push(traj.position(clock.program(tc)));
    }
    if sync.len() < 3 {
        return Err(SimError::Empty(
            "the bar is never mounted while the program runs: nothing to log".into(),
        ));
    }
    Ok(Logs {
        bar,
        joints,
        synchronous: sync,
        truth: LogTruth {
            standstills: standstill
                .iter()
                .map(|&(x, y)| (to_bar(x), to_bar(y)))
                .collect(),
            intact,
            holds: holds_at
                .iter()
                .map(|&k| {
                    let s = stop_start(k);
                    (to_bar(s), to_bar(s + stops[k].len))
                })
                .collect(),
            mounted: mounted_real
                .iter()
                .map(|&(x, y)| (to_bar(x.max(t_first)), to_bar(y.min(t_last))))
                .collect(),
        },
    })
}

/// The operator's pauses (with the moment in each, a fraction, at which the bar is mounted or
/// removed) and the controller's stops inside moves made with the bar (never in a dwell): the
/// stops, the (stop, fraction) toggles and the stops that are holds.
fn pauses_and_holds(
    rng: &mut impl Rng,
    traj: &Trajectory,
    opts: &LogOptions,
) -> (Vec<Stop>, Vec<(usize, f64)>, Vec<usize>) {
    let mut stops: Vec<Stop> = Vec::new();
    let mut toggles: Vec<(usize, f64)> = Vec::new(); // (stop index, fraction)
    for &p in &traj.pauses {
        stops.push(Stop {
            at: p,
            len: uniform(rng, opts.pause),
        });
        toggles.push((stops.len() - 1, rng.random_range(0.3..0.8)));
    }
    // Controller stops inside moves made with the bar (never in a dwell).
    let mut holds_at: Vec<usize> = Vec::new();
    let mounted_prog: Vec<(f64, f64)> = traj.windows.clone();
    for _ in 0..opts.holds {
        for _try in 0..1000 {
            let w = mounted_prog[rng
                .random_range(0..mounted_prog.len().max(1))
                .min(mounted_prog.len().saturating_sub(1))];
            if w.1 - w.0 < 1.0 {
                continue;
            }
            let at = rng.random_range(w.0 + 0.2..w.1 - 0.2);
            let moving = traj
                .velocity(at)
                .iter()
                .map(|v| v.abs())
                .fold(0.0, f64::max)
                > 0.05;
            let near_dwell = traj
                .dwells
                .iter()
                .any(|d| at > d.from - 0.1 && at < d.to + 0.1);
            let near_stop = stops.iter().any(|s| (s.at - at).abs() < 0.5);
            if moving && !near_dwell && !near_stop {
                stops.push(Stop {
                    at,
                    len: uniform(rng, opts.hold_len),
                });
                holds_at.push(stops.len() - 1);
                break;
            }
        }
    }
    (stops, toggles, holds_at)
}

/// Mount intervals (controller clock): from each mounting toggle to the removal after it.
fn mount_intervals(
    stops: &[Stop],
    toggles: &[(usize, f64)],
    stop_start: impl Fn(usize) -> f64,
) -> Vec<(f64, f64)> {
    let mut mounted_real: Vec<(f64, f64)> = Vec::new();
    if toggles.is_empty() {
        mounted_real.push((f64::NEG_INFINITY, f64::INFINITY));
    } else {
        for pair in toggles.chunks(2) {
            let (k, f) = pair[0];
            let on = stop_start(k) + f * stops[k].len;
            let off = pair
                .get(1)
                .map_or(f64::INFINITY, |&(k, f)| stop_start(k) + f * stops[k].len);
            mounted_real.push((on, off));
        }
    }
    mounted_real
}

/// The measurement dwells' standstills with the bar on (controller clock).
fn standstills(traj: &Trajectory, clock: &Clock, mounted_real: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let measuring = measurement_dwells(traj).poses;
    measuring
        .iter()
        .map(|d| {
            // From the arrival (before a pause that precedes the dwell) to the departure
            // (after a pause that follows it), cut to the time the bar is mounted.
            let arrive = clock.real(d.from);
            let leave = clock.real_after(d.to);
            let w = mounted_real
                .iter()
                .find(|&&(m0, m1)| m1 > arrive && m0 < leave)
                .copied()
                .unwrap_or((arrive, leave));
            (arrive.max(w.0), leave.min(w.1))
        })
        .collect()
}

/// What the bar log is made of, on the controller's clock: when the bar is mounted, where its
/// log has gaps, what it reads in someone's hands and where it vibrates.
struct BarScene<'a> {
    clock: &'a Clock,
    mounted: &'a [(f64, f64)],
    gaps: &'a [(f64, f64)],
    junk: &'a [Segment],
    vib: &'a [(f64, f64)],
}

/// The bar's samples on its own clock over [t_first, t_last] (controller clock), and the
/// synchronous recording of the same samples, its time counted from the bar log's first.
fn sample_bar(
    scene: &BarScene,
    sampler: &mut super::Sampler<'_>,
    rng: &mut impl Rng,
    opts: &LogOptions,
    (t_first, t_last): (f64, f64),
    temp_log: bool,
) -> (BarLog, Measured) {
    let BarScene {
        clock,
        mounted,
        gaps,
        junk,
        vib,
    } = scene;
    let is_mounted = |tc: f64| mounted.iter().any(|&(a, b)| tc >= a && tc < b);
    let a = 1.0 + opts.drift;
    let to_bar = |tc: f64| opts.offset + a * tc;
    let u_first = to_bar(t_first);
    let n = ((to_bar(t_last) - u_first) * opts.bar_rate).floor() as usize + 1;
    let mut bar = BarLog {
        temp: temp_log.then(Vec::new),
        ..BarLog::default()
    };
    let mut sync = Measured {
        temp: temp_log.then(Vec::new),
        ..Measured::default()
    };
    for k in 0..n {
        let u = u_first + k as f64 / opts.bar_rate;
        let tc = (u - opts.offset) / a;
        if gaps.iter().any(|&(x, y)| tc >= x && tc < y) {
            continue;
        }
        let drop = opts.dropout > 0.0 && rng.random::<f64>() < opts.dropout;
        let reading = if is_mounted(tc) {
            let tp = clock.program(tc);
            let (q, l) = sampler.sample(tp, tc.max(0.0));
            let mut l = l + opts.zero;
            for &(x, y) in vib.iter() {
                if tc >= x + 0.3 && tc <= y {
                    let s = tc - x - 0.3;
                    l += opts.vibration_amp
                        * (-s / 0.6).exp()
                        * (std::f64::consts::TAU * 15.0 * s).sin();
                }
            }
            if !drop {
                sync.t.push(u);
                sync.q.push(q);
                sync.length.push(l);
                if let Some(t) = sync.temp.as_mut() {
                    t.push(sampler.temperature(tc.max(0.0)));
                }
            }
            Some(l)
        } else {
            junk_at(junk, tc).map(|l| l + 1e-6 * super::gauss(rng))
        };
        if let (Some(l), false) = (reading, drop) {
            bar.t.push(u);
            bar.length.push(l);
            if let Some(t) = bar.temp.as_mut() {
                t.push(sampler.temperature(tc.max(0.0)));
            }
        }
    }
    // The synchronous recording's time counts from the bar log's first sample.
    let first = bar.t.first().copied().unwrap_or(u_first);
    for t in sync.t.iter_mut() {
        *t -= first;
    }
    (bar, sync)
}

/// A program's dwells sorted into measurement poses and settling dwells.
#[derive(Clone, Debug, PartialEq)]
pub struct MeasurementDwells {
    /// The measurement poses' standstills, in program order.
    pub poses: Vec<super::Dwell>,
    /// Dwells with the bar in place too short to be a measurement (shorter than
    /// [`SETTLING_SHARE`] of the longest), in program order.
    pub settling: Vec<super::Dwell>,
    /// Dwells with the bar off (before the first pause of a program that has one, or between a
    /// removal and the next mount): never measurements.
    pub off: Vec<super::Dwell>,
}

/// A standstill shorter than this share of the program's longest dwell is a settling dwell,
/// not a measurement: the plateau finder looks for standstills of at least this share of the
/// longest dwell ([`crate::logs::stop_and_measure`]), so a shorter one leaves no plateau to
/// match.
pub const SETTLING_SHARE: f64 = crate::logs::MIN_PLATEAU_SHARE;

/// The measurement poses of a stop-and-measure program: every dwell after the first move with
/// the bar in place (the whole program without an M0, else between a mount pause and the
/// next removal), dwells with no move between them taken as one standstill, except those
/// shorter than [`SETTLING_SHARE`] of the longest (a controller's settling time, not a
/// measurement).
pub fn measurement_dwells(traj: &Trajectory) -> MeasurementDwells {
    let mut stands: Vec<super::Dwell> = Vec::new();
    let mut off = Vec::new();
    for d in &traj.dwells {
        if traj.window_at(0.5 * (d.from + d.to)).is_none() {
            off.push(*d);
            continue;
        }
        match stands.last_mut() {
            // No move between them: the robot stands on at the same pose.
            Some(last) if (d.from - last.to).abs() < 1e-9 && last.q == d.q => last.to = d.to,
            _ => stands.push(*d),
        }
    }
    let longest = stands.iter().map(|d| d.to - d.from).fold(0.0, f64::max);
    let (poses, settling) = stands
        .into_iter()
        .partition(|d| d.to - d.from >= SETTLING_SHARE * longest && d.to > d.from);
    MeasurementDwells {
        poses,
        settling,
        off,
    }
}

/// A stop-and-measure program as a bar log is matched against it: its measurement dwells
/// ([`measurement_dwells`]), in order, with their poses' nominal lengths, sections and program
/// times (the twin's timing of the program: [`Trajectory`]).
pub fn template(traj: &Trajectory, model: &MeasurementModel) -> crate::logs::Template {
    let mut slots = Vec::new();
    let measuring = measurement_dwells(traj).poses;
    for d in &measuring {
        let Some(section) = traj.window_at(0.5 * (d.from + d.to)) else {
            continue;
        };
        let (a, b) = traj.windows[section];
        slots.push(crate::logs::Slot {
            pose: slots.len() + 1,
            length: model.length(&model.nominal, &d.q),
            q: d.q,
            section,
            start: d.from,
            end: d.to,
            after_pause: (d.from - a).abs() < 1e-9
                && traj.pauses.iter().any(|p| (p - a).abs() < 1e-9),
            before_pause: (d.to - b).abs() < 1e-9
                && traj.pauses.iter().any(|p| (p - b).abs() < 1e-9),
        });
    }
    let dwell = measuring.iter().map(|d| d.to - d.from).fold(0.0, f64::max);
    let poses = slots.len();
    crate::logs::Template {
        slots,
        dwell,
        poses,
    }
}

/// A handled bar: (from, to, length at from, length at to, in range) segments over the
/// unmounted stretches of [t0, t1].
type Segment = (f64, f64, f64, f64, bool);

fn handling(rng: &mut impl Rng, t0: f64, t1: f64, range: (f64, f64)) -> Vec<Segment> {
    let mut out = Vec::new();
    let mut t = t0;
    let mut len = uniform(rng, range);
    while t < t1 {
        let kind: f64 = rng.random();
        let dur = uniform(rng, (0.5, 6.0));
        let next = uniform(rng, range);
        if kind < 0.3 {
            // Lying still on the bench.
            out.push((t, t + dur, len, len, true));
        } else if kind < 0.8 {
            out.push((t, t + dur, len, next, true));
            len = next;
        } else {
            out.push((t, t + dur, len, len, false));
        }
        t += dur;
    }
    out
}

fn junk_at(junk: &[Segment], tc: f64) -> Option<f64> {
    let s = junk.iter().find(|s| tc >= s.0 && tc < s.1)?;
    if !s.4 {
        return None;
    }
    let f = (tc - s.0) / (s.1 - s.0);
    Some(s.2 + f * (s.3 - s.2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clock_inserts_stops_scales_moves_and_inverts() {
        let stops = [Stop { at: 1.0, len: 10.0 }, Stop { at: 3.0, len: 2.0 }];
        // A dwell from 2 to 2.5 s of program time; moves take 1.5 times as long.
        let c = Clock::new(&stops, &[(2.0, 2.5)], 4.0, 1.5);
        assert!((c.real(0.5) - 0.75).abs() < 1e-12);
        assert!((c.real(1.0) - 1.5).abs() < 1e-12);
        assert!((c.real_after(1.0) - 11.5).abs() < 1e-12);
        // 1 → 2: a move (1.5 s); 2 → 2.5: the dwell (0.5 s); 2.5 → 3: a move (0.75 s).
        assert!((c.real(2.0) - 13.0).abs() < 1e-12);
        assert!((c.real(2.5) - 13.5).abs() < 1e-12);
        assert!((c.real(3.0) - 14.25).abs() < 1e-12);
        assert!((c.real_after(3.0) - 16.25).abs() < 1e-12);
        assert!((c.real(4.0) - 17.75).abs() < 1e-12);
        for tp in [0.2, 0.9, 1.5, 2.2, 2.9, 3.5, 10.0] {
            assert!((c.program(c.real(tp)) - tp).abs() < 1e-12, "{tp}");
        }
        // Standing during a stop.
        assert_eq!(c.program(5.0), 1.0);
        assert_eq!(c.program(15.0), 3.0);
    }
}

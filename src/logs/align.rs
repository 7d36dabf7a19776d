//! Plateaus to poses: in = a stop-and-measure program's template (its measurement dwells in
//! order: nominal bar length, section, program times) and a bar log's plateaus; out = which
//! plateau is which pose, the bar's zero offset and the clock, or a refusal that names the
//! pose it cannot tell.
//!
//! The match is a sequence alignment (dynamic programming over plateaus × poses, both in time
//! order) scored as log-likelihood ratios: a pose matched to a plateau earns what its length,
//! its duration and its timing say for the match against a plateau of no pose; a pose without
//! a plateau (a gap in the log, the operator) and a plateau without a pose (a stop the
//! controller made, the longer the rarer; the bar handled while unmounted, between sections,
//! cheap) cost their rarity. Time between two matched plateaus is the program's moves between
//! them (and the dwells of poses skipped), with every plateau between them taken out as a
//! stop; a dwell's plateau lasts at least the dwell (a section's first pose dwells after its
//! mount pause and its last stands on into the removal pause: no upper bound there). Two
//! passes:
//!
//! 1. **No zero, no controller timing.** Between consecutive matches only differences count:
//!    the change of the reading against the change of the nominal length (1 mm scatter,
//!    heavy-tailed), the gap against the program's (log-normal, a factor 1.4: controllers
//!    run moves faster or slower than programmed, never dwells). The best alignment (Viterbi).
//! 2. **Zero and timing estimated.** From pass 1's matches: the bar's zero (median of reading
//!    − nominal) and the robot's scatter about it (MAD), the controller's move-time ratio
//!    (median) and the scatter of the gaps about it (MAD, at least a sample and a half). The
//!    reading is then scored against zero + nominal (Student-t, ν = 5, with a 1e-4 chance of
//!    any length), each gap against ratio·moves + dwells (Gaussian, plus a wider Gaussian at
//!    the share of pass 1's gaps beyond 3 sigmas and up to 0.5 s: plateau edges that a smooth
//!    stop or start moves; a delay up to half a dwell at 2 %: a stop too short to leave a
//!    plateau; anything else at 1e-5). The posterior of
//!    every (pose, plateau) pair over all alignments (forward–backward): a pose is matched
//!    when one plateau holds ≥ 99 % of it, missing when "no plateau" does; anything else is a
//!    refusal naming the pose.
//!
//! The clock is then fitted to the matched plateaus' program-timed edges (a dwell's end, and
//! its start where no pause precedes it), the controller's stops taken out: t_bar = o_s +
//! (1 + drift)·t_prog, one offset per section (pauses have unknown lengths), one drift.

use crate::stats::median;
use crate::units::{fmt_fixed, to_mm};

/// One measurement dwell of the program (SI: m, s of program time with pauses as zero).
#[derive(Clone, Debug, PartialEq)]
pub struct Slot {
    /// 1-based pose number (the program's `pose k/N`).
    pub pose: usize,
    /// Nominal bar length at the pose (m).
    pub length: f64,
    /// Joint values of the pose (rad, model joints).
    pub q: [f64; 6],
    /// The mount window (0-based section) it belongs to.
    pub section: usize,
    /// Program times of the dwell.
    pub start: f64,
    pub end: f64,
    /// The first pose of its section (its plateau starts during the mount pause) and the
    /// last (its plateau lasts into the removal pause).
    pub after_pause: bool,
    pub before_pause: bool,
}

impl Slot {
    /// How long the program dwells at the pose (s).
    pub fn dwell(&self) -> f64 {
        self.end - self.start
    }
}

/// A stop-and-measure program as the bar log is matched against it.
#[derive(Clone, Debug, PartialEq)]
pub struct Template {
    pub slots: Vec<Slot>,
    /// The longest dwell (s): what the plateau finder looks for (a slot's own is
    /// [`Slot::dwell`]).
    pub dwell: f64,
    /// Total number of poses the program names (`N` of `pose k/N`).
    pub poses: usize,
}

/// What one plateau is to the alignment (bar clock s; m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observed {
    pub from: f64,
    pub to: f64,
    pub mean: f64,
    /// The plateau's start (end) is at a gap in the log: the standstill may have begun
    /// earlier (lasted longer).
    pub cut_before: bool,
    pub cut_after: bool,
}

/// The clock relation t_bar = offset_s + (1 + drift)·t_prog, per section (pauses unknown).
#[derive(Clone, Debug, PartialEq)]
pub struct Timeline {
    /// Offset of each section (s); None where no pose of the section was matched.
    pub offsets: Vec<Option<f64>>,
    pub offset_std: Vec<Option<f64>>,
    /// Drift (dimensionless; ppm = 1e6 ×) and its standard uncertainty (None when one
    /// section's few edges cannot tell it).
    pub drift: f64,
    pub drift_std: Option<f64>,
    /// RMS of the edges about the timeline (s).
    pub rms: f64,
}

/// The alignment: for each slot, the plateau it is (index into the plateaus) or None.
#[derive(Clone, Debug, PartialEq)]
pub struct Alignment {
    pub matched: Vec<Option<usize>>,
    /// The posterior probability of each slot's verdict (matched to that plateau, or missing).
    pub confidence: Vec<f64>,
    /// The bar's zero: mean of reading − nominal over the matches (m), its standard deviation
    /// over them (robot errors included) and the mean's standard uncertainty.
    pub zero: f64,
    pub zero_spread: f64,
    pub zero_std: f64,
    pub timeline: Timeline,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AlignError {
    /// A pose that neither one plateau nor "missing" explains with confidence.
    #[error("{0}")]
    Ambiguous(String),
    /// Too little matched to be a run of this program.
    #[error("{0}")]
    NoMatch(String),
}

// ---- scoring --------------------------------------------------------------------------------

/// A pose without a plateau, and plateaus without a pose inside a section (a controller's
/// stop, which costs more the longer it lasts) or outside one (the bar handled while unmounted, before the first mount, after the
/// last removal): log prior odds.
const MISS: f64 = -4.0;
/// A pose without a plateau where the log has a gap: expected.
const MISS_IN_GAP: f64 = -0.5;
const EXTRA: f64 = -3.5;
/// Pass 2's timing: the rate of a delay too short to leave a plateau, and of any other odd
/// time between two plateaus.
const SHORT_STOP: f64 = 0.02;
const ODD_TIME: f64 = 1e-5;
/// Pass 2's lengths: the tails of the robot's errors, and the rate of a pose whose nominal
/// length is off by anything.
const LENGTH_NU: f64 = 5.0;
/// Neighbours on either side that set a slot's local zero.
const LOCAL: usize = 3;
/// A plateau next to a pause lasts its dwell and at least about this much of the operator's
/// time (s).
const PAUSE_SHARE: f64 = 0.5;
const ODD_LENGTH: f64 = 1e-4;
/// Pass 2's timing scatter grows by this share of the time predicted (moves vary).
const TIME_RELATIVE: f64 = 0.01;
const JUNK: f64 = -0.3;
/// Consecutive poses a transition may skip, and plateaus inside a section.
const MAX_SKIP_POSES: usize = 12;
const MAX_SKIP_PLATEAUS: usize = 6;
/// Pass 1: the nominal-vs-real length scatter of a robot before calibration (m), and the
/// spread of a move's real time about the program's (log scale).
const PASS1_LENGTH: f64 = 1e-3;
const PASS1_TIME_LOG: f64 = 0.35;
/// Floors of the pass-2 scatters: length (m) and time (s) beyond the sampling.
const LENGTH_FLOOR: f64 = 20e-6;
const TIME_FLOOR: f64 = 0.01;
/// Bounds of the share of gaps whose plateau edges moved, and of their scatter (times the
/// dwell: a plateau's edge cannot move by more than the plateau is long).
const EDGE_SHARE: (f64, f64) = (0.05, 0.4);
const EDGE_MAX: f64 = 0.25;
/// The longest ramp of an industrial robot's stop or start (s): an edge moves by less.
const EDGE_RAMP: f64 = 0.5;
/// A verdict is taken when its posterior reaches this.
pub const SURE: f64 = 0.99;
/// Student-t degrees of freedom of every residual (heavy tails: one odd pose does not break a
/// run).
const NU: f64 = 3.0;

/// The longest plateau a dwell inside a section leaves (s): the dwell, its edges a few samples
/// and a smooth stop's approach. A longer one holds a stop of the controller at the pose, or
/// close enough to it that the bar cannot tell; the dwell is then its last `dwell` seconds
/// (the move away starts when the dwell ends).
pub fn longest_dwell(dwell: f64, interval: f64) -> f64 {
    1.15 * dwell + 0.3 + 2.0 * interval
}

/// ln Γ(x) for x > 0 (Lanczos, g = 7): for the Student-t's normalisation.
fn ln_gamma(x: f64) -> f64 {
    const G: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        return (std::f64::consts::PI / (std::f64::consts::PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = G[0];
    let t = x + 7.5;
    for (i, g) in G.iter().enumerate().skip(1) {
        a += g / (x + i as f64);
    }
    0.5 * (std::f64::consts::TAU).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// ln of the standard Student-t density with ν degrees of freedom at z.
fn ln_t_nu(z: f64, nu: f64) -> f64 {
    ln_gamma(0.5 * (nu + 1.0))
        - ln_gamma(0.5 * nu)
        - 0.5 * (nu * std::f64::consts::PI).ln()
        - 0.5 * (nu + 1.0) * (1.0 + z * z / nu).ln()
}

/// ln of the Student-t density (ν = 3) of residual r at scale s.
fn ln_t(r: f64, s: f64) -> f64 {
    let z = r / s;
    // Γ(2)/(Γ(1.5)√(3π)) = 0.36755
    (0.367_552_6f64).ln() - s.ln() - 0.5 * (NU + 1.0) * (1.0 + z * z / NU).ln()
}

struct Scorer<'a> {
    tpl: &'a Template,
    obs: &'a [Observed],
    /// Sample interval of the log (s): the resolution of a plateau's edges.
    interval: f64,
    /// ln of the range a reading could have by chance (m) and of a time by chance (s, log).
    ln_len_range: f64,
    ln_time_range: f64,
    pass2: Option<Pass2>,
    /// Gaps in the log (bar clock): where a plateau may have been lost.
    gaps: &'a [(f64, f64)],
    /// The first and the last slot of each section.
    first_slot: Vec<usize>,
    last_slot: Vec<usize>,
}

#[derive(Clone)]
struct Pass2 {
    /// Per slot: what its reading should exceed its nominal length by (the bar's zero and the
    /// robot's error there, from its neighbours in the tour: the error is smooth in joint
    /// space and the tour keeps neighbours close), and the scatter about that.
    local_zero: Vec<f64>,
    length_scale: f64,
    /// The controller's move times over the program's (the dwells are exact), and the scatter
    /// of the time between consecutive plateaus about that (s).
    move_ratio: f64,
    time_sigma: f64,
    /// The share of gaps whose plateau edges moved beyond that scatter, and their scatter (s).
    edge_share: f64,
    edge_sigma: f64,
}

impl Scorer<'_> {
    fn slot(&self, k: usize) -> &Slot {
        &self.tpl.slots[k]
    }

    /// The dwells of slots a..b (s): a program may dwell longer at some poses than at others.
    fn held(&self, a: usize, b: usize) -> f64 {
        self.tpl.slots[a..b].iter().map(Slot::dwell).sum()
    }

    /// A plateau's duration against the dwell (any pose), and in pass 2 its length.
    fn unary(&self, k: usize, j: usize) -> f64 {
        let s = self.slot(k);
        let o = &self.obs[j];
        let dwell = s.dwell();
        let dur = o.to - o.from;
        // A standstill lasts at least the dwell (the controller times it exactly); its
        // detected edges are good to a few samples.
        let lo = 0.99 * dwell - 3.0 * self.interval - 0.02;
        let slack = 0.01 * dwell + self.interval + 0.02;
        let mut score = 0.0;
        // A plateau a gap cuts may have been as long as any dwell.
        let cut = o.cut_before || o.cut_after;
        if dur < lo && !cut {
            let z = (lo - dur) / slack;
            score -= 0.5 * z * z;
        }
        if !s.after_pause && !s.before_pause {
            // A dwell is as long as programmed; a hold during it makes it longer (rare).
            let hi = longest_dwell(dwell, self.interval);
            if dur > hi {
                score -= 2.0 + (dur - hi) / (0.5 * dwell);
            }
        } else if dur < dwell + PAUSE_SHARE && !cut {
            // Next to a pause the operator's time adds to the dwell (mounting or removing
            // the bar takes a while).
            let z = (dwell + PAUSE_SHARE - dur) / (0.5 * PAUSE_SHARE);
            score -= 0.5 * z * z;
        }
        if let Some(p) = &self.pass2 {
            // The robot's errors about the zero: the scatter pass 1 found (Student-t, ν = 5: a
            // robot's errors are larger in some regions of its joint space), and a rare pose
            // whose nominal length is off by anything.
            let r = (o.mean - p.local_zero[k] - s.length) / p.length_scale;
            let core = (ln_t_nu(r, LENGTH_NU) - p.length_scale.ln()).exp();
            let range = self.ln_len_range.exp();
            score += ((1.0 - ODD_LENGTH) * core + ODD_LENGTH / range).ln() + self.ln_len_range;
        }
        score
    }

    /// ln density of a gap's deviation from the program (s) in pass 2, `want` the time the
    /// program and the controller's move ratio give: the timing scatter (Gaussian); the
    /// plateau edges' own displacement (a second, wider Gaussian at the share pass 1 found it:
    /// a smooth stop or start reaches the bar's stillness tolerance early or late by up to its
    /// ramp, depending on how fast the bar's length changes near the pose); a delay up to half
    /// a dwell (a stop too short to leave a plateau) at a small rate; anything else only at a
    /// tiny one (a longer stop leaves a plateau, and a controller is not early).
    fn ln_timing(&self, p: &Pass2, delta: f64, want: f64) -> f64 {
        let gauss =
            |s: f64| (-0.5 * (delta / s).powi(2)).exp() / (s * (std::f64::consts::TAU).sqrt());
        let sigma = p.time_sigma + TIME_RELATIVE * want;
        let edge = p.edge_sigma + TIME_RELATIVE * want;
        let core = (1.0 - p.edge_share) * gauss(sigma) + p.edge_share * gauss(edge);
        let short = 0.5 * self.tpl.dwell + 3.0 * edge;
        let stop = if delta > 0.0 && delta <= short {
            SHORT_STOP / short
        } else {
            0.0
        };
        ((1.0 - SHORT_STOP - ODD_TIME) * core + stop + ODD_TIME / 30.0).ln()
    }

    /// The time from plateau jp's end to plateau j's start with the plateaus between them
    /// (stops) taken out, and what the program says it is: its moves and the dwells of the
    /// poses skipped (s).
    fn gap(&self, kp: usize, jp: usize, k: usize, j: usize) -> (f64, f64, f64) {
        let standing: f64 = (jp + 1..j).map(|x| self.obs[x].to - self.obs[x].from).sum();
        let got = (self.obs[j].from - self.obs[jp].to - standing).max(0.0);
        let want = self.slot(k).start - self.slot(kp).end;
        let dwells = self.held(kp + 1, k);
        (got, (want - dwells).max(0.0), dwells)
    }

    /// The transition from match (k', j') to match (k, j): skips, the time between the two
    /// plateaus, and (pass 1) the change of the reading.
    fn pair(&self, kp: usize, jp: usize, k: usize, j: usize) -> f64 {
        let (a, b) = (self.slot(kp), self.slot(k));
        let same = a.section == b.section;
        let mut score: f64 = (kp + 1..k)
            .map(|x| self.miss(x, Some((kp, jp)), Some((k, j))))
            .sum();
        // Across a pause, the bar is handled between the removal and the mount: the window
        // of junk; pass 2 knows the timing well enough to place it (after the last dwell of
        // the section before, before the first dwell of the next one ends).
        let junk = match (&self.pass2, same) {
            (_, true) => (f64::INFINITY, f64::NEG_INFINITY),
            (None, false) => (f64::NEG_INFINITY, f64::INFINITY),
            (Some(p), false) => (self.section_end(p, kp, jp), self.section_start(p, k, j)),
        };
        let mut holds = 0.0;
        for x in jp + 1..j {
            holds += self.skipped(x, junk.0, junk.1);
        }
        let (oa, ob) = (self.obs[jp], self.obs[j]);
        if same {
            let (got, moves, dwells) = self.gap(kp, jp, k, j);
            let timing = |got: f64| match &self.pass2 {
                None => {
                    // Controllers run moves faster or slower than programmed: a broad
                    // log-normal on the whole gap.
                    let tau = 0.2;
                    let r = ((got + tau) / (moves + dwells + tau)).ln();
                    ln_t(r, PASS1_TIME_LOG) + (10.0f64).ln()
                }
                Some(p) => {
                    let want = p.move_ratio * moves + dwells;
                    let sigma = p.time_sigma + TIME_RELATIVE * want;
                    if (oa.cut_after || ob.cut_before) && got - want >= -3.0 * sigma {
                        // A gap hides where the standstill ended (began): the time between
                        // is at most what the log shows.
                        0.0
                    } else {
                        self.ln_timing(p, got - want, want) + self.ln_time_range
                    }
                }
            };
            // The plateaus skipped are stops (their time taken out), or what a gap in the log
            // left of the skipped poses' dwells (their time is the dwells').
            let mut t = holds + timing(got);
            let (np, nj) = (k - kp - 1, j - jp - 1);
            if nj >= 1 && nj <= np {
                let whole = ob.from - oa.to;
                t = logsumexp(t, timing(whole));
            }
            score += t;
            if self.pass2.is_none() {
                let d = (ob.mean - oa.mean) - (b.length - a.length);
                score += ln_t(d, PASS1_LENGTH * std::f64::consts::SQRT_2) + self.ln_len_range;
            }
        } else {
            // Across a pause the bar time can only be longer than the moves.
            let moves = b.start - a.end;
            if ob.from - oa.to < 0.5 * moves - 1.0 {
                score -= 20.0;
            }
            if self.pass2.is_none() {
                // No zero yet: the section's first reading only by its difference.
                let d = (ob.mean - oa.mean) - (b.length - a.length);
                score += ln_t(d, 2.0 * PASS1_LENGTH) + self.ln_len_range;
            }
        }
        score
    }

    /// Plateaus before the first match / after the last one: the bar before the program and
    /// after it (handled, lying on the bench), or a controller's stops in the first / last
    /// section when poses before / after are skipped.
    fn lead(&self, k: usize, j: usize) -> f64 {
        let mut score: f64 = (0..k).map(|x| self.miss(x, None, Some((k, j)))).sum();
        // Before the first dwell of k's section only junk; after it (pass 2 places it), a
        // plateau before match (k, j) is a stop of the controller.
        let start = match &self.pass2 {
            Some(p) => self.section_start(p, k, j),
            None => f64::INFINITY,
        };
        for x in 0..j {
            score += self.skipped(x, f64::NEG_INFINITY, start);
        }
        score
    }

    fn trail(&self, k: usize, j: usize) -> f64 {
        let mut score: f64 = (k + 1..self.tpl.slots.len())
            .map(|x| self.miss(x, Some((k, j)), None))
            .sum();
        let end = match &self.pass2 {
            Some(p) => self.section_end(p, k, j),
            None => f64::NEG_INFINITY,
        };
        for x in j + 1..self.obs.len() {
            score += self.skipped(x, end, f64::INFINITY);
        }
        score
    }

    /// Slot x without a plateau, between the matches `before` and `after` (either may be
    /// absent): rare, unless the log has a gap where its standstill is due (pass 2 places it
    /// from the nearer match of its own section).
    fn miss(&self, x: usize, before: Option<(usize, usize)>, after: Option<(usize, usize)>) -> f64 {
        let Some(p) = &self.pass2 else {
            return MISS;
        };
        let s = self.slot(x);
        let dwell = s.dwell();
        let due = match (before, after) {
            (_, Some((k, j))) if self.slot(k).section == s.section => {
                let n = self.held(x + 1, k);
                let end =
                    self.obs[j].from - p.move_ratio * (self.slot(k).start - s.end - n).max(0.0) - n;
                Some((end - dwell, end))
            }
            (Some((k, j)), _) if self.slot(k).section == s.section => {
                let n = self.held(k + 1, x);
                let start =
                    self.obs[j].to + p.move_ratio * (s.start - self.slot(k).end - n).max(0.0) + n;
                Some((start, start + dwell))
            }
            _ => None,
        };
        let tol = 3.0 * p.time_sigma + 0.1;
        match due {
            Some((a, b)) if self.gaps.iter().any(|g| g.0 < b + tol && g.1 > a - tol) => MISS_IN_GAP,
            _ => MISS,
        }
    }

    /// A plateau of no pose: junk when it lies in the window the bar is off, else a stop of
    /// the controller (the longer, the rarer).
    fn skipped(&self, x: usize, from: f64, to: f64) -> f64 {
        let o = &self.obs[x];
        if o.from >= from && o.to <= to {
            JUNK
        } else {
            EXTRA - (o.to - o.from) / (2.0 * self.tpl.dwell)
        }
    }

    /// Bar time by which slot k's section has ended its last dwell, from match (k, j) (less a
    /// tolerance): the bar may come off after it.
    fn section_end(&self, p: &Pass2, k: usize, j: usize) -> f64 {
        let a = self.slot(k);
        let last = self.last_slot[a.section];
        let n = self.held(k + 1, last + 1);
        self.obs[j].to + p.move_ratio * (self.slot(last).end - a.end - n).max(0.0) + n
            - (3.0 * p.time_sigma + 0.3)
    }

    /// Bar time at which slot k's section begins its first dwell, from match (k, j) (plus a
    /// tolerance): the bar may have gone on before it.
    fn section_start(&self, p: &Pass2, k: usize, j: usize) -> f64 {
        let b = self.slot(k);
        let first = self.first_slot[b.section];
        if k == first {
            return self.obs[j].from + 3.0 * p.time_sigma + 0.3;
        }
        let n = self.held(first + 1, k);
        self.obs[j].from
            - p.move_ratio * (b.start - self.slot(first).end - n).max(0.0)
            - n
            - self.slot(first).dwell()
            + 3.0 * p.time_sigma
            + 0.3
    }

    /// The predecessors a match (k, j) may follow.
    fn preds(&self, k: usize, j: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        let k0 = k.saturating_sub(MAX_SKIP_POSES + 1);
        (k0..k).rev().flat_map(move |kp| {
            let same = self.slot(kp).section == self.slot(k).section;
            let j0 = if same {
                j.saturating_sub(MAX_SKIP_PLATEAUS + 1)
            } else {
                0
            };
            (j0..j).rev().map(move |jp| (kp, jp))
        })
    }
}

fn logsumexp(a: f64, b: f64) -> f64 {
    if a == f64::NEG_INFINITY {
        return b;
    }
    if b == f64::NEG_INFINITY {
        return a;
    }
    let m = a.max(b);
    m + ((a - m).exp() + (b - m).exp()).ln()
}

/// The best alignment (Viterbi): the matched (slot, plateau) pairs in order.
fn viterbi(sc: &Scorer) -> Vec<(usize, usize)> {
    let (kn, jn) = (sc.tpl.slots.len(), sc.obs.len());
    if kn == 0 || jn == 0 {
        return Vec::new();
    }
    let mut best = vec![f64::NEG_INFINITY; kn * jn];
    let mut from: Vec<Option<(usize, usize)>> = vec![None; kn * jn];
    for k in 0..kn {
        for j in 0..jn {
            let u = sc.unary(k, j);
            let mut b = sc.lead(k, j);
            let mut f = None;
            for (kp, jp) in sc.preds(k, j) {
                let v = best[kp * jn + jp];
                if v == f64::NEG_INFINITY {
                    continue;
                }
                let s = v + sc.pair(kp, jp, k, j);
                // Ties go to the nearer predecessor (the iteration order), deterministically.
                if s > b {
                    b = s;
                    f = Some((kp, jp));
                }
            }
            best[k * jn + j] = b + u;
            from[k * jn + j] = f;
        }
    }
    let mut end: Option<(usize, usize)> = None;
    let mut top = (kn as f64) * MISS + (jn as f64) * JUNK;
    for k in 0..kn {
        for j in 0..jn {
            let s = best[k * jn + j] + sc.trail(k, j);
            if s > top {
                top = s;
                end = Some((k, j));
            }
        }
    }
    let mut path = Vec::new();
    while let Some((k, j)) = end {
        path.push((k, j));
        end = from[k * jn + j];
    }
    path.reverse();
    path
}

/// Posterior probability of every (slot, plateau) pair over all alignments.
fn posterior(sc: &Scorer) -> Vec<f64> {
    let (kn, jn) = (sc.tpl.slots.len(), sc.obs.len());
    let idx = |k: usize, j: usize| k * jn + j;
    let unary: Vec<f64> = (0..kn * jn).map(|x| sc.unary(x / jn, x % jn)).collect();
    // Forward: log-sum over alignments ending with match (k, j), its unary included.
    let mut fwd = vec![f64::NEG_INFINITY; kn * jn];
    for k in 0..kn {
        for j in 0..jn {
            let mut s = sc.lead(k, j);
            for (kp, jp) in sc.preds(k, j) {
                let v = fwd[idx(kp, jp)];
                if v > f64::NEG_INFINITY {
                    s = logsumexp(s, v + sc.pair(kp, jp, k, j));
                }
            }
            fwd[idx(k, j)] = s + unary[idx(k, j)];
        }
    }
    // Backward: log-sum over the continuations after match (k, j).
    let mut bwd = vec![f64::NEG_INFINITY; kn * jn];
    // Successors are the reverse of `preds`: gather them by scanning preds of later cells.
    for k in (0..kn).rev() {
        for j in (0..jn).rev() {
            bwd[idx(k, j)] = sc.trail(k, j);
        }
    }
    for k in (0..kn).rev() {
        for j in (0..jn).rev() {
            // bwd(k, j) is final once every successor (k2 > k) is: push it to its preds.
            let here = bwd[idx(k, j)] + unary[idx(k, j)];
            for (kp, jp) in sc.preds(k, j) {
                let add = here + sc.pair(kp, jp, k, j);
                bwd[idx(kp, jp)] = logsumexp(bwd[idx(kp, jp)], add);
            }
        }
    }
    let mut z = (kn as f64) * MISS + (jn as f64) * JUNK;
    for x in 0..kn * jn {
        z = logsumexp(z, fwd[x] + sc.trail(x / jn, x % jn));
    }
    (0..kn * jn).map(|x| (fwd[x] + bwd[x] - z).exp()).collect()
}

// ---- the estimates between the passes --------------------------------------------------------

/// The median absolute deviation scaled to a normal sigma; 0 for no values.
fn mad(v: &[f64]) -> f64 {
    let Some(m) = median(v) else { return 0.0 };
    let dev: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
    1.4826 * median(&dev).unwrap_or(0.0)
}

/// The timeline fitted to the matched plateaus' program-timed edges: least squares with a
/// per-section offset and a common slope, edges beyond 4 robust sigmas left out and refitted.
fn fit_timeline(
    tpl: &Template,
    obs: &[Observed],
    pairs: &[(usize, usize)],
    sections: usize,
) -> Timeline {
    // (section, program time, bar time); a stop the controller made (a plateau of no pose
    // inside a section) delays everything after it by its length: taken out.
    let mut matched = vec![false; obs.len()];
    for &(_, j) in pairs {
        matched[j] = true;
    }
    let mut first_of = vec![usize::MAX; sections];
    for &(k, j) in pairs {
        let s = tpl.slots[k].section;
        first_of[s] = first_of[s].min(j);
    }
    let held = |s: usize, j: usize| -> f64 {
        (first_of[s].saturating_add(1)..j)
            .filter(|&x| !matched[x])
            .map(|x| obs[x].to - obs[x].from)
            .sum()
    };
    let mut edges: Vec<(usize, f64, f64)> = Vec::new();
    for &(k, j) in pairs {
        let s = &tpl.slots[k];
        let h = held(s.section, j);
        if !s.after_pause {
            edges.push((s.section, s.start, obs[j].from - h));
        }
        if !s.before_pause {
            edges.push((s.section, s.end, obs[j].to - h));
        }
    }
    let mut keep = vec![true; edges.len()];
    let mut tl = Timeline {
        offsets: vec![None; sections],
        offset_std: vec![None; sections],
        drift: 0.0,
        drift_std: None,
        rms: 0.0,
    };
    for _round in 0..3 {
        let used: Vec<&(usize, f64, f64)> = edges
            .iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(e, _)| e)
            .collect();
        if used.is_empty() {
            return tl;
        }
        // Slope from within-section deviations (offsets eliminated), then offsets.
        let mut sx = vec![0.0; sections];
        let mut sy = vec![0.0; sections];
        let mut n = vec![0usize; sections];
        for e in &used {
            sx[e.0] += e.1;
            sy[e.0] += e.2;
            n[e.0] += 1;
        }
        let (mut sxx, mut sxy) = (0.0, 0.0);
        for e in &used {
            let (mx, my) = (sx[e.0] / n[e.0] as f64, sy[e.0] / n[e.0] as f64);
            sxx += (e.1 - mx).powi(2);
            sxy += (e.1 - mx) * (e.2 - my);
        }
        let slope = if sxx > 1e-9 { sxy / sxx } else { 1.0 };
        let offsets: Vec<Option<f64>> = (0..sections)
            .map(|s| (n[s] > 0).then(|| (sy[s] - slope * sx[s]) / n[s] as f64))
            .collect();
        let res: Vec<f64> = edges
            .iter()
            .map(|e| e.2 - offsets[e.0].unwrap_or(0.0) - slope * e.1)
            .collect();
        let used_res: Vec<f64> = res
            .iter()
            .zip(&keep)
            .filter(|(_, k)| **k)
            .map(|(r, _)| *r)
            .collect();
        let dof = used_res.len() as f64 - n.iter().filter(|&&c| c > 0).count() as f64 - 1.0;
        let rss: f64 = used_res.iter().map(|r| r * r).sum();
        let sigma = if dof > 0.0 { (rss / dof).sqrt() } else { 0.0 };
        let robust = mad(&used_res).max(1e-4);
        tl = Timeline {
            offset_std: (0..sections)
                .map(|s| {
                    (n[s] > 0 && dof > 0.0).then(|| {
                        let mx = sx[s] / n[s] as f64;
                        sigma * (1.0 / n[s] as f64 + mx * mx / sxx.max(1e-12)).sqrt()
                    })
                })
                .collect(),
            offsets,
            drift: slope - 1.0,
            drift_std: (dof > 0.0 && sxx > 1e-9).then(|| sigma / sxx.sqrt()),
            rms: (rss / used_res.len() as f64).sqrt(),
        };
        let next: Vec<bool> = res.iter().map(|r| r.abs() <= 4.0 * robust).collect();
        if next == keep {
            break;
        }
        keep = next;
    }
    tl
}

// ---- the match ------------------------------------------------------------------------------

/// Where a slot's plateau is due on the bar clock, for messages.
fn due(tl: &Timeline, s: &Slot) -> Option<f64> {
    tl.offsets[s.section].map(|o| o + (1.0 + tl.drift) * s.start)
}

/// Matches the plateaus `obs` (time order, bar clock) to the template's slots. `interval`:
/// the log's sample interval (s).
pub fn align(
    tpl: &Template,
    obs: &[Observed],
    gaps: &[(f64, f64)],
    interval: f64,
) -> Result<Alignment, AlignError> {
    let kn = tpl.slots.len();
    if kn == 0 {
        return Err(AlignError::NoMatch(
            "the program has no measurement dwell (compile it with --dwell)".into(),
        ));
    }
    let sections = tpl.slots.iter().map(|s| s.section).max().unwrap_or(0) + 1;
    let (lmin, lmax) = tpl
        .slots
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), s| {
            (a.min(s.length), b.max(s.length))
        });
    let mut sc = Scorer {
        tpl,
        obs,
        interval,
        ln_len_range: (lmax - lmin + 0.02).ln(),
        ln_time_range: (30.0f64).ln(),
        pass2: None,
        gaps,
        first_slot: (0..sections)
            .map(|s| tpl.slots.iter().position(|x| x.section == s).unwrap_or(0))
            .collect(),
        last_slot: (0..sections)
            .map(|s| tpl.slots.iter().rposition(|x| x.section == s).unwrap_or(0))
            .collect(),
    };
    let first = viterbi(&sc);
    if first.len() < 2 {
        return Err(AlignError::NoMatch(format!(
            "{} of {} poses matched a plateau",
            first.len(),
            kn
        )));
    }
    // Pass 2: the zero and the scatter of the lengths, the controller's move-time ratio and
    // the scatter of the times between plateaus, from pass 1's matches.
    sc.pass2 = Some(sc.pass2_scales(&first));
    let timeline = fit_timeline(tpl, obs, &first, sections);
    let post = posterior(&sc);
    let (matched, confidence) = decide(tpl, obs, &post, &timeline)?;
    let pairs: Vec<(usize, usize)> = matched
        .iter()
        .enumerate()
        .filter_map(|(k, j)| j.map(|j| (k, j)))
        .collect();
    if pairs.len() < 2 {
        return Err(AlignError::NoMatch(format!(
            "{} of {} poses matched a plateau",
            pairs.len(),
            kn
        )));
    }
    let resid: Vec<f64> = pairs
        .iter()
        .map(|&(k, j)| obs[j].mean - tpl.slots[k].length)
        .collect();
    let n = resid.len() as f64;
    let zero = resid.iter().sum::<f64>() / n;
    let zero_spread =
        (resid.iter().map(|r| (r - zero).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
    let timeline = fit_timeline(tpl, obs, &pairs, sections);
    Ok(Alignment {
        matched,
        confidence,
        zero,
        zero_spread,
        zero_std: zero_spread / n.sqrt(),
        timeline,
    })
}

impl Scorer<'_> {
    /// Pass 2's scales from pass 1's matches `first` (slot, plateau).
    fn pass2_scales(&self, first: &[(usize, usize)]) -> Pass2 {
        let (tpl, obs, interval) = (self.tpl, self.obs, self.interval);
        let kn = tpl.slots.len();
        let resid: Vec<f64> = first
            .iter()
            .map(|&(k, j)| obs[j].mean - tpl.slots[k].length)
            .collect();
        let zero = median(&resid).unwrap_or(0.0);
        // The local zero of every slot: the median of its matched neighbours' (up to three on
        // either side, in its section, itself left out), else the global one.
        let mut of_slot: Vec<Option<f64>> = vec![None; kn];
        for (&(k, _), r) in first.iter().zip(&resid) {
            of_slot[k] = Some(*r);
        }
        let local_zero: Vec<f64> = (0..kn)
            .map(|k| {
                let sec = tpl.slots[k].section;
                let near: Vec<f64> = (k.saturating_sub(LOCAL)..(k + LOCAL + 1).min(kn))
                    .filter(|&i| i != k && tpl.slots[i].section == sec)
                    .filter_map(|i| of_slot[i])
                    .collect();
                if near.len() >= 2 {
                    median(&near).unwrap_or(zero)
                } else {
                    zero
                }
            })
            .collect();
        let loo: Vec<f64> = first
            .iter()
            .zip(&resid)
            .map(|(&(k, _), r)| r - local_zero[k])
            .collect();
        let length_scale = mad(&loo).max(LENGTH_FLOOR);
        let steps: Vec<(f64, f64, f64)> = first
            .windows(2)
            .filter(|w| tpl.slots[w[0].0].section == tpl.slots[w[1].0].section)
            .map(|w| self.gap(w[0].0, w[0].1, w[1].0, w[1].1))
            .collect();
        let ratios: Vec<f64> = steps
            .iter()
            .filter(|s| s.1 > 0.2)
            .map(|s| (s.0 - s.2) / s.1)
            .collect();
        let move_ratio = if ratios.len() >= 3 {
            median(&ratios).unwrap_or(1.0)
        } else {
            1.0
        };
        let errs: Vec<f64> = steps.iter().map(|s| s.0 - move_ratio * s.1 - s.2).collect();
        let time_sigma = mad(&errs).max(TIME_FLOOR + interval);
        // The gaps beyond 3 sigmas, up to what a ramp can move an edge: plateau edges a smooth
        // stop moved (beyond that: pass 1's wrong matches, stops); their RMS is the edge scatter,
        // their share its weight (bounded: a few steps cannot say it is rare, nor make every gap
        // uncertain).
        let edge_max = (EDGE_MAX * tpl.dwell).min(EDGE_RAMP);
        let wide: Vec<f64> = errs
            .iter()
            .copied()
            .filter(|e| e.abs() > 3.0 * time_sigma && e.abs() <= edge_max)
            .collect();
        let edge_share = ((wide.len() as f64 + 1.0) / (errs.len() as f64 + 2.0))
            .clamp(EDGE_SHARE.0, EDGE_SHARE.1);
        let edge_sigma = (wide.iter().map(|e| e * e).sum::<f64>() / wide.len().max(1) as f64)
            .sqrt()
            .clamp(3.0 * time_sigma, edge_max.max(3.0 * time_sigma));
        if std::env::var_os("EDBB_DEBUG").is_some() {
            eprintln!("pass1 {:?}\nratio {move_ratio} sigma {time_sigma} edge {edge_share} {edge_sigma} lscale {length_scale} zero {zero} errs {:?}\nsteps {:?}", first, errs, steps);
        }
        Pass2 {
            local_zero,
            length_scale,
            move_ratio,
            time_sigma,
            edge_share,
            edge_sigma,
        }
    }
}

/// Each slot's plateau from the posterior `post` (slot-major, one row of plateaus per slot)
/// and its probability (of the match, or of no plateau); an error where neither is sure.
fn decide(
    tpl: &Template,
    obs: &[Observed],
    post: &[f64],
    timeline: &Timeline,
) -> Result<(Vec<Option<usize>>, Vec<f64>), AlignError> {
    let kn = tpl.slots.len();
    let jn = obs.len();
    let mut matched = vec![None; kn];
    let mut confidence = vec![0.0; kn];
    for k in 0..kn {
        let row = &post[k * jn..(k + 1) * jn];
        let (j, p) = row
            .iter()
            .enumerate()
            .fold((0, -1.0), |b, (j, &p)| if p > b.1 { (j, p) } else { b });
        let missing = (1.0 - row.iter().sum::<f64>()).clamp(0.0, 1.0);
        if p >= SURE {
            matched[k] = Some(j);
            confidence[k] = p;
        } else if missing >= SURE {
            confidence[k] = missing;
        } else {
            let s = &tpl.slots[k];
            let mut cands: Vec<(usize, f64)> = row
                .iter()
                .enumerate()
                .filter(|(_, &p)| p >= 0.01)
                .map(|(j, &p)| (j, p))
                .collect();
            cands.sort_by(|a, b| b.1.total_cmp(&a.1));
            let mut what: Vec<String> = cands
                .iter()
                .take(2)
                .map(|(j, p)| {
                    format!(
                        "the plateau at {}..{} s ({} mm, p {})",
                        fmt_fixed(obs[*j].from, 2),
                        fmt_fixed(obs[*j].to, 2),
                        fmt_fixed(to_mm(obs[*j].mean), 3),
                        fmt_fixed(*p, 2)
                    )
                })
                .collect();
            if missing >= 0.01 {
                what.push(format!("no plateau (p {})", fmt_fixed(missing, 2)));
            }
            let when = due(timeline, s)
                .map(|t| format!(", due near {} s on the bar clock", fmt_fixed(t, 1)))
                .unwrap_or_default();
            return Err(AlignError::Ambiguous(format!(
                "pose {}/{} (nominal L {} mm{when}) could not be matched: {} fit it about equally; refusing to guess",
                s.pose,
                tpl.poses,
                fmt_fixed(to_mm(s.length), 3),
                what.join(" and ")
            )));
        }
    }
    Ok((matched, confidence))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A template of `n` poses in two sections, dwell 2 s, moves of 0.4..1.2 s.
    fn template(n: usize, seed: u64) -> Template {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut slots = Vec::new();
        let mut t = 0.0;
        for k in 0..n {
            let section = usize::from(k >= n / 2);
            let after_pause = k == 0 || k == n / 2;
            let before_pause = k + 1 == n || k + 1 == n / 2;
            if !after_pause {
                t += rng.random_range(0.4..1.2);
            }
            slots.push(Slot {
                pose: k + 1,
                length: rng.random_range(0.30..0.52),
                q: [0.0; 6],
                section,
                start: t,
                end: t + 2.0,
                after_pause,
                before_pause,
            });
            t += 2.0;
        }
        Template {
            slots,
            dwell: 2.0,
            poses: n,
        }
    }

    /// The plateaus a run of `tpl` leaves: offset, drift, zero, a 20 s pause with a junk
    /// plateau between the sections, small errors on every length.
    fn run(tpl: &Template, offset: f64, drift: f64, zero: f64, seed: u64) -> Vec<Observed> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut out = Vec::new();
        let a = 1.0 + drift;
        let mut shift = offset;
        for s in &tpl.slots {
            if s.after_pause && s.section > 0 {
                shift += 20.0;
                let t0 = shift + a * s.start - 12.0;
                out.push(Observed {
                    from: t0,
                    to: t0 + 3.0,
                    mean: rng.random_range(0.3..0.5),
                    cut_before: false,
                    cut_after: false,
                });
            }
            let from = shift + a * s.start - if s.after_pause { 5.0 } else { 0.0 };
            let to = shift + a * s.end + if s.before_pause { 4.0 } else { 0.0 };
            out.push(Observed {
                from: from + rng.random_range(-0.02..0.02),
                to: to + rng.random_range(-0.02..0.02),
                mean: s.length + zero + rng.random_range(-3e-4..3e-4),
                cut_before: false,
                cut_after: false,
            });
        }
        out
    }

    #[test]
    fn a_clean_run_matches_every_pose_and_recovers_zero_and_clock() {
        let tpl = template(30, 1);
        let obs = run(&tpl, -17.0, 150e-6, 0.012, 2);
        let a = align(&tpl, &obs, &[], 0.02).unwrap();
        // Every slot to its own plateau: the junk plateau (index 15) unmatched.
        let want: Vec<Option<usize>> = (0..30).map(|k| Some(k + usize::from(k >= 15))).collect();
        assert_eq!(a.matched, want);
        assert!((a.zero - 0.012).abs() < 2e-4, "{}", a.zero);
        let o = a.timeline.offsets[0].unwrap();
        assert!((o + 17.0).abs() < 0.05, "{o}");
        assert!(a.timeline.drift_std.unwrap() < 2e-3);
    }

    #[test]
    fn a_missing_plateau_and_an_extra_one() {
        let tpl = template(30, 3);
        let mut obs = run(&tpl, 25.0, -200e-6, -0.4, 4);
        // Pose 8's plateau is lost; a controller stop sits between poses 20 and 21.
        obs.remove(7);
        let (a, b) = (obs[19].to, obs[20].from);
        let hold = Observed {
            from: a + 0.2,
            to: a + 1.9,
            mean: 0.5 * (obs[19].mean + obs[20].mean),
            cut_before: false,
            cut_after: false,
        };
        for o in obs.iter_mut().skip(20) {
            o.from += 1.7;
            o.to += 1.7;
        }
        assert!(b > a);
        obs.insert(20, hold);
        let al = align(&tpl, &obs, &[], 0.02).unwrap();
        assert_eq!(al.matched[7], None);
        assert!(al.confidence[7] >= SURE);
        for k in 0..30 {
            if k == 7 {
                continue;
            }
            let j = al.matched[k].unwrap_or_else(|| panic!("pose {} unmatched", k + 1));
            let truth = k - usize::from(k > 7) + usize::from(k >= 15) + usize::from(k >= 20);
            assert_eq!(j, truth, "pose {}", k + 1);
        }
    }
}

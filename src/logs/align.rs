//! Plateaus to poses: in = a stop-and-measure program's template (its measurement dwells in
//! order: nominal bar length, section, program times) and a bar log's plateaus; out = which
//! plateau is which pose, the bar's zero offset and the clock, or a refusal that names the
//! pose it cannot tell.
//!
//! The match is a sequence alignment (dynamic programming over plateaus × poses, both in time
//! order) scored as log-likelihood ratios: a pose matched to a plateau earns what its length,
//! its duration and its timing say for the match; a pose without a plateau (a gap in the log,
//! the operator) and a plateau without a pose (a stop the controller made, the bar handled
//! while unmounted) cost what their rarity says. Two passes:
//!
//! 1. **No clock, no zero.** Between consecutive matches only differences count: the change
//!    of the reading against the change of the nominal length, the time from one plateau's
//!    end to the next one's start against the program's moves between them (a broad
//!    log-normal: controllers run moves faster or slower than programmed, never dwells), and
//!    each plateau's duration against the dwell (a section's first pose dwells after its mount
//!    pause, its last stands on into the removal pause: only a lower bound there). The best
//!    alignment (Viterbi) gives a first set of matches.
//! 2. **Zero and clock estimated.** From those matches: the zero offset (median of reading −
//!    nominal) and the timeline t_bar = o_s + (1 + drift)·t_prog per section s (pauses have
//!    unknown lengths: one offset per section, a common drift), fitted robustly to the plateau
//!    edges the program times (a dwell's end, and its start where no pause precedes it). The
//!    alignment is scored again with absolute terms (reading − zero − nominal, edge − timeline,
//!    each against the scatter the first pass left), and the posterior of every (pose,
//!    plateau) pair is computed over all alignments (forward–backward). A pose is matched
//!    when one plateau holds ≥ 99 % of it, missing when "no plateau" does; anything else is a
//!    refusal naming the pose.

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

/// A stop-and-measure program as the bar log is matched against it.
#[derive(Clone, Debug, PartialEq)]
pub struct Template {
    pub slots: Vec<Slot>,
    /// The dwell (s).
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
/// stop) or outside one (the bar handled while unmounted, before the first mount, after the
/// last removal): log prior odds.
const MISS: f64 = -6.0;
const EXTRA: f64 = -4.0;
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
const TIME_FLOOR: f64 = 0.02;
/// A verdict is taken when its posterior reaches this.
pub const SURE: f64 = 0.99;
/// Student-t degrees of freedom of every residual (heavy tails: one odd pose does not break a
/// run).
const NU: f64 = 3.0;

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
}

#[derive(Clone)]
struct Pass2 {
    zero: f64,
    length_scale: f64,
    timeline: Timeline,
    time_scale: f64,
}

impl Scorer<'_> {
    fn slot(&self, k: usize) -> &Slot {
        &self.tpl.slots[k]
    }

    /// A plateau's duration against the dwell (any pose), and in pass 2 its length and edges.
    fn unary(&self, k: usize, j: usize) -> f64 {
        let s = self.slot(k);
        let o = &self.obs[j];
        let dwell = self.tpl.dwell;
        let dur = o.to - o.from;
        let lo = 0.9 * dwell - 2.0 * self.interval;
        let slack = 0.05 * dwell + 2.0 * self.interval;
        let mut score = 0.0;
        if dur < lo {
            let z = (lo - dur) / slack;
            score -= 0.5 * z * z;
        }
        if !s.after_pause && !s.before_pause {
            // A dwell is as long as programmed; a hold during it makes it longer (rare).
            let hi = 1.15 * dwell + 0.3 + 2.0 * self.interval;
            if dur > hi {
                score -= 2.0 + (dur - hi) / (0.5 * dwell);
            }
        }
        if let Some(p) = &self.pass2 {
            score += ln_t(o.mean - p.zero - s.length, p.length_scale) + self.ln_len_range;
            if let Some(off) = p.timeline.offsets[s.section] {
                let a = 1.0 + p.timeline.drift;
                if !s.after_pause {
                    score += ln_t(o.from - off - a * s.start, p.time_scale) + self.ln_time_range;
                }
                if !s.before_pause {
                    score += ln_t(o.to - off - a * s.end, p.time_scale) + self.ln_time_range;
                }
            }
        }
        score
    }

    /// The transition from match (k', j') to match (k, j): skips, and (pass 1, or a section
    /// without a timeline) the differences between the two.
    fn pair(&self, kp: usize, jp: usize, k: usize, j: usize) -> f64 {
        let (a, b) = (self.slot(kp), self.slot(k));
        let same = a.section == b.section;
        let mut score = (k - kp - 1) as f64 * MISS;
        let mut standing = 0.0;
        for x in jp + 1..j {
            score += if same { EXTRA } else { JUNK };
            standing += self.obs[x].to - self.obs[x].from;
        }
        let (oa, ob) = (&self.obs[jp], &self.obs[j]);
        let gap = ob.from - oa.to;
        if same {
            let timed = self
                .pass2
                .as_ref()
                .is_some_and(|p| p.timeline.offsets[b.section].is_some());
            if !timed {
                // The moves between the two dwells (and the dwells of skipped poses): a stop
                // the controller made in between stood still for its plateau's length.
                let want = b.start - a.end;
                let got = (gap - standing).max(0.0);
                let tau = 0.2;
                let r = ((got + tau) / (want + tau)).ln();
                score += ln_t(r, PASS1_TIME_LOG) + (10.0f64).ln();
            }
            if self.pass2.is_none() {
                let d = (ob.mean - oa.mean) - (b.length - a.length);
                score += ln_t(d, PASS1_LENGTH * std::f64::consts::SQRT_2) + self.ln_len_range;
            }
        } else {
            // Across a pause the bar time can only be longer than the moves.
            let moves = b.start - a.end;
            if gap < 0.5 * moves - 1.0 {
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
        k as f64 * MISS + j as f64 * JUNK
    }

    fn trail(&self, k: usize, j: usize) -> f64 {
        (self.tpl.slots.len() - 1 - k) as f64 * MISS + (self.obs.len() - 1 - j) as f64 * JUNK
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

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn mad(v: &[f64]) -> f64 {
    let m = median(v.to_vec());
    1.4826 * median(v.iter().map(|x| (x - m).abs()).collect())
}

/// The timeline fitted to the matched plateaus' program-timed edges: least squares with a
/// per-section offset and a common slope, edges beyond 4 robust sigmas left out and refitted.
fn fit_timeline(
    tpl: &Template,
    obs: &[Observed],
    pairs: &[(usize, usize)],
    sections: usize,
) -> Timeline {
    // (section, program time, bar time)
    let mut edges: Vec<(usize, f64, f64)> = Vec::new();
    for &(k, j) in pairs {
        let s = &tpl.slots[k];
        if !s.after_pause {
            edges.push((s.section, s.start, obs[j].from));
        }
        if !s.before_pause {
            edges.push((s.section, s.end, obs[j].to));
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
pub fn align(tpl: &Template, obs: &[Observed], interval: f64) -> Result<Alignment, AlignError> {
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
    let span: f64 = tpl.slots.last().map_or(1.0, |s| s.end) + 60.0;
    let mut sc = Scorer {
        tpl,
        obs,
        interval,
        ln_len_range: (lmax - lmin + 0.02).ln(),
        ln_time_range: span.ln(),
        pass2: None,
    };
    let first = viterbi(&sc);
    if first.len() < 2 {
        return Err(AlignError::NoMatch(format!(
            "{} of {} poses matched a plateau",
            first.len(),
            kn
        )));
    }
    // Pass 2: the zero, the scatter of the lengths and the timeline from pass 1's matches.
    let resid: Vec<f64> = first
        .iter()
        .map(|&(k, j)| obs[j].mean - tpl.slots[k].length)
        .collect();
    let zero = median(resid.clone());
    let length_scale = mad(&resid).max(LENGTH_FLOOR);
    let timeline = fit_timeline(tpl, obs, &first, sections);
    let time_scale = timeline.rms.max(TIME_FLOOR + 2.0 * interval);
    sc.pass2 = Some(Pass2 {
        zero,
        length_scale,
        timeline: timeline.clone(),
        time_scale,
    });
    let post = posterior(&sc);
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
            let when = due(&timeline, s)
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
                });
            }
            let from = shift + a * s.start - if s.after_pause { 5.0 } else { 0.0 };
            let to = shift + a * s.end + if s.before_pause { 4.0 } else { 0.0 };
            out.push(Observed {
                from: from + rng.random_range(-0.02..0.02),
                to: to + rng.random_range(-0.02..0.02),
                mean: s.length + zero + rng.random_range(-3e-4..3e-4),
            });
        }
        out
    }

    #[test]
    fn a_clean_run_matches_every_pose_and_recovers_zero_and_clock() {
        let tpl = template(30, 1);
        let obs = run(&tpl, -17.0, 150e-6, 0.012, 2);
        let a = align(&tpl, &obs, 0.02).unwrap();
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
        };
        for o in obs.iter_mut().skip(20) {
            o.from += 1.7;
            o.to += 1.7;
        }
        assert!(b > a);
        obs.insert(20, hold);
        let al = align(&tpl, &obs, 0.02).unwrap();
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

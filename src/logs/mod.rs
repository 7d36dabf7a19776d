//! Instrument and controller logs (no synchronous joint log): in = a bar log (`t_s,length_mm`
//! on the instrument's own clock), a joint log (`t_s,q1_deg..q6_deg` on the controller's), and
//! the program they recorded; out = pose readings with their plateaus and the clock relation.
//! Pure functions: no file I/O, no printing.

/// The plateau core: the samples a plateau's mean uses, `trim` seconds in from either end
/// (the last creep of the arrival and the first of the departure stay out).
pub fn core_trim(duration: f64, rate: f64) -> f64 {
    (2.0 / rate).max(0.05 * duration)
}

/// Bar samples a dwell of `dwell` seconds at `rate` Hz leaves in its plateau's core: what one
/// stop-and-measure reading averages (the compiler's prediction assumes it).
pub fn plateau_core_samples(dwell: f64, rate: f64) -> usize {
    let core = dwell - 2.0 * core_trim(dwell, rate);
    if core <= 0.0 {
        return 0;
    }
    (core * rate).floor() as usize
}

/// The plateau finder looks for standstills at least this share of the program's longest
/// dwell: a dwell shorter than that is no measurement (a settling dwell).
pub const MIN_PLATEAU_SHARE: f64 = 0.5;

/// A plateau shorter than this many core samples is no reading (its mean is not a standstill
/// the bar can vouch for).
pub const MIN_PLATEAU_SAMPLES: usize = 5;

pub mod align;
pub mod format;
pub mod plateau;
pub mod sync;

pub use align::{Alignment, Observed, Slot, Template, Timeline};
pub use format::{parse_bar_log, parse_joint_log, BarLog, JointLog, LogError};
pub use plateau::Plateau;

use crate::units::{fmt_fixed, to_mm};
use serde::Serialize;

/// Why a log cannot be turned into readings: one line, naming what is wrong.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LogsError {
    #[error("{0}")]
    Bad(String),
}

fn bad(msg: impl Into<String>) -> LogsError {
    LogsError::Bad(msg.into())
}

/// One plateau in the report (DESIGN.md: `plateaus[]`): the pose it is (1-based, None when
/// unmatched), its span on the bar clock, the log rows it covers, the core's mean and spread
/// and the mean's standard uncertainty.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PlateauReport {
    pub pose: Option<usize>,
    pub t_from_s: f64,
    pub t_to_s: f64,
    /// Log rows (1-based data rows, inclusive) and the core samples averaged.
    pub rows: [usize; 2],
    pub samples: usize,
    pub mean_mm: f64,
    pub spread_um: f64,
    pub std_um: f64,
}

/// The clock relation (DESIGN.md: `clock`): t_bar = offset + (1 + drift·1e-6)·t_ref, the
/// bar's clock against the controller's.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ClockReport {
    /// What t_ref is: "program" (stop-and-measure: the controller's time running the program,
    /// see `t_ref`) or "joint_log" (the joint log's time stamps).
    pub reference: &'static str,
    /// When t_ref is zero, for people.
    pub t_ref: String,
    pub offset_s: f64,
    pub offset_std_s: Option<f64>,
    pub drift_ppm: f64,
    pub drift_std_ppm: Option<f64>,
    /// Stop-and-measure: how long the controller stood between each section and the next
    /// (the operator's removal and mount pauses, s of t_ref; null where a section has no
    /// matched pose), with their standard uncertainties. t_ref includes them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pauses_s: Option<Vec<Option<f64>>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pauses_std_s: Option<Vec<Option<f64>>>,
    /// RMS of the residual the clock was fitted to: plateau edges (s) or lengths (µm).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timeline_rms_s: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub length_rms_um: Option<f64>,
    /// A continuous run: the bar's smoothing c (reading = L + c·L''; see [`sync`]) and its
    /// standard uncertainty (s²), and the average over a window it equals, √(24c) (ms; null
    /// when c ≤ 0, e.g. none).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub smoothing_s2: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub smoothing_std_s2: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub averaging_window_ms: Option<Option<f64>>,
    /// How it was obtained, for people.
    pub method: String,
}

impl ClockReport {
    /// The largest change, between this clock and `other`, of the reference time a bar time
    /// in `[from, to]` (s, the bar's clock) is mapped to (s): how far a new synchronisation
    /// moved the samples of a run.
    pub fn moved_from(&self, other: &ClockReport, from: f64, to: f64) -> f64 {
        let at = |c: &ClockReport, u: f64| (u - c.offset_s) / (1.0 + c.drift_ppm * 1e-6);
        [from, to]
            .iter()
            .map(|&u| (at(self, u) - at(other, u)).abs())
            .fold(0.0, f64::max)
    }
}

/// The stop-and-measure clock from the timeline's per-section offsets (program time with
/// pauses as zero): one offset, that of the first section (t_ref counts from the program's
/// start with its first pause taken out: the bar, mounted during it, sees nothing of the
/// program before it ends), one drift, and the pauses between sections that the later
/// sections' offsets measure. An offset's uncertainty carries the timeline's and a quarter of
/// a sample interval (the edges' Type B: a plateau starts and ends between two samples).
fn program_clock(tl: &Timeline, interval: f64) -> ClockReport {
    let edge = 0.25 * interval;
    let with_edge = |s: Option<f64>| s.map(|s| s.hypot(edge));
    let first = tl.offsets.iter().position(Option::is_some).unwrap_or(0);
    let rate = 1.0 + tl.drift;
    let mut pauses = Vec::new();
    let mut pauses_std = Vec::new();
    for s in 1..tl.offsets.len() {
        match (tl.offsets[s - 1], tl.offsets[s]) {
            (Some(a), Some(b)) => {
                pauses.push(Some((b - a) / rate));
                pauses_std.push(
                    match (with_edge(tl.offset_std[s - 1]), with_edge(tl.offset_std[s])) {
                        (Some(x), Some(y)) => Some(x.hypot(y) / rate),
                        _ => None,
                    },
                );
            }
            _ => {
                pauses.push(None);
                pauses_std.push(None);
            }
        }
    }
    ClockReport {
        reference: "program",
        t_ref: if first == 0 {
            "the controller's time running the program, from its start, with its first pause (the bar's mounting) taken out: the bar sees nothing before it".into()
        } else {
            format!("the controller's time running the program, from its start, with every pause up to section {}'s mounting taken out (no pose of the sections before it matched)", first + 1)
        },
        offset_s: tl.offsets[first].unwrap_or(0.0),
        offset_std_s: with_edge(tl.offset_std[first]),
        drift_ppm: tl.drift * 1e6,
        drift_std_ppm: tl.drift_std.map(|s| s * 1e6),
        pauses_s: Some(pauses[first.min(pauses.len())..].to_vec()),
        pauses_std_s: Some(pauses_std[first.min(pauses_std.len())..].to_vec()),
        timeline_rms_s: Some(tl.rms),
        length_rms_um: None,
        method: "plateau edges against the program's dwell and move times, one offset per section (the pauses' lengths are unknown), one drift, robust least squares; the controller's stops taken out. The drift includes any difference between the controller's and the program's move times".into(),
        smoothing_s2: None,
        smoothing_std_s2: None,
        averaging_window_ms: None,
    }
}

/// A stop-and-measure run read from a bar log: the matched readings (in pose order) and
/// everything the report says about how they were found.
#[derive(Clone, Debug, PartialEq)]
pub struct StopAndMeasure {
    /// Per matched pose: (slot index into the template, plateau index).
    pub readings: Vec<(usize, usize)>,
    pub plateaus: Vec<Plateau>,
    pub alignment: Alignment,
    /// The bar clock's first sample (s): readings' times count from it.
    pub t0: f64,
    pub report: Vec<PlateauReport>,
    /// Poses without a plateau (1-based).
    pub missing: Vec<usize>,
    pub clock: ClockReport,
    /// The bar's zero: mean of reading − nominal length (m), its spread over the poses and its
    /// standard uncertainty.
    pub zero: f64,
    pub zero_std: f64,
}

/// The header's list of measurement poses of a stop-and-measure program (`measure a-b of N:
/// L v, v, ... mm`, written by every dialect's template), in order (m); None when the program
/// has none. Every dialect's reader hands the header comments over as `key: value` lines
/// (FANUC's 32-character remarks joined back).
pub fn measure_list(parsed: &crate::dialect::Parsed) -> Result<Option<Vec<f64>>, String> {
    let mut out: Vec<f64> = Vec::new();
    let mut total: Option<usize> = None;
    for h in &parsed.header {
        let Some(rest) = h.strip_prefix("measure ") else {
            continue;
        };
        let bad = || format!("header line '{h}' is not 'measure A-B of N: L v, ... mm'");
        let (range, values) = rest.split_once(':').ok_or_else(bad)?;
        let (ab, n) = range.split_once(" of ").ok_or_else(bad)?;
        let (a, b) = ab.split_once('-').ok_or_else(bad)?;
        let (a, b, n): (usize, usize, usize) = (
            a.trim().parse().map_err(|_| bad())?,
            b.trim().parse().map_err(|_| bad())?,
            n.trim().parse().map_err(|_| bad())?,
        );
        let v = values
            .trim()
            .strip_prefix('L')
            .and_then(|r| r.trim().strip_suffix("mm"))
            .ok_or_else(bad)?;
        let v: Vec<f64> = v
            .split(',')
            .map(|x| x.trim().parse::<f64>().map(|x| x * crate::units::MM))
            .collect::<Result<_, _>>()
            .map_err(|_| bad())?;
        if a != out.len() + 1 || b + 1 != a + v.len() || total.is_some_and(|t| t != n) {
            return Err(format!("header line '{h}': poses out of order"));
        }
        total = Some(n);
        out.extend(v);
    }
    match total {
        None => Ok(None),
        Some(n) if n == out.len() => Ok(Some(out)),
        Some(n) => Err(format!(
            "the header lists {} of its {n} measurement poses",
            out.len()
        )),
    }
}

/// The shortest time (s) a run of the template can take: its dwells and its moves, pauses
/// of no length. A log that covers less cannot hold the run.
pub fn program_time(tpl: &Template) -> f64 {
    let mut t = 0.0;
    let mut section = usize::MAX;
    let mut start = 0.0;
    let mut last = 0.0;
    for s in &tpl.slots {
        if s.section != section {
            t += last - start;
            section = s.section;
            start = s.start;
        }
        last = s.end;
    }
    t + last - start
}

/// Reads a stop-and-measure run: the plateaus of `bar`, matched to `tpl`'s poses.
pub fn stop_and_measure(tpl: &Template, bar: &BarLog) -> Result<StopAndMeasure, LogsError> {
    let dwell = tpl.dwell;
    let span = bar.t.last().copied().unwrap_or(0.0) - bar.t.first().copied().unwrap_or(0.0);
    let need = program_time(tpl);
    if span < 0.9 * need {
        return Err(bad(format!(
            "t_s: the log covers {} s, the program's {} dwells and moves take at least {} s: the log is shorter than the program",
            fmt_fixed(span, 1),
            tpl.slots.len(),
            fmt_fixed(need, 1)
        )));
    }
    let (plateaus, stats) = match plateau::detect(&bar.t, &bar.length, dwell, MIN_PLATEAU_SHARE * dwell)
    {
        Ok(x) => x,
        Err(e) if span > 100.0 * need => {
            return Err(bad(format!(
                "t_s: the log spans {} s for a program of {} s: is the time in another unit (milliseconds)? ({e})",
                fmt_fixed(span, 0),
                fmt_fixed(need, 1)
            )))
        }
        Err(e) => return Err(bad(e.to_string())),
    };
    if plateaus.is_empty() {
        return Err(bad(format!(
            "no plateau: the reading never stands still for {} s (half the program's {} s dwell); is this the log of a stop-and-measure run?",
            fmt_fixed(MIN_PLATEAU_SHARE * dwell, 2),
            fmt_fixed(dwell, 2)
        )));
    }
    let obs: Vec<Observed> = plateaus
        .iter()
        .map(|p| Observed {
            from: p.from,
            to: p.to,
            mean: p.mean,
            cut_before: p.cut_before,
            cut_after: p.cut_after,
        })
        .collect();
    if std::env::var_os("EDBB_DEBUG").is_some() {
        for (j, o) in obs.iter().enumerate() {
            eprintln!(
                "plateau {j}: {:.2}..{:.2} {:.3} mm",
                o.from,
                o.to,
                o.mean * 1e3
            );
        }
    }
    let gap = (3.0 * stats.interval).max(0.05);
    let gaps: Vec<(f64, f64)> = bar
        .t
        .windows(2)
        .filter(|w| w[1] - w[0] > gap)
        .map(|w| (w[0], w[1]))
        .collect();
    let alignment = match align::align(tpl, &obs, &gaps, stats.interval) {
        Ok(a) => a,
        Err(e) => return Err(bad(explain(tpl, bar, &plateaus, span, e))),
    };
    let matched = alignment.matched.iter().filter(|m| m.is_some()).count();
    if 2 * matched < tpl.slots.len() {
        return Err(bad(explain(
            tpl,
            bar,
            &plateaus,
            span,
            align::AlignError::NoMatch(format!(
                "only {matched} of {} poses matched a plateau",
                tpl.slots.len()
            )),
        )));
    }
    // A plateau inside a section longer than its dwell holds a stop of the controller next to
    // the pose: the reading is its last dwell, where the robot surely stood at the pose.
    let mut plateaus = plateaus;
    for (k, m) in alignment.matched.iter().enumerate() {
        let (s, Some(j)) = (&tpl.slots[k], *m) else {
            continue;
        };
        let p = &plateaus[j];
        if !s.after_pause
            && !s.before_pause
            && p.to - p.from > align::longest_dwell(dwell, stats.interval)
        {
            if let Some(q) = plateau::tail(&bar.t, &bar.length, p, dwell, stats.rate) {
                plateaus[j] = q;
            }
        }
    }
    let t0 = bar.t.first().copied().unwrap_or(0.0);
    let mut pose_of = vec![None; plateaus.len()];
    let mut readings = Vec::new();
    let mut missing = Vec::new();
    for (k, m) in alignment.matched.iter().enumerate() {
        match m {
            Some(j) => {
                pose_of[*j] = Some(tpl.slots[k].pose);
                readings.push((k, *j));
            }
            None => missing.push(tpl.slots[k].pose),
        }
    }
    let report = plateaus
        .iter()
        .zip(&pose_of)
        .map(|(p, pose)| PlateauReport {
            pose: *pose,
            t_from_s: p.from,
            t_to_s: p.to,
            rows: [p.first_row + 1, p.last_row + 1],
            samples: p.samples,
            mean_mm: to_mm(p.mean),
            spread_um: p.spread * 1e6,
            std_um: p.std * 1e6,
        })
        .collect();
    let clock = program_clock(&alignment.timeline, stats.interval);
    Ok(StopAndMeasure {
        readings,
        zero: alignment.zero,
        zero_std: alignment.zero_std,
        plateaus,
        alignment,
        t0,
        report,
        missing,
        clock,
    })
}

/// A failed match, with the likeliest reason when the log itself looks wrong: lengths in
/// another unit, times in another unit.
fn explain(
    tpl: &Template,
    bar: &BarLog,
    plateaus: &[Plateau],
    span: f64,
    e: align::AlignError,
) -> String {
    let spread = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let n = v.len();
        if n < 4 {
            return 0.0;
        }
        v[(9 * n) / 10 - 1] - v[n / 10]
    };
    // The readings as a whole (plateaus may be few when the unit hides every motion).
    let a = spread(bar.length.clone());
    let b = spread(tpl.slots.iter().map(|s| s.length).collect());
    if b > 0.0 && a > 0.0 && !(0.2..=5.0).contains(&(a / b)) {
        return format!(
            "length_mm: the readings span {} mm where the program's poses span {} mm: is the length in another unit? ({e})",
            fmt_fixed(to_mm(a), 4),
            fmt_fixed(to_mm(b), 3)
        );
    }
    let mut durations: Vec<f64> = plateaus.iter().map(|p| p.to - p.from).collect();
    durations.sort_by(f64::total_cmp);
    let typical = durations.get(durations.len() / 2).copied().unwrap_or(0.0);
    if typical > 20.0 * tpl.dwell && span > 100.0 * program_time(tpl) {
        return format!(
            "t_s: the plateaus last {} s where the program dwells {} s: is the time in another unit? ({e})",
            fmt_fixed(typical, 1),
            fmt_fixed(tpl.dwell, 2)
        );
    }
    e.to_string()
}

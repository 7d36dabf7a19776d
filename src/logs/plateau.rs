//! Plateaus of a bar log: in = the log (its own clock, any rate, gaps) and the dwell the
//! program commands; out = every stretch where the reading stands still long enough to be a
//! dwell, with its core mean and the mean's standard uncertainty.
//!
//! A sample is *still* when the means of the readings just before and just after it (half
//! windows of `h` seconds) agree within a trend tolerance and no reading of the window strays
//! from their mean by more than a range tolerance: a motion is a trend (the bar changes by
//! millimetres per second while the robot moves), a vibration of the standing robot is not.
//! Still runs (no gap in the log) that a short blip or gap splits, at the same level, are one
//! plateau; the edges are then grown sample by sample while the reading stays at the
//! plateau's level. The mean uses the core (`core_trim` in from either end); its
//! uncertainty is the core's spread over √n, inflated by (1 + ρ)/(1 − ρ) for the lag-1
//! correlation ρ of the core (a vibration's samples are not independent).

use super::core_trim;
use crate::stats::median_in_place;

/// Trend and range tolerances never fall below these (m): a bar's resolution and the
/// standstill jitter of a stopped robot; a vibration of the standing robot within the range
/// tolerance keeps its plateau (its spread goes into the uncertainty).
pub const TREND_FLOOR: f64 = 5e-6;
pub const RANGE_FLOOR: f64 = 50e-6;
/// Still runs closer than this (s) at the same level (within `MERGE_FLOOR` m or 8 noise
/// sigmas) are one plateau: a vibration burst or a dropout inside a dwell.
pub const MERGE_GAP: f64 = 0.5;
pub const MERGE_FLOOR: f64 = 20e-6;

/// One plateau of a bar log (bar clock, s; lengths m).
#[derive(Clone, Debug, PartialEq)]
pub struct Plateau {
    /// First and last still sample (bar clock).
    pub from: f64,
    pub to: f64,
    /// The log rows of those samples (0-based, inclusive).
    pub first_row: usize,
    pub last_row: usize,
    /// The core samples' mean, their standard deviation, their count and the mean's standard
    /// uncertainty.
    pub mean: f64,
    pub spread: f64,
    pub samples: usize,
    pub std: f64,
    /// Middle of the core (bar clock): the reading's time.
    pub t: f64,
    /// The plateau begins (ends) at a gap in the log or at the log's start (end): the
    /// standstill may have begun earlier (lasted longer) than the log shows.
    pub cut_before: bool,
    pub cut_after: bool,
}

impl Plateau {
    pub fn duration(&self) -> f64 {
        self.to - self.from
    }
}

/// What the detection saw in the log as a whole.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogStats {
    /// Median sample interval (s) and the rate it implies (Hz).
    pub interval: f64,
    pub rate: f64,
    /// Noise of one reading (m), from the quietest successive differences.
    pub noise: f64,
    /// Half window of the stillness test (s).
    pub half_window: f64,
}

/// Why no plateau list can be made.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PlateauError {
    #[error("{0}")]
    Log(String),
}

/// The log's sampling and noise; the half window suits `dwell` seconds of standstill.
pub fn stats(t: &[f64], l: &[f64], dwell: f64) -> Result<LogStats, PlateauError> {
    if t.len() < 3 {
        return Err(PlateauError::Log(format!(
            "{} rows: no plateau can be found in so short a log",
            t.len()
        )));
    }
    let mut dt: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
    // Not empty: at least three rows.
    let interval = median_in_place(&mut dt).unwrap_or(f64::NAN);
    let rate = 1.0 / interval;
    let gap = gap_limit(interval);
    // The quietest fifth of the successive differences: half-normal with scale σ√2.
    let mut d: Vec<f64> = t
        .windows(2)
        .zip(l.windows(2))
        .filter(|(tw, _)| tw[1] - tw[0] <= gap)
        .map(|(_, lw)| (lw[1] - lw[0]).abs())
        .collect();
    let noise = if d.len() >= 10 {
        let k = d.len() / 5;
        d.select_nth_unstable_by(k, f64::total_cmp);
        d[k] / (0.2534 * std::f64::consts::SQRT_2)
    } else {
        0.0
    };
    let half_window = (3.0 / rate).max((0.1f64).min(dwell / 4.0));
    if half_window > dwell / 2.0 {
        return Err(PlateauError::Log(format!(
            "the log's rate ({} Hz) leaves too few samples in a {} s dwell to tell a standstill from a motion: log at {} Hz or more, or dwell longer",
            crate::units::fmt_fixed(rate, 1),
            crate::units::fmt_fixed(dwell, 2),
            crate::units::fmt_fixed(12.0 / dwell, 0)
        )));
    }
    Ok(LogStats {
        interval,
        rate,
        noise,
        half_window,
    })
}

/// Successive samples further apart than this (s) are a gap in the log.
fn gap_limit(interval: f64) -> f64 {
    (3.0 * interval).max(0.05)
}

/// The plateaus of a bar log at least `min_duration` seconds long, in time order.
pub fn detect(
    t: &[f64],
    l: &[f64],
    dwell: f64,
    min_duration: f64,
) -> Result<(Vec<Plateau>, LogStats), PlateauError> {
    let st = stats(t, l, dwell)?;
    let n = t.len();
    let gap = gap_limit(st.interval);
    let trend_tol = |nl: usize, nr: usize| {
        (6.0 * st.noise * (1.0 / nl as f64 + 1.0 / nr as f64).sqrt()).max(TREND_FLOOR)
    };
    let range_tol = (8.0 * st.noise).max(RANGE_FLOOR);
    // Gap-free runs of the log: the stillness test never looks across a gap.
    let mut run_id = vec![0usize; n];
    for k in 1..n {
        run_id[k] = run_id[k - 1] + usize::from(t[k] - t[k - 1] > gap);
    }
    let mut prefix = vec![0.0f64; n + 1];
    for k in 0..n {
        prefix[k + 1] = prefix[k] + l[k];
    }
    let h = st.half_window;
    let mut still = vec![false; n];
    let (mut lo, mut hi) = (0usize, 0usize);
    // The window's extremes: monotone queues of indices (both ends only move forward).
    let mut maxq: std::collections::VecDeque<usize> = Default::default();
    let mut minq: std::collections::VecDeque<usize> = Default::default();
    let push =
        |q: &mut std::collections::VecDeque<usize>, k: usize, better: &dyn Fn(f64, f64) -> bool| {
            while q.back().is_some_and(|&b| !better(l[b], l[k])) {
                q.pop_back();
            }
            q.push_back(k);
        };
    push(&mut maxq, 0, &|a, b| a > b);
    push(&mut minq, 0, &|a, b| a < b);
    for i in 0..n {
        while lo < i && (t[i] - t[lo] > h || run_id[lo] != run_id[i]) {
            lo += 1;
        }
        if hi < i {
            hi = i;
            push(&mut maxq, i, &|a, b| a > b);
            push(&mut minq, i, &|a, b| a < b);
        }
        while hi + 1 < n && t[hi + 1] - t[i] <= h && run_id[hi + 1] == run_id[i] {
            hi += 1;
            push(&mut maxq, hi, &|a, b| a > b);
            push(&mut minq, hi, &|a, b| a < b);
        }
        while maxq.front().is_some_and(|&f| f < lo) {
            maxq.pop_front();
        }
        while minq.front().is_some_and(|&f| f < lo) {
            minq.pop_front();
        }
        let (nl, nr) = (i - lo, hi - i);
        if nl < 2 || nr < 2 {
            continue;
        }
        let ml = (prefix[i] - prefix[lo]) / nl as f64;
        let mr = (prefix[hi + 1] - prefix[i + 1]) / nr as f64;
        if (mr - ml).abs() > trend_tol(nl, nr) {
            continue;
        }
        let m = (prefix[hi + 1] - prefix[lo]) / (hi + 1 - lo) as f64;
        let (top, bottom) = match (maxq.front(), minq.front()) {
            (Some(&a), Some(&b)) => (l[a], l[b]),
            _ => continue,
        };
        still[i] = top - m <= range_tol && m - bottom <= range_tol;
    }
    // Still runs: (first, last) sample indices.
    let mut runs: Vec<(usize, usize)> = Vec::new();
    let mut k = 0;
    while k < n {
        if !still[k] {
            k += 1;
            continue;
        }
        let a = k;
        while k + 1 < n && still[k + 1] && run_id[k + 1] == run_id[a] {
            k += 1;
        }
        runs.push((a, k));
        k += 1;
    }
    let level = |a: usize, b: usize| {
        let mut v = l[a..=b].to_vec();
        median_in_place(&mut v).unwrap_or(f64::NAN)
    };
    // Merge runs a blip or a short gap splits, at the same level.
    let merge_tol = (8.0 * st.noise).max(MERGE_FLOOR);
    let mut merged: Vec<(usize, usize)> = Vec::new();
    for r in runs {
        if let Some(last) = merged.last_mut() {
            if t[r.0] - t[last.1] <= MERGE_GAP
                && (level(last.0, last.1) - level(r.0, r.1)).abs() <= merge_tol
            {
                last.1 = r.1;
                continue;
            }
        }
        merged.push(r);
    }
    // Grow the edges while the reading stays at the level, within the run's own scatter (a
    // vibration's included), and no gap intervenes.
    let mut out = Vec::new();
    let mut floor = 0usize;
    for (mut a, mut b) in merged {
        let lev = level(a, b);
        let count = (b - a + 1) as f64;
        let sd = (l[a..=b].iter().map(|x| (x - lev).powi(2)).sum::<f64>() / count).sqrt();
        let edge_tol = (4.0 * st.noise).max(3.0 * sd).max(TREND_FLOOR);
        while a > floor && t[a] - t[a - 1] <= gap && (l[a - 1] - lev).abs() <= edge_tol {
            a -= 1;
        }
        while b + 1 < n && t[b + 1] - t[b] <= gap && (l[b + 1] - lev).abs() <= edge_tol {
            b += 1;
        }
        floor = b + 1;
        if t[b] - t[a] < min_duration {
            continue;
        }
        if let Some(mut p) = summarise(t, l, a, b, st.rate) {
            p.cut_before = a == 0 || t[a] - t[a - 1] > gap;
            p.cut_after = b + 1 == n || t[b + 1] - t[b] > gap;
            out.push(p);
        }
    }
    Ok((out, st))
}

/// The last `span` seconds of plateau `p` of the log (t, l), summarised as a plateau of its
/// own (the gap flag at its end kept); None when too few samples remain.
pub fn tail(t: &[f64], l: &[f64], p: &Plateau, span: f64, rate: f64) -> Option<Plateau> {
    let a = (p.first_row..=p.last_row).find(|&k| t[k] >= p.to - span)?;
    let mut q = summarise(t, l, a, p.last_row, rate)?;
    q.cut_after = p.cut_after;
    Some(q)
}

/// The plateau over rows a..=b: its core's mean, spread and the mean's uncertainty.
fn summarise(t: &[f64], l: &[f64], a: usize, b: usize, rate: f64) -> Option<Plateau> {
    let (from, to) = (t[a], t[b]);
    let trim = core_trim(to - from, rate);
    let idx: Vec<usize> = (a..=b)
        .filter(|&k| t[k] >= from + trim && t[k] <= to - trim)
        .collect();
    let n = idx.len();
    if n < super::MIN_PLATEAU_SAMPLES {
        return None;
    }
    let mean = idx.iter().map(|&k| l[k]).sum::<f64>() / n as f64;
    let var = idx.iter().map(|&k| (l[k] - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    let spread = var.sqrt();
    let rho = if var > 0.0 {
        let c: f64 = idx
            .windows(2)
            .map(|w| (l[w[0]] - mean) * (l[w[1]] - mean))
            .sum::<f64>()
            / ((n - 1) as f64 * var);
        c.clamp(0.0, 0.95)
    } else {
        0.0
    };
    let std = spread / (n as f64).sqrt() * ((1.0 + rho) / (1.0 - rho)).sqrt();
    Some(Plateau {
        from,
        to,
        first_row: a,
        last_row: b,
        mean,
        spread,
        samples: n,
        std,
        t: 0.5 * (t[idx[0]] + t[idx[n - 1]]),
        cut_before: false,
        cut_after: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A log written by hand: stand, ramp, stand (with a vibration), ramp, stand, at `rate`.
    fn staircase(rate: f64, seed: u64) -> (Vec<f64>, Vec<f64>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut t = Vec::new();
        let mut l = Vec::new();
        let level = |x: f64| -> f64 {
            // 0-2 s at 400 mm; 2-2.5 ramp to 420; 2.5-4.5 at 420; 4.5-5 ramp to 410; 5-7 at 410.
            match x {
                x if x < 2.0 => 0.400,
                x if x < 2.5 => 0.400 + 0.020 * (x - 2.0) / 0.5,
                x if x < 4.5 => 0.420 + 10e-6 * (std::f64::consts::TAU * 15.0 * x).sin(),
                x if x < 5.0 => 0.420 - 0.010 * (x - 4.5) / 0.5,
                _ => 0.410,
            }
        };
        let mut x = 0.0;
        while x < 7.0 {
            t.push(x);
            let u1: f64 = rng.random_range(1e-12..1.0);
            let u2: f64 = rng.random();
            let g = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
            l.push(level(x) + 0.5e-6 * g);
            x += 1.0 / rate;
        }
        (t, l)
    }

    #[test]
    fn finds_the_three_stands_of_a_staircase_at_any_rate() {
        for rate in [25.0, 50.0, 500.0] {
            let (t, l) = staircase(rate, 3);
            let (p, st) = detect(&t, &l, 2.0, 1.0).unwrap();
            assert!((st.rate - rate).abs() < 1e-6 * rate);
            assert!(st.noise > 0.2e-6 && st.noise < 1.5e-6, "{}", st.noise);
            assert_eq!(p.len(), 3, "{rate} Hz: {p:?}");
            let want = [(0.0, 2.0, 0.400), (2.5, 4.5, 0.420), (5.0, 7.0, 0.410)];
            for (q, (a, b, m)) in p.iter().zip(want) {
                let dt = 2.0 / rate + 0.02;
                assert!((q.from - a).abs() <= dt, "{rate}: from {} vs {a}", q.from);
                assert!(
                    (q.to - b).abs() <= dt + 1.0 / rate,
                    "{rate}: to {} vs {b}",
                    q.to
                );
                assert!((q.mean - m).abs() < 4e-6, "{rate}: mean {} vs {m}", q.mean);
                assert!(q.std > 0.0 && q.std < 3e-6);
            }
            // The vibrating stand: its spread is the vibration's (10 µm amplitude: 7 µm rms).
            assert!(p[1].spread > 5e-6 && p[1].spread < 9e-6, "{}", p[1].spread);
            assert!(p[0].spread < 1e-6);
        }
    }

    #[test]
    fn a_gap_inside_a_stand_is_bridged_a_long_one_splits_it() {
        let (t, l) = staircase(50.0, 4);
        let cut = |from: f64, to: f64| -> (Vec<f64>, Vec<f64>) {
            t.iter()
                .zip(&l)
                .filter(|(x, _)| **x < from || **x >= to)
                .map(|(a, b)| (*a, *b))
                .unzip()
        };
        let (t1, l1) = cut(0.8, 1.0);
        let (p, _) = detect(&t1, &l1, 2.0, 1.0).unwrap();
        assert_eq!(p.len(), 3);
        assert!(p[0].from < 0.05 && p[0].to > 1.9, "{:?}", p[0]);
        let (t2, l2) = cut(0.6, 1.4);
        let (p, _) = detect(&t2, &l2, 2.0, 1.0).unwrap();
        assert_eq!(
            p.len(),
            2,
            "the first stand is cut into two short pieces: {p:?}"
        );
    }

    #[test]
    fn too_slow_a_log_is_refused_with_its_rate() {
        let t: Vec<f64> = (0..20).map(|k| k as f64).collect();
        let l = vec![0.4; 20];
        let e = detect(&t, &l, 2.0, 1.0).unwrap_err();
        assert!(e.to_string().contains("1.0 Hz"), "{e}");
    }
}

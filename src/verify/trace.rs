//! A recorded run of a program (`verify --trace`): in = the trace CSV (DESIGN.md "Trace":
//! `t_s,q1_deg,...,q6_deg` in the controller's axis values as the program writes them, any
//! rate), the controller mapping and the motion `verify` rebuilt from the program text; out = a
//! [`TraceReport`] (how close the run passed each measurement pose at the MAP, executed and
//! estimated time), or the first [`Failure`] of the executed path against the cell.
//!
//! The trace is matched to the program by itself: the program's targets are found along it in
//! order (each where the trace comes closest before it turns towards the next one), which gives
//! the mount state (the bar is in place from a mounted move's start pose to its end pose) and
//! the pose passes. Every step between two samples is checked as a straight joint move with the
//! checker of its mount state: the cell, the joint and harness limits, and while the bar is
//! mounted its range and cones, continuously.

use super::{Executed, Failure};
use crate::controller::ControllerMap;
use crate::ir::Reason;
use crate::safety::{Checker, Extremes, Violation};
use crate::units::{fmt_fixed, to_mm, DEG};
use serde::{Deserialize, Serialize};

/// The trace contract's header.
pub const HEADER: &str = "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg";

/// A recorded joint trajectory in model joints (rad).
#[derive(Clone, Debug, PartialEq)]
pub struct Trace {
    pub t: Vec<f64>,
    pub q: Vec<[f64; 6]>,
}

/// Reads a trace: the exact header (extra columns after the six joints are allowed), one
/// sample per row, strictly increasing times, finite numbers; the controller mapping undone.
/// Errors name the line.
pub fn read(text: &str, map: &ControllerMap) -> Result<Trace, String> {
    let mut lines = text.lines().enumerate();
    let (_, head) = lines.next().ok_or("empty: no header")?;
    let head = head.trim_end_matches('\r');
    if !(head == HEADER || head.starts_with(&format!("{HEADER},"))) {
        return Err(format!("line 1: the header must be {HEADER}"));
    }
    let (mut t, mut q) = (Vec::new(), Vec::new());
    for (i, line) in lines {
        let line = line.trim_end_matches('\r');
        if line.trim().is_empty() {
            continue;
        }
        let n = i + 1;
        let v: Vec<&str> = line.split(',').collect();
        if v.len() < 7 {
            return Err(format!("line {n}: 7 columns expected, found {}", v.len()));
        }
        let mut x = [0.0; 7];
        for k in 0..7 {
            x[k] = v[k]
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| format!("line {n}: column {}: '{}' is not a number", k + 1, v[k]))?;
        }
        if let Some(&last) = t.last() {
            if x[0] <= last {
                return Err(format!("line {n}: t_s {} does not increase", v[0].trim()));
            }
        }
        t.push(x[0]);
        let axes: [f64; 6] = std::array::from_fn(|k| x[k + 1]);
        q.push(map.undo(&axes).map(|d| d * DEG));
    }
    if t.len() < 2 {
        return Err("fewer than two samples".into());
    }
    Ok(Trace { t, q })
}

/// How close the run passed one measurement pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PosePass {
    /// Measurement pose number in the program (1-based, support poses not counted).
    pub pose: usize,
    /// The program line of its motion.
    pub line: usize,
    /// The MAP's closest distance to its place at the pose (mm).
    pub miss_mm: f64,
    /// When (s, trace time).
    pub t_s: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TraceReport {
    pub samples: usize,
    pub poses: Vec<PosePass>,
    pub worst_miss_mm: f64,
    /// The program's motion in the trace, pauses left out (from leaving each pause pose to
    /// arriving at the next), and the program's own estimate of it (s).
    pub executed_s: f64,
    pub estimated_s: f64,
    pub extremes: Extremes,
}

/// Matches the trace to the program's rebuilt motion and checks the executed path.
pub fn check(
    ck: &Checker,
    executed: &[Executed],
    trace: &Trace,
    estimated: f64,
) -> Result<TraceReport, Failure> {
    let n = trace.q.len();
    let dist =
        |a: &[f64; 6], b: &[f64; 6]| (0..6).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt();
    let model = ck.model;
    let map_at = |q: &[f64; 6]| model.map_position(&model.nominal, q);
    // Where the trace arrives at each target, and the MAP's closest pass.
    let mut arrive = Vec::with_capacity(executed.len());
    let mut passes = Vec::new();
    let mut cur = 0;
    let mut pose_no = 0;
    for (j, m) in executed.iter().enumerate() {
        let next = executed.get(j + 1).map(|x| x.target);
        // Once the trace is this much farther than its closest, it has gone on.
        let onward = next.map_or(f64::INFINITY, |b| {
            (0.25 * dist(&m.target, &b)).max(0.2 * DEG)
        });
        let target_map = map_at(&m.target);
        let (mut best, mut at) = (f64::INFINITY, cur);
        let mut best_map = f64::INFINITY;
        let mut i = cur;
        while i < n {
            let d = dist(&trace.q[i], &m.target);
            if d < best {
                best = d;
                at = i;
            }
            if !m.support {
                best_map = best_map.min((map_at(&trace.q[i]) - target_map).norm());
            }
            if d > best + onward {
                break;
            }
            i += 1;
        }
        if !best.is_finite() || (i == n && j + 1 < executed.len()) {
            return Err(super::fail(
                m.line,
                0.0,
                Reason::Program,
                "the trace does not follow the program: it ends before this move's target".into(),
            ));
        }
        arrive.push(at);
        cur = at;
        if !m.support {
            pose_no += 1;
            passes.push(PosePass {
                pose: pose_no,
                line: m.line,
                miss_mm: to_mm(best_map),
                t_s: trace.t[at],
            });
        }
    }
    // Mount state per sample: in place from a mounted move's start pose to its end pose.
    let mut mounted = vec![false; n];
    for j in 1..executed.len() {
        if executed[j].mounted {
            for m in mounted.iter_mut().take(arrive[j] + 1).skip(arrive[j - 1]) {
                *m = true;
            }
        }
    }
    let free = ck.unmounted();
    let mut ext = Extremes::default();
    for i in 0..n {
        let with = if mounted[i] { ck } else { &free };
        let fail = |v: Violation| Failure {
            line: 0,
            time: trace.t[i],
            violation: Violation {
                reason: v.reason,
                detail: format!(
                    "in the trace at t = {} s{}: {}",
                    fmt_fixed(trace.t[i], 3),
                    if mounted[i] { " (bar mounted)" } else { "" },
                    v.detail
                ),
            },
        };
        if i + 1 < n && mounted[i + 1] == mounted[i] {
            if trace.q[i + 1] != trace.q[i] || i == 0 {
                let mut e = Extremes::default();
                with.line(&trace.q[i], &trace.q[i + 1], &mut e)
                    .map_err(|(_, v)| fail(v))?;
                ext.merge(&e);
            }
        } else {
            let info = with.pose(&trace.q[i]).map_err(fail)?;
            let _ = info;
        }
    }
    // Executed time: from leaving each pause pose (or the approach's end) to arriving at the
    // next one, so the operator's pauses are left out.
    let still = |a: usize, b: usize| dist(&trace.q[a], &trace.q[b]) < 1e-9;
    let mut executed_s = 0.0;
    let mut from: Option<usize> = None;
    for (j, m) in executed.iter().enumerate() {
        let at = arrive[j];
        if let Some(f) = from {
            if j > 0 && (m.pause_after || j + 1 == executed.len()) {
                executed_s += trace.t[at] - trace.t[f];
                from = None;
            }
        }
        if from.is_none() && (j == 0 || m.pause_after) {
            // The last sample still standing at this pose.
            let mut leave = at;
            while leave + 1 < n && still(leave + 1, at) {
                leave += 1;
            }
            from = Some(leave);
        }
    }
    let worst = passes.iter().map(|p| p.miss_mm).fold(0.0, f64::max);
    Ok(TraceReport {
        samples: n,
        poses: passes,
        worst_miss_mm: worst,
        executed_s,
        estimated_s: estimated,
        extremes: ext,
    })
}

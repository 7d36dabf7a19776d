//! Compensated programs: in = a joint-move program in one of the six dialects (the subset its
//! reader takes), the controller mapping and a [`Compensator`]; out = the same program with
//! every move's joint values replaced by the compensated ones — the same text otherwise (lines,
//! comments, speeds, blends, pauses), plus one header comment that says it is compensated.
//!
//! The program is read with the dialect's own reader ([`crate::dialect`]): a line outside the
//! subset it takes is refused with its number. Each move's target (the nominal controller's
//! joints) is compensated as a joint target ([`Compensator::compensate`]); a move that cannot be
//! compensated is listed with its line and reason, and nothing is written. The new values are
//! printed with more decimals than a planned program needs where the language carries them
//! ([`crate::dialect::Language::decimals`]) and written by the dialect's writer where its reader
//! found the old ones ([`crate::dialect::Language::write`]: in FANUC LS, the position in `/POS`;
//! in RAPID, a declared jointtarget's declaration); this module never looks into the text
//! itself. A move whose text states its duration (G93 F, RAPID `\T`, URScript `t`, FANUC `sec`)
//! and would now ask an axis for more than its speed is slowed by the ratio of its Eq. 7 times.
//! Finally the new text is read back: it must command the same steps with exactly the
//! compensated values, no move faster than the axes allow.

use super::{round6, Compensated, Compensator, Status, Target};
use crate::controller::{ControllerMap, Units};
use crate::dialect::{apply, Dialect, MoveTime, NewValues, Parsed, Step, Timing, WriteError};
use crate::order::move_time;
use crate::timing::Limits;
use crate::units::{fmt_fixed, DEG};

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ProgramError {
    /// The dialect's reader refused the text.
    #[error("{dialect} program: line {line}: {msg}")]
    Read {
        dialect: String,
        line: usize,
        msg: String,
    },
    /// Read, but outside what compensate rewrites.
    #[error("line {line}: {msg}")]
    Unsupported { line: usize, msg: String },
}

impl From<WriteError> for ProgramError {
    fn from(e: WriteError) -> Self {
        ProgramError::Unsupported {
            line: e.line,
            msg: e.msg,
        }
    }
}

/// A move that cannot be compensated: its line and the reason.
#[derive(Clone, Debug, PartialEq)]
pub struct Refused {
    pub line: usize,
    pub status: Status,
}

/// The compensated program.
#[derive(Clone, Debug, PartialEq)]
pub struct Rewritten {
    pub text: String,
    pub moves: usize,
    pub decimals: usize,
    /// The calibrated robot's TCP position error at the printed values, per move (m).
    pub printed_residual: Vec<f64>,
    /// Lines whose stated duration was lengthened.
    pub retimed: Vec<usize>,
    /// Per move: its line and the model joints as printed (rad).
    pub joints: Vec<(usize, [f64; 6])>,
    /// The largest change of a joint by the compensation (rad).
    pub largest_change: f64,
}

pub enum Outcome {
    Written(Rewritten),
    Refused(Vec<Refused>),
}

fn unsupported(line: usize, msg: impl Into<String>) -> ProgramError {
    ProgramError::Unsupported {
        line,
        msg: msg.into(),
    }
}

/// One move of the program as read: its line, model joints (deg) and timing.
struct Move {
    line: usize,
    target: [f64; 6],
    timing: Timing,
}

/// The shortest time a move a → b (rad) may state: where the dialect's time word is the whole
/// move (RAPID `\T`, URScript `t`), its ramps at the joints' accelerations included; else the
/// time at the cruise (Eq. 7), the ramps on top.
fn shortest(dialect: &Dialect, a: &[f64; 6], b: &[f64; 6], lim: &Limits) -> f64 {
    match dialect.move_time {
        MoveTime::Total => crate::timing::move_time(a, b, lim, 1.0),
        _ => move_time(a, b, &lim.speed),
    }
}

/// Rewrites `text` (in `dialect`, read with `map`) with compensated joints. `lim` are the
/// robot file's joint speeds and accelerations (SI); `note` goes into the header comment.
/// `first` is the direction each joint comes into the program's first move from (+1, −1, 0:
/// not known), for a backlash; every later move comes from the one before.
pub fn rewrite(
    text: &str,
    dialect: &Dialect,
    map: &ControllerMap,
    comp: &Compensator,
    lim: &Limits,
    note: &str,
    first: [f64; 6],
) -> Result<Outcome, ProgramError> {
    let parsed = read(text, dialect, map)?;
    // A rewritten program is its lines joined by `\n`, ending with one: the values are
    // written into that form of the text, read again where the text was in another.
    let mut lines = text.lines().collect::<Vec<_>>().join("\n");
    lines.push('\n');
    let parsed = if lines == text {
        parsed
    } else {
        read(&lines, dialect, map)?
    };
    let text = lines;
    let moves: Vec<Move> = parsed
        .lines
        .iter()
        .filter_map(|l| match &l.step {
            Step::Move { target, timing, .. } => Some(Move {
                line: l.line,
                target: *target,
                timing: *timing,
            }),
            _ => None,
        })
        .collect();
    if moves.is_empty() {
        return Err(unsupported(0, "the program commands no motion"));
    }
    let results = compensated(&moves, comp, first);
    let refused: Vec<Refused> = moves
        .iter()
        .zip(&results)
        .filter(|(_, c)| !c.status.is_ok())
        .map(|(m, c)| Refused {
            line: m.line,
            status: c.status,
        })
        .collect();
    if !refused.is_empty() {
        return Ok(Outcome::Refused(refused));
    }

    let language = dialect.language();
    let dec = language.decimals(map.units);
    let new = printed(&moves, &results, dialect, map, comp, lim, dec)?;
    let edits = language.write(&text, &parsed, &new.values, note, map)?;
    let out = apply(&text, &edits)?;

    // The new text read back: the same steps, exactly the compensated values, no move faster
    // than the axes allow.
    let back = read(&out, dialect, map)?;
    check(&parsed, &back, &new.expected, &new.values, dialect, lim)?;
    Ok(Outcome::Written(Rewritten {
        text: out,
        moves: moves.len(),
        decimals: dec,
        printed_residual: new.printed_residual,
        retimed: new.retimed,
        joints: new.joints,
        largest_change: new.largest_change,
    }))
}

/// Every move compensated as a joint target. Each move comes from the one before, and a
/// backlash rests on the flank of the direction the joint's load side last moved in: the
/// approach of each move is the direction from the load-side joints the move before reaches
/// to the ones this move must reach (where the nominal program holds a joint, the
/// compensation's own change decides: the play is pushed to the new angle). Before its first
/// motion a joint comes from `first`. The load-side targets are the compensation's with the
/// play left out (a first pass).
fn compensated(moves: &[Move], comp: &Compensator, first: [f64; 6]) -> Vec<Compensated> {
    let plain: Vec<(Target, [f64; 6])> = moves
        .iter()
        .map(|m| (Target::Joints(m.target.map(|d| d * DEG)), [0.0; 6]))
        .collect();
    let targets: Vec<(Target, [f64; 6])> = if comp.effects().backlash.is_empty() {
        plain
    } else {
        let load: Vec<Option<[f64; 6]>> = comp
            .compensate_all(&plain)
            .iter()
            .map(|c| c.q.map(|q| comp.load(&q, &[0.0; 6])))
            .collect();
        let ap = super::targets::approach_along(&load, first);
        plain.iter().zip(ap).map(|((t, _), a)| (*t, a)).collect()
    };
    comp.compensate_all(&targets)
}

/// The compensated moves as they will be printed.
struct Printed {
    /// Per move, what its writer writes.
    values: Vec<NewValues>,
    /// Per move, the controller axes as printed.
    expected: Vec<[f64; 6]>,
    printed_residual: Vec<f64>,
    retimed: Vec<usize>,
    joints: Vec<(usize, [f64; 6])>,
    largest_change: f64,
}

/// The compensated joints printed with `dec` decimals, and each move's time or speed
/// percentage lowered where the new move would ask an axis for more than its speed.
fn printed(
    moves: &[Move],
    results: &[Compensated],
    dialect: &Dialect,
    map: &ControllerMap,
    comp: &Compensator,
    lim: &Limits,
    dec: usize,
) -> Result<Printed, ProgramError> {
    let speeds = &lim.speed;
    let k = 10f64.powi(dec as i32);
    let print = |v: f64| -> (String, f64) {
        let r = match map.units {
            Units::Deg => (v * k).round() / k,
            // Radians cut toward zero, as the emitter does: a limit that contains zero keeps
            // the value inside.
            Units::Rad => (v * k).trunc() / k,
        };
        let s = fmt_fixed(r, dec);
        let back = s.parse::<f64>().unwrap_or(r);
        (s, back)
    };
    let mut out = Printed {
        values: Vec::with_capacity(moves.len()),
        expected: Vec::with_capacity(moves.len()),
        printed_residual: Vec::with_capacity(moves.len()),
        retimed: Vec::new(),
        joints: Vec::with_capacity(moves.len()),
        largest_change: 0.0,
    };
    let mut prev: Option<([f64; 6], [f64; 6])> = None; // (old, new) model joints, rad
    let mut prev_axes = [0.0; 6]; // the previous move's new axis values, as printed
    let axis_speeds = map.axis_speeds(speeds);
    for (m, c) in moves.iter().zip(results) {
        let q = c.q.unwrap_or([0.0; 6]);
        let axes = map.apply(&q.map(|r| r / DEG));
        let printed: Vec<(String, f64)> = axes.iter().map(|&v| print(v)).collect();
        let values: [f64; 6] = std::array::from_fn(|i| printed[i].1);
        let new_q = map.undo(&values).map(|d| d * DEG);
        out.printed_residual
            .push(comp.residual(&c.target, &new_q, &c.approach));
        let old_q = m.target.map(|d| d * DEG);
        out.joints.push((m.line, new_q));
        out.largest_change = (0..6).fold(out.largest_change, |a, i| {
            a.max((new_q[i] - old_q[i]).abs())
        });
        let mut time = None;
        let mut percent = None;
        let old_percent = match m.timing {
            Timing::AxisPercent(p) => p,
            _ => [100.0; 6],
        };
        if let Some((po, pn)) = prev {
            let duration = match m.timing {
                Timing::Duration(t) => Some(t),
                _ => None,
            };
            let (t_old, t_new) = if duration.is_some() {
                (
                    shortest(dialect, &po, &old_q, lim),
                    shortest(dialect, &pn, &new_q, lim),
                )
            } else {
                (
                    move_time(&po, &old_q, speeds),
                    move_time(&pn, &new_q, speeds),
                )
            };
            match (duration, m.timing) {
                (Some(t), _) if t < t_new * (1.0 + 1e-9) && t_new > 0.0 => {
                    let scaled = if t_old > 0.0 {
                        t * t_new / t_old
                    } else {
                        t_new
                    };
                    time = Some(scaled.max(t_new * (1.0 + 1e-9)));
                    out.retimed.push(m.line);
                }
                (None, Timing::AxisPercent(p)) => {
                    // A percentage of every axis's speed: the controller times the move on its
                    // axes (J3 may follow J2); lower it where the compensated move would be
                    // faster than the joints allow.
                    let d = m
                        .timing
                        .duration(&prev_axes, &values, &axis_speeds)
                        .unwrap_or(f64::INFINITY);
                    if t_new > 0.0 && d < t_new * (1.0 + 1e-9) {
                        let full = (0..6)
                            .map(|i| (values[i] - prev_axes[i]).abs() / axis_speeds[i])
                            .fold(0.0, f64::max);
                        let most = (100.0 * full / (t_new * (1.0 + 1e-9))).floor().max(1.0);
                        let lowered = p.map(|x| x.min(most));
                        if lowered != p {
                            percent = Some(lowered);
                            out.retimed.push(m.line);
                        }
                    }
                }
                (None, Timing::PathFeed(_) | Timing::LeadSpeed(_)) => {
                    let d = m
                        .timing
                        .duration(
                            &map.apply(&pn.map(|r| r / DEG)),
                            &values,
                            &map.axis_speeds(speeds),
                        )
                        .unwrap_or(f64::INFINITY);
                    if d < t_new * (1.0 - 1e-6) {
                        return Err(unsupported(
                            m.line,
                            "the compensated move would ask an axis for more than its speed, and its feed (G94 F, URScript v) is not one compensate rescales: state the move's time (G93 F, URScript t)",
                        ));
                    }
                }
                _ => {}
            }
        }
        prev = Some((old_q, new_q));
        prev_axes = values;
        out.expected.push(values);
        out.values.push(NewValues {
            axes: std::array::from_fn(|i| printed[i].0.clone()),
            time,
            percent,
            old_percent,
        });
    }
    Ok(out)
}

fn read(text: &str, dialect: &Dialect, map: &ControllerMap) -> Result<Parsed, ProgramError> {
    dialect.read(text, map).map_err(|e| ProgramError::Read {
        dialect: dialect.name.clone(),
        line: e.line,
        msg: e.msg,
    })
}

fn check(
    before: &Parsed,
    after: &Parsed,
    expected: &[[f64; 6]],
    edits: &[NewValues],
    dialect: &Dialect,
    lim: &Limits,
) -> Result<(), ProgramError> {
    let speeds = &lim.speed;
    let steps = |p: &Parsed| -> Vec<(usize, Step)> {
        p.lines.iter().map(|l| (l.line, l.step.clone())).collect()
    };
    let (a, b) = (steps(before), steps(after));
    if a.len() != b.len() {
        return Err(unsupported(
            0,
            "the rewritten program does not read back with the same steps",
        ));
    }
    let mut k = 0;
    let mut prev: Option<([f64; 6], [f64; 6])> = None;
    for ((_, sa), (lb, sb)) in a.iter().zip(&b) {
        let same = match (sa, sb) {
            (
                Step::Move {
                    timing: ta,
                    blend: ba,
                    corner: ca,
                    ..
                },
                Step::Move {
                    target,
                    axes,
                    timing: tb,
                    blend: bb,
                    corner: cb,
                },
            ) => {
                let ok_axes = (0..6).all(|i| {
                    (axes[i] - expected[k][i]).abs() <= 1e-9 * expected[k][i].abs().max(1.0)
                });
                let ok_time = match (ta, tb, edits[k].time, edits[k].percent) {
                    (Timing::Duration(_), Timing::Duration(t), Some(want), _) => {
                        *t >= want * (1.0 - 1e-9)
                    }
                    (Timing::AxisPercent(_), Timing::AxisPercent(p), _, Some(want)) => *p == want,
                    (x, y, None, None) => x == y,
                    _ => false,
                };
                let q = target.map(|d| d * DEG);
                if let Some((pq, pa)) = prev {
                    let min = match tb {
                        Timing::Duration(_) => shortest(dialect, &pq, &q, lim),
                        _ => move_time(&pq, &q, speeds),
                    };
                    let d = after.duration(&pa, sb, speeds).unwrap_or(f64::INFINITY);
                    if d < min * (1.0 - 1e-6) {
                        return Err(unsupported(
                            *lb,
                            "the compensated move would be faster than the axes allow",
                        ));
                    }
                }
                prev = Some((q, *axes));
                k += 1;
                ok_axes && ok_time && ba == bb && ca == cb
            }
            (x, y) => x == y,
        };
        if !same {
            return Err(unsupported(
                *lb,
                "the rewritten line does not read back as the compensated move",
            ));
        }
    }
    Ok(())
}

/// What a rewritten program's report says of it (`file`: its name; `dialect`'s name), and a
/// note when moves leave the cell's joint margin (`margin`: the cell's, None without a cell).
pub fn report(
    w: &Rewritten,
    margin: Option<f64>,
    nominal: &crate::robot::Robot,
    file: String,
    dialect: &str,
) -> (super::ProgramReport, Option<String>) {
    // The cell's joint margin: a pose planned at its edge may cross it by the compensation
    // (hundredths of a degree); say where, and by how much.
    let cell = margin.is_some();
    let margin = margin.unwrap_or(0.0);
    let (lo, hi) = nominal.limits();
    let mut beyond = Vec::new();
    if cell {
        for (line, q) in &w.joints {
            for i in 0..6 {
                let over = (lo[i] + margin - q[i]).max(q[i] - (hi[i] - margin));
                if over > 0.0 {
                    beyond.push((*line, i + 1, round6(over / DEG)));
                }
            }
        }
    }
    let note = (!beyond.is_empty()).then(|| {
        format!(
            "{} moves leave the cell's joint margin of {} deg by up to {} deg (the compensation moves joints by up to {} deg): verify the compensated program with --joint-margin {} or plan with a larger margin",
            beyond.len(),
            fmt_fixed(margin / DEG, 3),
            fmt_fixed(beyond.iter().map(|b| b.2).fold(0.0, f64::max), 4),
            fmt_fixed(w.largest_change / DEG, 4),
            fmt_fixed(((margin / DEG) - (w.largest_change / DEG)).max(0.0) * 0.999, 3)
        )
    });
    let report = super::ProgramReport {
        largest_change_deg: round6(w.largest_change / DEG),
        beyond_joint_margin: beyond,
        file,
        dialect: dialect.to_string(),
        moves: w.moves,
        decimals: w.decimals,
        printed_residual_um: crate::calibrate::predict::spread(
            &w.printed_residual
                .iter()
                .map(|r| r * 1e6)
                .collect::<Vec<_>>(),
        )
        .into(),
        retimed_lines: w.retimed.clone(),
    };
    (report, note)
}

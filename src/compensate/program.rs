//! Compensated programs: in = a joint-move program in one of the six dialects (the subset its
//! reader takes), the controller mapping and a [`Compensator`]; out = the same program with
//! every move's joint values replaced by the compensated ones — the same text otherwise (lines,
//! comments, speeds, blends, pauses), plus one header comment that says it is compensated.
//!
//! The program is read with the dialect's own reader ([`crate::dialect`]): a line outside the
//! subset it takes is refused with its number. Each move's target (the nominal controller's
//! joints) is compensated as a joint target ([`Compensator::compensate`]); a move that cannot be
//! compensated is listed with its line and reason, and nothing is written. The new values are
//! written where the old ones stood (in FANUC LS, the position in `/POS`; in RAPID, a declared
//! jointtarget's declaration) with more decimals than a planned program needs where the language
//! carries them ([`decimals`]). A move whose text states its duration (G93 F, RAPID `\T`,
//! URScript `t`, FANUC `sec`) and would now ask an axis for more than its speed is slowed by
//! the ratio of its Eq. 7 times. Finally the new text is read back: it must command the same
//! steps with exactly the compensated values, no move faster than the axes allow.

use super::{Compensated, Compensator, Status, Target};
use crate::controller::{ControllerMap, Units};
use crate::dialect::{Dialect, MoveTime, Parsed, Step, Timing};
use crate::order::move_time;
use crate::timing::Limits;
use crate::units::{fmt_fixed, DEG};

/// Decimals of the compensated axis values: a planned program lives on the 0.001° grid, but a
/// compensation is finer than that, and 0.0005° is 17 µm at 2 m. FANUC LS positions resolve
/// 0.001° (as printed); SINUMERIK carries 4 decimals (the control resolves them with MD10210
/// INT_INCR_PER_DEG ≥ 10000, else it rounds to its resolution); KRL `REAL` and RAPID `num` are
/// 32-bit floats (1.5e-5° at 180°): 5; G-code 6; radians (URScript) 7 (6e-6°).
pub fn decimals(dialect: &str, units: Units) -> usize {
    match (dialect, units) {
        (_, Units::Rad) => 7,
        ("fanuc", _) => 3,
        ("sinumerik", _) => 4,
        ("krl" | "rapid", _) => 5,
        _ => 6,
    }
}

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

/// One move of the program and what replaces it.
struct Edit {
    line: usize,
    axes: [String; 6],
    /// The new duration token (s), when it changes.
    time: Option<f64>,
    /// The new axis speed percentages (KRL `$VEL_AXIS`, FANUC `n%`), when they change.
    percent: Option<[f64; 6]>,
    /// The percentages in force before (to restore them after the move in KRL).
    old_percent: [f64; 6],
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
    let speeds = &lim.speed;
    let parsed = read(text, dialect, map)?;
    let moves: Vec<(usize, [f64; 6], [f64; 6], Timing)> = parsed
        .lines
        .iter()
        .filter_map(|l| match &l.step {
            Step::Move {
                target,
                axes,
                timing,
                ..
            } => Some((l.line, *target, *axes, *timing)),
            _ => None,
        })
        .collect();
    if moves.is_empty() {
        return Err(unsupported(0, "the program commands no motion"));
    }
    // Each move comes from the one before, and a backlash rests on the flank of the direction
    // the joint's load side last moved in: the approach of each move is the direction from the
    // load-side joints the move before reaches to the ones this move must reach (where the
    // nominal program holds a joint, the compensation's own change decides: the play is pushed
    // to the new angle). Before its first motion a joint comes from `first`. The load-side
    // targets are the compensation's with the play left out (a first pass).
    let plain: Vec<(Target, [f64; 6])> = moves
        .iter()
        .map(|m| (Target::Joints(m.1.map(|d| d * DEG)), [0.0; 6]))
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
    let results: Vec<Compensated> = comp.compensate_all(&targets);
    let refused: Vec<Refused> = moves
        .iter()
        .zip(&results)
        .filter(|(_, c)| !c.status.is_ok())
        .map(|(m, c)| Refused {
            line: m.0,
            status: c.status,
        })
        .collect();
    if !refused.is_empty() {
        return Ok(Outcome::Refused(refused));
    }

    let dec = decimals(&dialect.name, map.units);
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
    let mut edits = Vec::with_capacity(moves.len());
    let mut printed_residual = Vec::with_capacity(moves.len());
    let mut retimed = Vec::new();
    let mut expected: Vec<[f64; 6]> = Vec::with_capacity(moves.len());
    let mut joints = Vec::with_capacity(moves.len());
    let mut largest_change: f64 = 0.0;
    let mut prev: Option<([f64; 6], [f64; 6])> = None; // (old, new) model joints, rad
    let mut prev_axes = [0.0; 6]; // the previous move's new axis values, as printed
    let axis_speeds = map.axis_speeds(speeds);
    for (m, c) in moves.iter().zip(&results) {
        let q = c.q.unwrap_or([0.0; 6]);
        let axes = map.apply(&q.map(|r| r / DEG));
        let printed: Vec<(String, f64)> = axes.iter().map(|&v| print(v)).collect();
        let values: [f64; 6] = std::array::from_fn(|i| printed[i].1);
        let new_q = map.undo(&values).map(|d| d * DEG);
        printed_residual.push(comp.residual(&c.target, &new_q, &c.approach));
        let old_q = m.1.map(|d| d * DEG);
        joints.push((m.0, new_q));
        largest_change = (0..6).fold(largest_change, |a, i| a.max((new_q[i] - old_q[i]).abs()));
        let mut time = None;
        let mut percent = None;
        let old_percent = match m.3 {
            Timing::AxisPercent(p) => p,
            _ => [100.0; 6],
        };
        if let Some((po, pn)) = prev {
            let duration = match m.3 {
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
            match (duration, m.3) {
                (Some(t), _) if t < t_new * (1.0 + 1e-9) && t_new > 0.0 => {
                    let scaled = if t_old > 0.0 {
                        t * t_new / t_old
                    } else {
                        t_new
                    };
                    time = Some(scaled.max(t_new * (1.0 + 1e-9)));
                    retimed.push(m.0);
                }
                (None, Timing::AxisPercent(p)) => {
                    // A percentage of every axis's speed: the controller times the move on its
                    // axes (J3 may follow J2); lower it where the compensated move would be
                    // faster than the joints allow.
                    let d =
                        m.3.duration(&prev_axes, &values, &axis_speeds)
                            .unwrap_or(f64::INFINITY);
                    if t_new > 0.0 && d < t_new * (1.0 + 1e-9) {
                        let full = (0..6)
                            .map(|i| (values[i] - prev_axes[i]).abs() / axis_speeds[i])
                            .fold(0.0, f64::max);
                        let most = (100.0 * full / (t_new * (1.0 + 1e-9))).floor().max(1.0);
                        let lowered = p.map(|x| x.min(most));
                        if lowered != p {
                            percent = Some(lowered);
                            retimed.push(m.0);
                        }
                    }
                }
                (None, Timing::PathFeed(_) | Timing::LeadSpeed(_)) => {
                    let d =
                        m.3.duration(
                            &map.apply(&pn.map(|r| r / DEG)),
                            &values,
                            &map.axis_speeds(speeds),
                        )
                        .unwrap_or(f64::INFINITY);
                    if d < t_new * (1.0 - 1e-6) {
                        return Err(unsupported(
                            m.0,
                            "the compensated move would ask an axis for more than its speed, and its feed (G94 F, URScript v) is not one compensate rescales: state the move's time (G93 F, URScript t)",
                        ));
                    }
                }
                _ => {}
            }
        }
        prev = Some((old_q, new_q));
        prev_axes = values;
        expected.push(values);
        edits.push(Edit {
            line: m.0,
            axes: std::array::from_fn(|i| printed[i].0.clone()),
            time,
            percent,
            old_percent,
        });
    }

    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    match dialect.name.as_str() {
        "ngc" => ngc(&mut lines, &edits)?,
        "sinumerik" => sinumerik(&mut lines, &edits, map)?,
        "krl" => krl(&mut lines, &edits)?,
        "rapid" => rapid(&mut lines, &edits)?,
        "urscript" => urscript(&mut lines, &edits)?,
        "fanuc" => fanuc(&mut lines, &edits)?,
        other => return Err(unsupported(0, format!("no rewriter for dialect '{other}'"))),
    }
    insert_note(&mut lines, &dialect.name, note)?;
    let mut out = lines.join("\n");
    out.push('\n');

    // The new text read back: the same steps, exactly the compensated values, no move faster
    // than the axes allow.
    let back = read(&out, dialect, map)?;
    check(&parsed, &back, &expected, &edits, dialect, lim)?;
    Ok(Outcome::Written(Rewritten {
        text: out,
        moves: moves.len(),
        decimals: dec,
        printed_residual,
        retimed,
        joints,
        largest_change,
    }))
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
    edits: &[Edit],
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

// ---- per-dialect rewriting ----------------------------------------------------------------

/// The code part of a line and the byte offset where a comment starts (`;`, `#`, `!` … outside
/// strings), for languages with one end-of-line comment character.
fn code_end(line: &str, comment: char) -> usize {
    let mut quote: Option<char> = None;
    for (k, c) in line.char_indices() {
        match (c, quote) {
            ('"', None) => quote = Some(c),
            (c, Some(q)) if c == q => quote = None,
            (c, None) if c == comment => return k,
            _ => {}
        }
    }
    line.len()
}

fn line_mut(lines: &mut [String], n: usize) -> Result<&mut String, ProgramError> {
    lines
        .get_mut(n.wrapping_sub(1))
        .ok_or_else(|| unsupported(n, "no such line"))
}

/// The number in `s` starting at byte `from` (after optional spaces): its byte range.
fn number_at(s: &str, from: usize) -> Option<(usize, usize)> {
    let b = s.as_bytes();
    let mut i = from;
    while i < b.len() && (b[i] == b' ' || b[i] == b'\t') {
        i += 1;
    }
    let start = i;
    while i < b.len() && (b[i].is_ascii_digit() || matches!(b[i], b'.' | b'-' | b'+' | b'e' | b'E'))
    {
        i += 1;
    }
    (i > start && b[start..i].iter().any(u8::is_ascii_digit)).then_some((start, i))
}

/// Replaces byte range `r` of `s`.
fn splice(s: &mut String, r: (usize, usize), with: &str) {
    s.replace_range(r.0..r.1, with);
}

/// RS274/NGC: the axis words X Y Z A B C of the line become all six compensated ones (at the
/// place of the first); a G93 F is rewritten when the move is slowed. G91 is refused.
fn ngc(lines: &mut [String], edits: &[Edit]) -> Result<(), ProgramError> {
    // G91 anywhere: the words would be increments.
    for (k, l) in lines.iter().enumerate() {
        if ngc_words(l).iter().any(|w| w.0 == 'G' && w.3 == "91") {
            return Err(unsupported(
                k + 1,
                "G91 (incremental) is not rewritten: write absolute joint values (G90)",
            ));
        }
    }
    const AXES: [char; 6] = ['X', 'Y', 'Z', 'A', 'B', 'C'];
    for e in edits {
        let line = line_mut(lines, e.line)?;
        let words = ngc_words(line);
        let axis: Vec<&(char, usize, usize, String)> =
            words.iter().filter(|w| AXES.contains(&w.0)).collect();
        let first = axis
            .first()
            .ok_or_else(|| unsupported(e.line, "no axis words on the move's line"))?
            .1;
        let full = AXES
            .iter()
            .zip(&e.axes)
            .map(|(a, v)| format!("{a}{v}"))
            .collect::<Vec<_>>()
            .join(" ");
        let mut spans: Vec<(usize, usize, String)> = axis
            .iter()
            .map(|w| {
                (
                    w.1,
                    w.2,
                    if w.1 == first {
                        full.clone()
                    } else {
                        String::new()
                    },
                )
            })
            .collect();
        if let Some(t) = e.time {
            let f = words
                .iter()
                .find(|w| w.0 == 'F')
                .ok_or_else(|| unsupported(e.line, "G93 move without F"))?;
            spans.push((f.1, f.2, format!("F{}", crate::emit::inverse_time_feed(t))));
        }
        spans.sort_by_key(|s| std::cmp::Reverse(s.0));
        for (a, b, with) in spans {
            // A removed word takes the space before it along.
            let a = if with.is_empty() && a > 0 && line.as_bytes()[a - 1] == b' ' {
                a - 1
            } else {
                a
            };
            splice(line, (a, b), &with);
        }
    }
    Ok(())
}

/// The words of an NGC line outside comments: (letter, start, end, number text).
fn ngc_words(line: &str) -> Vec<(char, usize, usize, String)> {
    let b = line.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'(' => {
                while i < b.len() && b[i] != b')' {
                    i += 1;
                }
                i += 1;
            }
            b';' => break,
            c if c.is_ascii_alphabetic() => {
                let start = i;
                // The reader drops every space, so a number may carry some.
                let mut j = i + 1;
                let mut end = j;
                while j < b.len()
                    && (b[j].is_ascii_digit() || matches!(b[j], b'.' | b'-' | b'+' | b' ' | b'\t'))
                {
                    if !matches!(b[j], b' ' | b'\t') {
                        end = j + 1;
                    }
                    j += 1;
                }
                let num: String = line[i + 1..end]
                    .chars()
                    .filter(|c| !c.is_whitespace())
                    .collect();
                out.push(((c as char).to_ascii_uppercase(), start, end, num));
                i = end.max(i + 1);
            }
            _ => i += 1,
        }
    }
    out
}

/// SINUMERIK: the axis words `NAME=value` (the mapping's axis names) become all six compensated
/// ones (at the place of the first); a G93 F is rewritten when the move is slowed. G91 is
/// refused.
fn sinumerik(
    lines: &mut [String],
    edits: &[Edit],
    map: &ControllerMap,
) -> Result<(), ProgramError> {
    for (k, l) in lines.iter().enumerate() {
        let code = &l[..code_end(l, ';')];
        if code
            .split_whitespace()
            .any(|w| w.eq_ignore_ascii_case("G91"))
        {
            return Err(unsupported(
                k + 1,
                "G91 (incremental) is not rewritten: write absolute joint values (G90)",
            ));
        }
    }
    for e in edits {
        let line = line_mut(lines, e.line)?;
        let end = code_end(line, ';');
        // Whitespace-separated words of the code part, with their byte ranges.
        let mut words: Vec<(usize, usize)> = Vec::new();
        let mut start: Option<usize> = None;
        for (k, c) in line[..end].char_indices() {
            match (c.is_whitespace(), start) {
                (false, None) => start = Some(k),
                (true, Some(s)) => {
                    words.push((s, k));
                    start = None;
                }
                _ => {}
            }
        }
        if let Some(s) = start {
            words.push((s, end));
        }
        let full = map
            .axis_names
            .iter()
            .zip(&e.axes)
            .map(|(n, v)| format!("{n}={v}"))
            .collect::<Vec<_>>()
            .join(" ");
        let mut spans: Vec<(usize, usize, String)> = Vec::new();
        let mut first = true;
        let mut feed = false;
        for &(a, b) in &words {
            let w = &line[a..b];
            if let Some((name, _)) = w.split_once('=') {
                if map.axis_names.iter().any(|n| n.eq_ignore_ascii_case(name)) {
                    spans.push((a, b, if first { full.clone() } else { String::new() }));
                    first = false;
                }
            } else if let Some(rest) = w.strip_prefix(['F', 'f']) {
                if rest.parse::<f64>().is_ok() {
                    feed = true;
                    if let Some(t) = e.time {
                        spans.push((a + 1, b, crate::emit::inverse_time_feed(t)));
                    }
                }
            }
        }
        if first {
            return Err(unsupported(e.line, "no axis words on the move's line"));
        }
        if e.time.is_some() && !feed {
            return Err(unsupported(e.line, "G93 move without F"));
        }
        spans.sort_by_key(|s| std::cmp::Reverse(s.0));
        for (a, b, with) in spans {
            let a = if with.is_empty() && a > 0 && line.as_bytes()[a - 1] == b' ' {
                a - 1
            } else {
                a
            };
            splice(line, (a, b), &with);
        }
    }
    Ok(())
}

/// The byte range of the bracket group that opens at `open` (inclusive of both brackets).
fn group(s: &str, open: usize, o: u8, c: u8) -> Option<(usize, usize)> {
    let b = s.as_bytes();
    let mut depth = 0;
    for (k, &ch) in b.iter().enumerate().skip(open) {
        if ch == o {
            depth += 1;
        } else if ch == c {
            depth -= 1;
            if depth == 0 {
                return Some((open, k + 1));
            }
        }
    }
    None
}

/// KUKA KRL: the PTP's axis aggregate becomes all six compensated axes; a move that must be
/// slower gets its lowered `$VEL_AXIS` set before it and the previous ones restored after it.
fn krl(lines: &mut Vec<String>, edits: &[Edit]) -> Result<(), ProgramError> {
    let mut inserts: Vec<(usize, Vec<String>, Vec<String>)> = Vec::new();
    for e in edits {
        if let Some(p) = e.percent {
            let set = |v: &[f64; 6]| -> Vec<String> {
                (0..6)
                    .filter(|&i| p[i] != e.old_percent[i])
                    .map(|i| format!("$VEL_AXIS[{}] = {}", i + 1, v[i] as i64))
                    .collect()
            };
            inserts.push((e.line, set(&p), set(&e.old_percent)));
        }
        let line = line_mut(lines, e.line)?;
        let end = code_end(line, ';');
        let open = line[..end]
            .find('{')
            .ok_or_else(|| unsupported(e.line, "no axis aggregate on the PTP line"))?;
        let r = group(line, open, b'{', b'}')
            .ok_or_else(|| unsupported(e.line, "the axis aggregate is not closed"))?;
        let agg = format!(
            "{{{}}}",
            e.axes
                .iter()
                .enumerate()
                .map(|(i, v)| format!("A{} {v}", i + 1))
                .collect::<Vec<_>>()
                .join(", ")
        );
        splice(line, r, &agg);
    }
    // Bottom up, so that the line numbers of the moves above stay.
    inserts.sort_by_key(|x| std::cmp::Reverse(x.0));
    for (line, before, after) in inserts {
        for (k, l) in after.into_iter().enumerate() {
            lines.insert(line + k, l);
        }
        for (k, l) in before.into_iter().enumerate() {
            lines.insert(line - 1 + k, l);
        }
    }
    Ok(())
}

/// ABB RAPID: the jointtarget's robot axes (the literal on the line, or a declared
/// jointtarget's declaration); `\T` rewritten when the move is slowed.
fn rapid(lines: &mut [String], edits: &[Edit]) -> Result<(), ProgramError> {
    let list = |e: &Edit| format!("[{}]", e.axes.join(", "));
    for e in edits {
        let code = lines
            .get(e.line.wrapping_sub(1))
            .ok_or_else(|| unsupported(e.line, "no such line"))?
            .clone();
        let lower = code.to_ascii_lowercase();
        let after = lower
            .find("moveabsj")
            .map(|k| k + "moveabsj".len())
            .ok_or_else(|| unsupported(e.line, "no MoveAbsJ on the move's line"))?;
        let arg = code[after..].trim_start();
        let arg_at = code.len() - arg.len();
        if arg.starts_with('[') {
            let inner = code[arg_at + 1..]
                .find('[')
                .map(|k| arg_at + 1 + k)
                .ok_or_else(|| unsupported(e.line, "a jointtarget is [[robax], [extax]]"))?;
            let r = group(&code, inner, b'[', b']')
                .ok_or_else(|| unsupported(e.line, "the jointtarget is not closed"))?;
            splice(line_mut(lines, e.line)?, r, &list(e));
        } else {
            // A declared jointtarget: rewrite its declaration. Another move to the same name
            // has the same nominal joints, so the same compensation.
            let name: String = arg
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            let decl = lines
                .iter()
                .position(|l| {
                    let w: Vec<String> = l
                        .split(":=")
                        .next()
                        .unwrap_or("")
                        .split_whitespace()
                        .map(|s| s.to_ascii_lowercase())
                        .collect();
                    w.len() >= 2
                        && w[w.len() - 2] == "jointtarget"
                        && w[w.len() - 1] == name.to_ascii_lowercase()
                })
                .ok_or_else(|| {
                    unsupported(e.line, format!("the declaration of jointtarget {name}"))
                })?;
            let d = &lines[decl];
            let v = d.find(":=").unwrap_or(0);
            let first = d[v..]
                .find('[')
                .map(|k| v + k)
                .and_then(|k| d[k + 1..].find('[').map(|j| k + 1 + j))
                .ok_or_else(|| unsupported(decl + 1, "a jointtarget is [[robax], [extax]]"))?;
            let r = group(d, first, b'[', b']')
                .ok_or_else(|| unsupported(decl + 1, "the jointtarget is not closed"))?;
            let text = list(e);
            splice(&mut lines[decl], r, &text);
        }
        if let Some(t) = e.time {
            let line = line_mut(lines, e.line)?;
            let lower = line.to_ascii_lowercase();
            let k = lower
                .find("\\t:=")
                .ok_or_else(|| unsupported(e.line, "a timed MoveAbsJ without \\T"))?;
            let r = number_at(line, k + 4)
                .ok_or_else(|| unsupported(e.line, "\\T without a number"))?;
            splice(line, r, &crate::emit::ceil_fixed(t, 3));
        }
    }
    Ok(())
}

/// URScript: the movej's joint list; a named `t=` rewritten when the move is slowed.
fn urscript(lines: &mut [String], edits: &[Edit]) -> Result<(), ProgramError> {
    for e in edits {
        let line = line_mut(lines, e.line)?;
        let end = code_end(line, '#');
        let call = line[..end]
            .find("movej")
            .ok_or_else(|| unsupported(e.line, "no movej on the move's line"))?;
        let open = line[call..end]
            .find('[')
            .map(|k| call + k)
            .ok_or_else(|| unsupported(e.line, "movej without its joint list"))?;
        let r = group(line, open, b'[', b']')
            .ok_or_else(|| unsupported(e.line, "the joint list is not closed"))?;
        let tail_from = r.0 + e.axes.join(", ").len() + 2;
        splice(line, r, &format!("[{}]", e.axes.join(", ")));
        if let Some(t) = e.time {
            let end = code_end(line, '#');
            let k = line[tail_from..end]
                .find("t=")
                .map(|k| tail_from + k)
                .filter(|&k| !line.as_bytes()[k - 1].is_ascii_alphanumeric())
                .ok_or_else(|| {
                    unsupported(
                        e.line,
                        "the move's time must be slowed, but it is not given as t=: name it",
                    )
                })?;
            let r =
                number_at(line, k + 2).ok_or_else(|| unsupported(e.line, "t= without a number"))?;
            splice(line, r, &crate::emit::ceil_fixed(t, 4));
        }
    }
    Ok(())
}

/// FANUC LS: the J1..J6 values of the move's position in `/POS`; a `sec`/`msec` time
/// rewritten when the move is slowed.
fn fanuc(lines: &mut [String], edits: &[Edit]) -> Result<(), ProgramError> {
    for e in edits {
        let jl = lines
            .get(e.line.wrapping_sub(1))
            .ok_or_else(|| unsupported(e.line, "no such line"))?
            .clone();
        let upper = jl.to_ascii_uppercase();
        let p = upper
            .find("P[")
            .map(|k| k + 2)
            .ok_or_else(|| unsupported(e.line, "no position P[k] on the move's line"))?;
        let idx: String = upper[p..]
            .chars()
            .take_while(|c| c.is_ascii_digit() || *c == ' ')
            .filter(|c| c.is_ascii_digit())
            .collect();
        let pos = lines
            .iter()
            .position(|l| l.trim() == "/POS")
            .ok_or_else(|| unsupported(e.line, "no /POS section"))?;
        let start = (pos + 1..lines.len())
            .find(|&k| {
                let t = lines[k].trim_start().to_ascii_uppercase();
                t.strip_prefix("P[")
                    .map(|r| {
                        let n: String = r
                            .chars()
                            .take_while(|c| c.is_ascii_digit() || *c == ' ')
                            .filter(|c| c.is_ascii_digit())
                            .collect();
                        n == idx
                    })
                    .unwrap_or(false)
            })
            .ok_or_else(|| unsupported(e.line, format!("P[{idx}] is not in /POS")))?;
        let mut found = [false; 6];
        for k in start..lines.len() {
            let l = &mut lines[k];
            for (i, f) in found.iter_mut().enumerate() {
                let key = format!("J{}", i + 1);
                let upper = l.to_ascii_uppercase();
                let mut from = 0;
                while let Some(at) = upper[from..].find(&key).map(|j| from + j) {
                    from = at + key.len();
                    let rest = &upper[from..];
                    let eq = rest.len() - rest.trim_start().len();
                    if !rest.trim_start().starts_with('=') {
                        continue;
                    }
                    if let Some(r) = number_at(l, from + eq + 1) {
                        splice(l, r, &e.axes[i]);
                        *f = true;
                    }
                    break;
                }
            }
            if lines[k].trim_end().ends_with("};") {
                break;
            }
        }
        if let Some(i) = found.iter().position(|f| !f) {
            return Err(unsupported(
                start + 1,
                format!("P[{idx}]: J{} not found", i + 1),
            ));
        }
        if let Some(p) = e.percent {
            let line = line_mut(lines, e.line)?;
            let pct = line
                .find('%')
                .ok_or_else(|| unsupported(e.line, "a J move without its speed n%"))?;
            let start = line[..pct]
                .rfind(|c: char| !c.is_ascii_digit())
                .map_or(0, |j| j + 1);
            splice(line, (start, pct), &format!("{}", p[0] as i64));
        }
        if let Some(t) = e.time {
            let line = line_mut(lines, e.line)?;
            let upper = line.to_ascii_uppercase();
            let (k, scale) = match upper.find("MSEC") {
                Some(k) => (k, 1000.0),
                None => (
                    upper
                        .find("SEC")
                        .ok_or_else(|| unsupported(e.line, "a timed J move without sec"))?,
                    1.0,
                ),
            };
            let num_end = line[..k].trim_end().len();
            let num_start = line[..num_end]
                .rfind(|c: char| !(c.is_ascii_digit() || c == '.'))
                .map_or(0, |j| j + 1);
            let digits = line[num_start..num_end]
                .split_once('.')
                .map_or(0, |(_, d)| d.len())
                .max(2);
            splice(
                line,
                (num_start, num_end),
                &crate::emit::ceil_fixed(t * scale, digits),
            );
        }
    }
    Ok(())
}

/// The header comment that marks a compensated program, where each language keeps its
/// header comments.
fn insert_note(lines: &mut Vec<String>, dialect: &str, note: &str) -> Result<(), ProgramError> {
    let clean = |s: &str| s.replace(['(', ')'], "");
    let find =
        |lines: &[String], pred: &dyn Fn(&str) -> bool| lines.iter().position(|l| pred(l.trim()));
    match dialect {
        "ngc" => lines.insert(0, format!("({})", clean(note))),
        "sinumerik" => lines.insert(0, format!("; {note}")),
        "krl" => {
            let k = find(lines, &|l| l.to_ascii_uppercase().starts_with("DEF "))
                .ok_or_else(|| unsupported(0, "no DEF line"))?;
            lines.insert(k + 1, format!("; {note}"));
        }
        "rapid" => {
            let k = find(lines, &|l| l.to_ascii_uppercase().starts_with("MODULE "))
                .ok_or_else(|| unsupported(0, "no MODULE line"))?;
            lines.insert(k + 1, format!("  ! {note}"));
        }
        "urscript" => {
            let k = find(lines, &|l| l.starts_with("def "))
                .ok_or_else(|| unsupported(0, "no def line"))?;
            lines.insert(k + 1, format!("  # {note}"));
        }
        "fanuc" => {
            let mn = find(lines, &|l| l == "/MN").ok_or_else(|| unsupported(0, "no /MN"))?;
            let chunks = crate::emit::wrap(note.replace(';', ","), 30);
            let n = chunks.len();
            // Renumber the /MN lines after the new ones, and the line count.
            for l in lines.iter_mut().skip(mn + 1) {
                if l.trim() == "/POS" || l.trim() == "/END" {
                    break;
                }
                let t = l.trim_start();
                if let Some((no, rest)) = t.split_once(':') {
                    if let Ok(v) = no.trim().parse::<usize>() {
                        let indent = l.len() - t.len();
                        let width = indent + no.len();
                        *l = format!("{:>width$}:{rest}", v + n);
                    }
                }
            }
            for (k, c) in chunks.iter().enumerate() {
                lines.insert(mn + 1 + k, format!("{:>4}:  !{c} ;", k + 1));
            }
            for l in lines.iter_mut() {
                let t = l.trim_start();
                if let Some(rest) = t.strip_prefix("LINE_COUNT") {
                    if let Ok(v) = rest
                        .trim()
                        .trim_start_matches('=')
                        .trim()
                        .trim_end_matches(';')
                        .trim()
                        .parse::<usize>()
                    {
                        *l = format!("LINE_COUNT = {};", v + n);
                    }
                    break;
                }
            }
        }
        _ => {}
    }
    Ok(())
}

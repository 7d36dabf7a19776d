//! FANUC LS reader (`fanuc.j2` beside it writes it): in = a teach pendant program as LS text
//! and the controller mapping; out = the motions, in program order, and where each move's
//! joint values (in `/POS`), speed and time, the `/MN` line numbers and `LINE_COUNT` sit.
//!
//! The subset a joint-space measurement program needs, strictly:
//! - `/PROG name`, an optional `/ATTR` block, `/MN` with lines `n:  instruction ;` numbered
//!   1, 2, … without gaps, `/POS` with one `P[k]{ GP1: UF : u, UT : t, J1= v deg, …, J6= v
//!   deg };` per position, `/END`;
//! - `J P[k] n% FINE|CNTn|CRn` (also `P[k:label]`; `n sec`/`n msec` as the move's time): `n%`
//!   runs the slowest axis at n % of its speed, all axes arriving together. FINE is an exact
//!   stop; CNTn is a blend with the value n, a continuity criterion bounding no corner region
//!   (verify refuses it with the bar in place); CRn (corner region) a blend verified as up to
//!   half of each adjacent move (no available FANUC document says what its distance bounds);
//! - `!remark` (at most 32 characters; a remark goes with the motion after it; `..` lines
//!   continue the header's long values), `MESSAGE[…]` (at most 24), `PAUSE`, `WAIT t(sec)`,
//!   `UFRAME_NUM=n`, `UTOOL_NUM=n`, `END`.

use crate::controller::ControllerMap;
use crate::dialect::{
    after_line, number, offset_in, perr, push_header, shifted, span, Line, MoveSpans, ParseError,
    Parsed, Step, Timing,
};
use std::ops::Range;

/// FANUC program names: a letter, then letters, digits and `_`, at most 36 characters.
pub fn valid_name(name: &str) -> bool {
    crate::dialect::valid_name(name, 36)
}

struct Motion {
    line: usize,
    p: usize,
    timing: Timing,
    blend: Option<f64>,
    /// CR (up to half of each adjacent move, assumed) rather than CNT (a continuity value).
    corner: Option<crate::dialect::CornerKind>,
    comment: Option<String>,
    /// Where its speed percentage's number and its time's number (with one second in its
    /// unit) sit, relative to the text `motion` was given.
    percent: Option<Range<usize>>,
    time: Option<(Range<usize>, f64)>,
    line_range: Range<usize>,
}

/// A position of `/POS`: its number, line, joint values and where each value sits.
struct Position {
    k: usize,
    line: usize,
    joints: [Option<f64>; 6],
    spans: [Option<Range<usize>>; 6],
}

enum Item {
    Move(Motion),
    Step(Line),
}

/// An `/MN` instruction other than a remark (`instr`, without its number and `;`): a motion or
/// a step, None for one that commands nothing (`MESSAGE`, frame numbers).
fn instruction(
    text: &str,
    raw: &str,
    line: usize,
    instr: &str,
    comment: Option<String>,
) -> Result<Option<Item>, ParseError> {
    let upper = instr.to_ascii_uppercase();
    if let Some(r) = upper.strip_prefix("J ") {
        let r = r.trim();
        let mut m = motion(line, r, comment)?;
        // `upper` has the byte offsets of `instr`.
        let at = offset_in(text, instr) + offset_in(&upper, r);
        m.percent = m.percent.map(|p| shifted(at, p));
        m.time = m.time.map(|(p, unit)| (shifted(at, p), unit));
        m.line_range = span(text, raw);
        return Ok(Some(Item::Move(m)));
    } else if let Some(r) = upper.strip_prefix("MESSAGE[") {
        let inner = r
            .strip_suffix(']')
            .ok_or_else(|| perr(line, "MESSAGE[ without ']'"))?;
        if inner.chars().count() > 24 {
            return Err(perr(line, "a MESSAGE holds at most 24 characters"));
        }
    } else if upper == "PAUSE" {
        return Ok(Some(Item::Step(Line {
            line,
            step: Step::Pause,
            comment,
        })));
    } else if upper == "END" {
        return Ok(Some(Item::Step(Line {
            line,
            step: Step::End,
            comment,
        })));
    } else if let Some(r) = upper.strip_prefix("WAIT ") {
        let s = r
            .trim()
            .strip_suffix("(SEC)")
            .ok_or_else(|| perr(line, "WAIT takes a time: WAIT t(sec)"))?;
        let secs = number(line, "WAIT", s)?;
        return Ok(Some(Item::Step(Line {
            line,
            step: Step::Dwell(secs),
            comment,
        })));
    } else if let Some(r) = upper
        .strip_prefix("UFRAME_NUM=")
        .or(upper.strip_prefix("UTOOL_NUM="))
    {
        r.trim()
            .parse::<u32>()
            .map_err(|_| perr(line, "UFRAME_NUM/UTOOL_NUM take a number"))?;
    } else {
        return Err(perr(
            line,
            format!("'{instr}' is not an instruction edbbgen reads (J, !, MESSAGE, PAUSE, WAIT)"),
        ));
    }
    Ok(None)
}

/// A line of `/POS` (`t`, trimmed): a position opens, closes, or gives joint values.
fn pos_line(
    text: &str,
    line: usize,
    t: &str,
    open_p: &mut Option<Position>,
    positions: &mut Vec<Position>,
) -> Result<(), ParseError> {
    if let Some(r) = t.strip_prefix("P[") {
        if open_p.is_some() {
            return Err(perr(line, "a position starts inside another (no '};')"));
        }
        let (idx, rest) = r
            .split_once(']')
            .ok_or_else(|| perr(line, "P[ without ']'"))?;
        let idx = idx.split(':').next().unwrap_or("");
        let kk: usize = idx
            .trim()
            .parse()
            .map_err(|_| perr(line, format!("P[{idx}]: not a position number")))?;
        if rest.trim() != "{" {
            return Err(perr(line, "a position starts with 'P[k]{'"));
        }
        if positions.iter().any(|p| p.k == kk) {
            return Err(perr(line, format!("P[{kk}] defined twice")));
        }
        *open_p = Some(Position {
            k: kk,
            line,
            joints: [None; 6],
            spans: Default::default(),
        });
    } else if t == "};" {
        let p = open_p
            .take()
            .ok_or_else(|| perr(line, "'};' without a position"))?;
        positions.push(p);
    } else {
        let p = open_p
            .as_mut()
            .ok_or_else(|| perr(line, "text outside a position"))?;
        if t == "GP1:" || t.starts_with("UF") {
            return Ok(());
        }
        for part in t.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (name, value) = part
                .split_once('=')
                .ok_or_else(|| perr(line, format!("'{part}' is not 'Jn = value deg'")))?;
            let i = match name.trim() {
                "J1" => 0,
                "J2" => 1,
                "J3" => 2,
                "J4" => 3,
                "J5" => 4,
                "J6" => 5,
                n => {
                    return Err(perr(
                        line,
                        format!("'{n}' is not a joint (J1..J6): joint representation only"),
                    ))
                }
            };
            let v = value
                .trim()
                .strip_suffix("deg")
                .ok_or_else(|| perr(line, format!("J{} needs 'deg'", i + 1)))?;
            if p.joints[i].is_some() {
                return Err(perr(line, format!("J{} given twice", i + 1)));
            }
            p.joints[i] = Some(number(line, "joint value", v)?);
            p.spans[i] = Some(span(text, v.trim()));
        }
    }
    Ok(())
}

pub fn parse(text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
    let mut out = Parsed {
        map: map.clone(),
        ..Parsed::default()
    };
    #[derive(PartialEq, Clone, Copy)]
    enum Sec {
        Start,
        Attr,
        Mn,
        Pos,
        End,
    }
    let mut sec = Sec::Start;
    let mut main = Main {
        next_no: 1,
        moved: false,
        remark: None,
        items: Vec::new(),
    };
    let mut positions: Vec<Position> = Vec::new();
    let mut open_p: Option<Position> = None;
    let mut end_line = 0;
    let mut line_count_seen = false;
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let t = raw.trim();
        if t.is_empty() {
            continue;
        }
        if let Some(rest) = t.strip_prefix("/PROG") {
            if sec != Sec::Start {
                return Err(perr(line, "/PROG twice"));
            }
            let name = rest.split_whitespace().next().unwrap_or("");
            if !valid_name(name) {
                return Err(perr(
                    line,
                    format!(
                        "/PROG {name}: not a program name (a letter, letters/digits/_, at most 36)"
                    ),
                ));
            }
            sec = Sec::Attr;
            continue;
        }
        if sec == Sec::Start {
            return Err(perr(line, "an LS program starts with /PROG name"));
        }
        match t {
            "/ATTR" if sec == Sec::Attr => continue,
            "/MN" if sec == Sec::Attr => {
                sec = Sec::Mn;
                // Header comments go after the /MN line.
                out.positions.header_at = Some(after_line(text, raw));
                continue;
            }
            "/POS" if sec == Sec::Mn => {
                sec = Sec::Pos;
                continue;
            }
            "/END" if sec == Sec::Pos || sec == Sec::Mn => {
                if open_p.is_some() {
                    return Err(perr(line, "/END inside a position (no '};')"));
                }
                sec = Sec::End;
                end_line = line;
                continue;
            }
            _ if t.starts_with('/') && !t.starts_with("/APPL") => {
                return Err(perr(
                    line,
                    format!("{t} out of place (/PROG, /ATTR, /MN, /POS, /END in this order)"),
                ))
            }
            _ => {}
        }
        match sec {
            Sec::Start => unreachable!(),
            Sec::End => return Err(perr(line, "text after /END")),
            Sec::Attr => {
                if !(t.ends_with(';') || t.ends_with(',') || t.starts_with("/APPL")) {
                    return Err(perr(
                        line,
                        "an /ATTR line ends with ';' (or ',' inside TCD)",
                    ));
                }
                if let Some(rest) = t.strip_prefix("LINE_COUNT").filter(|_| !line_count_seen) {
                    line_count_seen = true;
                    let n = rest.trim().trim_start_matches('=').trim();
                    if let Ok(v) = n.trim_end_matches(';').trim().parse::<usize>() {
                        out.positions.line_count = Some((span(text, raw), v));
                    }
                }
            }
            Sec::Mn => main.line(&mut out, text, raw, line)?,
            Sec::Pos => pos_line(text, line, t, &mut open_p, &mut positions)?,
        }
    }
    if sec != Sec::End {
        return Err(perr(
            text.lines().count(),
            "the program does not end with /END",
        ));
    }
    assemble(out, main.items, &positions, map, end_line)
}

/// The `/MN` section as it is read: the next line number, whether a move came yet (remarks
/// before the first are the header's), the remark waiting for its motion, the instructions.
struct Main {
    next_no: usize,
    moved: bool,
    remark: Option<String>,
    items: Vec<Item>,
}

impl Main {
    /// The `/MN` line `raw` (line number `line`).
    fn line(
        &mut self,
        out: &mut Parsed,
        text: &str,
        raw: &str,
        line: usize,
    ) -> Result<(), ParseError> {
        let t = raw.trim();
        let (no, rest) = t
            .split_once(':')
            .ok_or_else(|| perr(line, "an /MN line is 'n:  instruction ;'"))?;
        let no: usize = no
            .trim()
            .parse()
            .map_err(|_| perr(line, format!("'{}' is not a line number", no.trim())))?;
        if no != self.next_no {
            return Err(perr(
                line,
                format!("line number {no}, expected {}", self.next_no),
            ));
        }
        // The number with the indent before it: renumbered when lines are inserted.
        let line_at = offset_in(text, raw);
        out.positions
            .line_numbers
            .push((line_at..offset_in(text, t) + t.find(':').unwrap_or(0), no));
        self.next_no += 1;
        let instr = rest
            .trim_end()
            .strip_suffix(';')
            .ok_or_else(|| perr(line, "an /MN line ends with ';'"))?
            .trim();
        if instr.is_empty() {
            return Ok(());
        }
        if let Some(r) = instr.strip_prefix('!') {
            if r.chars().count() > 32 {
                return Err(perr(
                    line,
                    format!(
                        "a remark holds at most 32 characters, this one {}",
                        r.chars().count()
                    ),
                ));
            }
            if !self.moved {
                push_header(&mut out.header, r);
            }
            self.remark = Some(r.trim().to_string());
            return Ok(());
        }
        let comment = self.remark.take();
        if let Some(item) = instruction(text, raw, line, instr, comment)? {
            self.moved |= matches!(item, Item::Move(_));
            self.items.push(item);
        }
        Ok(())
    }
}

/// The program from its `/MN` instructions in order, each motion's joints from `/POS`, and the
/// final `/END` step.
fn assemble(
    mut out: Parsed,
    items: Vec<Item>,
    positions: &[Position],
    map: &ControllerMap,
    end_line: usize,
) -> Result<Parsed, ParseError> {
    for it in items {
        match it {
            Item::Step(l) => out.lines.push(l),
            Item::Move(m) => {
                let pos = positions
                    .iter()
                    .find(|p| p.k == m.p)
                    .ok_or_else(|| perr(m.line, format!("P[{}] is not in /POS", m.p)))?;
                let mut axes = [0.0; 6];
                for i in 0..6 {
                    axes[i] = pos.joints[i]
                        .ok_or_else(|| perr(pos.line, format!("P[{}] lacks J{}", m.p, i + 1)))?;
                }
                out.positions.moves.push(MoveSpans {
                    line: m.line,
                    axes: pos.spans.iter().flatten().cloned().collect(),
                    time: m.time.as_ref().map(|t| t.0.clone()),
                    time_per_s: m.time.as_ref().map_or(1.0, |t| t.1),
                    percent: m.percent.clone(),
                    line_range: m.line_range.clone(),
                });
                out.lines.push(Line {
                    line: m.line,
                    step: Step::Move {
                        target: map.undo(&axes),
                        axes,
                        timing: m.timing,
                        blend: m.blend,
                        corner: m.corner,
                    },
                    comment: m.comment,
                });
            }
        }
    }
    out.lines.push(Line {
        line: end_line,
        step: Step::End,
        comment: None,
    });
    Ok(out)
}

/// `P[k] 100% CNT10` (upper case) → the motion.
fn motion(line: usize, s: &str, comment: Option<String>) -> Result<Motion, ParseError> {
    let r = s
        .strip_prefix("P[")
        .ok_or_else(|| perr(line, "J takes a position P[k]"))?;
    let (idx, rest) = r
        .split_once(']')
        .ok_or_else(|| perr(line, "P[ without ']'"))?;
    let idx = idx.split(':').next().unwrap_or("");
    let p: usize = idx
        .trim()
        .parse()
        .map_err(|_| perr(line, format!("P[{idx}]: not a position number")))?;
    let words: Vec<&str> = rest.split_whitespace().collect();
    // The speed word, its number (where the number sits in `s`) and the termination.
    let (speed, number_text, term) = match words.as_slice() {
        [sp, term] => {
            let n = ["%", "MSEC", "SEC"]
                .iter()
                .find_map(|u| sp.strip_suffix(u))
                .unwrap_or(sp);
            (sp.to_string(), n, *term)
        }
        [n, unit, term] if *unit == "SEC" || *unit == "MSEC" => (format!("{n}{unit}"), *n, *term),
        _ => {
            return Err(perr(
                line,
                "J P[k] takes a speed and a termination (n% FINE|CNTn)",
            ))
        }
    };
    let timing = if let Some(n) = speed.strip_suffix('%') {
        let v: u32 = n.parse().map_err(|_| {
            perr(
                line,
                format!("'{speed}': a joint speed is an integer percentage"),
            )
        })?;
        if !(1..=100).contains(&v) {
            return Err(perr(line, "a joint speed is 1..100 %"));
        }
        Timing::AxisPercent([f64::from(v); 6])
    } else if let Some(n) = speed.strip_suffix("MSEC") {
        Timing::Duration(number(line, "msec", n)? / 1000.0)
    } else if let Some(n) = speed.strip_suffix("SEC") {
        Timing::Duration(number(line, "sec", n)?)
    } else {
        return Err(perr(
            line,
            format!("'{speed}' is not a joint speed (n%, t sec, t msec)"),
        ));
    };
    let blend = if term == "FINE" {
        None
    } else if let Some(n) = term.strip_prefix("CNT").or(term.strip_prefix("CR")) {
        let v: u32 = n
            .parse()
            .map_err(|_| perr(line, format!("'{term}' needs an integer")))?;
        if v > 100 && term.starts_with("CNT") {
            return Err(perr(line, "CNT takes 0..100"));
        }
        (v > 0).then_some(f64::from(v))
    } else {
        return Err(perr(
            line,
            format!("'{term}' is not a termination (FINE, CNTn, CRn)"),
        ));
    };
    // No available FANUC document says what CR's distance bounds: up to half of each adjacent
    // move (the dialect's cap) is assumed, not a TCP distance.
    let corner = term
        .starts_with("CR")
        .then_some(crate::dialect::CornerKind::Moves);
    let at = span(s, number_text);
    let (percent, time) = if speed.ends_with('%') {
        (Some(at), None)
    } else if speed.ends_with("MSEC") {
        (None, Some((at, 1000.0)))
    } else {
        (None, Some((at, 1.0)))
    };
    Ok(Motion {
        line,
        p,
        timing,
        blend,
        corner,
        comment,
        percent,
        time,
        line_range: 0..0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Units;

    fn map() -> ControllerMap {
        ControllerMap::identity(Units::Deg, ["J1", "J2", "J3", "J4", "J5", "J6"])
    }

    const OK: &str = "/PROG  EDBB\n/ATTR\nOWNER = MNEDITOR;\nTCD:  STACK_SIZE = 0,\n      PAUSE_REQUEST = 0;\n/MN\n\
           1:  !fixture: 1, 2, ;\n   2:  !.. 3 mm ;\n   3:  !pose 1/2 ;\n   4:  J P[1] 100% FINE ;\n   5:  MESSAGE[Mount the EDBB] ;\n\
           6:  PAUSE ;\n   7:  !support ;\n   8:  J P[2] 50% CNT10 ;\n/POS\nP[1]{\n   GP1:\n    UF : 0, UT : 1,\n\
        J1 = 1.000 deg,  J2 = 2.000 deg,  J3 = 3.000 deg,\n    J4 = 4.000 deg,  J5 = 5.000 deg,  J6 = 6.000 deg\n};\n\
        P[2]{\n   GP1:\n    UF : 0, UT : 1,\n    J1 = 2.000 deg,  J2 = 2.000 deg,  J3 = 3.000 deg,\n    J4 = 4.000 deg,  J5 = 5.000 deg,  J6 = 6.000 deg\n};\n/END\n";

    #[test]
    fn reads_mn_and_pos() {
        let p = parse(OK, &map()).unwrap();
        assert_eq!(p.header_value("fixture"), Some("1, 2, 3 mm"));
        let steps: Vec<&Step> = p.lines.iter().map(|l| &l.step).collect();
        assert!(
            matches!(steps[0], Step::Move { timing: Timing::AxisPercent(pc), blend: None, .. } if pc[0] == 100.0)
        );
        assert!(matches!(steps[1], Step::Pause));
        assert!(
            matches!(steps[2], Step::Move { blend: Some(b), target, .. } if *b == 10.0 && target[0] == 2.0)
        );
        assert_eq!(p.lines[2].comment.as_deref(), Some("support"));
        assert!(matches!(steps[3], Step::End));
    }

    #[test]
    fn rejects_with_the_line_number() {
        for (from, to, msg) in [
            ("   2:  !.. 3 mm ;", "   3:  !.. 3 mm ;", "expected 2"),
            (
                "J P[2] 50% CNT10",
                "J P[3] 50% CNT10",
                "P[3] is not in /POS",
            ),
            ("J P[2] 50% CNT10", "J P[2] 150% CNT10", "1..100"),
            (
                "J P[2] 50% CNT10",
                "L P[2] 50mm/sec CNT10",
                "not an instruction",
            ),
            ("/END\n", "", "does not end"),
            (
                "!support ;",
                "!support with a remark that is much too long ;",
                "at most 32",
            ),
        ] {
            let text = OK.replacen(from, to, 1);
            let e = parse(&text, &map()).unwrap_err();
            assert!(e.msg.contains(msg), "{to:?}: {e}");
        }
    }
}

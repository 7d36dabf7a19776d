//! SINUMERIK 840D part-program reader (`sinumerik.j2` beside it writes it): in = program text
//! and the controller mapping (its axis names); out = the motions, in program order, and where
//! each move's axis words and F value sit in the text.
//!
//! The subset a joint-space measurement program needs, strictly:
//! - blocks with an optional `N` number; comments after `;`; `MSG("…")` and `FGROUP(…)` alone in
//!   their block (after its `N` number, if any);
//! - axes as `NAME=value` with the mapping's machine-axis names, absolute (G90) or incremental
//!   (G91); `G71`/`G710` (metric) only;
//! - G0 (every axis at its maximum speed) and G1 with G93 (inverse time: F = 1/min per block,
//!   required in every G1 block) or G94 (units per minute along the axis path);
//! - G60 (exact stop, modal), G9 (exact stop in its block), G641 with `ADIS=` (rounding
//!   distance, mm at the MAP); plain G64 (no distance) is refused: verify could not check it;
//! - G4 F (dwell, s: in a G4 block F is the time, not a feed); M0/M1 (pause); M2/M17/M30 (end).

use crate::controller::ControllerMap;
use crate::dialect::{
    number, offset_in, perr, push_header, Line, MoveSpans, ParseError, Parsed, Positions, Step,
    Timing,
};
use std::ops::Range;

/// Splits a block into code and the comment after `;` (outside strings).
fn split(raw: &str) -> (&str, Option<&str>) {
    let mut in_str = false;
    for (k, c) in raw.char_indices() {
        match c {
            '"' => in_str = !in_str,
            ';' if !in_str => return (&raw[..k], Some(raw[k + 1..].trim())),
            _ => {}
        }
    }
    (raw, None)
}

/// A statement that stands alone in its block (after its optional block number): `MSG(…)`
/// or `FGROUP(…)` on the axes `names`. False for any other block.
fn standalone(line: usize, code: &str, names: &[String]) -> Result<bool, ParseError> {
    // Statements that stand alone in their block (after its optional block number).
    let upper = match code.split_once(char::is_whitespace) {
        Some((n, rest))
            if n.len() > 1
                && n.starts_with('N')
                && n[1..].bytes().all(|b| b.is_ascii_digit())
                && (rest.trim_start().starts_with("MSG(")
                    || rest.trim_start().starts_with("FGROUP(")) =>
        {
            rest.trim_start().to_string()
        }
        _ => code.to_string(),
    };
    if let Some(rest) = upper.strip_prefix("MSG(") {
        if !rest.ends_with(')') {
            return Err(perr(line, "MSG( without its closing parenthesis"));
        }
        let inner = rest[..rest.len() - 1].trim();
        if !(inner.is_empty()
            || (inner.len() >= 2 && inner.starts_with('"') && inner.ends_with('"')))
        {
            return Err(perr(line, "MSG needs a quoted text or nothing"));
        }
        return Ok(true);
    }
    if let Some(rest) = upper.strip_prefix("FGROUP(") {
        let inner = rest
            .strip_suffix(')')
            .ok_or_else(|| perr(line, "FGROUP( without its closing parenthesis"))?;
        for a in inner.split(',').map(str::trim).filter(|a| !a.is_empty()) {
            if !names.iter().any(|n| n == a) {
                return Err(perr(
                    line,
                    format!("FGROUP: '{a}' is not one of the axes {}", names.join(", ")),
                ));
            }
        }
        return Ok(true);
    }
    Ok(false)
}

/// What a block says: its words, with the modal state they set for the blocks after it.
#[derive(Default)]
struct Block {
    axis: [Option<f64>; 6],
    /// Where the block's axis words and its F value sit in the text.
    axis_spans: Vec<Range<usize>>,
    f_span: Option<Range<usize>>,
    /// Some(true) = G0, Some(false) = G1.
    g_motion: Option<bool>,
    dwell: bool,
    /// G9: an exact stop in this block.
    exact_here: bool,
    f_word: Option<f64>,
    /// Some(true) = M0/M1 (pause), Some(false) = an end.
    m_word: Option<bool>,
}

/// The modal state that carries from block to block.
struct Modal {
    absolute: bool,
    inverse_time: bool,
    /// G641 active.
    blend_mode: bool,
    adis: Option<f64>,
}

/// The words of block `line` (its code `upper`, upper case, starting at byte `code_at` of the
/// text; `names` the axes): what they command, the modal state they set, and a G91 in
/// `positions` (the values after it cannot be rewritten).
fn block(
    line: usize,
    code_at: usize,
    upper: &str,
    names: &[String],
    modal: &mut Modal,
    positions: &mut Positions,
) -> Result<Block, ParseError> {
    let mut b = Block::default();
    for word in upper.split_whitespace() {
        let w_at = code_at + offset_in(upper, word);
        if let Some((name, value)) = word.split_once('=') {
            if name == "ADIS" {
                let v = number(line, "ADIS", value)?;
                if v < 0.0 {
                    return Err(perr(line, "ADIS must be >= 0"));
                }
                modal.adis = Some(v);
            } else if let Some(i) = names.iter().position(|n| n == name) {
                if b.axis[i].is_some() {
                    return Err(perr(line, format!("{name} given twice")));
                }
                b.axis[i] = Some(number(line, name, value)?);
                b.axis_spans.push(w_at..w_at + word.len());
            } else {
                return Err(perr(
                    line,
                    format!("'{name}=' is not an axis ({}) or ADIS", names.join(", ")),
                ));
            }
            continue;
        }
        if !word.is_ascii() {
            return Err(perr(line, format!("word '{word}' is not supported")));
        }
        let (letter, num) = word.split_at(1);
        match letter {
            "N" => {
                num.parse::<u64>()
                    .map_err(|_| perr(line, format!("block number '{word}'")))?;
            }
            "G" => {
                match num {
                    "0" | "00" => b.g_motion = Some(true),
                    "1" | "01" => b.g_motion = Some(false),
                    "4" | "04" => b.dwell = true,
                    "9" | "09" => b.exact_here = true,
                    "60" => modal.blend_mode = false,
                    "641" => modal.blend_mode = true,
                    "64" => {
                        return Err(perr(
                            line,
                            "G64 without a rounding distance: edbbgen reads G641 ADIS= (or G60)",
                        ))
                    }
                    "71" | "710" => {}
                    "70" | "700" => {
                        return Err(perr(
                            line,
                            "G70/G700 (inch) is not supported: joint values are degrees",
                        ))
                    }
                    "90" => modal.absolute = true,
                    "91" => {
                        modal.absolute = false;
                        // The values that follow are increments: new absolute values
                        // cannot be written over them.
                        positions.unwritable.get_or_insert(perr(
                            line,
                            "G91 (incremental) is not rewritten: write absolute joint values (G90)",
                        ));
                    }
                    "93" => modal.inverse_time = true,
                    "94" => modal.inverse_time = false,
                    _ => {
                        return Err(perr(
                            line,
                            format!("{word} is not supported in a joint-space program"),
                        ))
                    }
                }
            }
            "M" => match num {
                "0" | "00" | "1" | "01" => b.m_word = Some(true),
                "2" | "02" | "17" | "30" => b.m_word = Some(false),
                _ => return Err(perr(line, format!("{word} is not supported"))),
            },
            "F" => {
                b.f_word = Some(number(line, "F", num)?);
                b.f_span = Some(w_at + 1..w_at + word.len());
            }
            _ => {
                return Err(perr(
                    line,
                    format!("word '{word}' is not supported (axes are written NAME=value)"),
                ))
            }
        }
    }
    Ok(b)
}

pub fn parse(text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
    let mut out = Parsed {
        map: map.clone(),
        ..Parsed::default()
    };
    let names: Vec<String> = map
        .axis_names
        .iter()
        .map(|n| n.to_ascii_uppercase())
        .collect();
    let mut pos: [Option<f64>; 6] = [None; 6];
    let mut modal = Modal {
        absolute: true,
        inverse_time: false,
        blend_mode: false,
        adis: None,
    };
    let mut feed: Option<f64> = None;
    let mut rapid: Option<bool> = None;
    let mut moved = false;
    let mut ended = false;
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let (code, comment) = split(raw);
        let code = code.trim();
        if code.is_empty() {
            if let (Some(c), false) = (comment, moved) {
                push_header(&mut out.header, c);
            }
            continue;
        }
        if ended {
            return Err(perr(line, "code after the program end (M30/M2/M17)"));
        }
        let code_at = offset_in(text, code);
        let upper = code.to_ascii_uppercase();
        if standalone(line, &upper, &names)? {
            continue;
        }
        let b = block(
            line,
            code_at,
            &upper,
            &names,
            &mut modal,
            &mut out.positions,
        )?;
        if b.dwell {
            let t = b.f_word.ok_or_else(|| perr(line, "G4 needs F (seconds)"))?;
            if t < 0.0 {
                return Err(perr(line, "G4 F must be >= 0 seconds"));
            }
            out.lines.push(Line {
                line,
                step: Step::Dwell(t),
                comment: comment.map(str::to_string),
            });
        } else if let Some(f) = b.f_word {
            if f <= 0.0 {
                return Err(perr(line, "F must be positive"));
            }
            feed = Some(f);
        }
        if let Some(g) = b.g_motion {
            rapid = Some(g);
        }
        if b.axis.iter().any(Option::is_some) {
            if b.dwell {
                return Err(perr(line, "G4 and axis motion in one block"));
            }
            let is_rapid =
                rapid.ok_or_else(|| perr(line, "axes without a motion mode (G0 or G1)"))?;
            let mut target = [0.0; 6];
            for i in 0..6 {
                target[i] = match (b.axis[i], pos[i]) {
                    (Some(v), Some(p)) if !modal.absolute => p + v,
                    (Some(v), _) => v,
                    (None, Some(p)) => p,
                    (None, None) => {
                        return Err(perr(
                            line,
                            format!("first move must give all six axes ({} missing)", names[i]),
                        ))
                    }
                };
                pos[i] = Some(target[i]);
            }
            let timing = if is_rapid {
                Timing::Rapid
            } else if modal.inverse_time {
                // With G93 the F word belongs to its block.
                let f = b
                    .f_word
                    .filter(|_| !b.dwell)
                    .ok_or_else(|| perr(line, "G1 in G93 needs its own F (1/min)"))?;
                Timing::Duration(60.0 / f)
            } else {
                Timing::PathFeed(feed.ok_or_else(|| perr(line, "G1 without a feed rate F"))?)
            };
            let blend = if modal.blend_mode && !b.exact_here {
                Some(modal.adis.ok_or_else(|| perr(line, "G641 without ADIS="))?)
            } else {
                None
            };
            out.lines.push(Line {
                line,
                step: Step::Move {
                    target: map.undo(&target),
                    axes: target,
                    timing,
                    blend,
                    corner: None,
                },
                comment: comment.map(str::to_string),
            });
            out.positions.moves.push(MoveSpans {
                line,
                axes: b.axis_spans,
                time: b.f_span,
                time_per_s: 1.0,
                percent: None,
                line_range: offset_in(text, raw)..offset_in(text, raw) + raw.len(),
            });
            moved = true;
        }
        match b.m_word {
            Some(true) => out.lines.push(Line {
                line,
                step: Step::Pause,
                comment: comment.map(str::to_string),
            }),
            Some(false) => {
                out.lines.push(Line {
                    line,
                    step: Step::End,
                    comment: comment.map(str::to_string),
                });
                ended = true;
            }
            None => {}
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Units;

    fn map() -> ControllerMap {
        ControllerMap::identity(Units::Deg, ["X1", "Y1", "Z1", "A1", "B1", "C1"])
    }

    #[test]
    fn reads_moves_blends_pauses() {
        let text = "; EDBB\n; fixture: 1, 2, 3 mm\nG71 G90 G60\nFGROUP(X1, Y1, Z1, A1, B1, C1)\n\
                    G0 X1=1 Y1=2 Z1=3 A1=4 B1=5 C1=6 ; pose 1/2\nMSG(\"Mount\")\nM0\nMSG()\nG93\n\
                    G641 ADIS=10.000\nG1 X1=2 F120 ; pose 2/2\nG60\nG1 Y1=-1 F60 ; support\nG4 F0.5\nM30\n";
        let p = parse(text, &map()).unwrap();
        assert_eq!(p.header_value("fixture"), Some("1, 2, 3 mm"));
        let moves: Vec<_> = p.targets().map(|(_, t)| *t).collect();
        assert_eq!(moves[2], [2.0, -1.0, 3.0, 4.0, 5.0, 6.0]);
        let steps: Vec<&Step> = p.lines.iter().map(|l| &l.step).collect();
        assert!(matches!(steps[1], Step::Pause));
        assert!(
            matches!(steps[2], Step::Move { timing: Timing::Duration(t), blend: Some(b), .. } if *t == 0.5 && *b == 10.0)
        );
        assert!(matches!(steps[3], Step::Move { blend: None, .. }));
        assert!(matches!(steps[4], Step::Dwell(d) if *d == 0.5));
        assert!(matches!(steps[5], Step::End));
    }

    #[test]
    fn rejects_with_the_line_number() {
        for (text, line, msg) in [
            ("G0 X1=1 Y1=2\n", 1, "first move must give all six"),
            (
                "G0 X1=1 Y1=2 Z1=3 A1=4 B1=5 C1=6\nG93\nG1 X1=3\n",
                3,
                "needs its own F",
            ),
            ("G64\n", 1, "G64 without a rounding distance"),
            ("G0 X2=1\n", 1, "not an axis"),
            (
                "G641\nG0 X1=1 Y1=2 Z1=3 A1=4 B1=5 C1=6\n",
                2,
                "G641 without ADIS",
            ),
            ("M30\nG0 X1=1\n", 2, "after the program end"),
            ("G2 X1=1\n", 1, "G2 is not supported"),
        ] {
            let e = parse(text, &map()).unwrap_err();
            assert_eq!(e.line, line, "{text:?}: {e}");
            assert!(e.msg.contains(msg), "{text:?}: {e}");
        }
    }

    #[test]
    fn reads_block_numbers_before_msg_and_fgroup() {
        let text = "; BY HAND\nN10 G71 G90 G60\nN20 FGROUP(X1, Y1, Z1, A1, B1, C1)\n\
                    N30 G0 X1=1 Y1=2 Z1=3 A1=4 B1=5 C1=6\nN40 MSG(\"MOUNT\")\nN50 M0\nN60 G4 F2.0\nN70 M30\n";
        let p = parse(text, &map()).unwrap();
        assert!(matches!(p.lines[2].step, Step::Dwell(t) if t == 2.0));
    }
}

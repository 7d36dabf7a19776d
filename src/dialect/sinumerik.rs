//! SINUMERIK 840D part-program reader (`templates/sinumerik.j2` writes it): in = program text
//! and the controller mapping (its axis names); out = the motions, in program order.
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

use super::{number, perr, push_header, Line, ParseError, Parsed, Step, Timing};
use crate::controller::ControllerMap;

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
    let mut absolute = true;
    let mut inverse_time = false;
    let mut feed: Option<f64> = None;
    let mut rapid: Option<bool> = None;
    let mut blend_mode = false; // G641 active
    let mut adis: Option<f64> = None;
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
        let upper = code.to_ascii_uppercase();
        // Statements that stand alone in their block (after its optional block number).
        let upper = match upper.split_once(char::is_whitespace) {
            Some((n, rest))
                if n.len() > 1
                    && n.starts_with('N')
                    && n[1..].bytes().all(|b| b.is_ascii_digit())
                    && (rest.trim_start().starts_with("MSG(")
                        || rest.trim_start().starts_with("FGROUP(")) =>
            {
                rest.trim_start().to_string()
            }
            _ => upper,
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
            continue;
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
            continue;
        }
        let mut axis: [Option<f64>; 6] = [None; 6];
        let (mut g_motion, mut dwell, mut exact_here) = (None, false, false);
        let (mut f_word, mut m_word) = (None, None);
        for word in upper.split_whitespace() {
            if let Some((name, value)) = word.split_once('=') {
                if name == "ADIS" {
                    let v = number(line, "ADIS", value)?;
                    if v < 0.0 {
                        return Err(perr(line, "ADIS must be >= 0"));
                    }
                    adis = Some(v);
                } else if let Some(i) = names.iter().position(|n| n == name) {
                    if axis[i].is_some() {
                        return Err(perr(line, format!("{name} given twice")));
                    }
                    axis[i] = Some(number(line, name, value)?);
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
                        "0" | "00" => g_motion = Some(true),
                        "1" | "01" => g_motion = Some(false),
                        "4" | "04" => dwell = true,
                        "9" | "09" => exact_here = true,
                        "60" => blend_mode = false,
                        "641" => blend_mode = true,
                        "64" => return Err(perr(
                            line,
                            "G64 without a rounding distance: edbbgen reads G641 ADIS= (or G60)",
                        )),
                        "71" | "710" => {}
                        "70" | "700" => {
                            return Err(perr(
                                line,
                                "G70/G700 (inch) is not supported: joint values are degrees",
                            ))
                        }
                        "90" => absolute = true,
                        "91" => absolute = false,
                        "93" => inverse_time = true,
                        "94" => inverse_time = false,
                        _ => {
                            return Err(perr(
                                line,
                                format!("{word} is not supported in a joint-space program"),
                            ))
                        }
                    }
                }
                "M" => match num {
                    "0" | "00" | "1" | "01" => m_word = Some(true),
                    "2" | "02" | "17" | "30" => m_word = Some(false),
                    _ => return Err(perr(line, format!("{word} is not supported"))),
                },
                "F" => f_word = Some(number(line, "F", num)?),
                _ => {
                    return Err(perr(
                        line,
                        format!("word '{word}' is not supported (axes are written NAME=value)"),
                    ))
                }
            }
        }
        if dwell {
            let t = f_word.ok_or_else(|| perr(line, "G4 needs F (seconds)"))?;
            if t < 0.0 {
                return Err(perr(line, "G4 F must be >= 0 seconds"));
            }
            out.lines.push(Line {
                line,
                step: Step::Dwell(t),
                comment: comment.map(str::to_string),
            });
        } else if let Some(f) = f_word {
            if f <= 0.0 {
                return Err(perr(line, "F must be positive"));
            }
            feed = Some(f);
        }
        if let Some(g) = g_motion {
            rapid = Some(g);
        }
        if axis.iter().any(Option::is_some) {
            if dwell {
                return Err(perr(line, "G4 and axis motion in one block"));
            }
            let is_rapid =
                rapid.ok_or_else(|| perr(line, "axes without a motion mode (G0 or G1)"))?;
            let mut target = [0.0; 6];
            for i in 0..6 {
                target[i] = match (axis[i], pos[i]) {
                    (Some(v), Some(p)) if !absolute => p + v,
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
            } else if inverse_time {
                // With G93 the F word belongs to its block.
                let f = f_word
                    .filter(|_| !dwell)
                    .ok_or_else(|| perr(line, "G1 in G93 needs its own F (1/min)"))?;
                Timing::Duration(60.0 / f)
            } else {
                Timing::PathFeed(feed.ok_or_else(|| perr(line, "G1 without a feed rate F"))?)
            };
            let blend = if blend_mode && !exact_here {
                Some(adis.ok_or_else(|| perr(line, "G641 without ADIS="))?)
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
            moved = true;
        }
        match m_word {
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

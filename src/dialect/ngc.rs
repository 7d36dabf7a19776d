//! RS274/NGC reader (`templates/ngc.j2` writes it): in = program text and the controller
//! mapping; out = the motions it commands ([`Line`]s), in program order, with the modal state
//! that shapes each one.
//!
//! This reader is deliberately independent of the emitter: `verify` and `simulate` must judge a
//! program by its text, not by what the compiler meant. It understands the subset of RS274/NGC
//! that a joint-space measurement program needs and rejects the rest with the line number:
//! - axis words X Y Z A B C = controller axes 1-6 (the mapping's units, degrees by default),
//!   absolute (G90) or incremental (G91);
//! - G0 (rapid, at the joints' maximum speeds) and G1 with feed in G94 (units/min along the
//!   joint-space path) or G93 (inverse time: the move takes 1/F minutes);
//! - G64, with or without P (LinuxCNC's path blending, P its tolerance on X Y Z), and G61
//!   (exact stop); G4 P (dwell, s);
//! - M0/M1 (pause), M2/M30 (end); comments in parentheses or after ';'; optional N words;
//!   `%` lines; the safe-start words G17, G40, G49, G54, G80 (no effect on joint moves);
//! - G21 only (millimetre mode; G20 is refused: degrees do not scale with inches).

use super::{Line, ParseError, Parsed, Step, Timing};
use crate::controller::ControllerMap;

const AXES: &str = "XYZABC";

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FeedMode {
    /// G94: F is the path speed in units per minute.
    UnitsPerMinute,
    /// G93: F is 1 / (duration in minutes).
    InverseTime,
}

/// Parses a program. Positions start unknown: the first move must name all six joints.
pub fn parse(text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
    let mut out = Parsed {
        map: map.clone(),
        ..Parsed::default()
    };
    let mut pos: [Option<f64>; 6] = [None; 6];
    let mut absolute = true;
    let mut feed_mode = FeedMode::UnitsPerMinute;
    let mut feed: Option<f64> = None;
    let mut blend: Option<f64> = None;
    let mut motion: Option<bool> = None; // Some(true) = G0 modal, Some(false) = G1 modal
    let mut seen_code = false;
    let mut ended = false;

    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let err = |msg: String| ParseError { line, msg };
        let (code, comment) = split_comment(raw).map_err(|m| err(m.to_string()))?;
        let code = code.trim();
        // `%` opens and closes a program file (RS274/NGC, LinuxCNC): no code.
        if code.is_empty() || code == "%" {
            if !seen_code {
                if let Some(c) = comment {
                    out.header.push(c);
                }
            }
            continue;
        }
        if ended {
            return Err(err("code after the program end (M2/M30)".into()));
        }
        seen_code = true;
        let words = words(code).map_err(err)?;
        let mut axis: [Option<f64>; 6] = [None; 6];
        let mut g_motion: Option<bool> = None;
        let mut dwell = false;
        let mut p_word: Option<f64> = None;
        let mut m_word: Option<u32> = None;
        let mut blend_cmd: Option<bool> = None; // Some(true) = G64, Some(false) = G61
        for (letter, value) in words {
            match letter {
                'N' => {}
                'G' => match gcode(value) {
                    Some(0) => g_motion = Some(true),
                    Some(1) => g_motion = Some(false),
                    Some(4) => dwell = true,
                    // Modal states a CNC's safe-start line sets that do nothing to joint
                    // moves: XY plane, no cutter compensation, no tool length offset, the
                    // first work offset (as without any), no canned cycle.
                    Some(17 | 21 | 40 | 49 | 54 | 80) => {}
                    Some(20) => {
                        return Err(err(
                            "G20 (inch) is not supported: joint values are degrees, use G21".into(),
                        ))
                    }
                    Some(61) => blend_cmd = Some(false),
                    Some(64) => blend_cmd = Some(true),
                    Some(90) => absolute = true,
                    Some(91) => absolute = false,
                    Some(93) => feed_mode = FeedMode::InverseTime,
                    Some(94) => feed_mode = FeedMode::UnitsPerMinute,
                    _ => {
                        return Err(err(format!(
                            "G{} is not supported in a joint-space program",
                            fmt_num(value)
                        )))
                    }
                },
                'M' => match gcode(value) {
                    Some(m @ (0 | 1 | 2 | 30)) => m_word = Some(m),
                    _ => return Err(err(format!("M{} is not supported", fmt_num(value)))),
                },
                'F' => {
                    if !(value.is_finite() && value > 0.0) {
                        return Err(err(format!("F{} must be positive", fmt_num(value))));
                    }
                    feed = Some(value);
                }
                'P' => p_word = Some(value),
                'Q' => {}
                c if AXES.contains(c) => {
                    let i = AXES.find(c).unwrap_or(0);
                    if axis[i].is_some() {
                        return Err(err(format!("{c} given twice")));
                    }
                    axis[i] = Some(value);
                }
                c => return Err(err(format!("word {c} is not supported"))),
            }
        }
        let comment_text = comment;
        if let Some(b) = blend_cmd {
            blend = if b {
                // P is LinuxCNC's path tolerance on X Y Z; without it the planner keeps the best
                // speed. Either way a corner may take up to half of each move (the corner model).
                let p = p_word.unwrap_or(0.0);
                if !(p.is_finite() && p >= 0.0) {
                    return Err(err("G64 P must be a tolerance >= 0".into()));
                }
                Some(p)
            } else {
                None
            };
        }
        if dwell {
            let p = p_word.ok_or_else(|| err("G4 needs P (seconds)".into()))?;
            if !(p.is_finite() && p >= 0.0) {
                return Err(err("G4 P must be >= 0 seconds".into()));
            }
            out.lines.push(Line {
                line,
                step: Step::Dwell(p),
                comment: comment_text.clone(),
            });
        }
        if let Some(g) = g_motion {
            motion = Some(g);
        }
        if axis.iter().any(Option::is_some) {
            let rapid =
                motion.ok_or_else(|| err("axis words without a motion mode (G0 or G1)".into()))?;
            let mut target = [0.0; 6];
            for i in 0..6 {
                target[i] = match (axis[i], pos[i]) {
                    (Some(v), Some(p)) if !absolute => p + v,
                    (Some(v), _) => v,
                    (None, Some(p)) => p,
                    (None, None) => {
                        return Err(err(format!(
                            "first move must give all six joints ({} missing)",
                            AXES.chars().nth(i).unwrap_or('?')
                        )))
                    }
                };
                if !target[i].is_finite() {
                    return Err(err("joint value is not finite".into()));
                }
                pos[i] = Some(target[i]);
            }
            let timing = if rapid {
                Timing::Rapid
            } else {
                let f = feed.ok_or_else(|| err("G1 without a feed rate F".into()))?;
                match feed_mode {
                    FeedMode::InverseTime => Timing::Duration(60.0 / f),
                    FeedMode::UnitsPerMinute => Timing::PathFeed(f),
                }
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
                comment: comment_text.clone(),
            });
            if feed_mode == FeedMode::InverseTime && !rapid {
                // RS274: in G93 every G1 needs its own F.
                feed = None;
            }
        } else if g_motion.is_some() && !dwell && blend_cmd.is_none() {
            // G0/G1 alone just sets the mode.
        }
        match m_word {
            Some(0 | 1) => out.lines.push(Line {
                line,
                step: Step::Pause,
                comment: comment_text,
            }),
            Some(_) => {
                out.lines.push(Line {
                    line,
                    step: Step::End,
                    comment: comment_text,
                });
                ended = true;
            }
            None => {}
        }
    }
    Ok(out)
}

fn gcode(v: f64) -> Option<u32> {
    let r = v.round();
    ((v - r).abs() < 1e-9 && r >= 0.0).then_some(r as u32)
}

fn fmt_num(v: f64) -> String {
    if v.fract() == 0.0 {
        format!("{}", v as i64)
    } else {
        format!("{v}")
    }
}

/// Splits a line into code and the text of its comments (parentheses or ';').
fn split_comment(raw: &str) -> Result<(String, Option<String>), &'static str> {
    let mut code = String::with_capacity(raw.len());
    let mut comments: Vec<String> = Vec::new();
    let mut chars = raw.chars();
    while let Some(c) = chars.next() {
        match c {
            '(' => {
                let mut text = String::new();
                loop {
                    match chars.next() {
                        Some(')') => break,
                        Some('(') => return Err("nested comment"),
                        Some(ch) => text.push(ch),
                        None => return Err("unclosed comment"),
                    }
                }
                comments.push(text.trim().to_string());
            }
            ';' => {
                comments.push(chars.by_ref().collect::<String>().trim().to_string());
                break;
            }
            _ => code.push(c),
        }
    }
    let comment = if comments.is_empty() {
        None
    } else {
        Some(comments.join(" "))
    };
    Ok((code, comment))
}

/// Words of a code line: letter + number, spaces allowed between them.
fn words(code: &str) -> Result<Vec<(char, f64)>, String> {
    let s: Vec<char> = code.chars().filter(|c| !c.is_whitespace()).collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < s.len() {
        let letter = s[i].to_ascii_uppercase();
        if !letter.is_ascii_alphabetic() {
            return Err(format!("unexpected '{}'", s[i]));
        }
        i += 1;
        let start = i;
        while i < s.len() && (s[i].is_ascii_digit() || matches!(s[i], '.' | '-' | '+')) {
            i += 1;
        }
        let num: String = s[start..i].iter().collect();
        let value: f64 = num
            .parse()
            .map_err(|_| format!("{letter} needs a number, got '{num}'"))?;
        out.push((letter, value));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Units;

    fn parse(text: &str) -> Result<Parsed, ParseError> {
        super::parse(
            text,
            &ControllerMap::identity(Units::Deg, ["X", "Y", "Z", "A", "B", "C"]),
        )
    }

    #[test]
    fn reads_an_edbbgen_program() {
        let text = "(EDBB program)\n(fixture: 258.000, 1468.000, 708.000 mm in the robot base frame)\nG21 G90 G94\nG64 P10.000 (blend)\n\
                    G0 X1 Y2 Z3 A4 B5 C6 (pose 1/3)\nM0 (mount)\nG93\nG1 X2 F120 (pose 2/3)\nG1 Y-1 F60\nG94\nG4 P0.5\nM0\nM2\n";
        let p = parse(text).unwrap();
        assert_eq!(p.header.len(), 2);
        assert_eq!(
            p.header_value("fixture"),
            Some("258.000, 1468.000, 708.000 mm in the robot base frame")
        );
        let moves: Vec<_> = p.targets().map(|(_, t)| *t).collect();
        assert_eq!(
            moves,
            vec![
                [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
                [2.0, 2.0, 3.0, 4.0, 5.0, 6.0],
                [2.0, -1.0, 3.0, 4.0, 5.0, 6.0]
            ]
        );
        match &p.lines[2].step {
            Step::Move {
                timing: Timing::Duration(t),
                blend: Some(b),
                ..
            } => {
                assert_eq!((*t, *b), (0.5, 10.0))
            }
            s => panic!("{s:?}"),
        }
        assert!(matches!(p.lines[4].step, Step::Dwell(d) if d == 0.5));
        assert!(matches!(p.lines.last().unwrap().step, Step::End));
        assert_eq!(p.lines[2].comment.as_deref(), Some("pose 2/3"));
    }

    #[test]
    fn rejects_with_the_line_number() {
        let bad = [
            ("G0 X1 Y2 Z3\n", 1, "first move must give all six joints"),
            (
                "G0 X1 Y2 Z3 A4 B5 C6\nG93\nG1 X2\n",
                3,
                "G1 without a feed rate",
            ),
            ("G0 X1 Y2 Z3 A4 B5 C6\nG2 X2\n", 2, "G2 is not supported"),
            ("G20\n", 1, "G20"),
            ("G0 X1 (open\n", 1, "unclosed comment"),
            ("G0 Xabc\n", 1, "X needs a number"),
            ("M2\nG0 X1\n", 2, "after the program end"),
            ("G64 P-1\n", 1, "G64 P must be a tolerance"),
        ];
        for (text, line, msg) in bad {
            let e = parse(text).unwrap_err();
            assert_eq!(e.line, line, "{text:?}: {e}");
            assert!(e.msg.contains(msg), "{text:?}: {e}");
        }
    }

    #[test]
    fn incremental_moves_accumulate() {
        let p = parse("G0 X0 Y0 Z0 A0 B0 C0\nG91 G0 X10 C-5\nG0 X10\n").unwrap();
        let last = p.targets().last().unwrap().1;
        assert_eq!(*last, [20.0, 0.0, 0.0, 0.0, 0.0, -5.0]);
    }

    #[test]
    fn reads_percent_lines_and_a_safe_start() {
        let p = parse(
            "%\n(by hand)\nG21 G90 G94 G17 G40 G49 G80 G54\nG0 X1 Y2 Z3 A4 B5 C6\nG4 P2\nM2\n%\n",
        )
        .unwrap();
        assert_eq!(p.header, vec!["by hand".to_string()]);
        assert!(matches!(p.lines[1].step, Step::Dwell(t) if t == 2.0));
    }
}

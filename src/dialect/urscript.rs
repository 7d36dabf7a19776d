//! Universal Robots URScript reader (`templates/urscript.j2` writes it): in = a `.script`
//! program and the controller mapping; out = the motions, in program order.
//!
//! The subset a joint-space measurement program needs, strictly:
//! - one `def name():` … `end`; comments after `#`; one call or assignment per line, no
//!   control flow; a name assigned joint positions `[q1, …, q6]` or a number (`global`/`local`
//!   allowed) stands for them in later calls; `d2r(x)` converts a literal in degrees;
//! - `movej([q1, …, q6], a=…, v=…, t=…, r=…)` (positional or named; radians; `t` > 0 is the
//!   move's time, else `v` the leading joint's speed; `r` the blend radius in metres at the TCP,
//!   0 = stop);
//! - `popup(…, blocking=True)` (the operator's pause: a popup that does not block is refused),
//!   `sleep(t)` (dwell), `halt()` (end), `set_tcp(p[…])`, `textmsg(…)`, `set_payload(…)`.

use super::{number, perr, push_header, Line, ParseError, Parsed, Step, Timing};
use crate::controller::ControllerMap;

/// Splits a line into code and the comment after `#` (outside strings).
fn split(raw: &str) -> (&str, Option<&str>) {
    let mut quote: Option<char> = None;
    for (k, c) in raw.char_indices() {
        match (c, quote) {
            ('"' | '\'', None) => quote = Some(c),
            (c, Some(q)) if c == q => quote = None,
            ('#', None) => return (&raw[..k], Some(raw[k + 1..].trim())),
            _ => {}
        }
    }
    (raw, None)
}

/// Splits arguments at commas outside brackets and strings.
fn args(s: &str) -> Vec<&str> {
    let (mut depth, mut quote, mut start) = (0i32, None::<char>, 0);
    let mut out = Vec::new();
    for (k, c) in s.char_indices() {
        match (c, quote) {
            ('"' | '\'', None) => quote = Some(c),
            (c, Some(q)) if c == q => quote = None,
            ('[' | '(', None) => depth += 1,
            (']' | ')', None) => depth -= 1,
            (',', None) if depth == 0 => {
                out.push(s[start..k].trim());
                start = k + 1;
            }
            _ => {}
        }
    }
    let last = s[start..].trim();
    if !last.is_empty() || !out.is_empty() {
        out.push(last);
    }
    out
}

/// A value a program assigns to a name: joint positions or a number.
#[derive(Clone, Copy)]
enum Value {
    Joints([f64; 6]),
    Number(f64),
}

/// A number: a literal, `d2r(literal)` (degrees to radians), or a variable holding one.
fn scalar(line: usize, what: &str, s: &str, vars: &[(String, Value)]) -> Result<f64, ParseError> {
    let s = s.trim();
    if let Some(deg) = s.strip_prefix("d2r(").and_then(|r| r.strip_suffix(')')) {
        return Ok(number(line, what, deg)?.to_radians());
    }
    if s.starts_with(|c: char| c.is_ascii_alphabetic() || c == '_') {
        return match vars.iter().rev().find(|(n, _)| n == s) {
            Some((_, Value::Number(x))) => Ok(*x),
            Some(_) => Err(perr(
                line,
                format!("{what}: {s} holds joint positions, not a number"),
            )),
            None => Err(perr(line, format!("{what}: '{s}' is not assigned before"))),
        };
    }
    number(line, what, s)
}

/// Joint positions: a list `[q1, ..., q6]` (numbers or `d2r(…)`) or a variable holding one.
fn joints(line: usize, s: &str, vars: &[(String, Value)]) -> Result<[f64; 6], ParseError> {
    let s = s.trim();
    let Some(list) = s.strip_prefix('[').and_then(|r| r.strip_suffix(']')) else {
        return match vars.iter().rev().find(|(n, _)| n == s) {
            Some((_, Value::Joints(q))) => Ok(*q),
            _ => Err(perr(
                line,
                "movej takes the joint positions as a list [q1, ..., q6] (radians) or a name assigned one",
            )),
        };
    };
    let v: Vec<f64> = args(list)
        .iter()
        .map(|x| scalar(line, "joint position", x, vars))
        .collect::<Result<_, _>>()?;
    if v.len() != 6 {
        return Err(perr(
            line,
            format!("movej needs 6 joint positions, not {}", v.len()),
        ));
    }
    Ok(std::array::from_fn(|i| v[i]))
}

/// `name = value` (optionally `global`/`local`), if the line is an assignment.
fn assignment(code: &str) -> Option<(&str, &str)> {
    let code = code
        .strip_prefix("global ")
        .or_else(|| code.strip_prefix("local "))
        .unwrap_or(code);
    let (lhs, rhs) = code.split_once('=')?;
    let lhs = lhs.trim();
    let ident = lhs
        .chars()
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && lhs.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    (ident && !rhs.starts_with('=')).then_some((lhs, rhs.trim()))
}

pub fn parse(text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
    let mut out = Parsed {
        map: map.clone(),
        ..Parsed::default()
    };
    let (mut in_def, mut ended, mut moved) = (false, false, false);
    let mut vars: Vec<(String, Value)> = Vec::new();
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
            return Err(perr(line, "code after the program's end"));
        }
        if !in_def {
            let rest = code
                .strip_prefix("def ")
                .ok_or_else(|| perr(line, "a URScript program starts with def name():"))?;
            let name = rest.trim().strip_suffix("():").unwrap_or("");
            if !super::valid_name(name, 64) {
                return Err(perr(
                    line,
                    format!("def {}: not 'def name():'", rest.trim()),
                ));
            }
            in_def = true;
            continue;
        }
        if code == "end" {
            out.lines.push(Line {
                line,
                step: Step::End,
                comment: None,
            });
            ended = true;
            continue;
        }
        if let Some((name, value)) = assignment(code) {
            let v = if value.starts_with('[') {
                Value::Joints(joints(line, value, &vars)?)
            } else {
                Value::Number(scalar(line, name, value, &vars).map_err(|_| {
                    perr(
                        line,
                        format!("{name} = {value}: edbbgen reads names assigned joint positions [q1, ..., q6] or a number"),
                    )
                })?)
            };
            vars.push((name.to_string(), v));
            continue;
        }
        let (name, rest) = code
            .split_once('(')
            .ok_or_else(|| perr(line, format!("'{code}' is not a call edbbgen reads")))?;
        let inner = rest
            .strip_suffix(')')
            .ok_or_else(|| perr(line, "a call ends with ')'"))?;
        let a = args(inner);
        let named = |key: &str| {
            a.iter().find_map(|x| {
                x.split_once('=')
                    .filter(|(k, _)| k.trim() == key)
                    .map(|(_, v)| v.trim())
            })
        };
        let comment = comment.map(str::to_string);
        match name.trim() {
            "movej" => {
                let axes = joints(line, a.first().copied().unwrap_or(""), &vars)?;
                // Positional a, v, t, r after q, or named.
                let positional: Vec<&str> = a[1..]
                    .iter()
                    .copied()
                    .filter(|x| !x.contains('='))
                    .collect();
                for x in a[1..].iter().filter(|x| x.contains('=')) {
                    let key = x.split('=').next().unwrap_or("").trim();
                    if !["a", "v", "t", "r"].contains(&key) {
                        return Err(perr(line, format!("movej has no argument '{key}'")));
                    }
                }
                if positional.len() > 4 {
                    return Err(perr(line, "movej takes q, a, v, t, r"));
                }
                let arg = |key: &str, idx: usize, default: f64| -> Result<f64, ParseError> {
                    match named(key).or(positional.get(idx).copied()) {
                        Some(s) => {
                            let x = scalar(line, key, s, &vars)?;
                            if x < 0.0 {
                                return Err(perr(line, format!("movej {key} must be >= 0")));
                            }
                            Ok(x)
                        }
                        None => Ok(default),
                    }
                };
                let (acc, speed, t, r) = (
                    arg("a", 0, 1.4)?,
                    arg("v", 1, 1.05)?,
                    arg("t", 2, 0.0)?,
                    arg("r", 3, 0.0)?,
                );
                if acc <= 0.0 || speed <= 0.0 {
                    return Err(perr(line, "movej a and v must be positive"));
                }
                let timing = if t > 0.0 {
                    Timing::Duration(t)
                } else {
                    Timing::LeadSpeed(speed)
                };
                let blend = (r > 0.0).then_some(r * 1e3);
                out.lines.push(Line {
                    line,
                    step: Step::Move {
                        target: map.undo(&axes),
                        axes,
                        timing,
                        blend,
                        corner: None,
                    },
                    comment,
                });
                moved = true;
            }
            "popup" => {
                if named("blocking") != Some("True") {
                    return Err(perr(
                        line,
                        "popup without blocking=True does not wait for the operator",
                    ));
                }
                let msg = a.first().copied().unwrap_or("");
                if !(msg.len() >= 2
                    && (msg.starts_with('"') && msg.ends_with('"')
                        || msg.starts_with('\'') && msg.ends_with('\'')))
                {
                    return Err(perr(line, "popup's first argument is the message text"));
                }
                out.lines.push(Line {
                    line,
                    step: Step::Pause,
                    comment,
                });
            }
            "sleep" => {
                let t = scalar(line, "sleep", a.first().copied().unwrap_or(""), &vars)?;
                if t < 0.0 {
                    return Err(perr(line, "sleep needs a time >= 0"));
                }
                out.lines.push(Line {
                    line,
                    step: Step::Dwell(t),
                    comment,
                });
            }
            "halt" => {
                out.lines.push(Line {
                    line,
                    step: Step::End,
                    comment,
                });
            }
            "set_tcp" => {
                let p = a.first().copied().unwrap_or("");
                let list = p
                    .strip_prefix("p[")
                    .and_then(|r| r.strip_suffix(']'))
                    .ok_or_else(|| perr(line, "set_tcp takes a pose p[x, y, z, rx, ry, rz]"))?;
                let n = list
                    .split(',')
                    .map(|x| number(line, "set_tcp", x))
                    .collect::<Result<Vec<_>, _>>()?;
                if n.len() != 6 {
                    return Err(perr(line, "set_tcp takes a pose of 6 numbers"));
                }
            }
            "textmsg" | "set_payload" => {}
            other => {
                return Err(perr(
                    line,
                    format!(
                    "'{other}' is not a call edbbgen reads (movej, popup, sleep, halt, set_tcp)"
                ),
                ))
            }
        }
    }
    if !in_def {
        return Err(perr(0, "no def: not a URScript program"));
    }
    if !ended {
        return Err(perr(text.lines().count(), "the program has no end"));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Units;

    fn map() -> ControllerMap {
        ControllerMap::identity(
            Units::Rad,
            ["base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3"],
        )
    }

    const OK: &str = "def edbb():\n  # fixture: 1, 2, 3 mm\n  set_tcp(p[0.06, 0.03, 0.12, 0, 0, 0])\n\
        movej([0.1, 0.2, 0.3, 0.4, 0.5, 0.6], a=1.4, v=1.05, r=0)  # pose 1/2\n\
        popup(\"Mount the bar\", title=\"EDBB\", blocking=True)\n  movej([0.2, 0.2, 0.3, 0.4, 0.5, 0.6], t=0.7, r=0.01)  # support\n\
        sleep(0.5)\nend\n";

    #[test]
    fn reads_movej_time_blend_and_popups() {
        let p = parse(OK, &map()).unwrap();
        assert_eq!(p.header_value("fixture"), Some("1, 2, 3 mm"));
        let steps: Vec<&Step> = p.lines.iter().map(|l| &l.step).collect();
        assert!(
            matches!(steps[0], Step::Move { timing: Timing::LeadSpeed(v), blend: None, .. } if *v == 1.05)
        );
        assert!(matches!(steps[1], Step::Pause));
        assert!(
            matches!(steps[2], Step::Move { timing: Timing::Duration(t), blend: Some(b), target, .. }
            if *t == 0.7 && (*b - 10.0).abs() < 1e-12 && (target[0] - 0.2f64.to_degrees()).abs() < 1e-12)
        );
        assert_eq!(p.lines[2].comment.as_deref(), Some("support"));
        assert!(matches!(steps[3], Step::Dwell(_)));
        assert!(matches!(steps[4], Step::End));
    }

    #[test]
    fn rejects_with_the_line_number() {
        for (from, to, msg) in [
            ("blocking=True", "blocking=False", "does not wait"),
            (
                "[0.2, 0.2, 0.3, 0.4, 0.5, 0.6]",
                "[0.2, 0.2, 0.3]",
                "6 joint positions",
            ),
            ("sleep(0.5)", "movel(p[0, 0, 0, 0, 0, 0])", "'movel' is not"),
            ("end\n", "", "no end"),
            ("t=0.7", "q=0.7", "no argument 'q'"),
        ] {
            let text = OK.replacen(from, to, 1);
            let e = parse(&text, &map()).unwrap_err();
            assert!(e.msg.contains(msg), "{to:?}: {e}");
        }
    }

    #[test]
    fn reads_named_joint_lists_numbers_and_degrees() {
        let text = "def mine():\n  # by hand\n  global home = [d2r(0), d2r(-90), d2r(90), 0, 0, 0]\n  \
            p1 = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]\n  vel = 0.5\n  wait = 2\n  movej(home, a=1.2, v=vel)\n  \
            movej(p1, 1.2, vel)\n  sleep(wait)\nend\n";
        let p = parse(text, &map()).unwrap();
        let steps: Vec<&Step> = p.lines.iter().map(|l| &l.step).collect();
        assert!(
            matches!(steps[0], Step::Move { timing: Timing::LeadSpeed(v), target, .. }
            if *v == 0.5 && (target[1] + 90.0).abs() < 1e-9 && (target[2] - 90.0).abs() < 1e-9)
        );
        assert!(
            matches!(steps[1], Step::Move { target, .. } if (target[5] - 0.6f64.to_degrees()).abs() < 1e-12)
        );
        assert!(matches!(steps[2], Step::Dwell(t) if *t == 2.0));
        for (bad, msg) in [
            ("movej(p2, a=1.2, v=vel)", "a name assigned one"),
            ("sleep(p1)", "holds joint positions"),
            (
                "q = get_actual_joint_positions()",
                "edbbgen reads names assigned",
            ),
        ] {
            let e = parse(&text.replace("sleep(wait)", bad), &map()).unwrap_err();
            assert!(e.msg.contains(msg), "{bad}: {e}");
        }
    }
}

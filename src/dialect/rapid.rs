//! ABB RAPID reader (`templates/rapid.j2` writes it): in = a program module and the
//! controller mapping; out = the motions of its `main` routine, in program order.
//!
//! The subset a joint-space measurement program needs, strictly:
//! - `MODULE name` … `ENDMODULE`; data declarations (`CONST|PERS|VAR type name := value;`)
//!   before the routine; one `PROC main()` … `ENDPROC`; comments are `!` lines of their own
//!   or follow a statement's `;`;
//! - `MoveAbsJ jointtarget[\NoEOffs], speed[\T:=t], zone, tool;` with the jointtarget literal
//!   (`[[j1..j6], [external axes]]`, degrees) or a declared one; `\T` is the move's time (a
//!   move without it runs at speed data that verify cannot turn into joint speeds: only the
//!   approach may); zone `fine` (exact stop), a built-in `zN` or a declared zonedata
//!   (`pzone_tcp`, mm at the tool's TCP); the tool a declared tooldata or `tool0`;
//! - `TPWrite "…";` (at most 80 characters), `Stop;` (pause), `WaitTime [\InPos,] t;`
//!   (dwell; `\InPos` starts it once the robot stands still),
//!   `ConfJ`/`ConfL`.

use super::{number, perr, push_header, Line, ParseError, Parsed, Step, Timing};
use crate::controller::ControllerMap;

/// Built-in zonedata: name → the largest of its pzone_tcp, pzone_ori and pzone_eax (mm): the
/// corner path may begin (tool reorientation, external axes) anywhere within it (ABB's
/// predefined zones: pzone_ori = pzone_eax = 1.5 × pzone_tcp from z5 on).
const ZONES: &[(&str, f64)] = &[
    ("z0", 0.3),
    ("z1", 1.0),
    ("z5", 8.0),
    ("z10", 15.0),
    ("z15", 23.0),
    ("z20", 30.0),
    ("z30", 45.0),
    ("z40", 60.0),
    ("z50", 75.0),
    ("z60", 90.0),
    ("z80", 120.0),
    ("z100", 150.0),
    ("z150", 225.0),
    ("z200", 300.0),
];

/// RAPID identifiers: a letter, then letters, digits and `_`, at most 32 characters.
pub fn valid_name(name: &str) -> bool {
    super::valid_name(name, 32)
}

struct Data {
    ty: String,
    name: String,
    value: String,
}

/// Splits `s` at `sep` outside brackets and strings.
fn split_top(s: &str, sep: char) -> Vec<&str> {
    let (mut depth, mut in_str, mut start) = (0i32, false, 0);
    let mut out = Vec::new();
    for (k, c) in s.char_indices() {
        match c {
            '"' => in_str = !in_str,
            '[' | '(' if !in_str => depth += 1,
            ']' | ')' if !in_str => depth -= 1,
            c if c == sep && depth == 0 && !in_str => {
                out.push(&s[start..k]);
                start = k + c.len_utf8();
            }
            _ => {}
        }
    }
    out.push(&s[start..]);
    out
}

/// The numbers of a flat list `[a, b, …]`.
fn list(line: usize, what: &str, s: &str) -> Result<Vec<f64>, ParseError> {
    let inner = s
        .trim()
        .strip_prefix('[')
        .and_then(|r| r.strip_suffix(']'))
        .ok_or_else(|| perr(line, format!("{what}: '{}' is not a list [..]", s.trim())))?;
    inner.split(',').map(|v| number(line, what, v)).collect()
}

pub fn parse(text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
    let mut out = Parsed {
        map: map.clone(),
        ..Parsed::default()
    };
    #[derive(PartialEq)]
    enum At {
        Start,
        Module,
        Proc,
        AfterProc,
        End,
    }
    let mut at = At::Start;
    let mut data: Vec<Data> = Vec::new();
    let mut pending_comment: Option<String> = None;
    let mut moved = false;
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let code = raw.trim();
        if code.is_empty() {
            continue;
        }
        if let Some(c) = code.strip_prefix('!') {
            // Comments before the first move are the header; inside the routine a comment line
            // goes with the statement after it.
            if !moved {
                push_header(&mut out.header, c);
            }
            if at == At::Proc {
                pending_comment = Some(c.trim().to_string());
            }
            continue;
        }
        // A comment after a complete statement or declaration goes with it.
        let parts = split_top(code, '!');
        let code = match parts.as_slice() {
            [_] => code,
            [stmt, ..] if stmt.trim_end().ends_with(';') => {
                let c = code[stmt.len() + 1..].trim().to_string();
                if at == At::Proc {
                    pending_comment = Some(c);
                }
                stmt.trim_end()
            }
            _ => {
                return Err(perr(
                    line,
                    "a RAPID comment ('!') follows a complete statement (';') or takes a line of its own",
                ))
            }
        };
        let upper = code.to_ascii_uppercase();
        match at {
            At::Start => {
                let name = upper
                    .strip_prefix("MODULE ")
                    .ok_or_else(|| perr(line, "a RAPID program module starts with MODULE name"))?;
                let name = name.split('(').next().unwrap_or("").trim();
                if !valid_name(name) {
                    return Err(perr(line, format!("MODULE {name}: not a RAPID name (a letter, letters/digits/_, at most 32)")));
                }
                at = At::Module;
                continue;
            }
            At::End => return Err(perr(line, "code after ENDMODULE")),
            At::AfterProc | At::Module if upper == "ENDMODULE" => {
                if at == At::Module {
                    return Err(perr(line, "the module has no PROC main()"));
                }
                at = At::End;
                continue;
            }
            At::Module => {
                if upper.replace(' ', "") == "PROCMAIN()" {
                    at = At::Proc;
                    continue;
                }
                let stmt = code
                    .strip_suffix(';')
                    .ok_or_else(|| perr(line, "a declaration ends with ';'"))?;
                let mut words = stmt.splitn(2, ":=");
                let decl = words.next().unwrap_or("");
                let value = words
                    .next()
                    .ok_or_else(|| perr(line, "a declaration needs ':= value' (or PROC main())"))?;
                let w: Vec<&str> = decl.split_whitespace().collect();
                let w = match w.first().map(|s| s.to_ascii_uppercase()) {
                    Some(s) if s == "LOCAL" || s == "TASK" => &w[1..],
                    _ => &w[..],
                };
                let [kind, ty, name] = w else {
                    return Err(perr(
                        line,
                        "a declaration is CONST|PERS|VAR type name := value;",
                    ));
                };
                if !matches!(kind.to_ascii_uppercase().as_str(), "CONST" | "PERS" | "VAR")
                    || !valid_name(ty)
                    || !valid_name(name)
                {
                    return Err(perr(
                        line,
                        "a declaration is CONST|PERS|VAR type name := value;",
                    ));
                }
                if data.iter().any(|d| d.name.eq_ignore_ascii_case(name)) {
                    return Err(perr(line, format!("'{name}' declared twice")));
                }
                let v = value.trim();
                if v.matches('[').count() != v.matches(']').count() {
                    return Err(perr(
                        line,
                        format!("the value of {name} has unbalanced brackets"),
                    ));
                }
                data.push(Data {
                    ty: ty.to_ascii_lowercase(),
                    name: name.to_string(),
                    value: v.to_string(),
                });
                continue;
            }
            At::AfterProc => return Err(perr(line, "only one routine, PROC main(), is read")),
            At::Proc => {}
        }
        // Inside PROC main().
        if upper == "ENDPROC" {
            at = At::AfterProc;
            continue;
        }
        let stmt = code
            .strip_suffix(';')
            .ok_or_else(|| perr(line, "a statement ends with ';'"))?
            .trim();
        let comment = pending_comment.take();
        let (word, args) = stmt
            .split_once(|c: char| c.is_whitespace())
            .unwrap_or((stmt, ""));
        match word.to_ascii_uppercase().as_str() {
            "MOVEABSJ" => {
                let parts = split_top(args, ',');
                if parts.len() != 4 {
                    return Err(perr(line, "MoveAbsJ takes jointtarget, speed, zone, tool"));
                }
                let opt = |p: &str| -> Vec<String> {
                    split_top(p, '\\')
                        .iter()
                        .map(|s| s.trim().to_string())
                        .collect()
                };
                let (jt, speed, zone, tool) =
                    (opt(parts[0]), opt(parts[1]), opt(parts[2]), opt(parts[3]));
                let lookup = |name: &str, ty: &str| {
                    data.iter()
                        .find(|d| d.name.eq_ignore_ascii_case(name) && d.ty == ty)
                        .map(|d| d.value.clone())
                };
                let jt_value = if jt[0].starts_with('[') {
                    jt[0].clone()
                } else {
                    lookup(&jt[0], "jointtarget").ok_or_else(|| {
                        perr(line, format!("'{}' is not a declared jointtarget", jt[0]))
                    })?
                };
                for s in &jt[1..] {
                    if !(s.eq_ignore_ascii_case("NoEOffs")
                        || s.to_ascii_uppercase().starts_with("ID:="))
                    {
                        return Err(perr(
                            line,
                            format!("\\{s} is not an argument of the jointtarget"),
                        ));
                    }
                }
                let inner = jt_value
                    .trim()
                    .strip_prefix('[')
                    .and_then(|r| r.strip_suffix(']'))
                    .ok_or_else(|| perr(line, "a jointtarget is [[robax], [extax]]"))?;
                let halves = split_top(inner, ',');
                if halves.len() != 2 {
                    return Err(perr(line, "a jointtarget is [[robax], [extax]]"));
                }
                let robax = list(line, "robax", halves[0])?;
                let extax = list(line, "extax", halves[1])?;
                if robax.len() != 6 || extax.len() != 6 {
                    return Err(perr(
                        line,
                        "a jointtarget has 6 robot and 6 external axis values",
                    ));
                }
                let axes: [f64; 6] = std::array::from_fn(|i| robax[i]);
                // Speed: \T is the time; speed data alone is a TCP speed.
                let mut timing = Timing::Unknown;
                let sp = &speed[0];
                if !(sp.eq_ignore_ascii_case("vmax")
                    || sp.starts_with(['v', 'V']) && sp[1..].parse::<f64>().is_ok()
                    || lookup(sp, "speeddata").is_some())
                {
                    return Err(perr(
                        line,
                        format!("'{sp}' is not speed data (vN, vmax or a declared speeddata)"),
                    ));
                }
                for s in &speed[1..] {
                    match s.split_once(":=") {
                        Some((n, v)) if n.trim().eq_ignore_ascii_case("T") => {
                            let t = number(line, "\\T", v)?;
                            if t <= 0.0 {
                                return Err(perr(line, "\\T must be a positive time (s)"));
                            }
                            timing = Timing::Duration(t);
                        }
                        Some((n, _)) if n.trim().eq_ignore_ascii_case("V") => {}
                        _ => {
                            return Err(perr(
                                line,
                                format!("\\{s} is not an argument of the speed"),
                            ))
                        }
                    }
                }
                let z = &zone[0];
                let blend = if z.eq_ignore_ascii_case("fine") {
                    None
                } else if let Some((_, tcp)) = ZONES.iter().find(|(n, _)| n.eq_ignore_ascii_case(z))
                {
                    Some(*tcp)
                } else {
                    let v = lookup(z, "zonedata").ok_or_else(|| {
                        perr(
                            line,
                            format!("'{z}' is not fine, a zN or a declared zonedata"),
                        )
                    })?;
                    let inner = v
                        .trim()
                        .strip_prefix('[')
                        .and_then(|r| r.strip_suffix(']'))
                        .unwrap_or("");
                    let f: Vec<&str> = inner.split(',').map(str::trim).collect();
                    if f.len() != 7 {
                        return Err(perr(line, format!("zonedata {z} has 7 fields")));
                    }
                    if f[0].eq_ignore_ascii_case("TRUE") {
                        None
                    } else if f[0].eq_ignore_ascii_case("FALSE") {
                        // The zone any part of the corner path may begin in.
                        let tcp = number(line, "pzone_tcp", f[1])?;
                        let ori = number(line, "pzone_ori", f[2])?;
                        let eax = number(line, "pzone_eax", f[3])?;
                        Some(tcp.max(ori).max(eax))
                    } else {
                        return Err(perr(
                            line,
                            format!("zonedata {z}: finep must be TRUE or FALSE"),
                        ));
                    }
                };
                if zone.len() > 1 {
                    return Err(perr(line, "\\Z and \\Inpos are not read: use zonedata"));
                }
                if !(tool[0].eq_ignore_ascii_case("tool0")
                    || lookup(&tool[0], "tooldata").is_some())
                {
                    return Err(perr(
                        line,
                        format!("'{}' is not a declared tooldata", tool[0]),
                    ));
                }
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
            "TPWRITE" => {
                let s = args.trim();
                if !(s.len() >= 2 && s.starts_with('"') && s.ends_with('"')) || s.len() - 2 > 80 {
                    return Err(perr(
                        line,
                        "TPWrite takes one string of at most 80 characters",
                    ));
                }
            }
            "STOP" => out.lines.push(Line {
                line,
                step: Step::Pause,
                comment,
            }),
            "WAITTIME" => {
                // `\InPos`: the time starts once the robot stands still (a dwell after a stop).
                let a = args.trim();
                let a = match a.get(..6) {
                    Some(w) if w.eq_ignore_ascii_case("\\InPos") => {
                        a[6..].trim_start().strip_prefix(',').unwrap_or(&a[6..])
                    }
                    _ => a,
                };
                let t = number(line, "WaitTime", a)?;
                if t < 0.0 {
                    return Err(perr(line, "WaitTime needs a time >= 0"));
                }
                out.lines.push(Line {
                    line,
                    step: Step::Dwell(t),
                    comment,
                });
            }
            "CONFJ" | "CONFL" => {}
            w => {
                return Err(perr(
                    line,
                    format!(
                    "'{w}' is not an instruction edbbgen reads (MoveAbsJ, TPWrite, Stop, WaitTime)"
                ),
                ))
            }
        }
    }
    match at {
        At::End => {
            out.lines.push(Line {
                line: text.lines().count(),
                step: Step::End,
                comment: None,
            });
            Ok(out)
        }
        At::Start => Err(perr(0, "no MODULE: not a RAPID program module")),
        _ => Err(perr(
            text.lines().count(),
            "the module does not end with ENDPROC and ENDMODULE",
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Units;

    fn map() -> ControllerMap {
        ControllerMap::identity(
            Units::Deg,
            ["rax_1", "rax_2", "rax_3", "rax_4", "rax_5", "rax_6"],
        )
    }

    const OK: &str = "MODULE EDBB\n  ! fixture: 1, 2, 3 mm\n  PERS tooldata tEdbb := [TRUE, [[1, 2, 3], [1, 0, 0, 0]], [0.001, [0, 0, 0.001], [1, 0, 0, 0], 0, 0, 0]];\n\
        CONST zonedata zEdbb := [FALSE, 10, 15, 15, 1.5, 15, 1.5];\n  PROC main()\n    ! pose 1/2\n\
        MoveAbsJ [[1, 2, 3, 4, 5, 6], [9E+09, 9E+09, 9E+09, 9E+09, 9E+09, 9E+09]]\\NoEOffs, v1000, fine, tEdbb;\n\
        TPWrite \"Mount\";\n    Stop;\n    ! support\n    MoveAbsJ [[2, 2, 3, 4, 5, 6], [9E+09, 9E+09, 9E+09, 9E+09, 9E+09, 9E+09]]\\NoEOffs, v1000\\T:=0.700, zEdbb, tEdbb;\n\
        ENDPROC\nENDMODULE\n";

    #[test]
    fn reads_moveabsj_time_zone_and_pauses() {
        let p = parse(OK, &map()).unwrap();
        assert_eq!(p.header_value("fixture"), Some("1, 2, 3 mm"));
        let steps: Vec<&Step> = p.lines.iter().map(|l| &l.step).collect();
        assert!(matches!(
            steps[0],
            Step::Move {
                timing: Timing::Unknown,
                blend: None,
                ..
            }
        ));
        assert!(matches!(steps[1], Step::Pause));
        assert!(
            matches!(steps[2], Step::Move { timing: Timing::Duration(t), blend: Some(b), target, .. } if *t == 0.7 && *b == 15.0 && target[0] == 2.0)
        );
        assert_eq!(p.lines[2].comment.as_deref(), Some("support"));
        assert!(matches!(steps[3], Step::End));
    }

    #[test]
    fn rejects_with_the_line_number() {
        for (from, to, msg) in [
            ("zEdbb, tEdbb", "zBad, tEdbb", "'zBad' is not fine"),
            ("fine, tEdbb", "fine, tBad", "not a declared tooldata"),
            ("ENDMODULE\n", "", "does not end"),
            ("[[1, 2, 3, 4, 5, 6]", "[[1, 2, 3, 4, 5]", "6 robot"),
            ("Stop;", "Stop", "ends with ';'"),
            ("TPWrite \"Mount\";", "MoveJ p, v, z, t;", "'MOVEJ' is not"),
        ] {
            let text = OK.replacen(from, to, 1);
            let e = parse(&text, &map()).unwrap_err();
            assert!(e.msg.contains(msg), "{to:?}: {e}");
        }
    }

    #[test]
    fn reads_a_comment_after_a_statement() {
        let text = "MODULE Mine\n  CONST jointtarget jHome := [[0, 0, 0, 0, 90, 0], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]]; ! home\n\
            PROC main()\n    MoveAbsJ jHome\\NoEOffs, v500, fine, tool0; ! go home\n    WaitTime \\InPos, 2; ! measure\n  ENDPROC\nENDMODULE\n";
        let p = parse(text, &map()).unwrap();
        assert_eq!(p.lines[0].comment.as_deref(), Some("go home"));
        assert!(matches!(p.lines[1].step, Step::Dwell(t) if t == 2.0));
        let e = parse(&text.replace("tool0; !", "tool0 !"), &map()).unwrap_err();
        assert!(e.msg.contains("complete statement"), "{e}");
    }
}

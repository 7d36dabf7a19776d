//! KUKA KRL reader (`templates/krl.j2` writes it): in = a `.src` program and the controller
//! mapping; out = the motions, in program order.
//!
//! The subset a joint-space measurement program needs, strictly:
//! - `&` attribute lines, then `DEF name( )` … `END`; declarations (`DECL type name[…]`, DECL
//!   left out for the simple and position types, `= value` allowed) only before the first
//!   statement; every variable a statement assigns must be declared;
//! - `PTP {A1 v, …, A6 v}` (axis-specific, degrees; the first PTP names all six) or `PTP name`
//!   with a declared `E6AXIS`/`AXIS` variable assigned in the program (an aggregate sets the
//!   components it names; `E1`..`E6` are external axes, not read), optionally
//!   `C_DIS` (approximate with `$APO.CDIS` mm at the TCP). `C_PTP` is refused: its criterion
//!   is a percentage of the axis angle, which verify cannot check;
//! - `$VEL_AXIS[i] = n` (1..100 %: every PTP runs the slowest axis at its percentage, all axes
//!   arriving together), `$ACC_AXIS[i]`, `$APO.CDIS`, `$ADVANCE`, `$TOOL`, `$BASE`;
//! - `HALT` (pause), `WAIT SEC t` (dwell), message calls (`Set_KrlMsg`), comments after `;`.

use super::{number, perr, push_header, Line, ParseError, Parsed, Step, Timing};
use crate::controller::ControllerMap;

/// Types whose variables hold joint values (an E6AXIS's external axes E1..E6 are not read).
const AXIS_TYPES: &[&str] = &["AXIS", "E6AXIS"];

/// Types a declaration may name without DECL.
const IMPLICIT_TYPES: &[&str] = &[
    "INT", "REAL", "BOOL", "CHAR", "AXIS", "E6AXIS", "POS", "E6POS", "FRAME",
];

/// Splits a line into code and the comment after `;` (outside strings).
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

/// KRL names: letters, digits, `_` and `$`, not starting with a digit, at most 24 characters.
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 24
        && !name.starts_with(|c: char| c.is_ascii_digit())
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '$')
}

/// The name a variable reference starts with (`edbbPar[1]` → `EDBBPAR`).
fn base_name(s: &str) -> String {
    s.split(['[', '.', ' ', '='])
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_uppercase()
}

/// Parses `{A1 10.0, A2 -5.0, …}` into axis values.
fn axis_aggregate(line: usize, agg: &str) -> Result<[Option<f64>; 6], ParseError> {
    let inner = agg
        .trim()
        .strip_prefix('{')
        .and_then(|r| r.strip_suffix('}'))
        .ok_or_else(|| perr(line, "PTP needs an axis aggregate {A1 …, A6 …}"))?;
    let mut out = [None; 6];
    for part in inner.split(',') {
        let mut it = part.split_whitespace();
        let (Some(name), Some(value), None) = (it.next(), it.next(), it.next()) else {
            return Err(perr(
                line,
                format!("'{}' in the axis aggregate is not 'Ai value'", part.trim()),
            ));
        };
        let name = name.to_ascii_uppercase();
        let i = match name.as_str() {
            "A1" => 0,
            "A2" => 1,
            "A3" => 2,
            "A4" => 3,
            "A5" => 4,
            "A6" => 5,
            // An E6AXIS's external axes: not the robot's joints (a value is still a number).
            "E1" | "E2" | "E3" | "E4" | "E5" | "E6" => {
                number(line, &name, value)?;
                continue;
            }
            _ => return Err(perr(line, format!("'{name}' is not a robot axis (A1..A6)"))),
        };
        if out[i].is_some() {
            return Err(perr(line, format!("{name} given twice")));
        }
        out[i] = Some(number(line, &name, value)?);
    }
    Ok(out)
}

pub fn parse(text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
    let mut out = Parsed {
        map: map.clone(),
        ..Parsed::default()
    };
    let mut declared: Vec<String> = Vec::new();
    // Declared names with their types, and the values axis variables hold (latest last).
    let mut types: Vec<(String, String)> = Vec::new();
    let mut axis_vars: Vec<(String, [Option<f64>; 6])> = Vec::new();
    let (mut in_def, mut statements, mut ended, mut moved) = (false, false, false, false);
    let mut pos: [Option<f64>; 6] = [None; 6];
    let mut vel: [Option<f64>; 6] = [None; 6];
    let mut cdis: Option<f64> = None;
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        let (code, comment) = split(raw);
        let code = code.trim();
        if code.is_empty() {
            if let (Some(c), true, false) = (comment, in_def, moved) {
                push_header(&mut out.header, c);
            }
            continue;
        }
        let upper = code.to_ascii_uppercase();
        if ended {
            return Err(perr(line, "code after END"));
        }
        if !in_def {
            if upper.starts_with('&') {
                continue;
            }
            let rest = upper
                .strip_prefix("DEF ")
                .ok_or_else(|| perr(line, "a KRL program starts with DEF name( )"))?;
            let name = rest.split('(').next().unwrap_or("").trim();
            if !valid_name(name) || !rest.contains('(') || !rest.trim_end().ends_with(')') {
                return Err(perr(
                    line,
                    format!("DEF {}: not a program name with ( )", rest.trim()),
                ));
            }
            in_def = true;
            continue;
        }
        if upper == "END" {
            out.lines.push(Line {
                line,
                step: Step::End,
                comment: None,
            });
            ended = true;
            continue;
        }
        // A declaration: `DECL type name [= value]`, or without DECL for the simple and
        // position types (KRL lets it out).
        let decl = upper
            .strip_prefix("DECL ")
            .map(|_| code[5..].trim())
            .or_else(|| {
                let ty = upper.split_whitespace().next().unwrap_or("");
                (IMPLICIT_TYPES.contains(&ty) && upper.len() > ty.len()).then_some(code)
            });
        if let Some(rest) = decl {
            if statements {
                return Err(perr(
                    line,
                    "DECL after the first statement: declarations come first",
                ));
            }
            let (ty, rest) = rest
                .split_once(char::is_whitespace)
                .ok_or_else(|| perr(line, "DECL needs a type and a name"))?;
            let (names, value) = match rest.split_once('=') {
                Some((n, v)) => (n, Some(v.trim())),
                None => (rest, None),
            };
            let ty = ty.to_ascii_uppercase();
            for name in names.split(',') {
                let name = base_name(name.trim());
                if !valid_name(&name) {
                    return Err(perr(
                        line,
                        format!("'{name}' is not a KRL name (letters, digits, _, at most 24)"),
                    ));
                }
                if let (Some(v), true) = (value, AXIS_TYPES.contains(&ty.as_str())) {
                    axis_vars.push((name.clone(), axis_aggregate(line, v)?));
                }
                declared.push(name.clone());
                types.push((name, ty.clone()));
            }
            continue;
        }
        statements = true;
        if let Some(rest) = upper.strip_prefix("PTP ").map(|_| code[4..].trim()) {
            let (axis, tail) = if rest.starts_with('{') {
                let close = rest
                    .rfind('}')
                    .ok_or_else(|| perr(line, "PTP needs an axis aggregate {A1 …, A6 …}"))?;
                let (agg, tail) = rest.split_at(close + 1);
                (axis_aggregate(line, agg)?, tail)
            } else {
                // A declared axis variable.
                let (name, tail) = rest.split_once(char::is_whitespace).unwrap_or((rest, ""));
                let name = name.to_ascii_uppercase();
                let axis = match axis_vars.iter().rev().find(|(n, _)| *n == name) {
                    Some((_, a)) if a.iter().all(Option::is_some) => *a,
                    Some(_) => return Err(perr(line, format!("{name} does not give all six axes A1..A6"))),
                    None => {
                        return Err(perr(line, match types.iter().find(|(n, _)| *n == name) {
                            Some((_, ty)) if AXIS_TYPES.contains(&ty.as_str()) => format!("{name} has no value yet"),
                            Some((_, ty)) => format!("PTP {name}: a {ty} is a Cartesian target; edbbgen reads axis targets (an E6AXIS or AXIS, or {{A1 …, A6 …}})"),
                            None => format!("PTP {name}: not a declared E6AXIS or AXIS (a target in $config.dat or a .dat file is not read)"),
                        }))
                    }
                };
                (axis, tail)
            };
            let blend = match tail.trim().to_ascii_uppercase().as_str() {
                "" => None,
                "C_DIS" => Some(cdis.ok_or_else(|| perr(line, "C_DIS before $APO.CDIS is set"))?),
                "C_PTP" => {
                    return Err(perr(line, "C_PTP approximates by a percentage of the axis angle, which edbbgen cannot check: use C_DIS with $APO.CDIS"))
                }
                t => return Err(perr(line, format!("'{t}' after PTP is not supported (C_DIS or nothing)"))),
            };
            let mut target = [0.0; 6];
            for i in 0..6 {
                target[i] = match (axis[i], pos[i]) {
                    (Some(v), _) => v,
                    (None, Some(p)) => p,
                    (None, None) => {
                        return Err(perr(
                            line,
                            format!("the first PTP must give all six axes (A{} missing)", i + 1),
                        ))
                    }
                };
                pos[i] = Some(target[i]);
            }
            let mut pct = [0.0; 6];
            for i in 0..6 {
                pct[i] = vel[i].ok_or_else(|| perr(line, format!("PTP before $VEL_AXIS[{}] is set: its speed would be whatever the controller had", i + 1)))?;
            }
            out.lines.push(Line {
                line,
                step: Step::Move {
                    target: map.undo(&target),
                    axes: target,
                    timing: Timing::AxisPercent(pct),
                    blend,
                    corner: None,
                },
                comment: comment.map(str::to_string),
            });
            moved = true;
            continue;
        }
        if upper == "HALT" {
            out.lines.push(Line {
                line,
                step: Step::Pause,
                comment: comment.map(str::to_string),
            });
            continue;
        }
        if let Some(rest) = upper.strip_prefix("WAIT SEC ") {
            let t = number(line, "WAIT SEC", rest)?;
            if t < 0.0 {
                return Err(perr(line, "WAIT SEC needs a time >= 0"));
            }
            out.lines.push(Line {
                line,
                step: Step::Dwell(t),
                comment: None,
            });
            continue;
        }
        // Assignments.
        let Some((lhs, rhs)) = code.split_once('=') else {
            return Err(perr(line, format!("'{code}' is not a statement edbbgen reads (PTP, HALT, WAIT SEC, an assignment)")));
        };
        let lhs = lhs.trim().to_ascii_uppercase();
        let rhs = rhs.trim();
        if let Some(idx) = lhs
            .strip_prefix("$VEL_AXIS[")
            .and_then(|r| r.strip_suffix(']'))
        {
            let i: usize = idx
                .trim()
                .parse()
                .map_err(|_| perr(line, "$VEL_AXIS index must be 1..6"))?;
            let v: i64 = rhs
                .parse()
                .map_err(|_| perr(line, format!("$VEL_AXIS is an INT percentage, not '{rhs}'")))?;
            if !(1..=6).contains(&i) || !(1..=100).contains(&v) {
                return Err(perr(line, "$VEL_AXIS[1..6] takes 1..100 %"));
            }
            vel[i - 1] = Some(v as f64);
        } else if let Some(idx) = lhs
            .strip_prefix("$ACC_AXIS[")
            .and_then(|r| r.strip_suffix(']'))
        {
            let i: usize = idx
                .trim()
                .parse()
                .map_err(|_| perr(line, "$ACC_AXIS index must be 1..6"))?;
            let v: i64 = rhs
                .parse()
                .map_err(|_| perr(line, format!("$ACC_AXIS is an INT percentage, not '{rhs}'")))?;
            if !(1..=6).contains(&i) || !(1..=100).contains(&v) {
                return Err(perr(line, "$ACC_AXIS[1..6] takes 1..100 %"));
            }
        } else if lhs == "$APO.CDIS" {
            let v = number(line, "$APO.CDIS", rhs)?;
            if v < 0.0 {
                return Err(perr(line, "$APO.CDIS must be >= 0 mm"));
            }
            cdis = Some(v);
        } else if lhs == "$ADVANCE" {
            let v: i64 = rhs
                .parse()
                .map_err(|_| perr(line, "$ADVANCE is an INT 0..5"))?;
            if !(0..=5).contains(&v) {
                return Err(perr(line, "$ADVANCE takes 0..5"));
            }
        } else if lhs == "$TOOL" || lhs == "$BASE" || lhs == "$APO.CPTP" {
            if rhs.is_empty() {
                return Err(perr(line, format!("{lhs} needs a value")));
            }
        } else {
            let name = base_name(&lhs);
            if name.starts_with('$') {
                return Err(perr(
                    line,
                    format!("{name} is not a system variable edbbgen reads"),
                ));
            }
            if !declared.contains(&name) {
                return Err(perr(
                    line,
                    format!("'{name}' is not declared (DECL before the first statement)"),
                ));
            }
            if types
                .iter()
                .any(|(n, ty)| *n == name && AXIS_TYPES.contains(&ty.as_str()))
            {
                // An axis variable takes the components given; the others keep their values.
                if lhs.trim() != name {
                    return Err(perr(
                        line,
                        format!("{lhs}: edbbgen reads whole axis aggregates assigned to {name}"),
                    ));
                }
                let new = axis_aggregate(line, rhs)?;
                let mut value = axis_vars
                    .iter()
                    .rev()
                    .find(|(n, _)| *n == name)
                    .map_or([None; 6], |(_, a)| *a);
                for (v, n) in value.iter_mut().zip(new) {
                    if n.is_some() {
                        *v = n;
                    }
                }
                axis_vars.push((name, value));
                continue;
            }
            if rhs.is_empty()
                || rhs.matches('{').count() != rhs.matches('}').count()
                || rhs.matches('(').count() != rhs.matches(')').count()
                || rhs.matches('"').count() % 2 != 0
            {
                return Err(perr(line, format!("the value of {name} is not balanced")));
            }
        }
    }
    if !in_def {
        return Err(perr(0, "no DEF line: not a KRL program"));
    }
    if !ended {
        return Err(perr(text.lines().count(), "the program has no END"));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::Units;

    fn map() -> ControllerMap {
        ControllerMap::identity(Units::Deg, ["A1", "A2", "A3", "A4", "A5", "A6"])
    }

    const OK: &str = "&ACCESS RVP\nDEF EDBB( )\n; fixture: 1, 2, 3 mm\nDECL INT h\n$VEL_AXIS[1] = 100\n$VEL_AXIS[2] = 100\n\
        $VEL_AXIS[3] = 100\n$VEL_AXIS[4] = 100\n$VEL_AXIS[5] = 100\n$VEL_AXIS[6] = 50\n$APO.CDIS = 10.0\n\
        PTP {A1 1, A2 2, A3 3, A4 4, A5 5, A6 6} ; pose 1/2\nh = 3\nHALT\nPTP {A1 2} C_DIS ; support\nWAIT SEC 0.5\nEND\n";

    #[test]
    fn reads_ptp_speeds_and_approximation() {
        let p = parse(OK, &map()).unwrap();
        assert_eq!(p.header_value("fixture"), Some("1, 2, 3 mm"));
        let steps: Vec<&Step> = p.lines.iter().map(|l| &l.step).collect();
        assert!(
            matches!(steps[0], Step::Move { timing: Timing::AxisPercent(p), blend: None, .. } if p[5] == 50.0)
        );
        assert!(matches!(steps[1], Step::Pause));
        assert!(
            matches!(steps[2], Step::Move { target, blend: Some(b), .. } if *b == 10.0 && target[0] == 2.0 && target[5] == 6.0)
        );
        assert_eq!(p.lines[2].comment.as_deref(), Some("support"));
        assert!(matches!(steps[3], Step::Dwell(_)));
        assert!(matches!(steps[4], Step::End));
    }

    #[test]
    fn rejects_with_the_line_number() {
        for (from, to, msg) in [
            ("PTP {A1 2} C_DIS", "PTP {A1 2} C_PTP", "C_PTP"),
            ("h = 3", "k = 3", "'K' is not declared"),
            ("$VEL_AXIS[6] = 50", "$VEL_AXIS[6] = 150", "1..100"),
            ("END\n", "", "no END"),
            (
                "PTP {A1 1, A2 2, A3 3, A4 4, A5 5, A6 6}",
                "PTP {A1 1, A2 2}",
                "all six axes",
            ),
            ("HALT", "DECL INT k", "DECL after the first statement"),
        ] {
            let text = OK.replacen(from, to, 1);
            let e = parse(&text, &map()).unwrap_err();
            assert!(e.msg.contains(msg), "{to:?}: {e}");
        }
    }

    #[test]
    fn reads_axis_variables() {
        let text = "DEF mine( )\nDECL E6AXIS xHome = {A1 0, A2 -90, A3 90, A4 0, A5 0, A6 0, E1 0}\n\
            E6AXIS xP1, xP2\nE6POS pC\n$VEL_AXIS[1] = 20\n$VEL_AXIS[2] = 20\n$VEL_AXIS[3] = 20\n\
            $VEL_AXIS[4] = 20\n$VEL_AXIS[5] = 20\n$VEL_AXIS[6] = 20\nxP1 = {A1 10, A2 -80, A3 80, A4 5, A5 6, A6 7}\n\
            xP2 = xP1\nxP2 = {A1 20}\nPTP xHome\nPTP xP1 ; pose\nWAIT SEC 2\nPTP xP2 C_DIS\nEND\n";
        // `xP2 = xP1` is a copy edbbgen does not follow: refused.
        let e = parse(text, &map()).unwrap_err();
        assert!(e.msg.contains("axis aggregate"), "{e}");
        let text = text.replace(
            "xP2 = xP1\n",
            "xP2 = {A1 10, A2 -80, A3 80, A4 5, A5 6, A6 7}\n",
        );
        let e = parse(&text, &map()).unwrap_err();
        assert!(e.msg.contains("C_DIS before $APO.CDIS"), "{e}");
        let text = text.replace(" C_DIS", "");
        let p = parse(&text, &map()).unwrap();
        let t: Vec<[f64; 6]> = p.targets().map(|(_, t)| *t).collect();
        assert_eq!(t[0], [0.0, -90.0, 90.0, 0.0, 0.0, 0.0]);
        assert_eq!(t[1], [10.0, -80.0, 80.0, 5.0, 6.0, 7.0]);
        assert_eq!(t[2], [20.0, -80.0, 80.0, 5.0, 6.0, 7.0]);
        assert!(matches!(p.lines[2].step, Step::Dwell(d) if d == 2.0));
        for (from, to, msg) in [
            ("PTP xHome", "PTP pC", "Cartesian target"),
            ("PTP xHome", "PTP XHOME_CFG", "not a declared E6AXIS"),
        ] {
            let e = parse(&text.replacen(from, to, 1), &map()).unwrap_err();
            assert!(e.msg.contains(msg), "{to}: {e}");
        }
    }
}

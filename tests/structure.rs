//! Strict structural checks per controller language, written from the languages' rules and
//! independent of edbbgen's readers: balanced blocks and brackets, declared names, value ranges,
//! the lengths the controllers allow. Each returns the first problem found.
//!
//! Sources of the limits: KUKA KSS 8 (names at most 24 characters; `$VEL_AXIS`/`$ACC_AXIS`
//! INT 1..100 %; message texts `CHAR[80]`, originator `CHAR[24]`); ABB RAPID (identifiers at
//! most 32 characters, strings at most 80); FANUC TP (remarks at most 32 characters, MESSAGE at
//! most 24, joint speed 1..100 %, CNT 0..100, LINE_COUNT = the /MN lines); SINUMERIK 840D
//! (blocks at most 512 characters); URScript (joint positions within ±360°, `popup(...,
//! blocking=True)` to wait); RS274/NGC (LinuxCNC's `rs274` checks the rest). Dwells: KRL `WAIT
//! SEC t`, RAPID `WaitTime [\InPos,] t;`, URScript `sleep(t)`, FANUC `WAIT t(sec)` (0.01 s
//! steps), SINUMERIK `G4 F t` in a block of its own.

fn balanced(line: &str) -> bool {
    let (mut round, mut square, mut curly, mut quote) = (0i32, 0i32, 0i32, false);
    for c in line.chars() {
        match c {
            '"' => quote = !quote,
            _ if quote => {}
            '(' => round += 1,
            ')' => round -= 1,
            '[' => square += 1,
            ']' => square -= 1,
            '{' => curly += 1,
            '}' => curly -= 1,
            _ => {}
        }
        if round < 0 || square < 0 || curly < 0 {
            return false;
        }
    }
    !quote && round == 0 && square == 0 && curly == 0
}

fn name_ok(name: &str, max: usize) -> bool {
    !name.is_empty()
        && name.len() <= max
        && name
            .chars()
            .next()
            .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

fn num(s: &str) -> Result<f64, String> {
    s.trim()
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| format!("'{}' is not a number", s.trim()))
}

/// Checks `text` in dialect `d`; `stem` is the file name the program is stored under.
pub fn check(d: &str, text: &str, stem: &str) -> Result<(), String> {
    if !text.ends_with('\n') {
        return Err("the text does not end with a newline".into());
    }
    let r = match d {
        "krl" => krl(text, stem),
        "rapid" => rapid(text),
        "urscript" => urscript(text),
        "fanuc" => fanuc(text, stem),
        "sinumerik" => sinumerik(text),
        "ngc" => ngc(text),
        _ => Err(format!("no structural check for {d}")),
    };
    r
}

fn code_of(line: &str, comment: char) -> &str {
    let mut quote = false;
    for (k, c) in line.char_indices() {
        match c {
            '"' => quote = !quote,
            c if c == comment && !quote => return &line[..k],
            _ => {}
        }
    }
    line
}

fn krl(text: &str, stem: &str) -> Result<(), String> {
    let lines: Vec<&str> = text.lines().collect();
    let code: Vec<(usize, &str)> = lines
        .iter()
        .enumerate()
        .map(|(k, l)| (k + 1, code_of(l, ';').trim()))
        .filter(|(_, l)| !l.is_empty())
        .collect();
    let mut it = code.iter().skip_while(|(_, l)| l.starts_with('&'));
    let (n, def) = it.next().ok_or("no DEF line")?;
    let name = def
        .strip_prefix("DEF ")
        .and_then(|r| r.strip_suffix("( )").or(r.strip_suffix("()")))
        .ok_or(format!("line {n}: the program must start with DEF name( )"))?;
    if !name_ok(name, 24) {
        return Err(format!(
            "line {n}: '{name}' is not a KRL name (at most 24 characters)"
        ));
    }
    if !name.eq_ignore_ascii_case(stem) {
        return Err(format!(
            "line {n}: DEF {name} does not match the file name {stem}.src"
        ));
    }
    if code.last().map(|(_, l)| *l) != Some("END") {
        return Err("the program does not close with END".into());
    }
    let mut declared: Vec<String> = Vec::new();
    let mut statements = false;
    for (n, l) in it {
        if !balanced(l) {
            return Err(format!("line {n}: unbalanced brackets or quotes: {l}"));
        }
        if *l == "END" {
            continue;
        }
        if let Some(d) = l.strip_prefix("DECL ") {
            if statements {
                return Err(format!("line {n}: DECL after a statement"));
            }
            let name = d.split_whitespace().nth(1).unwrap_or("");
            let name = name.split('[').next().unwrap_or("");
            if !name_ok(name, 24) {
                return Err(format!(
                    "line {n}: '{name}' is not a KRL name (at most 24 characters)"
                ));
            }
            declared.push(name.to_ascii_uppercase());
            continue;
        }
        statements = true;
        if let Some(r) = l.strip_prefix("PTP ") {
            let agg = r.split('}').next().unwrap_or("").trim_start_matches('{');
            for part in agg.split(',') {
                let mut w = part.split_whitespace();
                let (a, v) = (w.next().unwrap_or(""), w.next().unwrap_or(""));
                if !["A1", "A2", "A3", "A4", "A5", "A6"].contains(&a) {
                    return Err(format!("line {n}: '{a}' is not an axis A1..A6"));
                }
                let v = num(v).map_err(|e| format!("line {n}: {e}"))?;
                if v.abs() > 720.0 {
                    return Err(format!("line {n}: {a} {v} outside ±720 deg"));
                }
            }
            continue;
        }
        if *l == "HALT" {
            continue;
        }
        if let Some(t) = l.strip_prefix("WAIT SEC ") {
            // A dwell: REAL seconds, stops the advance run.
            if num(t)? < 0.0 {
                return Err(format!("line {n}: WAIT SEC needs a time >= 0"));
            }
            continue;
        }
        let (lhs, rhs) = l
            .split_once('=')
            .ok_or(format!("line {n}: not a statement: {l}"))?;
        let lhs = lhs.trim();
        let rhs = rhs.trim();
        if lhs.starts_with("$VEL_AXIS[") || lhs.starts_with("$ACC_AXIS[") {
            let v: i64 = rhs
                .parse()
                .map_err(|_| format!("line {n}: {lhs} is an INT"))?;
            if !(1..=100).contains(&v) {
                return Err(format!("line {n}: {lhs} = {v}: 1..100 %"));
            }
        } else if lhs == "$APO.CDIS" {
            if num(rhs)? < 0.0 {
                return Err(format!("line {n}: $APO.CDIS >= 0"));
            }
        } else if lhs == "$ADVANCE" {
            let v: i64 = rhs
                .parse()
                .map_err(|_| format!("line {n}: $ADVANCE is an INT"))?;
            if !(0..=5).contains(&v) {
                return Err(format!("line {n}: $ADVANCE 0..5"));
            }
        } else if lhs == "$TOOL" {
        } else {
            let name = lhs.split('[').next().unwrap_or("").to_ascii_uppercase();
            if !declared.contains(&name) {
                return Err(format!("line {n}: '{lhs}' is not declared"));
            }
            if let Some(t) = rhs.split("MSG_TXT[] \"").nth(1) {
                if t.split('"').next().unwrap_or("").len() > 80 {
                    return Err(format!(
                        "line {n}: a message text holds at most 80 characters"
                    ));
                }
            }
            if let Some(t) = rhs.split("MODUL[] \"").nth(1) {
                if t.split('"').next().unwrap_or("").len() > 24 {
                    return Err(format!(
                        "line {n}: a message originator holds at most 24 characters"
                    ));
                }
            }
            if rhs.contains("Set_KrlMsg(") {
                for arg in ["edbbMsg", "edbbPar[]", "edbbOpt"] {
                    if !rhs.contains(arg) {
                        return Err(format!("line {n}: Set_KrlMsg without {arg}"));
                    }
                }
            }
        }
    }
    Ok(())
}

fn rapid(text: &str) -> Result<(), String> {
    let mut depth = 0;
    let mut names: Vec<String> = vec!["tool0".into(), "fine".into(), "v1000".into()];
    for (k, raw) in text.lines().enumerate() {
        let n = k + 1;
        let l = raw.trim();
        if l.starts_with('!') || l.is_empty() {
            continue;
        }
        if !balanced(l) {
            return Err(format!("line {n}: unbalanced brackets or quotes"));
        }
        for s in l.split('"').skip(1).step_by(2) {
            if s.len() > 80 {
                return Err(format!("line {n}: a string holds at most 80 characters"));
            }
        }
        if let Some(m) = l.strip_prefix("MODULE ") {
            if depth != 0 || !name_ok(m.trim(), 32) {
                return Err(format!("line {n}: MODULE name (at most 32 characters)"));
            }
            depth = 1;
        } else if l == "ENDMODULE" {
            if depth != 1 {
                return Err(format!("line {n}: ENDMODULE out of place"));
            }
            depth = 0;
        } else if l == "PROC main()" {
            if depth != 1 {
                return Err(format!("line {n}: PROC out of place"));
            }
            depth = 2;
        } else if l == "ENDPROC" {
            if depth != 2 {
                return Err(format!("line {n}: ENDPROC out of place"));
            }
            depth = 1;
        } else if depth == 1 {
            let w: Vec<&str> = l.split_whitespace().collect();
            if w.len() < 4 || !["CONST", "PERS", "VAR"].contains(&w[0]) || !name_ok(w[2], 32) {
                return Err(format!("line {n}: not a declaration"));
            }
            names.push(w[2].to_string());
        } else if depth == 2 {
            if !l.ends_with(';') {
                return Err(format!("line {n}: a statement ends with ';'"));
            }
            if let Some(r) = l.strip_prefix("MoveAbsJ ") {
                let parts: Vec<&str> = r.trim_end_matches(';').rsplitn(3, ", ").collect();
                let (tool, zone) = (parts[0].trim(), parts[1].trim());
                for used in [tool, zone] {
                    if !names.iter().any(|d| d == used) {
                        return Err(format!("line {n}: '{used}' is not declared"));
                    }
                }
                let jt = r.split("]]").next().unwrap_or("").trim_start_matches("[[");
                let (rob, ext) = jt
                    .split_once("], [")
                    .ok_or(format!("line {n}: jointtarget"))?;
                if rob.split(',').count() != 6 || ext.split(',').count() != 6 {
                    return Err(format!("line {n}: a jointtarget has 6 + 6 values"));
                }
                for v in rob.split(',') {
                    if num(v)?.abs() > 720.0 {
                        return Err(format!("line {n}: joint value outside ±720 deg"));
                    }
                }
            } else if let Some(r) = l.strip_prefix("WaitTime ") {
                // WaitTime [\InPos,] Time: num seconds.
                let r = r.trim_end_matches(';');
                let t = r.strip_prefix("\\InPos,").unwrap_or(r);
                if num(t)? < 0.0 {
                    return Err(format!("line {n}: WaitTime needs a time >= 0"));
                }
            } else if !(l.starts_with("TPWrite \"") || l == "Stop;") {
                return Err(format!("line {n}: unexpected statement {l}"));
            }
        } else {
            return Err(format!("line {n}: code outside the module"));
        }
    }
    if depth != 0 {
        return Err("the module does not close with ENDPROC and ENDMODULE".into());
    }
    Ok(())
}

fn urscript(text: &str) -> Result<(), String> {
    let lines: Vec<&str> = text.lines().collect();
    let first = lines.first().ok_or("empty")?;
    let name = first
        .strip_prefix("def ")
        .and_then(|r| r.strip_suffix("():"))
        .ok_or("line 1: the program must be def name():")?;
    if !name_ok(name, 64) {
        return Err(format!("line 1: '{name}' is not a name"));
    }
    if lines.last() != Some(&"end") {
        return Err("the program does not close with end".into());
    }
    for (k, raw) in lines
        .iter()
        .enumerate()
        .skip(1)
        .take(lines.len().saturating_sub(2))
    {
        let n = k + 1;
        let l = code_of(raw, '#');
        if l.trim().is_empty() {
            continue;
        }
        if !l.starts_with("  ") || l.starts_with("   ") {
            return Err(format!("line {n}: the body is indented by two spaces"));
        }
        let l = l.trim();
        if !balanced(l) {
            return Err(format!("line {n}: unbalanced brackets or quotes"));
        }
        let call = l.split('(').next().unwrap_or("");
        match call {
            "movej" => {
                let q = l
                    .strip_prefix("movej([")
                    .and_then(|r| r.split(']').next())
                    .ok_or(format!("line {n}: movej takes a joint list"))?;
                let v: Vec<f64> = q.split(',').map(num).collect::<Result<_, _>>()?;
                if v.len() != 6 || v.iter().any(|x| x.abs() > std::f64::consts::TAU) {
                    return Err(format!("line {n}: 6 joint positions within ±2π rad"));
                }
                for (key, max) in [("t=", 1e4), ("r=", 2.0), ("v=", 10.0), ("a=", 100.0)] {
                    if let Some(s) = l.split(key).nth(1) {
                        let x = num(s.split([',', ')']).next().unwrap_or(""))?;
                        if !(0.0..=max).contains(&x) || (key == "t=" && x == 0.0) {
                            return Err(format!("line {n}: {key}{x} out of range"));
                        }
                    }
                }
            }
            "popup" => {
                if !l.contains("blocking=True") {
                    return Err(format!(
                        "line {n}: a popup without blocking=True does not wait"
                    ));
                }
            }
            "set_tcp" => {}
            "sleep" => {
                let t = l
                    .strip_prefix("sleep(")
                    .and_then(|r| r.strip_suffix(')'))
                    .ok_or(format!("line {n}: sleep(t)"))?;
                if num(t)? <= 0.0 {
                    return Err(format!("line {n}: sleep needs a time > 0"));
                }
            }
            _ => return Err(format!("line {n}: unexpected call {call}")),
        }
    }
    Ok(())
}

fn fanuc(text: &str, stem: &str) -> Result<(), String> {
    let lines: Vec<&str> = text.lines().collect();
    let name = lines
        .first()
        .and_then(|l| l.strip_prefix("/PROG"))
        .map(str::trim)
        .ok_or("line 1: /PROG name")?;
    if !name_ok(name, 36) || name != name.to_ascii_uppercase() {
        return Err(format!(
            "line 1: '{name}' is not an upper-case program name"
        ));
    }
    if !name.eq_ignore_ascii_case(stem) {
        return Err(format!(
            "line 1: /PROG {name} does not match the file name {stem}.ls"
        ));
    }
    let pos = |s: &str| lines.iter().position(|l| *l == s).ok_or(format!("no {s}"));
    let (attr, mn, ps, end) = (pos("/ATTR")?, pos("/MN")?, pos("/POS")?, pos("/END")?);
    if !(attr < mn && mn < ps && ps < end && end == lines.len() - 1) {
        return Err("sections out of order (/ATTR, /MN, /POS, /END last)".into());
    }
    let count: usize = lines[attr..mn]
        .iter()
        .find_map(|l| l.strip_prefix("LINE_COUNT = "))
        .and_then(|v| v.trim_end_matches(';').trim().parse().ok())
        .ok_or("no LINE_COUNT")?;
    if count != ps - mn - 1 {
        return Err(format!(
            "LINE_COUNT {count} but /MN has {} lines",
            ps - mn - 1
        ));
    }
    let mut used = Vec::new();
    for (k, l) in lines[mn + 1..ps].iter().enumerate() {
        let (no, rest) = l.split_once(':').ok_or(format!("/MN line {l}"))?;
        if no.trim() != (k + 1).to_string() {
            return Err(format!(
                "/MN line number {} where {} is due",
                no.trim(),
                k + 1
            ));
        }
        let instr = rest
            .strip_suffix(" ;")
            .ok_or(format!("/MN line {} does not end with ' ;'", k + 1))?
            .trim();
        if let Some(r) = instr.strip_prefix('!') {
            if r.len() > 32 {
                return Err(format!(
                    "/MN line {}: a remark holds at most 32 characters",
                    k + 1
                ));
            }
        } else if let Some(m) = instr.strip_prefix("MESSAGE[") {
            if m.trim_end_matches(']').len() > 24 {
                return Err(format!(
                    "/MN line {}: a MESSAGE holds at most 24 characters",
                    k + 1
                ));
            }
        } else if let Some(j) = instr.strip_prefix("J P[") {
            let (p, rest) = j.split_once(']').ok_or("J P[")?;
            used.push(p.parse::<usize>().map_err(|_| "P number")?);
            let w: Vec<&str> = rest.split_whitespace().collect();
            let pct: i64 = w[0].trim_end_matches('%').parse().map_err(|_| "speed")?;
            if !(1..=100).contains(&pct) {
                return Err(format!("/MN line {}: speed {pct}%: 1..100", k + 1));
            }
            if let Some(c) = w[1].strip_prefix("CNT") {
                let c: i64 = c.parse().map_err(|_| "CNT")?;
                if !(0..=100).contains(&c) {
                    return Err(format!("/MN line {}: CNT{c}: 0..100", k + 1));
                }
            } else if w[1] != "FINE" {
                return Err(format!("/MN line {}: termination {}", k + 1, w[1]));
            }
        } else if let Some(w) = instr.strip_prefix("WAIT ") {
            // WAIT t(sec): a timer wait, 0.01 s resolution.
            let t = w
                .strip_suffix("(sec)")
                .ok_or(format!("/MN line {}: WAIT t(sec)", k + 1))?;
            let v = num(t)?;
            if v < 0.0 || ((v * 100.0).round() - v * 100.0).abs() > 1e-9 {
                return Err(format!(
                    "/MN line {}: WAIT {t}: a time >= 0 in 0.01 s steps",
                    k + 1
                ));
            }
        } else if !["PAUSE", "UFRAME_NUM=0", "UTOOL_NUM=1"].contains(&instr) {
            return Err(format!("/MN line {}: unexpected {instr}", k + 1));
        }
    }
    let defined: Vec<usize> = lines[ps + 1..end]
        .iter()
        .filter_map(|l| l.strip_prefix("P[").and_then(|r| r.split(']').next()))
        .filter_map(|p| p.parse().ok())
        .collect();
    let expect: Vec<usize> = (1..=used.len()).collect();
    if used != expect || defined != expect {
        return Err(format!(
            "positions P[1]..P[{}] must be used once each in order and defined once each",
            used.len()
        ));
    }
    let joints = lines[ps + 1..end]
        .iter()
        .filter(|l| l.contains(" deg"))
        .count();
    if joints != 2 * used.len() {
        return Err("every position has J1..J6 on two lines".into());
    }
    for l in &lines[ps + 1..end] {
        for part in l.split(',').filter(|p| p.contains(" deg")) {
            let v = num(part
                .split('=')
                .nth(1)
                .unwrap_or("")
                .trim()
                .trim_end_matches("deg"))?;
            if v.abs() > 720.0 {
                return Err(format!("joint value {v} outside ±720 deg"));
            }
        }
    }
    Ok(())
}

fn sinumerik(text: &str) -> Result<(), String> {
    let mut axes: Option<Vec<String>> = None;
    let mut ended = false;
    for (k, raw) in text.lines().enumerate() {
        let n = k + 1;
        if raw.len() > 512 {
            return Err(format!("line {n}: a block holds at most 512 characters"));
        }
        let l = code_of(raw, ';').trim();
        if l.is_empty() {
            continue;
        }
        if ended {
            return Err(format!("line {n}: code after M30"));
        }
        if !balanced(l) {
            return Err(format!("line {n}: unbalanced brackets or quotes"));
        }
        if let Some(r) = l.strip_prefix("FGROUP(") {
            let list: Vec<String> = r
                .trim_end_matches(')')
                .split(", ")
                .map(str::to_string)
                .collect();
            if list.len() != 6 || list.iter().any(|a| !name_ok(a, 16)) {
                return Err(format!("line {n}: FGROUP names the six axes"));
            }
            axes = Some(list);
            continue;
        }
        if l.starts_with("MSG(") {
            continue;
        }
        let words: Vec<&str> = l.split_whitespace().collect();
        if words.contains(&"G4") {
            // A dwell: G4 F (seconds) in a block of its own.
            let ok = words.len() == 2
                && words[1]
                    .strip_prefix('F')
                    .and_then(|f| num(f).ok())
                    .is_some_and(|t| t >= 0.0);
            if !ok {
                return Err(format!(
                    "line {n}: a dwell is G4 F<seconds> in a block of its own"
                ));
            }
            continue;
        }
        for w in &words {
            if let Some((a, v)) = w.split_once('=') {
                if a == "ADIS" {
                    if num(v)? < 0.0 {
                        return Err(format!("line {n}: ADIS >= 0"));
                    }
                    continue;
                }
                let ok = axes.as_ref().is_some_and(|x| x.iter().any(|x| x == a));
                if !ok {
                    return Err(format!("line {n}: axis {a} not in FGROUP"));
                }
                if num(v)?.abs() > 720.0 {
                    return Err(format!("line {n}: {a} outside ±720 deg"));
                }
            } else if let Some(f) = w.strip_prefix('F') {
                if num(f)? <= 0.0 {
                    return Err(format!("line {n}: F > 0"));
                }
            } else if !matches!(
                *w,
                "G0" | "G1" | "G60" | "G641" | "G71" | "G90" | "G93" | "G94" | "M0" | "M30"
            ) {
                return Err(format!("line {n}: unexpected word {w}"));
            }
        }
        if words.contains(&"M30") {
            ended = true;
        }
    }
    if !ended {
        return Err("the program does not end with M30".into());
    }
    Ok(())
}

fn ngc(text: &str) -> Result<(), String> {
    if text.lines().last() != Some("M2") {
        return Err("the program does not end with M2".into());
    }
    for (k, l) in text.lines().enumerate() {
        if !balanced(l) || l.len() > 256 {
            return Err(format!(
                "line {}: unbalanced or longer than 256 characters",
                k + 1
            ));
        }
    }
    Ok(())
}

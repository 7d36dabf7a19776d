//! Emission: in = a [`Template`] (a bundled dialect's, or a user's file extending one)
//! and a [`Program`]; out = the program text. Dialects are data: the template decides the
//! syntax, Rust only supplies the values ([`target`] fills what depends on the controller) and
//! a few number filters, so every dialect rounds the same way. The reader of each dialect, the
//! other end, is in [`crate::dialect`].
//!
//! The template context is the Program IR and nothing else: `h` (the [`crate::ir::Header`])
//! and `moves` (the [`crate::ir::Move`]s). Filters (besides minijinja's built-ins):
//!
//! | filter | does |
//! |---|---|
//! | `f(d)` | fixed `d` decimals, never `-0.000` ([`fmt_fixed`]) |
//! | `feed` | inverse-time F word for a duration: 60/t rounded down to 4 decimals |
//! | `ceil(d)` | rounds up to `d` decimals (a duration that must not shrink) |
//! | `pct` | a speed percentage as the integer the controllers take: rounded down, 1..100 |
//! | `comment` | text safe inside an RS274 comment (parentheses become brackets) |
//! | `wrap(w)` | splits text into chunks of at most `w` characters; continuation chunks start with `..` |
//! | `rjust(w)` | right-aligns to `w` characters |
//! | `ident(n)` | a name of letters, digits and `_`, a letter first, at most `n` characters |

use crate::controller::ControllerMap;
use crate::dialect::{Dialect, Template};
use crate::ir::Program;
use crate::units::fmt_fixed;
use minijinja::{Environment, Value};

/// The template source of a bundled dialect.
pub fn dialect(name: &str) -> Option<&'static str> {
    crate::dialect::source(name)
}

pub use crate::dialect::wrap;
pub use crate::units::{ceil_fixed, inverse_time_feed, DEG_DECIMALS};

/// A joint value (degrees) as the program will carry it: on the 0.001° grid every dialect
/// prints exactly (FANUC LS positions and SINUMERIK rotary axes resolve 0.001°).
pub fn round_deg(v: f64) -> f64 {
    let k = 10f64.powi(DEG_DECIMALS);
    (v * k).round() / k
}

/// A joint vector (rad) exactly as the program text will carry it (and `verify` read it back).
pub fn emitted(q: &[f64; 6]) -> [f64; 6] {
    q.map(|r| round_deg(crate::units::to_deg(r)) * crate::units::DEG)
}

/// A speed percentage as controllers take it: an integer, rounded *down* (never faster than
/// planned), at least 1 and at most 100.
pub fn percent(p: f64) -> i64 {
    if !p.is_finite() {
        return 100;
    }
    ((p * (1.0 + 1e-12)).floor() as i64).clamp(1, 100)
}

/// The program for one controller: the plan's `base` with the dialect, the mapping, every
/// move's axis values (exactly as printed) and speed percentage filled in. `speeds` are the
/// robot file's joint speeds (rad/s), each controller axis's 100 %.
pub fn target(
    base: &Program,
    dialect: &Dialect,
    map: &ControllerMap,
    speeds: &[f64; 6],
) -> Program {
    let mut p = base.clone();
    let decimals = map.units.decimals();
    let h = &mut p.header;
    h.dialect = dialect.name.clone();
    h.controller = map.describe();
    h.axis_names = map.axis_names.to_vec();
    h.axis_units = map.units.name().to_string();
    h.axis_decimals = decimals;
    // The accelerations the times assume, per controller axis in its units.
    h.accelerations = map.axis_speeds(&h.accelerations.map(|a| a * crate::units::DEG));
    // Degrees: the plan's grid, printed exactly. Radians: cut toward zero at the printed
    // decimals, so a pose on a limit that contains zero (joint ranges, harness ranges) stays
    // inside it when read back.
    let printed = |v: f64| match map.units {
        crate::controller::Units::Deg => fmt_fixed(v, decimals).parse::<f64>().unwrap_or(v),
        crate::controller::Units::Rad => {
            let k = 10f64.powi(decimals as i32);
            fmt_fixed((v * k).trunc() / k, decimals)
                .parse::<f64>()
                .unwrap_or(v)
        }
    };
    let vmax = map.axis_speeds(speeds);
    let mut prev: Option<[f64; 6]> = None;
    for m in &mut p.moves {
        let axes = map.apply(&m.q_deg).map(printed);
        m.axes = axes;
        // Synchronous joint moves: the slowest axis leads; this percentage of every axis's
        // maximum makes it cruise at the planned speed (the ramps come on top).
        m.speed_pct = match prev {
            Some(a) if m.cruise_s > 0.0 => {
                let lead = (0..6)
                    .map(|i| (axes[i] - a[i]).abs() / vmax[i])
                    .fold(0.0, f64::max);
                100.0 * lead / m.cruise_s
            }
            _ => 100.0,
        };
        prev = Some(axes);
    }
    p
}

/// Decimals a template may ask of a number (an f64 carries about 16 significant digits; a
/// controller reads far fewer), and the widest column it may pad to.
const MAX_DECIMALS: usize = 15;
const MAX_WIDTH: usize = 256;

/// A template's count argument `n` if at most `max`, else a template error naming the limit
/// (a user's template asking for a billion decimals is an error, not a panic or a gigabyte).
fn digits(n: usize, max: usize) -> Result<usize, minijinja::Error> {
    if n <= max {
        Ok(n)
    } else {
        Err(minijinja::Error::new(
            minijinja::ErrorKind::InvalidOperation,
            format!("{n} is more than the {max} a filter takes"),
        ))
    }
}

/// Renders `program` with `template`. The output always ends with one newline.
pub fn render(template: &Template, program: &Program) -> Result<String, String> {
    let mut env = Environment::new();
    env.set_undefined_behavior(minijinja::UndefinedBehavior::Strict);
    env.add_filter("f", |v: f64, decimals: usize| {
        Ok::<_, minijinja::Error>(fmt_fixed(v, digits(decimals, MAX_DECIMALS)?))
    });
    env.add_filter("feed", inverse_time_feed);
    env.add_filter("ceil", |v: f64, decimals: usize| {
        Ok::<_, minijinja::Error>(ceil_fixed(v, digits(decimals, MAX_DECIMALS)?))
    });
    env.add_filter("pct", percent);
    // Text inside an RS274 comment: parentheses would end or nest it.
    env.add_filter("comment", |v: String| v.replace('(', "[").replace(')', "]"));
    env.add_filter("wrap", wrap);
    env.add_filter("say", say);
    env.add_filter("rjust", |v: Value, width: usize| {
        let width = digits(width, MAX_WIDTH)?;
        Ok::<_, minijinja::Error>(format!("{:>width$}", v.to_string()))
    });
    env.add_filter("ident", |v: String, max: usize| ident(&v, max));
    for (name, source) in crate::dialect::bundled() {
        env.add_template(name, source).map_err(one_line)?;
    }
    env.add_template("program", &template.source)
        .map_err(one_line)?;
    let tmpl = env.get_template("program").map_err(one_line)?;
    let ctx = minijinja::context! { h => Value::from_serialize(&program.header), moves => Value::from_serialize(&program.moves) };
    let mut text = tmpl.render(ctx).map_err(one_line)?;
    while text.ends_with('\n') {
        text.pop();
    }
    text.push('\n');
    Ok(text)
}

/// An operator message as lines of at most `width` characters for a controller's string
/// literal: printable ASCII only (`"` becomes `'`, anything else `?`), broken at spaces where
/// possible. Never empty: an empty text gives one empty line.
pub fn say(text: String, width: usize) -> Vec<String> {
    let width = width.max(8);
    let clean: String = text
        .chars()
        .map(|c| match c {
            '"' => '\'',
            ' '..='~' => c,
            _ => '?',
        })
        .collect();
    let mut out = Vec::new();
    let mut line = String::new();
    for word in clean.split(' ').filter(|w| !w.is_empty()) {
        let mut word = word;
        if !line.is_empty() && line.len() + 1 + word.len() > width {
            out.push(std::mem::take(&mut line));
        }
        while word.len() > width {
            let (a, b) = word.split_at(width);
            if !line.is_empty() {
                out.push(std::mem::take(&mut line));
            }
            out.push(a.to_string());
            word = b;
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(word);
    }
    if !line.is_empty() || out.is_empty() {
        out.push(line);
    }
    out
}

/// A name of letters, digits and `_` with a letter first, at most `max` characters.
pub fn ident(name: &str, max: usize) -> String {
    let mut s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect();
    if !s.chars().next().is_some_and(|c| c.is_ascii_alphabetic()) {
        s.insert(0, 'P');
    }
    s.truncate(max.max(1));
    s
}

fn one_line(e: minijinja::Error) -> String {
    let mut s = e.to_string().replace('\n', " ");
    if let Some(line) = e.line() {
        s = format!("line {line}: {s}");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn number_filters_never_run_faster_than_planned() {
        assert_eq!(ceil_fixed(1.2341, 3), "1.235");
        assert_eq!(ceil_fixed(1.234, 3), "1.234");
        assert_eq!(inverse_time_feed(0.7), "85.7142");
        assert_eq!(percent(99.99), 99);
        assert_eq!(percent(100.0), 100);
        assert_eq!(percent(250.0), 100);
        assert_eq!(percent(0.2), 1);
    }

    #[test]
    fn say_gives_printable_lines_within_the_width_and_keeps_every_word() {
        let text = "mount the LDBB \"here\", set 125 N µ, then resume".to_string();
        let lines = say(text, 12);
        assert!(lines.iter().all(|l| l.len() <= 12), "{lines:?}");
        assert!(lines
            .iter()
            .all(|l| l.chars().all(|c| (' '..='~').contains(&c) && c != '"')));
        assert_eq!(
            lines.join(" "),
            "mount the LDBB 'here', set 125 N ?, then resume"
        );
        assert_eq!(
            say("abcdefghijklmnopqrst".into(), 8),
            ["abcdefgh", "ijklmnop", "qrst"]
        );
        assert_eq!(say(String::new(), 8), [""]);
    }

    #[test]
    fn wrap_keeps_every_chunk_within_the_width() {
        let text = "fixture: 258.000, 1468.000, 708.000 mm in the robot base frame".to_string();
        let w = wrap(text.clone(), 30);
        assert!(w.iter().all(|c| c.len() <= 30), "{w:?}");
        assert!(w[1..].iter().all(|c| c.starts_with(".. ")));
        let join = |w: &[String]| {
            let mut h = Vec::new();
            for c in w {
                crate::dialect::push_header(&mut h, c);
            }
            h
        };
        assert_eq!(join(&w), vec![text]);
        let long_text = "sha256: ".to_string() + &"ab".repeat(40) + " end";
        let long = wrap(long_text.clone(), 30);
        assert!(long.iter().all(|c| c.len() <= 30), "{long:?}");
        assert_eq!(join(&long), vec![long_text]);
    }

    #[test]
    fn ident_makes_names() {
        assert_eq!(ident("nj130-prog", 24), "nj130_prog");
        assert_eq!(ident("1abc", 24), "P1abc");
        assert_eq!(ident("abcdef", 4), "abcd");
    }
}

//! Emission: in = a dialect template (text under `templates/`) and a [`Program`]; out = the
//! program text. Dialects are data: the template decides the syntax, Rust only supplies the
//! values and the one number formatter ([`fmt_fixed`]) so every dialect rounds the same way.

use crate::ir::Program;
use crate::units::fmt_fixed;
use minijinja::{Environment, Value};

/// The bundled dialects, compiled into the binary (the files under `templates/` are the source).
pub const DIALECTS: &[(&str, &str)] = &[("ngc", include_str!("../../templates/ngc.j2"))];

pub fn dialect(name: &str) -> Option<&'static str> {
    DIALECTS.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

pub use crate::units::DEG_DECIMALS;

/// A joint value (degrees) as the program will carry it.
pub fn round_deg(v: f64) -> f64 {
    let k = 10f64.powi(DEG_DECIMALS);
    (v * k).round() / k
}

/// A joint vector (rad) exactly as the program text will carry it (and `verify` read it back).
pub fn emitted(q: &[f64; 6]) -> [f64; 6] {
    q.map(|r| round_deg(crate::units::to_deg(r)) * crate::units::DEG)
}

/// The inverse-time feed word for a move of `seconds`: 60/t rounded *down* to 4 decimals, so
/// the move never runs faster than planned.
pub fn inverse_time_feed(seconds: f64) -> String {
    let f = if seconds > 0.0 { 60.0 / seconds } else { 0.0 };
    fmt_fixed((f * 1e4 * (1.0 - 1e-12)).floor() / 1e4, 4)
}

/// Renders `program` with `template`. The output always ends with one newline.
pub fn render(template: &str, program: &Program) -> Result<String, String> {
    let mut env = Environment::new();
    env.set_undefined_behavior(minijinja::UndefinedBehavior::Strict);
    env.add_filter("f", |v: f64, decimals: usize| fmt_fixed(v, decimals));
    env.add_filter("feed", inverse_time_feed);
    // Text inside an RS274 comment: parentheses would end or nest it.
    env.add_filter("comment", |v: String| v.replace('(', "[").replace(')', "]"));
    env.add_template("program", template).map_err(one_line)?;
    let tmpl = env.get_template("program").map_err(one_line)?;
    let ctx = minijinja::context! { h => Value::from_serialize(&program.header), moves => Value::from_serialize(&program.moves) };
    let mut text = tmpl.render(ctx).map_err(one_line)?;
    while text.ends_with('\n') {
        text.pop();
    }
    text.push('\n');
    Ok(text)
}

fn one_line(e: minijinja::Error) -> String {
    let mut s = e.to_string().replace('\n', " ");
    if let Some(line) = e.line() {
        s = format!("line {line}: {s}");
    }
    s
}

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

/// Renders `program` with `template`. The output always ends with one newline.
pub fn render(template: &str, program: &Program) -> Result<String, String> {
    let mut env = Environment::new();
    env.set_undefined_behavior(minijinja::UndefinedBehavior::Strict);
    env.add_filter("f", |v: f64, decimals: usize| fmt_fixed(v, decimals));
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

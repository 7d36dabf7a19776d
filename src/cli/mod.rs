//! The command line: argv in, an exit code (or one exit-2 error line) out. Each subcommand's
//! file parses its flags once into checked options, calls the library, writes files (temp
//! file, then rename) and prints results; `common`, `progress` and `logruns` hold what they
//! share, and no subcommand's file imports another's. Progress bars live here and only here.

/// Prints a summary on stdout (like `println!`) unless `-q` asked for quiet; warnings and
/// errors go to stderr regardless, and output a flag asked for is printed with `println!`.
macro_rules! say {
    ($quiet:expr, $($arg:tt)*) => {
        if !$quiet {
            println!($($arg)*);
        }
    };
}

/// [`say!`] without the newline (`print!`).
macro_rules! say_raw {
    ($quiet:expr, $($arg:tt)*) => {
        if !$quiet {
            print!($($arg)*);
        }
    };
}

pub mod args;
mod calibrate_cli;
mod common;
mod compensate_cli;
mod compile_cli;
mod help;
mod ldbb_cli;
mod logruns;
mod model_cli;
mod place_cli;
mod progress;
mod twin_cli;
mod verify_cli;

use crate::{pipeline, robot};
use args::{Cli, Command, DialectsArgs};
use clap::Parser;
use std::io::Write;

/// Everything that ends the program with exit code 2: one line, naming the file, field or flag.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{0}")]
    Usage(String),
    #[error(transparent)]
    Load(#[from] robot::LoadError),
    #[error(transparent)]
    Pipeline(#[from] pipeline::PipelineError),
    #[error(transparent)]
    Cell(#[from] crate::cell::CellError),
    #[error(transparent)]
    Plot(#[from] crate::plot::PlotError),
    #[error(transparent)]
    Report(#[from] crate::report::ReportError),
    #[error(transparent)]
    Place(#[from] crate::place::PlaceError),
    #[error(transparent)]
    Controller(#[from] crate::controller::ControllerError),
    #[error("{path}: {msg}")]
    File { path: String, msg: String },
}

fn usage(msg: impl Into<String>) -> Error {
    Error::Usage(msg.into())
}

/// Runs the CLI on `argv`; returns the exit code (0 ok, 1 check failed) or an exit-2 error.
pub fn run(argv: Vec<std::ffi::OsString>) -> Result<i32, Error> {
    let cli = match Cli::try_parse_from(argv) {
        Ok(c) => c,
        Err(e) => {
            use clap::error::ErrorKind;
            if matches!(e.kind(), ErrorKind::DisplayHelp | ErrorKind::DisplayVersion) {
                let _ = e.print();
                return Ok(0);
            }
            // clap's message spans several lines; the first names the problem.
            let text = e.render().to_string();
            let line = text
                .lines()
                .find(|l| !l.trim().is_empty())
                .unwrap_or("invalid arguments");
            return Err(usage(line.trim_start_matches("error: ").to_string()));
        }
    };
    match cli.command {
        Some(Command::Model(m)) => model_cli::run(&m),
        Some(Command::Verify(v)) => verify_cli::run(&v),
        Some(Command::Simulate(a)) => twin_cli::simulate(&a),
        Some(Command::Diagnose(a)) => twin_cli::diagnose(&a),
        Some(Command::Circle(a)) => twin_cli::circle(&a),
        Some(Command::Ldbb(a)) => ldbb_cli::ldbb(&a),
        Some(Command::LdbbCircle(a)) => ldbb_cli::circle(&a),
        Some(Command::SimulateLdbb(a)) => ldbb_cli::simulate(&a),
        Some(Command::Dialects(a)) => run_dialects(&a),
        Some(Command::Calibrate(a)) => calibrate_cli::calibrate(&a),
        Some(Command::Place(a)) => place_cli::place(&a),
        Some(Command::Compensate(a)) => compensate_cli::compensate(&a),
        Some(Command::Completions(a)) => {
            let mut cmd = <Cli as clap::CommandFactory>::command();
            clap_complete::generate(a.shell, &mut cmd, "edbbgen", &mut std::io::stdout());
            Ok(0)
        }
        Some(Command::Man(a)) => {
            let mut cmd = <Cli as clap::CommandFactory>::command();
            if let Some(name) = &a.subcommand {
                let names: Vec<String> = cmd
                    .get_subcommands()
                    .map(|c| c.get_name().to_string())
                    .collect();
                cmd = cmd
                    .find_subcommand(name)
                    .cloned()
                    .ok_or_else(|| {
                        usage(format!(
                            "man: unknown subcommand '{name}' (one of: {})",
                            names.join(", ")
                        ))
                    })?
                    .name(format!("edbbgen-{name}"))
                    .version(env!("CARGO_PKG_VERSION"));
            }
            let out = man_page(cmd, a.subcommand.as_deref())
                .map_err(|e| usage(format!("man page: {e}")))?;
            // A closed pipe (`| head`) is the reader's choice, not an error.
            let _ = std::io::stdout().write_all(&out);
            Ok(0)
        }
        None => compile_cli::run(&cli.compile),
    }
}

/// The man page of the compiler or a subcommand: clap_mangen's sections, with EXAMPLES and
/// EXIT STATUS before VERSION (the examples in place of clap's EXTRA section).
fn man_page(cmd: clap::Command, subcommand: Option<&str>) -> std::io::Result<Vec<u8>> {
    let examples = match subcommand {
        None => help::COMPILE,
        Some(name) => help::examples(Some(name)).unwrap_or(""),
    };
    let has_subcommands = cmd.get_subcommands().next().is_some();
    let man = clap_mangen::Man::new(cmd);
    let mut out = Vec::new();
    man.render_title(&mut out)?;
    man.render_name_section(&mut out)?;
    man.render_synopsis_section(&mut out)?;
    man.render_description_section(&mut out)?;
    man.render_options_section(&mut out)?;
    if has_subcommands {
        man.render_subcommands_section(&mut out)?;
    }
    let mut roff = roff::Roff::new();
    roff.control("SH", ["EXAMPLES"]);
    for line in examples.lines().skip(1) {
        let line = line.trim_start();
        if let Some(comment) = line.strip_prefix("# ") {
            roff.control("PP", []).text([roff::roman(comment)]);
        } else if !line.is_empty() {
            roff.control("IP", [])
                .control("EX", [])
                .text([roff::roman(line)])
                .control("EE", []);
        }
    }
    roff.control("SH", ["EXIT STATUS"]);
    for status in help::EXIT_STATUS.lines() {
        let (code, text) = status.split_once("  ").unwrap_or((status, ""));
        roff.control("TP", [])
            .text([roff::bold(code)])
            .text([roff::roman(text)]);
    }
    roff.to_writer(&mut out)?;
    man.render_version_section(&mut out)?;
    Ok(out)
}

// ---- dialects -----------------------------------------------------------------------------

fn run_dialects(a: &DialectsArgs) -> Result<i32, Error> {
    let all = crate::dialect::all();
    if let Some(dest) = &a.json {
        common::check_outputs(&[Some(dest.as_path())])?;
        let list: Vec<serde_json::Value> = all
            .iter()
            .map(|d| {
                serde_json::json!({
                    "name": d.name,
                    "title": d.title,
                    "extensions": d.extensions,
                    "units": d.units,
                    "units_configurable": d.units_configurable,
                    "axis_names": d.axis_names,
                    "axis_names_configurable": d.axis_names_configurable,
                    "j3_coupling": d.j3_coupling,
                    "name_max": d.name_max,
                    "name_must_match_file": d.name_must_match_file,
                    "approximations": d.approximations,
                })
            })
            .collect();
        let doc = serde_json::json!({"schema": "edbbgen.dialects/1", "dialects": list});
        common::write_json(
            dest,
            &serde_json::to_string_pretty(&doc).unwrap_or_default(),
        )?;
        if common::is_stdout(dest) {
            return Ok(0);
        }
    }
    for d in all {
        let coupling = match d.j3_coupling {
            crate::controller::Coupling::Factor(0) => "no J2/J3 coupling".to_string(),
            crate::controller::Coupling::Factor(k) => format!("J3 coupling {k}"),
            crate::controller::Coupling::Auto(_) => {
                "J3 measured from the horizontal (coupling from the robot's joint axes)".to_string()
            }
        };
        say!(
            a.quiet,
            "{:<10} .{:<8} {}; axes {} in {}; {}",
            d.name,
            d.extensions[0],
            d.title,
            d.axis_names.join(" "),
            d.units.name(),
            coupling
        );
        for ap in &d.approximations {
            say!(a.quiet, "{:<20}approximates: {ap}", "");
        }
    }
    Ok(0)
}

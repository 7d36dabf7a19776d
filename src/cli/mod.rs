//! The command line: parse argv, resolve flags once into checked options, call the pipeline,
//! write files (temp file + rename) and print results. Progress bars live here and only here.

pub mod args;
mod calibrate_cli;
mod compensate_cli;
mod ldbb_cli;
mod logs_cli;
mod place_cli;
mod twin_cli;

use crate::cell::CellSpec;
use crate::model::{self, IdentifyOptions, MeasurementModel, Status};
use crate::pipeline::{self, CompileOptions};
use crate::robot::{self, LoadOptions, Robot};
use crate::units::{fmt_fixed, to_mm, DEG, MM};
use args::{CellArgs, Cli, Command, CompileArgs, DialectsArgs, ModelArgs, VerifyArgs};
use clap::Parser;
use nalgebra::{DMatrix, Vector3};
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

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
        Some(Command::Model(m)) => run_model(&m),
        Some(Command::Verify(v)) => run_verify(&v),
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
            let mut out = Vec::new();
            clap_mangen::Man::new(cmd)
                .render(&mut out)
                .map_err(|e| usage(format!("man page: {e}")))?;
            // A closed pipe (`| head`) is the reader's choice, not an error.
            let _ = std::io::stdout().write_all(&out);
            Ok(0)
        }
        None => run_compile(&cli.compile),
    }
}

// ---- flag parsing -------------------------------------------------------------------------

fn numbers(flag: &str, s: &str, n: Option<usize>) -> Result<Vec<f64>, Error> {
    let vals: Result<Vec<f64>, _> = s.split(',').map(|t| t.trim().parse::<f64>()).collect();
    let vals = vals.map_err(|_| {
        usage(format!(
            "{flag}: '{s}' is not a comma-separated list of numbers"
        ))
    })?;
    if vals.iter().any(|v| !v.is_finite()) {
        return Err(usage(format!(
            "{flag}: '{s}' contains a value that is not finite"
        )));
    }
    if let Some(n) = n {
        if vals.len() != n {
            return Err(usage(format!(
                "{flag}: '{s}' has {} values, expected {n}",
                vals.len()
            )));
        }
    }
    Ok(vals)
}

fn xyz_mm(flag: &str, s: &str) -> Result<Vector3<f64>, Error> {
    let v = numbers(flag, s, Some(3))?;
    Ok(Vector3::new(v[0], v[1], v[2]) * MM)
}

fn scalar(flag: &str, s: &str) -> Result<f64, Error> {
    Ok(numbers(flag, s, Some(1))?[0])
}

fn bar_range(s: &str) -> Result<(f64, f64), Error> {
    let (a, b) = s
        .split_once("..")
        .ok_or_else(|| usage(format!("--bar: '{s}' is not MIN..MAX (mm)")))?;
    let (a, b) = (scalar("--bar", a)?, scalar("--bar", b)?);
    if !(a > 0.0 && b > a) {
        return Err(usage(format!("--bar: '{s}' needs 0 < MIN < MAX")));
    }
    Ok((a * MM, b * MM))
}

fn steps(s: &str) -> Result<[f64; 6], Error> {
    let v = numbers("--step", s, None)?;
    let v: Vec<f64> = match v.len() {
        1 => vec![v[0]; 6],
        6 => v,
        n => {
            return Err(usage(format!(
                "--step: '{s}' has {n} values, expected 1 or 6"
            )))
        }
    };
    if v.iter().any(|&x| !(0.1..=180.0).contains(&x)) {
        return Err(usage(format!(
            "--step: '{s}': each step must be between 0.1 and 180 degrees"
        )));
    }
    Ok(std::array::from_fn(|i| v[i] * DEG))
}

fn load_robot(path: &Path, cell: &CellArgs, spec: &CellSpec) -> Result<Robot, Error> {
    let opts = LoadOptions {
        flange_link: cell.flange.clone(),
        package_paths: cell.package_path.clone(),
        speeds: spec.speeds,
        accelerations: spec.accelerations,
        ..LoadOptions::default()
    };
    Ok(robot::load(path, &opts)?)
}

/// The cell: the file (or the defaults), then every flag that overrides it.
fn resolve_cell(a: &CellArgs) -> Result<CellSpec, Error> {
    let mut spec = match &a.cell {
        Some(p) => crate::cell::load(p)?,
        None => CellSpec::default(),
    };
    if let Some(t) = &a.tool {
        spec.map = Some(xyz_mm("--tool", t)?);
    }
    if let Some(b) = &a.bar {
        (spec.bar_min, spec.bar_max) = bar_range(b)?;
        (spec.stated.bar_min, spec.stated.bar_max) = (true, true);
    }
    if let Some(f) = &a.floor {
        spec.floor_z = scalar("--floor", f)? * MM;
    }
    if let Some(b) = &a.ball {
        let b = scalar("--ball", b)?;
        if !(b > 0.0 && b < 200.0) {
            return Err(usage(format!(
                "--ball: {b} mm must be between 0 and 200 mm"
            )));
        }
        spec.ball = b * MM;
        spec.stated.ball = true;
    }
    set_margins(&mut spec, a.margin.as_deref(), a.joint_margin.as_deref())?;
    Ok(spec)
}

/// `--margin MM` and `--joint-margin DEG` over the cell's values, range-checked.
pub(crate) fn set_margins(
    spec: &mut CellSpec,
    margin: Option<&str>,
    joint_margin: Option<&str>,
) -> Result<(), Error> {
    if let Some(m) = margin {
        let m = scalar("--margin", m)?;
        if !(0.0..=500.0).contains(&m) {
            return Err(usage(format!(
                "--margin: {m} mm must be between 0 and 500 mm"
            )));
        }
        spec.margin = m * MM;
        spec.stated.margin = true;
    }
    if let Some(m) = joint_margin {
        let m = scalar("--joint-margin", m)?;
        if !(0.0..=30.0).contains(&m) {
            return Err(usage(format!(
                "--joint-margin: {m} deg must be between 0 and 30 deg"
            )));
        }
        spec.joint_margin = m * DEG;
        spec.stated.joint_margin = true;
    }
    Ok(())
}

/// The fixture: the flag, else the cell file's, else (verify) the program header's.
fn resolve_fixture(
    flag: Option<&str>,
    spec: &CellSpec,
    header: Option<&str>,
) -> Result<Vector3<f64>, Error> {
    if let Some(f) = flag {
        return xyz_mm("--fixture", f);
    }
    if let Some(f) = spec.fixture {
        return Ok(f);
    }
    if let Some(h) = header {
        let nums = h.split("mm").next().unwrap_or("");
        return xyz_mm("program header (fixture)", nums.trim());
    }
    Err(usage(
        "--fixture: required (or give it in the cell file as [fixture] position)",
    ))
}

// ---- progress -----------------------------------------------------------------------------

struct Bar(Option<indicatif::ProgressBar>);

impl Bar {
    fn new(quiet: bool, label: &'static str) -> Self {
        if quiet || !std::io::stderr().is_terminal() {
            return Bar(None);
        }
        let pb = indicatif::ProgressBar::with_draw_target(
            Some(0),
            indicatif::ProgressDrawTarget::stderr(),
        );
        if let Ok(style) = indicatif::ProgressStyle::with_template(
            "{msg:>10} [{bar:40}] {percent:>3}% {elapsed}/{eta}",
        ) {
            pb.set_style(style.progress_chars("=> "));
        }
        pb.set_message(label);
        Bar(Some(pb))
    }
}

impl crate::sample::Progress for Bar {
    fn start(&self, total: u64) {
        if let Some(p) = &self.0 {
            p.set_length(total);
        }
    }
    fn inc(&self, n: u64) {
        if let Some(p) = &self.0 {
            p.inc(n);
        }
    }
    fn finish(&self) {
        if let Some(p) = &self.0 {
            p.finish_and_clear();
        }
    }
}

/// `--timings`: the wall time of every pipeline stage on stderr, passing the progress
/// callbacks on to the bar.
struct Timed<'a> {
    inner: &'a dyn crate::sample::Progress,
    on: bool,
    t0: std::time::Instant,
    stage: std::sync::Mutex<(std::time::Instant, &'static str)>,
}

impl<'a> Timed<'a> {
    /// Timing from `t0`, in the stage `first`.
    fn new(
        inner: &'a dyn crate::sample::Progress,
        on: bool,
        first: &'static str,
        t0: std::time::Instant,
    ) -> Self {
        Timed {
            inner,
            on,
            t0,
            stage: std::sync::Mutex::new((t0, first)),
        }
    }

    /// Ends the current stage (printing its time) and starts `next`.
    fn next(&self, next: &'static str) {
        if !self.on {
            return;
        }
        let now = std::time::Instant::now();
        let mut st = self.stage.lock().unwrap_or_else(|e| e.into_inner());
        eprintln!(
            "edbbgen: timing: {:<22}{:>8.3} s",
            st.1,
            (now - st.0).as_secs_f64()
        );
        *st = (now, next);
    }

    /// Ends the last stage and prints the total.
    fn done(&self) {
        if self.on {
            self.next("");
            eprintln!(
                "edbbgen: timing: {:<22}{:>8.3} s",
                "total",
                self.t0.elapsed().as_secs_f64()
            );
        }
    }
}

impl crate::sample::Progress for Timed<'_> {
    fn stage(&self, name: &'static str) {
        self.next(name);
        self.inner.stage(name);
    }
    fn start(&self, total: u64) {
        self.inner.start(total);
    }
    fn inc(&self, n: u64) {
        self.inner.inc(n);
    }
    fn finish(&self) {
        self.inner.finish();
    }
}

// ---- the compiler -------------------------------------------------------------------------

/// The output template: a user's file (`--template`) or a bundled dialect (`--dialect`).
fn resolve_template(dialect: &str, file: Option<&Path>) -> Result<String, Error> {
    match file {
        Some(p) => {
            let text = read_input(p, "template", crate::files::Kind::Config)?;
            // The dialect it extends decides how its programs are read back: checked first.
            crate::dialect::Template::from_source(&text).map_err(|e| Error::File {
                path: p.display().to_string(),
                msg: e.to_string(),
            })?;
            Ok(text)
        }
        None => crate::emit::dialect(dialect)
            .map(str::to_string)
            .ok_or_else(|| {
                usage(format!(
                    "--dialect: unknown dialect '{dialect}' (available: {})",
                    crate::dialect::names().join(", ")
                ))
            }),
    }
}

fn run_compile(a: &CompileArgs) -> Result<i32, Error> {
    let started = std::time::Instant::now();
    // Required by clap; the Options only exist because subcommands negate the requirement.
    let (Some(robot_path), Some(output)) = (&a.robot, &a.output) else {
        return Err(usage("ROBOT and -o are required"));
    };
    let spec = resolve_cell(&a.cell)?;
    let fixture = resolve_fixture(a.fixture.as_deref(), &spec, None)?;
    let blend = scalar("--blend", &a.blend)?;
    if !(0.0..=100.0).contains(&blend) {
        return Err(usage(format!("--blend: {blend} mm is outside 0..100 mm")));
    }
    let start = match &a.start {
        Some(s) => {
            let v = numbers("--start", s, Some(6))?;
            std::array::from_fn(|i| v[i] * DEG)
        }
        None => [0.0; 6],
    };
    if a.max_candidates < 30 {
        return Err(usage("--max-candidates: must be at least 30"));
    }
    let template = resolve_template(&a.dialect, a.template.as_deref())?;
    let dialect = crate::dialect::Template::from_source(&template)
        .map_err(|e| usage(e.to_string()))?
        .dialect;
    let program_name = program_name(output, dialect)?;
    check_outputs(&[
        (!a.check).then_some(output.as_path()),
        a.report.as_deref(),
        a.html.as_deref(),
    ])?;
    if let Some(stage) = &a.emit {
        if !EMIT_STAGES.contains(&stage.as_str()) {
            return Err(usage(format!(
                "--emit: unknown stage '{stage}' (one of: {})",
                EMIT_STAGES.join(", ")
            )));
        }
    }
    let step = steps(&a.step)?;
    let robot = load_robot(robot_path, &a.cell, &spec)?;
    controller_map(&spec, a.cell.cell.as_deref(), dialect, &robot)?;
    let (lo, hi) = robot.limits();
    let start = std::array::from_fn(|i| f64::clamp(start[i], lo[i], hi[i]));
    let bar_noise = scalar("--bar-noise", &a.bar_noise)?;
    if bar_noise <= 0.0 {
        return Err(usage(format!(
            "--bar-noise: {bar_noise} um must be positive"
        )));
    }
    let bar_rate = scalar("--bar-rate", &a.bar_rate)?;
    if !(1.0..=100_000.0).contains(&bar_rate) {
        return Err(usage(format!(
            "--bar-rate: {bar_rate} Hz is outside 1..100000 Hz"
        )));
    }
    let dwell = match &a.dwell {
        Some(d) => {
            // On the 0.01 s grid every dialect prints exactly (FANUC's WAIT resolves 0.01 s).
            let d = (scalar("--dwell", d)? * 100.0).round() / 100.0;
            if !(0.1..=60.0).contains(&d) {
                return Err(usage(format!("--dwell: {d} s is outside 0.1..60 s")));
            }
            let n = crate::logs::plateau_core_samples(d, bar_rate);
            if n < crate::logs::MIN_PLATEAU_SAMPLES {
                return Err(usage(format!(
                    "--dwell: {d} s at --bar-rate {bar_rate} Hz leaves {n} bar samples per pose, fewer than the {} a plateau needs: dwell longer",
                    crate::logs::MIN_PLATEAU_SAMPLES
                )));
            }
            Some(d)
        }
        None => None,
    };
    let focus = a.focus.as_deref().map(parse_focus).transpose()?;
    let opts = CompileOptions {
        focus,
        fixture,
        cell: spec,
        step,
        max_candidates: a.max_candidates,
        seed: a.cell.seed,
        poses: a.poses,
        blend: blend * MM,
        start,
        program_name,
        bar_noise: bar_noise * 1e-6,
        bar_rate,
        dwell,
        tour_cost: if a.tour_cost == "eq7" {
            pipeline::TourCost::Eq7
        } else {
            pipeline::TourCost::Trapezoid
        },
    };
    let bar = Bar::new(a.cell.quiet, "sampling");
    let timed = Timed::new(&bar, a.timings, "load", started);
    let out = match pipeline::compile(&robot, &opts, &template, &timed) {
        Ok(out) => {
            timed.done();
            out
        }
        Err(e) if e.exit_code() == 1 => {
            eprintln!("edbbgen: {e}");
            return Ok(1);
        }
        Err(e) => return Err(e.into()),
    };
    for w in &out.warnings {
        eprintln!("edbbgen: warning: {w}");
    }
    let ext = output
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    if ext.as_ref().is_none_or(|e| !dialect.extensions.contains(e)) {
        eprintln!(
            "edbbgen: warning: {}: a {} program usually ends in .{}; verify and simulate then need --dialect {}",
            output.display(),
            dialect.name,
            dialect.extensions[0],
            dialect.name
        );
    }
    if let Some(stage) = &a.emit {
        println!("{}", emit_stage(&out, stage));
    }
    if let Some(r) = &a.report {
        write_atomic(
            r,
            &(serde_json::to_string_pretty(&out.report).unwrap_or_default() + "\n"),
        )?;
    }

    if a.check {
        let old = std::fs::read_to_string(output).unwrap_or_default();
        if old == out.text {
            eprintln!("edbbgen: {} is up to date", output.display());
            return Ok(0);
        }
        if !output.exists() {
            eprintln!("edbbgen: {} does not exist", output.display());
        }
        let name = output.display().to_string();
        let diff = similar::TextDiff::from_lines(&old, &out.text);
        print!(
            "{}",
            diff.unified_diff()
                .context_radius(3)
                .header(&format!("{name} (on disk)"), &format!("{name} (compiled)"))
        );
        return Ok(1);
    }
    // The page is rendered before anything is written, so a failure leaves no file at all.
    let html = match &a.html {
        Some(_) => Some(crate::report::render(&crate::report::compile::page(
            &robot, &out,
        )?)?),
        None => None,
    };
    let mut files: Vec<(&Path, &str)> = vec![(output.as_path(), out.text.as_str())];
    if let (Some(path), Some(html)) = (&a.html, &html) {
        files.push((path.as_path(), html.as_str()));
    }
    write_all_atomic(&files)?;
    if a.emit.is_none() {
        let h = &out.program.header;
        let v = &out.verified;
        println!(
            "{}: {} poses + {} support ({} identifiable parameters, cond {}), estimated {} s as programmed (support poses and blends included); ordering: {} s in tour order, {} s unsorted (the measurement poses alone, direct moves); verified: min clearance {} mm ({} / {}), bar {}..{} mm; predicted MAP position uncertainty after calibration {} um RMS over the joint space ({} um bar noise at {} Hz)",
            output.display(),
            h.poses,
            h.supports,
            h.identifiable,
            fmt_fixed(h.cond, 2),
            fmt_fixed(h.time_s, 1),
            fmt_fixed(h.time_direct_s, 1),
            fmt_fixed(h.time_unsorted_s, 1),
            fmt_fixed(to_mm(v.min_clearance.distance), 1),
            v.min_clearance.a,
            v.min_clearance.b,
            fmt_fixed(to_mm(v.extremes.min_length), 1),
            fmt_fixed(to_mm(v.extremes.max_length), 1),
            fmt_fixed(h.predicted_std_um, 2),
            fmt_fixed(h.bar_noise_um, 2),
            fmt_fixed(h.bar_rate_hz, 0),
        );
        if h.dwell_s > 0.0 {
            println!(
                "stop-and-measure: exact stop and {} s dwell at each of the {} measurement poses; predicted {} um RMS over the joint space from the plateau means ({} samples each), {} um from the same run recorded with a synchronous joint log",
                fmt_fixed(h.dwell_s, 2),
                h.measure_mm.len(),
                fmt_fixed(h.predicted_std_um, 2),
                h.plateau_samples,
                fmt_fixed(h.predicted_continuous_std_um, 2)
            );
        }
    }
    Ok(0)
}

/// `--focus`: a calibration report (its drift's moved parameters, then the joint zeros) or a
/// comma-separated list of parameter names (not the fixture's).
fn parse_focus(s: &str) -> Result<Vec<usize>, Error> {
    if s.to_ascii_lowercase().ends_with(".json") {
        let path = Path::new(s);
        let text = read_input(path, "calibration report", crate::files::Kind::Config)?;
        let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| Error::File {
            path: s.to_string(),
            msg: format!("not JSON: {e}"),
        })?;
        if v.get("schema").and_then(|x| x.as_str()) != Some("edbbgen.calibrate/1") {
            return Err(Error::File {
                path: s.to_string(),
                msg: "not a calibration report (schema edbbgen.calibrate/1)".into(),
            });
        }
        return Ok(crate::compensate::drift::check_parameters(Some(&v)));
    }
    let mut out = Vec::new();
    for name in s.split(',').map(str::trim) {
        match model::PARAM_NAMES.iter().position(|n| *n == name) {
            Some(i) if i >= model::ALPHA => {
                if !out.contains(&i) {
                    out.push(i);
                }
            }
            _ => {
                return Err(usage(format!(
                    "--focus: '{name}' is not a robot parameter (alpha1..6, a1..6, d1..6, theta1..6, x_map, y_map, z_map) or a calibration report (.json)"
                )))
            }
        }
    }
    Ok(out)
}

/// The program name from the output file's stem; languages whose program name must equal the
/// file name (KRL, FANUC) refuse a stem they cannot carry.
fn program_name(output: &Path, dialect: &crate::dialect::Dialect) -> Result<String, Error> {
    let stem = output
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    if dialect.name_must_match_file && !crate::dialect::valid_name(&stem, dialect.name_max) {
        return Err(usage(format!(
            "-o: '{}': a {} program's name is its file name, which must be letters, digits and _, a letter first, at most {} characters",
            output.display(),
            dialect.name,
            dialect.name_max
        )));
    }
    Ok(stem)
}

/// The controller mapping for `dialect`: the cell's `[controller]` over the dialect's defaults;
/// an error names the cell file.
pub(crate) fn controller_map(
    spec: &CellSpec,
    cell: Option<&Path>,
    dialect: &crate::dialect::Dialect,
    robot: &Robot,
) -> Result<crate::controller::ControllerMap, Error> {
    crate::controller::ControllerMap::resolve(
        spec.controller.as_ref(),
        &dialect.defaults(),
        &dialect.name,
        robot,
    )
    .map_err(|e| Error::File {
        path: cell.map_or_else(
            || format!("--dialect {}", dialect.name),
            |p| p.display().to_string(),
        ),
        msg: e.to_string(),
    })
}

/// The dialect of a program file to read: `--dialect`, else its extension, else its text.
pub(crate) fn program_dialect(
    flag: Option<&str>,
    path: &Path,
    text: &str,
) -> Result<&'static crate::dialect::Dialect, Error> {
    match flag {
        Some(name) => crate::dialect::by_name(name).ok_or_else(|| {
            usage(format!(
                "--dialect: unknown dialect '{name}' (available: {})",
                crate::dialect::names().join(", ")
            ))
        }),
        None => crate::dialect::detect(path, text).ok_or_else(|| Error::File {
            path: path.display().to_string(),
            msg: format!(
                "cannot tell the program's dialect from its name or text; give --dialect ({})",
                crate::dialect::names().join(", ")
            ),
        }),
    }
}

// ---- dialects -----------------------------------------------------------------------------

fn run_dialects(a: &DialectsArgs) -> Result<i32, Error> {
    let all = crate::dialect::all();
    if a.json {
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
        println!("{}", serde_json::to_string_pretty(&doc).unwrap_or_default());
        return Ok(0);
    }
    for d in all {
        let coupling = match d.j3_coupling {
            crate::controller::Coupling::Factor(0) => "no J2/J3 coupling".to_string(),
            crate::controller::Coupling::Factor(k) => format!("J3 coupling {k}"),
            crate::controller::Coupling::Auto(_) => {
                "J3 measured from the horizontal (coupling from the robot's joint axes)".to_string()
            }
        };
        println!(
            "{:<10} .{:<8} {}; axes {} in {}; {}",
            d.name,
            d.extensions[0],
            d.title,
            d.axis_names.join(" "),
            d.units.name(),
            coupling
        );
        for ap in &d.approximations {
            println!("{:<20}approximates: {ap}", "");
        }
    }
    Ok(0)
}

const EMIT_STAGES: &[&str] = &[
    "model",
    "identifiability",
    "sample",
    "pool",
    "selection",
    "path",
    "plan",
    "program",
    "report",
];

fn emit_stage(c: &pipeline::Compiled, stage: &str) -> String {
    let v = match stage {
        "model" => serde_json::to_value(&c.model),
        "identifiability" => serde_json::to_value(&c.identifiability),
        "sample" => serde_json::to_value(&c.sample),
        "pool" => serde_json::to_value(&c.pool),
        "selection" => serde_json::to_value(&c.selection),
        "path" => serde_json::to_value(&c.path),
        "plan" => serde_json::to_value(&c.plan),
        "report" => serde_json::to_value(&c.report),
        _ => serde_json::to_value(&c.program),
    };
    v.and_then(|v| serde_json::to_string_pretty(&v))
        .unwrap_or_default()
}

/// Writes the whole file or nothing: a temp file beside the target, then rename.
/// An input file's text, within the limit of its kind (see [`crate::files`]).
fn read_input(path: &Path, what: &str, kind: crate::files::Kind) -> Result<String, Error> {
    crate::files::read_text(path, kind).map_err(|e| Error::File {
        path: path.display().to_string(),
        msg: match e {
            crate::files::ReadError::Io(e) => format!("cannot read {what}: {e}"),
            other => other.to_string(),
        },
    })
}

/// Refuses, before any work, an output whose directory does not exist or is not a directory:
/// a long compile must not end in "cannot write".
pub(crate) fn check_outputs(paths: &[Option<&Path>]) -> Result<(), Error> {
    for path in paths.iter().flatten() {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        if !dir.is_dir() {
            return Err(Error::File {
                path: path.display().to_string(),
                msg: format!("cannot write: directory {} does not exist", dir.display()),
            });
        }
        if path.is_dir() {
            return Err(Error::File {
                path: path.display().to_string(),
                msg: "cannot write: it is a directory".into(),
            });
        }
    }
    Ok(())
}

fn write_atomic(path: &Path, text: &str) -> Result<(), Error> {
    write_all_atomic(&[(path, text)])
}

/// Writes several files as one: every temp file is written and synced first, and only then
/// are they renamed into place, so a failure on any of them leaves none behind.
fn write_all_atomic(files: &[(&Path, &str)]) -> Result<(), Error> {
    let mut staged = Vec::with_capacity(files.len());
    for (path, text) in files {
        let err = |msg: String| Error::File {
            path: path.display().to_string(),
            msg,
        };
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let mut builder = tempfile::Builder::new();
        builder.prefix(".edbbgen-").suffix(".tmp");
        // A temp file is private (0600) by default; the output is an ordinary file (0666 less
        // the user's umask), like one written by any other program.
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            builder.permissions(std::fs::Permissions::from_mode(0o666));
        }
        let mut tmp = builder
            .tempfile_in(&dir)
            .map_err(|e| err(format!("cannot write (directory {}): {e}", dir.display())))?;
        tmp.write_all(text.as_bytes())
            .map_err(|e| err(format!("cannot write: {e}")))?;
        tmp.as_file()
            .sync_all()
            .map_err(|e| err(format!("cannot write: {e}")))?;
        staged.push((path, tmp));
    }
    for (path, tmp) in staged {
        tmp.persist(path).map_err(|e| Error::File {
            path: path.display().to_string(),
            msg: format!("cannot write: {}", e.error),
        })?;
    }
    Ok(())
}

// ---- verify -------------------------------------------------------------------------------

/// `verify --json`: the summary, and what the collision check covered (every body, the number
/// of pairs checked, every excluded pair with its reason), so that nothing is skipped unseen.
#[derive(serde::Serialize)]
struct VerifyReport<'a> {
    schema: &'static str,
    #[serde(flatten)]
    summary: &'a crate::verify::Summary,
    bodies: &'a [String],
    pairs_checked: usize,
    excluded_pairs: &'a [crate::collision::ExcludedPair],
    notes: &'a [String],
    /// The limits checked and where each came from (flag or cell, the program header, default).
    limits: &'a VerifyLimits,
}

/// The limits `verify` checks with and where each came from (`--json`'s `limits`).
#[derive(serde::Serialize)]
struct VerifyLimits {
    bar_mm: [f64; 2],
    margin_mm: f64,
    joint_margin_deg: f64,
    /// The most any corner may blend: the header's statement (None: not stated).
    blend_mm: Option<f64>,
    /// The joint accelerations (deg/s², per joint) the move times are checked at: the robot
    /// file's or the cell's, never the header's (a note says where the header differs).
    accelerations_deg: [f64; 6],
    /// Per limit: "flag or cell", "header" or "default".
    from: std::collections::BTreeMap<&'static str, &'static str>,
}

/// Every limit the program header states is the one `verify` checks unless a flag or the cell
/// file states it: a program compiled with `--bar 150..300` or `--margin 5` verifies as it
/// was made. An explicit flag or cell value wins; where the header states a looser one, the
/// returned notes say so (the program was made to less than this check asks).
fn header_limits(
    spec: &mut CellSpec,
    lim: &crate::verify::HeaderLimits,
    robot: &Robot,
) -> (VerifyLimits, Vec<String>) {
    let mut notes = Vec::new();
    let mut from = std::collections::BTreeMap::new();
    let source = |stated: bool, header: bool| match (stated, header) {
        (true, _) => "flag or cell",
        (false, true) => "header",
        (false, false) => "default",
    };
    let st = spec.stated;
    if let Some([lo, hi]) = lim.bar_mm {
        let cell = [to_mm(spec.bar_min), to_mm(spec.bar_max)];
        if !st.bar_min {
            spec.bar_min = lo * MM;
        }
        if !st.bar_max {
            spec.bar_max = hi * MM;
        }
        if (st.bar_min && lo < cell[0] - 0.05) || (st.bar_max && hi > cell[1] + 0.05) {
            notes.push(format!(
                "the program header states bar range {}..{} mm, wider than the {}..{} mm this check uses (flag or cell)",
                fmt_fixed(lo, 1), fmt_fixed(hi, 1), fmt_fixed(cell[0], 1), fmt_fixed(cell[1], 1)
            ));
        }
    }
    from.insert(
        "bar",
        match (st.bar_min, st.bar_max, lim.bar_mm.is_some()) {
            (true, true, _) => "flag or cell",
            (true, false, true) | (false, true, true) => "flag or cell and header",
            (_, _, header) => source(false, header),
        },
    );
    let mut scalar = |name: &'static str,
                      unit: &str,
                      stated: bool,
                      header: Option<f64>,
                      value: &mut f64,
                      scale: f64| {
        if let Some(h) = header {
            if !stated {
                *value = h * scale;
            } else if h < *value / scale - 0.05 {
                notes.push(format!(
                    "the program header states {name} {} {unit}, less than the {} {unit} this check uses (flag or cell)",
                    fmt_fixed(h, 1),
                    fmt_fixed(*value / scale, 1)
                ));
            }
        }
        from.insert(name, source(stated, header.is_some()));
    };
    scalar(
        "safety margin",
        "mm",
        st.margin,
        lim.margin_mm,
        &mut spec.margin,
        MM,
    );
    scalar(
        "joint margin",
        "deg",
        st.joint_margin,
        lim.joint_margin_deg,
        &mut spec.joint_margin,
        DEG,
    );
    from.insert(
        "corner blend",
        if lim.blend_mm.is_some() {
            "header"
        } else {
            "default"
        },
    );
    // The accelerations are the robot's (its file or the cell's `[robot] accelerations`): they
    // are what it does, whatever the program assumed. Where the header assumed others, the
    // program's times were made for another robot or cell: a note says so.
    let accelerations_deg = robot.max_accelerations().map(|a| a / DEG);
    if let Some((stated, half)) = lim.accelerations_deg {
        if (0..6).any(|i| (stated[i] - accelerations_deg[i]).abs() > half + 1e-9) {
            let list = |a: &[f64; 6]| a.map(|v| fmt_fixed(v, 1)).join(", ");
            notes.push(format!(
                "the program header states joint accelerations {} deg/s^2, but the robot{} has {} deg/s^2: the program's times were made for other accelerations (this check uses the robot's)",
                list(&stated),
                if spec.accelerations.is_some() { " (cell)" } else { " file" },
                list(&accelerations_deg)
            ));
        }
    }
    from.insert(
        "joint accelerations",
        if spec.accelerations.is_some() {
            "cell"
        } else {
            "robot file"
        },
    );
    (
        VerifyLimits {
            accelerations_deg,
            bar_mm: [to_mm(spec.bar_min), to_mm(spec.bar_max)],
            margin_mm: to_mm(spec.margin),
            joint_margin_deg: spec.joint_margin / DEG,
            blend_mm: lim.blend_mm,
            from,
        },
        notes,
    )
}

fn run_verify(a: &VerifyArgs) -> Result<i32, Error> {
    let mut spec = resolve_cell(&a.cell)?;
    let text = read_input(&a.program, "program", crate::files::Kind::Program)?;
    let dialect = program_dialect(a.dialect.as_deref(), &a.program, &text)?;
    let robot = load_robot(&a.robot, &a.cell, &spec)?;
    let axes = controller_map(&spec, a.cell.cell.as_deref(), dialect, &robot)?;
    let parsed = dialect.read(&text, &axes).map_err(|e| Error::File {
        path: a.program.display().to_string(),
        msg: format!("{} program: {e}", dialect.name),
    })?;
    if parsed.targets().next().is_none() {
        return Err(Error::File {
            path: a.program.display().to_string(),
            msg: "the program commands no motion: nothing to verify".into(),
        });
    }
    let fixture = resolve_fixture(a.fixture.as_deref(), &spec, parsed.header_value("fixture"))?;
    // The bar range, margins and blend: flag or cell, else the program header's.
    let stated = crate::verify::HeaderLimits::read(&parsed).map_err(|msg| Error::File {
        path: a.program.display().to_string(),
        msg,
    })?;
    let (limits, limit_notes) = header_limits(&mut spec, &stated, &robot);
    // MAP: flag or cell, else the program header's, else the robot file's.
    let header_map = match (spec.map, parsed.header_value("MAP")) {
        (None, Some(h)) => Some(xyz_mm(
            "program header (MAP)",
            h.split("mm").next().unwrap_or("").trim(),
        )?),
        _ => None,
    };
    let (map, _) = pipeline::resolve_map(&robot, spec.map.or(header_map));
    let cell = pipeline::make_cell(&robot, fixture, map, &spec)?;
    let model = MeasurementModel::new(&robot, fixture, map);
    let (scene, scene_report) = pipeline::build_scene(&robot, &spec, &fixture, &map)?;
    let ck = crate::safety::Checker::new(&robot, &model, &cell, &scene, spec.margin);
    if let Some(path) = &a.trace {
        return verify_trace(a, path, &ck, &robot, &parsed, dialect, &axes);
    }
    match crate::verify::check(&ck, &robot, &parsed, dialect) {
        Ok(s) => {
            let notes: Vec<String> = robot.notes.iter().chain(&limit_notes).cloned().collect();
            if a.json {
                let report = VerifyReport {
                    schema: "edbbgen.verify/1",
                    summary: &s,
                    bodies: &scene_report.bodies,
                    pairs_checked: scene_report.pairs_checked,
                    excluded_pairs: &scene_report.excluded,
                    notes: &notes,
                    limits: &limits,
                };
                println!(
                    "{}",
                    serde_json::to_string_pretty(&report).unwrap_or_default()
                );
            } else {
                for n in &notes {
                    eprintln!("edbbgen: warning: {n}");
                }
                println!(
                    "{}: ok: {} poses, {} support poses, {} moves, {} blends, {}{} s; min clearance {} mm ({} / {}); bar {}..{} mm; max cone angles {} deg (socket), {} deg (cup); {} bodies, {} pairs checked, {} excluded (--json lists them)",
                    a.program.display(),
                    s.poses,
                    s.supports,
                    s.moves,
                    s.blends,
                    if s.dwells > 0 {
                        format!("{} dwells ({} s), ", s.dwells, fmt_fixed(s.dwell_s, 1))
                    } else {
                        String::new()
                    },
                    fmt_fixed(s.duration, 1),
                    fmt_fixed(to_mm(s.min_clearance.distance), 1),
                    s.min_clearance.a,
                    s.min_clearance.b,
                    fmt_fixed(to_mm(s.extremes.min_length), 2),
                    fmt_fixed(to_mm(s.extremes.max_length), 2),
                    fmt_fixed(s.extremes.max_socket_angle / DEG, 1),
                    fmt_fixed(s.extremes.max_cup_angle / DEG, 1),
                    scene_report.bodies.len(),
                    scene_report.pairs_checked,
                    scene_report.excluded.len(),
                );
            }
            Ok(0)
        }
        Err(f) => {
            for n in &limit_notes {
                eprintln!("edbbgen: warning: {n}");
            }
            eprintln!("edbbgen: {}: {f}", a.program.display());
            Ok(1)
        }
    }
}

/// `verify --trace`: the program checked as usual, then the recorded run against it.
fn verify_trace(
    a: &VerifyArgs,
    path: &Path,
    ck: &crate::safety::Checker,
    robot: &Robot,
    parsed: &crate::dialect::Parsed,
    dialect: &crate::dialect::Dialect,
    axes: &crate::controller::ControllerMap,
) -> Result<i32, Error> {
    let text = read_input(path, "trace", crate::files::Kind::Measured)?;
    let trace = crate::verify::trace::read(&text, axes).map_err(|msg| Error::File {
        path: path.display().to_string(),
        msg,
    })?;
    let (summary, executed) = match crate::verify::rebuild(ck, robot, parsed, dialect) {
        Ok(x) => x,
        Err(f) => {
            eprintln!("edbbgen: {}: {f}", a.program.display());
            return Ok(1);
        }
    };
    match crate::verify::trace::check(ck, &executed, &trace, summary.duration) {
        Ok(r) => {
            if a.json {
                #[derive(serde::Serialize)]
                struct Out<'a> {
                    schema: &'static str,
                    program: &'a crate::verify::Summary,
                    trace: &'a crate::verify::trace::TraceReport,
                }
                let out = Out {
                    schema: "edbbgen.verify-trace/1",
                    program: &summary,
                    trace: &r,
                };
                println!("{}", serde_json::to_string_pretty(&out).unwrap_or_default());
            } else {
                let worst = r
                    .poses
                    .iter()
                    .max_by(|x, y| x.miss_mm.total_cmp(&y.miss_mm));
                println!(
                    "{}: ok: {} samples; {} measurement poses passed within {} mm at the MAP{}; executed {} s, estimated {} s; bar {}..{} mm; max cone angles {} deg (socket), {} deg (cup)",
                    path.display(),
                    r.samples,
                    r.poses.len(),
                    fmt_fixed(r.worst_miss_mm, 3),
                    worst.map_or(String::new(), |w| format!(" (worst: pose {}, line {})", w.pose, w.line)),
                    fmt_fixed(r.executed_s, 2),
                    fmt_fixed(r.estimated_s, 2),
                    fmt_fixed(to_mm(r.extremes.min_length), 2),
                    fmt_fixed(to_mm(r.extremes.max_length), 2),
                    fmt_fixed(r.extremes.max_socket_angle / DEG, 1),
                    fmt_fixed(r.extremes.max_cup_angle / DEG, 1),
                );
            }
            Ok(0)
        }
        Err(f) if f.violation.reason == crate::ir::Reason::Program => Err(Error::File {
            path: path.display().to_string(),
            msg: format!("line {}: {}", f.line, f.violation.detail),
        }),
        Err(f) => {
            eprintln!("edbbgen: {}: {f}", path.display());
            Ok(1)
        }
    }
}

// ---- model --------------------------------------------------------------------------------

fn run_model(a: &ModelArgs) -> Result<i32, Error> {
    let spec = resolve_cell(&a.cell)?;
    let fixture = resolve_fixture(a.fixture.as_deref(), &spec, None)?;
    if a.samples < 60 {
        return Err(usage("--samples: must be at least 60"));
    }
    let robot = load_robot(&a.robot, &a.cell, &spec)?;
    let (map, mut warnings) = pipeline::resolve_map(&robot, spec.map);
    // Identifiability is geometry: the shell and the floor decide which poses count, not cones.
    let cell = pipeline::make_cell(&robot, fixture, map, &spec)?;
    let model = MeasurementModel::new(&robot, fixture, map);
    let rows = pipeline::rich_rows(&robot, &model, &cell, a.samples, a.cell.seed)
        .map_err(|closest| pipeline::PipelineError::no_pose(&cell, closest))?;
    let known = model::analyse(&rows, &IdentifyOptions::default());
    let free = model::analyse(
        &rows,
        &IdentifyOptions {
            fixture_known: false,
            map_known: true,
        },
    );
    warnings.extend(pipeline::map_warnings(&model, &known));
    let ids = &known.identifiable;
    let norms: Vec<f64> = ids
        .iter()
        .map(|&j| (rows.iter().map(|r| r[j] * r[j]).sum::<f64>() / rows.len() as f64).sqrt())
        .collect();
    let jm = DMatrix::from_fn(rows.len(), ids.len(), |i, k| rows[i][ids[k]] / norms[k]);
    let obs = model::observability(&jm);
    // What this pose set would buy: one reading per pose at the bar's noise.
    let bar_noise = scalar("--bar-noise", &a.bar_noise)?;
    if bar_noise <= 0.0 {
        return Err(usage(format!(
            "--bar-noise: {bar_noise} um must be positive"
        )));
    }
    let space =
        crate::calibrate::predict::workspace(&robot, pipeline::PREDICTION_POSES, a.cell.seed);
    let predicted = crate::calibrate::predict::spread(&crate::calibrate::predict::after_readings(
        &model,
        &rows,
        ids,
        bar_noise * 1e-6,
        &space,
    ));

    let changes: Vec<serde_json::Value> = free
        .params
        .iter()
        .zip(&known.params)
        .filter(|(f, k)| f.status != k.status)
        .map(|(f, k)| serde_json::json!({"name": f.name, "fixture_known": k.status, "fixture_free": f.status}))
        .collect();
    let fixed = |id: &model::Identifiability| -> Vec<serde_json::Value> {
        id.params
            .iter()
            .filter(|p| !matches!(p.status, Status::Identifiable))
            .map(|p| serde_json::to_value(p).unwrap_or_default())
            .collect()
    };
    if a.json {
        let report = serde_json::json!({
            "schema": "edbbgen.model/1",
            "robot": robot.name,
            "robot_file": robot.source,
            "fixture_mm": fixture.map(to_mm).as_slice(),
            "map_mm": map.map(to_mm).as_slice(),
            "bar_mm": [to_mm(cell.bar_min), to_mm(cell.bar_max)],
            "poses": rows.len(),
            "seed": a.cell.seed,
            "fixture_known": {
                "identifiable_count": known.count(),
                "identifiable": known.identifiable.iter().map(|&j| model::PARAM_NAMES[j]).collect::<Vec<_>>(),
                "fixed": fixed(&known),
            },
            "fixture_free": {
                "identifiable_count": free.count(),
                "identifiable": free.identifiable.iter().map(|&j| model::PARAM_NAMES[j]).collect::<Vec<_>>(),
                "changes": changes,
            },
            "params": known.params,
            "observability": obs,
            "predicted_position_std_um": {
                "workspace_rms": predicted.rms * 1e6,
                "workspace_p95": predicted.p95 * 1e6,
                "bar_noise_um": bar_noise,
                "readings": "one per pose",
            },
            "map_on_flange_axis": model::map_offset_from_joint6_axis(&model) < model::AXIS_TOLERANCE,
            "warnings": warnings,
        });
        println!(
            "{}",
            serde_json::to_string_pretty(&report).unwrap_or_default()
        );
    } else {
        print!(
            "{}",
            model_text(&robot, &cell, &known, &free, &obs, rows.len())
        );
        println!(
            "predicted MAP position uncertainty after calibrating from these poses (one reading each, {} um bar noise): {} um RMS, {} um p95 over the joint space",
            fmt_fixed(bar_noise, 2),
            fmt_fixed(predicted.rms * 1e6, 2),
            fmt_fixed(predicted.p95 * 1e6, 2)
        );
    }
    for w in &warnings {
        eprintln!("edbbgen: warning: {w}");
    }
    Ok(0)
}

fn describe(p: &model::ParamInfo) -> String {
    match &p.status {
        Status::Dependent { on } => format!("{} (dependent on {})", p.name, on.join(", ")),
        Status::Negligible => format!("{} (negligible)", p.name),
        Status::Known => format!("{} (known)", p.name),
        Status::Identifiable => p.name.clone(),
    }
}

fn model_text(
    robot: &Robot,
    cell: &crate::ir::Cell,
    known: &model::Identifiability,
    free: &model::Identifiability,
    obs: &model::Observability,
    n: usize,
) -> String {
    let v3 = |v: &Vector3<f64>| {
        format!(
            "{}, {}, {}",
            fmt_fixed(to_mm(v.x), 1),
            fmt_fixed(to_mm(v.y), 1),
            fmt_fixed(to_mm(v.z), 1)
        )
    };
    let mut s = String::new();
    s += &format!("{} [{}]\n", robot.name, robot.source);
    s += &format!(
        "fixture {} mm (base), MAP {} mm (flange), bar {}..{} mm\n",
        v3(&cell.fixture),
        v3(&cell.map),
        fmt_fixed(to_mm(cell.bar_min), 1),
        fmt_fixed(to_mm(cell.bar_max), 1)
    );
    s += &format!("pose set: {n} random poses with the MAP in the bar shell\n\n");
    s += &format!(
        "fixture and MAP known: {} identifiable parameters\n",
        known.count()
    );
    let names = |id: &model::Identifiability| {
        id.identifiable
            .iter()
            .map(|&j| model::PARAM_NAMES[j])
            .collect::<Vec<_>>()
            .join(" ")
    };
    s += &format!("  identifiable: {}\n", names(known));
    let fixed: Vec<String> = known
        .params
        .iter()
        .filter(|p| matches!(p.status, Status::Dependent { .. } | Status::Negligible))
        .map(describe)
        .collect();
    s += &format!(
        "  fixed:        {}\n",
        if fixed.is_empty() {
            "-".into()
        } else {
            fixed.join("; ")
        }
    );
    s += "  known:        x_fix y_fix z_fix x_map y_map z_map\n\n";
    s += &format!("fixture free: {} identifiable parameters\n", free.count());
    for (f, k) in free.params.iter().zip(&known.params) {
        if f.status != k.status {
            s += &format!("  {}\n", describe(f));
        }
    }
    s += &format!(
        "\nobservability (scaled Jacobian, {n} poses): O1 {}  O2 (cond) {}  O3 {}  O4 {}\n",
        fmt_fixed(obs.o1, 4),
        fmt_fixed(obs.o2, 2),
        fmt_fixed(obs.o3, 4),
        fmt_fixed(obs.o4, 4)
    );
    s
}

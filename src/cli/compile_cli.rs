//! The compiler's command (no subcommand): flags → checked `CompileOptions` → the pipeline →
//! the program (or `--check`'s diff, `--emit`'s stage), its report and page, written together.

use super::args::CompileArgs;
use super::common::{
    bar_noise, bar_rate, check_outputs, controller_map, load_robot, program_name, read_input,
    resolve_cell, resolve_fixture, resolve_template, write_all_atomic, write_atomic,
};
use super::progress::{Bar, Timed};
use super::{usage, Error};
use crate::model;
use crate::pipeline::{self, CompileOptions};
use crate::units::{fmt_fixed, length_um, to_mm, DEG, MM};
use std::path::Path;

// ---- the compiler -------------------------------------------------------------------------

pub fn run(a: &CompileArgs) -> Result<i32, Error> {
    let started = std::time::Instant::now();
    // Required by clap; the Options only exist because subcommands negate the requirement.
    let (Some(robot_path), Some(output)) = (&a.robot, &a.output) else {
        return Err(usage("ROBOT and -o are required"));
    };
    let spec = resolve_cell(&a.cell)?;
    let fixture = resolve_fixture(a.fixture, &spec, None)?;
    let blend = a.blend;
    if !(0.0..=100.0).contains(&blend) {
        return Err(usage(format!("--blend: {blend} mm is outside 0..100 mm")));
    }
    let start = a.start.map_or([0.0; 6], |s| s.0.map(|x| x * DEG));
    if a.max_candidates < 30 {
        return Err(usage("--max-candidates: must be at least 30"));
    }
    let template = resolve_template(&a.dialect, a.template.as_deref())?;
    let dialect = crate::dialect::Template::from_source(&template)
        .map_err(|e| usage(e.to_string()))?
        .dialect;
    let program_name = program_name(output, dialect)?;
    if a.report.is_some() {
        eprintln!("edbbgen: warning: --report is now spelled --json (like every subcommand's report); --report will be removed");
    }
    let report = a.json.as_deref().or(a.report.as_deref());
    check_outputs(&[
        (!a.check).then_some(output.as_path()),
        report,
        a.html.as_deref(),
    ])?;
    let step = a.step.rad();
    let robot = load_robot(robot_path, &a.cell, &spec)?;
    controller_map(&spec, a.cell.cell.as_deref(), dialect, &robot)?;
    let (lo, hi) = robot.limits();
    let start = std::array::from_fn(|i| f64::clamp(start[i], lo[i], hi[i]));
    let bar_noise = bar_noise(a.bar_noise)?;
    let bar_rate = bar_rate(a.bar_rate)?;
    let dwell = a.dwell.map(|d| dwell(d, bar_rate)).transpose()?;
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
    warn_extension(output, dialect);
    if let Some(stage) = &a.emit {
        println!("{}", emit_stage(&out, stage));
    }
    if let Some(r) = report {
        write_atomic(
            r,
            &(serde_json::to_string_pretty(&out.report).unwrap_or_default() + "\n"),
        )?;
    }

    if a.check {
        return Ok(golden_check(output, &out.text));
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
        summary(a.cell.quiet, output, &out);
    }
    Ok(0)
}

/// `--check`: the compiled program against the file on disk; 0 when equal, else 1 with a
/// unified diff on stdout.
fn golden_check(output: &Path, text: &str) -> i32 {
    let old = std::fs::read_to_string(output).unwrap_or_default();
    if old == text {
        eprintln!("edbbgen: {} is up to date", output.display());
        return 0;
    }
    if !output.exists() {
        eprintln!("edbbgen: {} does not exist", output.display());
    }
    let name = output.display().to_string();
    let diff = similar::TextDiff::from_lines(old.as_str(), text);
    print!(
        "{}",
        diff.unified_diff()
            .context_radius(3)
            .header(&format!("{name} (on disk)"), &format!("{name} (compiled)"))
    );
    1
}

/// The summary lines: the program, its timing, what `verify` found and what it buys.
fn summary(quiet: bool, output: &Path, out: &pipeline::Compiled) {
    let h = &out.program.header;
    let v = &out.verified;
    say!(
        quiet,
        "{}: {} poses + {} support ({} identifiable parameters, cond {}), estimated {} s as programmed (support poses and blends included); ordering: {} s in tour order, {} s unsorted (the measurement poses alone, direct moves); verified: min clearance {} mm ({} / {}), bar {}..{} mm; predicted MAP position uncertainty after calibration {} RMS over the joint space ({} bar noise at {} Hz)",
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
        length_um(h.predicted_std_um),
        length_um(h.bar_noise_um),
        fmt_fixed(h.bar_rate_hz, 0),
    );
    if h.dwell_s > 0.0 {
        say!(
            quiet,
            "stop-and-measure: exact stop and {} s dwell at each of the {} measurement poses; predicted {} RMS over the joint space from the plateau means ({} samples each), {} from the same run recorded with a synchronous joint log",
            fmt_fixed(h.dwell_s, 2),
            h.measure_mm.len(),
            length_um(h.predicted_std_um),
            h.plateau_samples,
            length_um(h.predicted_continuous_std_um)
        );
    }
}

/// A program whose extension is not its dialect's is read back only with `--dialect`: say so.
fn warn_extension(output: &Path, dialect: &crate::dialect::Dialect) {
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
}

/// `--dwell S`: on the 0.01 s grid every dialect prints exactly (FANUC's WAIT resolves 0.01 s),
/// long enough for a plateau at the bar's rate.
fn dwell(d: f64, bar_rate: f64) -> Result<f64, Error> {
    let d = (d * 100.0).round() / 100.0;
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
    Ok(d)
}

/// `--focus`: a calibration report (its drift's moved parameters, then the joint zeros) or a
/// comma-separated list of parameter names (not the fixture's).
pub(super) fn parse_focus(s: &str) -> Result<Vec<usize>, Error> {
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

pub(super) fn emit_stage(c: &pipeline::Compiled, stage: &str) -> String {
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

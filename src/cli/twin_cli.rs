//! `simulate`, `diagnose` and `circle`: flags → checked options → twin/diagnose stages → files.

use super::args::{CircleArgs, DiagnoseArgs, Range, SimulateArgs, Xyz};
use super::common::{
    check_outputs, controller_map, file_err, header_xyz, program_dialect, read_input,
    write_all_atomic, write_atomic,
};
use super::{logruns, usage, Error};
use crate::model::{MeasurementModel, N_PARAMS};
use crate::robot::{self, Robot};
use crate::twin::{self, SimOptions, Truth};
use crate::units::{fmt_fixed, MM};
use nalgebra::Vector3;
use std::path::Path;

fn read(path: &Path, what: &str, kind: crate::files::Kind) -> Result<String, Error> {
    read_input(path, what, kind)
}

fn load(path: &Path) -> Result<Robot, Error> {
    Ok(robot::load(path, &Default::default())?)
}

fn tool_or_robot(flag: Option<Xyz>, robot: &Robot) -> Vector3<f64> {
    match flag {
        Some(s) => s.m(),
        None => robot.tool.unwrap_or_else(Vector3::zeros),
    }
}

pub fn simulate(a: &SimulateArgs) -> Result<i32, Error> {
    let (flag, rate) = match a.rate {
        Some(r) => {
            eprintln!("edbbgen: warning: --rate is now spelled --bar-rate (like the compiler's); --rate will be removed");
            ("--rate", r)
        }
        None => ("--bar-rate", a.bar_rate),
    };
    if !(1.0..=10_000.0).contains(&rate) {
        return Err(usage(format!("{flag}: {rate} Hz is outside 1..10000 Hz")));
    }
    let text = read(&a.program, "program", crate::files::Kind::Program)?;
    let spec = match &a.cell {
        Some(p) => crate::cell::load(p)?,
        None => Default::default(),
    };
    // The twin's robot moves at the cell's joint speeds and accelerations where it states them
    // (as compile and verify take them).
    let mut robot = robot::load(
        &a.robot,
        &robot::LoadOptions {
            speeds: spec.speeds,
            accelerations: spec.accelerations,
            ..Default::default()
        },
    )?;
    let dialect = program_dialect(a.dialect.as_deref(), &a.program, &text)?;
    let axes = controller_map(&spec, a.cell.as_deref(), dialect, &robot)?;
    let parsed = dialect
        .read(&text, &axes)
        .map_err(|e| file_err(&a.program, format!("{} program: {e}", dialect.name)))?;
    // Without a cell that states them, the controller's accelerations are the ones the program
    // header states its times with (the robot file's are often a default): the twin then runs
    // the program in the times it states.
    if spec.accelerations.is_none() {
        let stated = crate::verify::HeaderLimits::read(&parsed)
            .map_err(|e| file_err(&a.program, e))?
            .accelerations_deg;
        if let Some((acc, _)) = stated {
            for (j, v) in robot.joints.iter_mut().zip(acc) {
                j.max_acceleration = v * crate::units::DEG;
            }
        }
    }
    let truth_text = read(&a.truth, "truth", crate::files::Kind::Config)?;
    let truth = Truth::from_toml(&truth_text).map_err(|e| file_err(&a.truth, e))?;
    let fixture = match &a.fixture {
        Some(s) => s.m(),
        None => parsed
            .header_value("fixture")
            .and_then(header_xyz)
            .ok_or_else(|| {
                usage("--fixture: not given and the program header has no (fixture: X, Y, Z mm)")
            })?,
    };
    let map = match (&a.tool, parsed.header_value("MAP").and_then(header_xyz)) {
        (Some(s), _) => s.m(),
        (None, Some(m)) => m,
        (None, None) => tool_or_robot(None, &robot),
    };
    let model = MeasurementModel::new(&robot, fixture, map);
    if let Some(bar_path) = &a.bar_log {
        let lopts = log_options(a, rate, &parsed)?;
        check_outputs(&[
            Some(a.output.as_path()),
            Some(bar_path.as_path()),
            a.joint_log.as_deref(),
        ])?;
        let traj = twin::Trajectory::from_program(&robot, &model, &parsed)
            .map_err(|e| file_err(&a.program, e))?;
        let logs = twin::logsim::simulate_logs(&robot, &model, &traj, &truth, &lopts)
            .map_err(|e| file_err(&a.program, e))?;
        let sync = logs.synchronous.to_csv();
        let bar = logs.bar.to_csv();
        let joints = a.joint_log.as_ref().map(|_| {
            // The controller logs its own axis values (the mapping applied), in degrees.
            let mut j = logs.joints.clone();
            for q in j.q.iter_mut() {
                *q = axes.log_axes(q);
            }
            j.to_csv()
        });
        let mut files: Vec<(&Path, &str)> = vec![
            (a.output.as_path(), sync.as_str()),
            (bar_path.as_path(), bar.as_str()),
        ];
        if let (Some(p), Some(j)) = (&a.joint_log, &joints) {
            files.push((p.as_path(), j.as_str()));
        }
        write_all_atomic(&files)?;
        say!(
            a.quiet,
            "{}: {} rows on the bar's clock ({} Hz, offset {} s, drift {} ppm), {} plateaus lost or cut, {} controller stops; {}: the {} mounted samples with the true joints{}",
            bar_path.display(),
            logs.bar.len(),
            fmt_fixed(lopts.bar_rate, 0),
            fmt_fixed(lopts.offset, 3),
            fmt_fixed(lopts.drift * 1e6, 1),
            logs.truth.intact.iter().filter(|p| !**p).count(),
            logs.truth.holds.len(),
            a.output.display(),
            logs.synchronous.len(),
            match &a.joint_log {
                Some(p) => format!(
                    "; {}: {} rows at {} Hz",
                    p.display(),
                    logs.joints.len(),
                    fmt_fixed(lopts.joint_rate, 0)
                ),
                None => String::new(),
            }
        );
        return Ok(0);
    }
    let opts = SimOptions { rate, seed: a.seed };
    let m = twin::simulate(&robot, &model, &parsed, &truth, &opts)
        .map_err(|e| file_err(&a.program, e))?;
    write_atomic(&a.output, &m.to_csv())?;
    say!(
        a.quiet,
        "{}: {} rows over {:.1} s at {rate} Hz",
        a.output.display(),
        m.len(),
        m.t.last().copied().unwrap_or(0.0)
    );
    Ok(0)
}

/// `simulate`'s log flags, checked.
fn log_options(
    a: &SimulateArgs,
    rate: f64,
    parsed: &crate::dialect::Parsed,
) -> Result<twin::logsim::LogOptions, Error> {
    let joint_rate = a.joint_rate;
    if !(1.0..=10_000.0).contains(&joint_rate) {
        return Err(usage(format!(
            "--joint-rate: {joint_rate} Hz is outside 1..10000 Hz"
        )));
    }
    let drift = a.clock_drift;
    if drift.abs() > 10_000.0 {
        return Err(usage(format!(
            "--clock-drift: {drift} ppm is beyond the ±10000 ppm of any clock"
        )));
    }
    let Range(p0, p1) = a.pause;
    if p0 < 0.0 {
        return Err(usage(format!("--pause: {p0}..{p1} needs 0 <= MIN <= MAX")));
    }
    let move_scale = a.move_scale;
    if !(0.2..=5.0).contains(&move_scale) {
        return Err(usage(format!(
            "--move-scale: {move_scale} is outside 0.2..5"
        )));
    }
    let dropout = a.dropout;
    if !(0.0..1.0).contains(&dropout) {
        return Err(usage(format!(
            "--dropout: {dropout} is not a probability below 1"
        )));
    }
    let poses = |flag: &str, v: &Option<String>| -> Result<Vec<usize>, Error> {
        match v {
            None => Ok(Vec::new()),
            Some(s) => s
                .split(',')
                .map(|x| match x.trim().parse::<usize>() {
                    Ok(k) if k >= 1 => Ok(k),
                    _ => Err(usage(format!(
                        "{flag}: '{s}' is not a list of pose numbers (1-based)"
                    ))),
                })
                .collect(),
        }
    };
    // A handled bar takes the lengths of the bar's range (the program header's, if it says).
    let bar_range = parsed
        .header_value("bar range")
        .and_then(|v| {
            let r = v.split(' ').next()?.trim_end_matches(';');
            let (x, y) = r.split_once("..")?;
            Some((x.parse::<f64>().ok()? * MM, y.parse::<f64>().ok()? * MM))
        })
        .unwrap_or((0.300, 0.520));
    Ok(twin::logsim::LogOptions {
        bar_rate: rate,
        joint_rate,
        offset: a.clock_offset,
        drift: drift * 1e-6,
        pause: (p0, p1),
        zero: a.bar_zero * MM,
        gaps: a.gaps,
        dropout,
        missing: poses("--missing", &a.missing)?,
        holds: a.holds,
        move_scale,
        vibration: poses("--vibration", &a.vibration)?,
        handling: !a.no_handling,
        bar_range,
        seed: a.seed,
        ..Default::default()
    })
}

pub fn diagnose(a: &DiagnoseArgs) -> Result<i32, Error> {
    let flag_fixture = a.fixture.map(|f| f.m());
    if a.bar_log.is_some() && a.program.is_none() && a.joint_log.is_none() {
        return Err(usage(
            "--bar-log: needs --program (the stop-and-measure program it recorded) or --joint-log",
        ));
    }
    check_outputs(&[a.json.as_deref(), a.plot.as_deref(), a.html.as_deref()])?;
    let robot = load(&a.robot)?;
    let program = match &a.program {
        Some(p) => Some(logruns::read_program(&robot, p)?),
        None => None,
    };
    // The MAP: the flag, else the program header's, else the robot file's.
    let map = match (
        &a.tool,
        program.as_ref().and_then(|p| p.parsed.header_value("MAP")),
    ) {
        (Some(s), _) => s.m(),
        (None, Some(h)) => header_xyz(h)
            .ok_or_else(|| usage("the program header's MAP is not X, Y, Z mm: give --tool"))?,
        (None, None) => tool_or_robot(None, &robot),
    };
    let (m, fixture, text_hash, source, extra, lines) = match (&a.measured, &a.bar_log) {
        (Some(path), _) => {
            let fixture =
                flag_fixture.ok_or_else(|| usage("--fixture: required with --measured"))?;
            let text = read(path, "measured data", crate::files::Kind::Measured)?;
            let m = twin::parse_csv(&text, N_PARAMS + 2).map_err(|e| file_err(path, e))?;
            (
                m,
                fixture,
                robot::sha256_hex(text.as_bytes()),
                path.clone(),
                None,
                Vec::new(),
            )
        }
        (None, Some(bar)) => {
            let run = logruns::read_run(
                &robot,
                bar,
                program.as_ref(),
                a.joint_log.as_deref(),
                flag_fixture,
                map,
            )?;
            let (fixture, sha256) = (run.fixture, run.sha256.clone());
            let files = logruns::RunFiles {
                bar,
                program: a.program.as_deref(),
                joint_log: a.joint_log.as_deref(),
            };
            let (measured, extra, summary) = logruns::on_own_geometry(&robot, run, map, &files)?;
            (measured, fixture, sha256, bar.clone(), Some(extra), summary)
        }
        (None, None) => return Err(usage("--measured or --bar-log: one is required")),
    };
    if m.len() < N_PARAMS + 2 {
        return Err(file_err(
            &source,
            format!(
                "{} readings, fewer than the {} the fit needs",
                m.len(),
                N_PARAMS + 2
            ),
        ));
    }
    let model = MeasurementModel::new(&robot, fixture, map);
    let (lower, upper) = robot.limits();
    let opts = crate::diagnose::DiagnoseOptions {
        masses: robot.masses.clone(),
        joint_ranges: Some(std::array::from_fn(|j| (lower[j], upper[j]))),
        noise: a.noise.map(|u| u * 1e-6),
        ..Default::default()
    };
    let d = crate::diagnose::run(&model, &m, &opts).map_err(|e| file_err(&source, e))?;
    // Everything is rendered before the first file is written: a failure leaves no file.
    let mut report = serde_json::to_value(&d.report).unwrap_or_default();
    if let (Some(extra), Some(obj)) = (&extra, report.as_object_mut()) {
        obj.insert(
            "run".into(),
            serde_json::to_value(extra).unwrap_or_default(),
        );
    }
    let json = serde_json::to_string_pretty(&report).unwrap_or_default() + "\n";
    let svg = match &a.plot {
        Some(_) => Some(crate::diagnose::plot::svg(&d)?),
        None => None,
    };
    let html = match &a.html {
        Some(_) => {
            let hash = robot::sha256_hex(
                format!(
                    "{}\n{}\n{:?}\n{:?}\n",
                    robot.digest,
                    text_hash,
                    fixture.as_slice(),
                    map.as_slice()
                )
                .as_bytes(),
            );
            let name = format!("{} [{}]", robot.name, robot.source);
            let page = crate::report::diagnose::page(&m, &d, &name, &hash)?;
            Some(crate::report::render(&page)?)
        }
        None => None,
    };
    if let Some(p) = &a.json {
        write_atomic(p, &json)?;
    }
    if let (Some(p), Some(svg)) = (&a.plot, &svg) {
        write_atomic(p, svg)?;
    }
    if let (Some(p), Some(html)) = (&a.html, &html) {
        write_atomic(p, html)?;
    }
    for l in &lines {
        say!(a.quiet, "{l}");
    }
    say_raw!(a.quiet, "{}", d.summary);
    Ok(0)
}

pub fn circle(a: &CircleArgs) -> Result<i32, Error> {
    let fixture = a.fixture.m();
    let (diameter, speed) = (a.diameter, a.speed);
    if !(diameter > 0.0 && speed > 0.0) {
        return Err(usage("--diameter and --speed must be positive"));
    }
    let robot = load(&a.robot)?;
    let map = tool_or_robot(a.tool, &robot);
    let model = MeasurementModel::new(&robot, fixture, map);
    let opts = twin::circle::CircleOptions {
        diameter: diameter * MM,
        speed: speed * MM,
        ..Default::default()
    };
    let text = twin::circle::program(&robot, &model, &opts).map_err(|e| usage(e.to_string()))?;
    write_atomic(&a.output, &text)?;
    say!(
        a.quiet,
        "{}: circle test, {} moves",
        a.output.display(),
        text.matches("\nG1 ").count()
    );
    Ok(0)
}

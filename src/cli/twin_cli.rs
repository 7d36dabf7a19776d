//! `simulate`, `diagnose` and `circle`: flags → checked options → twin/diagnose stages → files.

use super::args::{CircleArgs, DiagnoseArgs, SimulateArgs};
use super::{scalar, usage, write_atomic, xyz_mm, Error};
use crate::model::{MeasurementModel, N_PARAMS};
use crate::robot::{self, Robot};
use crate::twin::{self, SimOptions, Truth};
use crate::units::MM;
use nalgebra::Vector3;
use std::path::Path;

fn read(path: &Path, what: &str, kind: crate::files::Kind) -> Result<String, Error> {
    super::read_input(path, what, kind)
}

fn file_err(path: &Path, msg: impl std::fmt::Display) -> Error {
    Error::File {
        path: path.display().to_string(),
        msg: msg.to_string(),
    }
}

fn load(path: &Path) -> Result<Robot, Error> {
    Ok(robot::load(path, &Default::default())?)
}

/// The first three numbers of a header value such as "258.000, 1468.000, 708.000 mm ...".
fn header_xyz(v: &str) -> Option<Vector3<f64>> {
    let nums: Vec<f64> = v
        .split([',', ' '])
        .filter_map(|w| w.trim().parse::<f64>().ok())
        .take(3)
        .collect();
    (nums.len() == 3).then(|| Vector3::new(nums[0], nums[1], nums[2]) * MM)
}

fn tool_or_robot(flag: Option<&str>, robot: &Robot) -> Result<Vector3<f64>, Error> {
    match flag {
        Some(s) => xyz_mm("--tool", s),
        None => Ok(robot.tool.unwrap_or_else(Vector3::zeros)),
    }
}

pub fn simulate(a: &SimulateArgs) -> Result<i32, Error> {
    let rate = scalar("--rate", &a.rate)?;
    if !(1.0..=10_000.0).contains(&rate) {
        return Err(usage(format!("--rate: {rate} Hz is outside 1..10000 Hz")));
    }
    let robot = load(&a.robot)?;
    let text = read(&a.program, "program", crate::files::Kind::Program)?;
    let spec = match &a.cell {
        Some(p) => crate::cell::load(p)?,
        None => Default::default(),
    };
    let dialect = super::program_dialect(a.dialect.as_deref(), &a.program, &text)?;
    let axes = super::controller_map(&spec, a.cell.as_deref(), dialect, &robot)?;
    let parsed = dialect
        .read(&text, &axes)
        .map_err(|e| file_err(&a.program, format!("{} program: {e}", dialect.name)))?;
    let truth_text = read(&a.truth, "truth", crate::files::Kind::Config)?;
    let truth = Truth::from_toml(&truth_text).map_err(|e| file_err(&a.truth, e))?;
    let fixture = match &a.fixture {
        Some(s) => xyz_mm("--fixture", s)?,
        None => parsed
            .header_value("fixture")
            .and_then(header_xyz)
            .ok_or_else(|| {
                usage("--fixture: not given and the program header has no (fixture: X, Y, Z mm)")
            })?,
    };
    let map = match (&a.tool, parsed.header_value("MAP").and_then(header_xyz)) {
        (Some(s), _) => xyz_mm("--tool", s)?,
        (None, Some(m)) => m,
        (None, None) => tool_or_robot(None, &robot)?,
    };
    let model = MeasurementModel::new(&robot, fixture, map);
    let opts = SimOptions { rate, seed: a.seed };
    let m = twin::simulate(&robot, &model, &parsed, &truth, &opts)
        .map_err(|e| file_err(&a.program, e))?;
    write_atomic(&a.output, &m.to_csv())?;
    println!(
        "{}: {} rows over {:.1} s at {rate} Hz",
        a.output.display(),
        m.len(),
        m.t.last().copied().unwrap_or(0.0)
    );
    Ok(0)
}

pub fn diagnose(a: &DiagnoseArgs) -> Result<i32, Error> {
    let fixture = xyz_mm("--fixture", &a.fixture)?;
    let robot = load(&a.robot)?;
    let map = tool_or_robot(a.tool.as_deref(), &robot)?;
    let text = read(&a.measured, "measured data", crate::files::Kind::Measured)?;
    let m = twin::parse_csv(&text, N_PARAMS + 2).map_err(|e| file_err(&a.measured, e))?;
    let model = MeasurementModel::new(&robot, fixture, map);
    let opts = crate::diagnose::DiagnoseOptions {
        masses: robot.masses.clone(),
        ..Default::default()
    };
    let d = crate::diagnose::run(&model, &m, &opts).map_err(|e| file_err(&a.measured, e))?;
    // Everything is rendered before the first file is written: a failure leaves no file.
    let json = serde_json::to_string_pretty(&d.report).unwrap_or_default() + "\n";
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
                    robot::sha256_hex(text.as_bytes()),
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
    print!("{}", d.summary);
    Ok(0)
}

pub fn circle(a: &CircleArgs) -> Result<i32, Error> {
    let fixture = xyz_mm("--fixture", &a.fixture)?;
    let diameter = scalar("--diameter", &a.diameter)?;
    let speed = scalar("--speed", &a.speed)?;
    if !(diameter > 0.0 && speed > 0.0) {
        return Err(usage("--diameter and --speed must be positive"));
    }
    let robot = load(&a.robot)?;
    let map = tool_or_robot(a.tool.as_deref(), &robot)?;
    let model = MeasurementModel::new(&robot, fixture, map);
    let opts = twin::circle::CircleOptions {
        diameter: diameter * MM,
        speed: speed * MM,
        ..Default::default()
    };
    let text = twin::circle::program(&robot, &model, &opts).map_err(|e| usage(e.to_string()))?;
    write_atomic(&a.output, &text)?;
    println!(
        "{}: circle test, {} moves",
        a.output.display(),
        text.matches("\nG1 ").count()
    );
    Ok(0)
}

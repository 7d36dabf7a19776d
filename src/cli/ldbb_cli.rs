//! `ldbb`, `ldbb-circle` and `simulate-ldbb`: flags → checked options → the LDBB stages
//! ([`crate::ldbb`]) → files (temp + rename), kept apart from `cli/mod.rs` so the subcommands
//! merge cleanly with others.

use super::args::{LdbbArgs, LdbbCircleArgs, SimulateLdbbArgs};
use super::common::{
    check_outputs, controller_map, program_name, read_input, resolve_template, set_margins,
    write_atomic,
};
use super::{usage, Error};
use crate::files::Kind;
use crate::ldbb::setup::Setup;
use crate::ldbb::{self, data, program, sim};
use crate::robot::{self, Robot};
use crate::units::{fmt_fixed, length_um, DEG, MM};
use std::path::{Path, PathBuf};

fn read(path: &Path, what: &str, kind: Kind) -> Result<String, Error> {
    read_input(path, what, kind)
}

fn file_err(path: &Path, msg: impl std::fmt::Display) -> Error {
    Error::File {
        path: path.display().to_string(),
        msg: msg.to_string(),
    }
}

fn load_setup(path: &Path) -> Result<(Setup, String), Error> {
    let text = read(path, "setup", Kind::Config)?;
    let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
    let setup = Setup::from_toml(&text, &dir).map_err(|e| file_err(path, e))?;
    Ok((setup, text))
}

/// The robot of the setup or the flag, with the setup's base and end links (URDF only).
fn load_robot(
    flag: Option<&Path>,
    setup: &Setup,
    setup_path: &Path,
    package_paths: &[PathBuf],
) -> Result<Option<Robot>, Error> {
    let Some(path) = flag.map(Path::to_path_buf).or_else(|| setup.robot.clone()) else {
        return Ok(None);
    };
    let urdf = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("urdf") || e.eq_ignore_ascii_case("xml"));
    if !urdf && (setup.base_link.is_some() || setup.end_link.is_some()) {
        return Err(file_err(
            setup_path,
            format!(
                "base_link/end_link: given, but {} is not a URDF (they name URDF links)",
                path.display()
            ),
        ));
    }
    let opts = robot::LoadOptions {
        flange_link: setup.end_link.clone(),
        base_link: setup.base_link.clone(),
        package_paths: package_paths.to_vec(),
        ..Default::default()
    };
    Ok(Some(robot::load(&path, &opts)?))
}

/// The setup as it enters an inputs hash: its text without the `robot` path, whose file enters
/// through the robot's content digest. A program's hash then names what was computed, not
/// where the checkout lies.
fn setup_identity(text: &str) -> String {
    match text.parse::<toml_edit::DocumentMut>() {
        Ok(mut doc) => {
            doc.remove("robot");
            doc.to_string()
        }
        Err(_) => text.to_string(),
    }
}

fn hash(parts: &[&[u8]]) -> String {
    let mut all = Vec::new();
    for p in parts {
        all.extend_from_slice(robot::sha256_hex(p).as_bytes());
        all.push(b'\n');
    }
    robot::sha256_hex(&all)
}

pub fn ldbb(a: &LdbbArgs) -> Result<i32, Error> {
    let step = a.grid_step;
    let opts = ldbb::Options {
        grid_step: step * DEG,
        sine: match a.sine.as_str() {
            "nonlinear" => ldbb::SineModel::Nonlinear,
            _ => ldbb::SineModel::Linear,
        },
        start: match a.sine_start.as_str() {
            "paper" => ldbb::SineStart::Paper,
            _ => ldbb::SineStart::Linear,
        },
    };
    let (setup, setup_text) = load_setup(&a.setup)?;
    let text = read(&a.loaded, "loaded circle data", Kind::Measured)?;
    let loaded = data::parse_loaded(&text).map_err(|e| file_err(&a.loaded, e))?;
    let (reference, ref_text) = match &a.reference {
        Some(p) => {
            let t = read(p, "reference", Kind::Measured)?;
            (
                Some(data::parse_reference(&t).map_err(|e| file_err(p, e))?),
                t,
            )
        }
        None => (None, String::new()),
    };
    let robot = load_robot(a.robot.as_deref(), &setup, &a.setup, &a.package_path)?;
    if robot.is_some() {
        setup.tool().map_err(|e| file_err(&a.setup, e))?;
    }
    let analysis = ldbb::run(&loaded, &setup, robot.as_ref(), reference.as_ref(), &opts).map_err(
        |e| match e {
            ldbb::LdbbError::Options(m) if m.starts_with("--") => usage(m),
            ldbb::LdbbError::Options(m) if m.starts_with("reference") => match &a.reference {
                Some(p) => file_err(p, m),
                None => usage(m),
            },
            ldbb::LdbbError::Robot(m) => file_err(&a.setup, m),
            e => file_err(&a.loaded, e),
        },
    )?;
    // Everything is rendered before the first file is written: a failure leaves no file.
    let json = serde_json::to_string_pretty(&analysis.report).unwrap_or_default() + "\n";
    let svg = match &a.plot {
        Some(_) => Some(ldbb::plot::svg(&analysis)?),
        None => None,
    };
    let html = match &a.html {
        Some(_) => {
            let digest = robot.as_ref().map_or(String::new(), |r| r.digest.clone());
            let h = hash(&[
                text.as_bytes(),
                setup_identity(&setup_text).as_bytes(),
                ref_text.as_bytes(),
                digest.as_bytes(),
                format!("{opts:?}").as_bytes(),
            ]);
            let name = |p: &Path| {
                p.file_name()
                    .map(|f| f.to_string_lossy().into_owned())
                    .unwrap_or_default()
            };
            let mut source = format!("{} with {}", name(&a.loaded), name(&a.setup));
            if let Some(r) = &robot {
                source += &format!(", robot {} [{}]", r.name, r.source);
            }
            if let Some(p) = &a.reference {
                source += &format!(", reference {}", name(p));
            }
            let page = crate::report::ldbb::page(&analysis, &source, &h)?;
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
    for w in &analysis.warnings {
        eprintln!("edbbgen: warning: {w}");
    }
    say_raw!(a.quiet, "{}", ldbb::summary(&analysis));
    Ok(0)
}

pub fn circle(a: &LdbbCircleArgs) -> Result<i32, Error> {
    let positive = |flag: &str, x: f64, max: f64| -> Result<f64, Error> {
        if !(x > 0.0 && x <= max) {
            return Err(usage(format!("{flag}: {x} must be in (0, {max}]")));
        }
        Ok(x)
    };
    let mut opts = program::ProgramOptions {
        step: positive("--step", a.step, 10.0)? * DEG,
        blend: positive("--blend", a.blend, 50.0)? * MM,
        stroke: positive("--stroke", a.stroke, 50.0)? * MM,
        program_name: String::new(),
    };
    let template = resolve_template(&a.dialect, a.template.as_deref())?;
    let dialect = crate::dialect::Template::from_source(&template)
        .map_err(|e| usage(e.to_string()))?
        .dialect;
    opts.program_name = program_name(&a.output, dialect)?;
    check_outputs(&[Some(a.output.as_path())])?;
    let (setup, setup_text) = load_setup(&a.setup)?;
    setup.tool().map_err(|e| file_err(&a.setup, e))?;
    // The cell is read once: its text enters the inputs hash, its parse the program's cell.
    let cell_text = match &a.cell {
        Some(p) => read(p, "cell", Kind::Config)?,
        None => String::new(),
    };
    let base = match &a.cell {
        Some(p) => Some(crate::cell::from_str(&cell_text, p)?),
        None => None,
    };
    let mut spec = program::cell(&setup, base, &opts).map_err(|e| file_err(&a.setup, e))?;
    set_margins(&mut spec, a.margin, a.joint_margin)?;
    let robot = load_robot(Some(&a.robot), &setup, &a.setup, &a.package_path)?
        .ok_or_else(|| usage("ROBOT: required"))?;
    // A mapping the cell's [controller] cannot give is the cell's error, named as such.
    controller_map(&spec, a.cell.as_deref(), dialect, &robot)?;
    let h = hash(&[
        robot.digest.as_bytes(),
        setup_identity(&setup_text).as_bytes(),
        cell_text.as_bytes(),
        format!("{opts:?} {:?} {:?}", spec.margin, spec.joint_margin).as_bytes(),
        template.as_bytes(),
    ]);
    let out = match program::compile(&robot, &setup, &spec, &opts, &template, &h) {
        Ok(out) => out,
        Err(program::ProgramError::Unsafe(m)) => {
            eprintln!("edbbgen: {m}");
            return Ok(1);
        }
        Err(program::ProgramError::Template(m)) => {
            return Err(match &a.template {
                Some(p) => file_err(p, m),
                None => usage(format!("--dialect {}: {m}", a.dialect)),
            })
        }
        Err(program::ProgramError::Input(m)) => return Err(file_err(&a.setup, m)),
    };
    write_atomic(&a.output, &out.text)?;
    let v = &out.verified;
    say!(
        a.quiet,
        "{}: LDBB loaded circle test, {} loads x {} circles, {} moves, {} s of motion; verified: min clearance {} mm ({} / {}), bar {}..{} mm, path within {} of the circle",
        a.output.display(),
        setup.loads.len(),
        setup.repeats,
        v.moves,
        fmt_fixed(v.duration, 1),
        fmt_fixed(v.min_clearance.distance / MM, 1),
        v.min_clearance.a,
        v.min_clearance.b,
        fmt_fixed(v.extremes.min_length / MM, 3),
        fmt_fixed(v.extremes.max_length / MM, 3),
        length_um(out.path_deviation * 1e6),
    );
    Ok(0)
}

pub fn simulate(a: &SimulateLdbbArgs) -> Result<i32, Error> {
    let (setup, _) = load_setup(&a.setup)?;
    setup.tool().map_err(|e| file_err(&a.setup, e))?;
    let truth_text = read(&a.truth, "truth", Kind::Config)?;
    let truth = sim::Truth::from_toml(&truth_text).map_err(|e| file_err(&a.truth, e))?;
    let robot = load_robot(a.robot.as_deref(), &setup, &a.setup, &a.package_path)?
        .ok_or_else(|| usage("--robot: required (or give robot = \"...\" in the setup)"))?;
    let s = sim::simulate(&robot, &setup, &truth, a.seed).map_err(|e| file_err(&a.setup, e))?;
    let csv = s.loaded.to_csv();
    let lt = a.reference.as_ref().map(|_| s.reference.to_csv());
    write_atomic(&a.output, &csv)?;
    if let (Some(p), Some(lt)) = (&a.reference, &lt) {
        write_atomic(p, lt)?;
    }
    say!(
        a.quiet,
        "{}: {} rows, {} loads x {} circles of {} samples",
        a.output.display(),
        s.loaded.samples.len(),
        setup.loads.len(),
        setup.repeats,
        setup.circle.samples_per_circle
    );
    Ok(0)
}

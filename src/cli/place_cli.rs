//! `place`: flags → checked placement options → the placement stage → the ranking on stdout,
//! the JSON report, the HTML page and the winners' cell files, all written together or not at
//! all.

use super::args::{PlaceArgs, Prior};
use super::common::{
    bar_noise, bar_rate, load_robot, numbers, read_input, resolve_cell, write_all_atomic,
};
use super::progress::Bar;
use super::{usage, Error};
use crate::cell::CellSpec;
use crate::pipeline;
use crate::place::{self, cellfile, PlaceOptions, Region};
use crate::units::{fmt_fixed, to_mm, DEG, MM};
use nalgebra::Vector3;
use std::path::{Path, PathBuf};

/// `--region X0..X1,Y0..Y1,Z0..Z1` (mm).
fn region(s: &str) -> Result<Region, Error> {
    let bad = || {
        usage(format!(
            "--region: '{s}' is not X0..X1,Y0..Y1,Z0..Z1 (mm, each lower end at most the upper)"
        ))
    };
    let parts: Vec<&str> = s.split(',').collect();
    if parts.len() != 3 {
        return Err(bad());
    }
    let mut lo = Vector3::zeros();
    let mut hi = Vector3::zeros();
    for (k, p) in parts.iter().enumerate() {
        let (a, b) = p.split_once("..").ok_or_else(bad)?;
        let (a, b) = (
            a.trim().parse::<f64>().map_err(|_| bad())?,
            b.trim().parse::<f64>().map_err(|_| bad())?,
        );
        if !(a.is_finite() && b.is_finite() && a <= b) {
            return Err(bad());
        }
        lo[k] = a * MM;
        hi[k] = b * MM;
    }
    Ok(Region { lo, hi })
}

fn grid(s: &str) -> Result<[usize; 3], Error> {
    let v = numbers("--grid", s, Some(3))?;
    if v.iter()
        .any(|&n| n.fract() != 0.0 || !(1.0..=100.0).contains(&n))
    {
        return Err(usage(format!(
            "--grid: '{s}': each count must be a whole number from 1 to 100"
        )));
    }
    Ok([v[0] as usize, v[1] as usize, v[2] as usize])
}

/// Where the winners' cell files go: `DIR/place-K.cell.toml` for a directory, else
/// `PREFIX-K.cell.toml`.
fn cell_paths(target: &Path, k: usize) -> Vec<PathBuf> {
    (1..=k)
        .map(|i| {
            if target.is_dir() {
                target.join(format!("place-{i}.cell.toml"))
            } else {
                let mut s = target.as_os_str().to_owned();
                s.push(format!("-{i}.cell.toml"));
                PathBuf::from(s)
            }
        })
        .collect()
}

/// What the written cell must carry besides the fixture so that a compile with it alone is
/// the compile that was estimated: every flag given, and an assumed stand.
fn settings(
    a: &PlaceArgs,
    spec: &CellSpec,
    stand_changed: bool,
) -> Vec<(&'static str, &'static str, cellfile::Setting)> {
    use cellfile::Setting::{Number, Triple};
    let c = &a.cell;
    let mm = |v: f64| (to_mm(v) * 1e6).round() / 1e6;
    let mut out = Vec::new();
    if stand_changed {
        out.push(("fixture", "stand_radius", Number(mm(spec.stand_radius))));
    }
    if let (Some(_), Some(m)) = (&c.tool, spec.map) {
        out.push(("tool", "map", Triple([mm(m.x), mm(m.y), mm(m.z)])));
    }
    if c.bar.is_some() {
        out.push(("bar", "min", Number(mm(spec.bar_min))));
        out.push(("bar", "max", Number(mm(spec.bar_max))));
    }
    if c.ball.is_some() {
        out.push(("bar", "ball", Number(mm(spec.ball))));
    }
    if c.floor.is_some() {
        out.push(("floor", "z", Number(mm(spec.floor_z))));
    }
    if c.margin.is_some() {
        out.push(("safety", "margin", Number(mm(spec.margin))));
    }
    if c.joint_margin.is_some() {
        out.push((
            "safety",
            "joint_margin",
            Number((spec.joint_margin / DEG * 1e6).round() / 1e6),
        ));
    }
    out
}

/// `--prior MM,DEG`: what a parameter the data do not determine costs. calibrate's third
/// value, the set-up's prior, has nothing to act on here: the score takes the set-up as given.
fn prior(p: Prior) -> Result<crate::calibrate::predict::Prior, Error> {
    if p.setup_mm.is_some() {
        return Err(usage(
            "--prior: place takes MM,DEG: its score takes the set-up (fixture, MAP) as given, so a set-up prior has nothing to act on",
        ));
    }
    Ok(crate::calibrate::predict::Prior {
        length: p.length_mm * MM,
        angle: p.angle_deg * DEG,
        ..Default::default()
    })
}

/// `--stand MM`: the radius of the fixture's stand, 0 to 500 mm.
fn stand(r: f64) -> Result<f64, Error> {
    if !(0.0..=500.0).contains(&r) {
        return Err(usage(format!(
            "--stand: {r} mm must be between 0 and 500 mm"
        )));
    }
    Ok(r * MM)
}

/// `--write-cell`: a cell file per winning position (the user's cell with the fixture moved, a
/// header saying where it came from and what it is predicted to buy).
#[allow(clippy::too_many_arguments)]
fn placed_cells(
    a: &PlaceArgs,
    target: &Path,
    robot: &crate::robot::Robot,
    placement: &place::Placement,
    rep: &place::report::Report,
    spec: &crate::cell::CellSpec,
    pspec: &crate::cell::CellSpec,
    cell_text: Option<&str>,
    step: [f64; 6],
) -> Result<Vec<(PathBuf, String)>, Error> {
    let winners = placement.winners();
    let mut cells: Vec<(PathBuf, String)> = Vec::new();
    let sets = settings(a, pspec, pspec.stand_radius != spec.stand_radius);
    let paths = cell_paths(target, winners.len());
    for (k, (&w, path)) in winners.iter().zip(&paths).enumerate() {
        let c = &placement.candidates[w];
        let mut header = vec![format!(
            "fixture placed by edbbgen {} for {} [{}] (sha256 {})",
            env!("CARGO_PKG_VERSION"),
            robot.name,
            robot.source,
            &robot.digest[..16.min(robot.digest.len())]
        )];
        header.push(format!(
            "predicted MAP position uncertainty after calibrating from a program compiled here: {} µm RMS over the joint space (rank {} of {}; compile step {} deg, {} candidates)",
            c.score_um.map_or_else(|| "-".into(), place::report::um),
            c.rank.map_or_else(|| "-".into(), |r| r.to_string()),
            placement.ranking.len(),
            fmt_fixed(step[0] / DEG, 0),
            a.max_candidates
        ));
        if let Some(cp) = &rep.campaign {
            header.push(format!(
                "run {} of a campaign of {}: together {} µm RMS ({} x better than the best single position)",
                k + 1,
                cp.count,
                place::report::um(cp.predicted_um),
                fmt_fixed(cp.gain_over_best_single, 2)
            ));
        }
        header.push(format!(
            "compile: edbbgen {} --cell {} -o program.nc",
            robot.source,
            path.file_name()
                .map_or_else(String::new, |f| f.to_string_lossy().into_owned())
        ));
        let text =
            cellfile::write(cell_text, &c.fixture, &sets, &header).map_err(|msg| Error::File {
                path: a
                    .cell
                    .cell
                    .as_ref()
                    .map_or_else(|| path.display().to_string(), |p| p.display().to_string()),
                msg,
            })?;
        cells.push((path.clone(), text));
    }
    Ok(cells)
}

pub fn place(a: &PlaceArgs) -> Result<i32, Error> {
    // Everything about the command line first.
    let spec = resolve_cell(&a.cell)?;
    let current = match &a.fixture {
        Some(f) => Some(f.m()),
        None => spec.fixture,
    };
    let region_flag = a.region.as_deref().map(region).transpose()?;
    let grid = grid(&a.grid)?;
    let at: Vec<Vector3<f64>> = a.at.iter().map(|s| place::rounded(s.0)).collect();
    if !(1..=10).contains(&a.count) {
        return Err(usage(format!("--count: {} must be from 1 to 10", a.count)));
    }
    if !(1..=100).contains(&a.top) {
        return Err(usage(format!("--top: {} must be from 1 to 100", a.top)));
    }
    if a.max_candidates < 30 {
        return Err(usage("--max-candidates: must be at least 30"));
    }
    let step = a.step.rad();
    let bar_noise = bar_noise(a.bar_noise)?;
    let bar_rate = bar_rate(a.bar_rate)?;
    let prior = a.prior.map(prior).transpose()?.unwrap_or_default();
    let stand = a.stand.map(stand).transpose()?;
    let cell_text = match &a.cell.cell {
        Some(p) => Some(read_input(p, "the cell", crate::files::Kind::Config)?),
        None => None,
    };

    let robot = load_robot(&a.robot, &a.cell, &spec)?;
    let (pspec, stand_note) = place::placement_spec(&spec, stand);
    let (map, mut warnings) = pipeline::resolve_map(&robot, pspec.map);
    warnings.extend(stand_note.clone());
    let region = match region_flag {
        Some(r) => r,
        None => place::default_region(&robot, &map, &pspec, a.cell.seed),
    };
    let mut opts = PlaceOptions::new(pspec.clone(), region);
    opts.grid = grid;
    opts.at = at;
    opts.current = current;
    opts.count = a.count;
    opts.top = a.top;
    opts.proxy_step = step;
    opts.compile.step = step;
    opts.compile.max_candidates = a.max_candidates;
    opts.compile.seed = a.cell.seed;
    opts.compile.bar_noise = bar_noise * 1e-6;
    opts.compile.bar_rate = bar_rate;
    opts.prior = prior;

    let bar = Bar::new(a.cell.quiet, "placing");
    // A cell that leaves no room is the cell file's fault: the line names it.
    let placement = place::run(&robot, &opts, &bar).map_err(|e| match (&e, &a.cell.cell) {
        (place::PlaceError::NoRoom { .. }, Some(p)) => Error::File {
            path: p.display().to_string(),
            msg: e.to_string(),
        },
        _ => e.into(),
    })?;
    let mut rep = place::report::report(&robot, &placement);
    warnings.extend(rep.warnings.iter().cloned());
    rep.warnings = warnings.clone();

    // Render everything before the first file is written: a failure leaves no file.
    let json = serde_json::to_string_pretty(&rep).unwrap_or_default() + "\n";
    let html = match &a.html {
        Some(_) => Some(crate::report::render(&crate::report::place::page(
            &robot, &rep, a.show,
        )?)?),
        None => None,
    };
    let cells = match &a.write_cell {
        Some(target) => placed_cells(
            a,
            target,
            &robot,
            &placement,
            &rep,
            &spec,
            &pspec,
            cell_text.as_deref(),
            step,
        )?,
        None => Vec::new(),
    };
    let mut files: Vec<(&Path, &str)> = Vec::new();
    if let Some(p) = &a.json {
        files.push((p.as_path(), json.as_str()));
    }
    if let (Some(p), Some(h)) = (&a.html, &html) {
        files.push((p.as_path(), h.as_str()));
    }
    for (p, t) in &cells {
        files.push((p.as_path(), t.as_str()));
    }
    write_all_atomic(&files)?;

    say_raw!(a.cell.quiet, "{}", place::report::text(&rep, a.show));
    for (p, _) in &cells {
        say!(a.cell.quiet, "wrote {}", p.display());
    }
    if let Some((first, _)) = cells.first() {
        say!(
            a.cell.quiet,
            "next: edbbgen {} --cell {} -o program.nc",
            a.robot.display(),
            first.display()
        );
    }
    for w in &warnings {
        eprintln!("edbbgen: warning: {w}");
    }
    Ok(0)
}

//! `verify`: flags → the cell, the robot and the program read back → `verify::check` (or
//! `--trace`'s recorded run) → one line or the JSON report; exit 1 on a failed check.

use super::args::VerifyArgs;
use super::common::{
    check_outputs, controller_map, is_stdout, load_robot, program_dialect, read_input,
    resolve_cell, resolve_fixture, write_json, xyz_mm,
};
use super::Error;
use crate::model::MeasurementModel;
use crate::pipeline;
use crate::robot::Robot;
use crate::units::{fmt_fixed, length_mm, to_mm, DEG};
use std::path::Path;

// ---- verify -------------------------------------------------------------------------------

/// `verify --json`: the summary, and what the collision check covered (every body, the number
/// of pairs checked, every excluded pair with its reason), so that nothing is skipped unseen.
#[derive(serde::Serialize)]
pub(super) struct VerifyReport<'a> {
    schema: &'static str,
    #[serde(flatten)]
    summary: &'a crate::verify::Summary,
    bodies: &'a [String],
    pairs_checked: usize,
    excluded_pairs: &'a [crate::collision::ExcludedPair],
    notes: &'a [String],
    /// The limits checked and where each came from (flag or cell, the program header, default).
    limits: &'a crate::verify::limits::Limits,
}

pub fn run(a: &VerifyArgs) -> Result<i32, Error> {
    let mut spec = resolve_cell(&a.cell)?;
    check_outputs(&[a.json.as_deref()])?;
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
    let fixture = resolve_fixture(a.fixture, &spec, parsed.header_value("fixture"))?;
    // The bar range, margins and blend: flag or cell, else the program header's.
    let stated = crate::verify::HeaderLimits::read(&parsed).map_err(|msg| Error::File {
        path: a.program.display().to_string(),
        msg,
    })?;
    let (limits, limit_notes) = crate::verify::limits::resolve(&mut spec, &stated, &robot);
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
            if let Some(dest) = &a.json {
                let report = VerifyReport {
                    schema: "edbbgen.verify/1",
                    summary: &s,
                    bodies: &scene_report.bodies,
                    pairs_checked: scene_report.pairs_checked,
                    excluded_pairs: &scene_report.excluded,
                    notes: &notes,
                    limits: &limits,
                };
                write_json(
                    dest,
                    &serde_json::to_string_pretty(&report).unwrap_or_default(),
                )?;
            }
            if a.json.as_deref().is_none_or(|d| !is_stdout(d)) {
                for n in &notes {
                    eprintln!("edbbgen: warning: {n}");
                }
                say!(
                    a.cell.quiet,
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
pub(super) fn verify_trace(
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
            if let Some(dest) = &a.json {
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
                write_json(
                    dest,
                    &serde_json::to_string_pretty(&out).unwrap_or_default(),
                )?;
            }
            if a.json.as_deref().is_none_or(|d| !is_stdout(d)) {
                let worst = r
                    .poses
                    .iter()
                    .max_by(|x, y| x.miss_mm.total_cmp(&y.miss_mm));
                say!(
                    a.cell.quiet,
                    "{}: ok: {} samples; {} measurement poses passed within {} at the MAP{}; executed {} s, estimated {} s; bar {}..{} mm; max cone angles {} deg (socket), {} deg (cup)",
                    path.display(),
                    r.samples,
                    r.poses.len(),
                    length_mm(r.worst_miss_mm),
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

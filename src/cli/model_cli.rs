//! `model`: flags → random poses in the bar shell → identifiability (fixture known and free),
//! observability and the uncertainty one reading per pose would give → text or JSON.

use super::args::ModelArgs;
use super::common::{
    bar_noise, check_outputs, is_stdout, load_robot, resolve_cell, resolve_fixture, write_json,
};
use super::{usage, Error};
use crate::model::{self, IdentifyOptions, MeasurementModel, Status};
use crate::pipeline;
use crate::robot::Robot;
use crate::units::{fmt_fixed, length_um, to_mm};
use nalgebra::{DMatrix, Vector3};

// ---- model --------------------------------------------------------------------------------

pub fn run(a: &ModelArgs) -> Result<i32, Error> {
    let spec = resolve_cell(&a.cell)?;
    let fixture = resolve_fixture(a.fixture, &spec, None)?;
    if a.samples < 60 {
        return Err(usage("--samples: must be at least 60"));
    }
    check_outputs(&[a.json.as_deref()])?;
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
    let bar_noise = bar_noise(a.bar_noise)?;
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
    if let Some(dest) = &a.json {
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
        write_json(
            dest,
            &serde_json::to_string_pretty(&report).unwrap_or_default(),
        )?;
    }
    if a.json.as_deref().is_none_or(|d| !is_stdout(d)) {
        say_raw!(
            a.cell.quiet,
            "{}",
            model_text(&robot, &cell, &known, &free, &obs, rows.len())
        );
        say!(
            a.cell.quiet,
            "predicted MAP position uncertainty after calibrating from these poses (one reading each, {} bar noise): {} RMS, {} p95 over the joint space",
            length_um(bar_noise),
            length_um(predicted.rms * 1e6),
            length_um(predicted.p95 * 1e6)
        );
    }
    for w in &warnings {
        eprintln!("edbbgen: warning: {w}");
    }
    Ok(0)
}

pub(super) fn describe(p: &model::ParamInfo) -> String {
    match &p.status {
        Status::Dependent { on } => format!("{} (dependent on {})", p.name, on.join(", ")),
        Status::Negligible => format!("{} (negligible)", p.name),
        Status::Known => format!("{} (known)", p.name),
        Status::Identifiable => p.name.clone(),
    }
}

pub(super) fn model_text(
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

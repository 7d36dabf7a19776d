//! The program stage: in = the planned, timed path, its selection, identifiability and
//! predicted accuracy; out = the dialect-neutral [`Program`] (header and moves, degrees and
//! millimetres) that `emit` writes for a controller.

use super::{CompileOptions, Planned, Predicted};
use crate::emit;
use crate::ir::{Header, Move, Path, Program};
use crate::model::Identifiability;
use crate::safety::Checker;
use crate::units::{to_deg, to_mm};

/// The program the plan describes: one move per waypoint, with its pose number, section, bar
/// mount/removal flags, blend, time and nominal bar length.
pub fn base(
    ck: &Checker,
    opts: &CompileOptions,
    id: &Identifiability,
    planned: &Planned,
    path: &Path,
    predicted: &super::Predicted,
) -> Program {
    let moves = moves(ck, planned, path, opts.dwell.unwrap_or(0.0));
    let mut header = header(ck, opts, id, planned, path, predicted);
    if let Some(dwell) = opts.dwell {
        // The key of a stop-and-measure run: the poses it dwells at, in order, and their
        // nominal lengths; the estimated time includes the dwells.
        header.dwell_s = dwell;
        header.measure_mm = moves
            .iter()
            .filter(|m| m.dwell_s > 0.0)
            .map(|m| m.length_mm)
            .collect();
        let total = dwell * header.measure_mm.len() as f64;
        header.time_s += total;
        header.time_unsorted_s += total;
        header.time_direct_s += total;
        header.plateau_samples = predicted.plateau_samples.unwrap_or(0);
        header.predicted_continuous_std_um = predicted.continuous_workspace_rms.unwrap_or(0.0);
    }
    Program { header, moves }
}

fn header(
    ck: &Checker,
    opts: &CompileOptions,
    id: &Identifiability,
    planned: &Planned,
    path: &Path,
    predicted: &Predicted,
) -> Header {
    let (robot, cell, plan) = (ck.robot, ck.cell, &planned.plan);
    let selection = &planned.selection;
    let cond = selection
        .curve
        .iter()
        .find(|c| c.0 == selection.indices.len())
        .map_or(f64::NAN, |c| c.1);
    Header {
        title: crate::ir::EDBB_TITLE.to_string(),
        instrument: "EDBB".to_string(),
        notes: Vec::new(),
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        robot: robot.name.clone(),
        robot_file: robot.source.clone(),
        fixture_mm: opts.fixture.map(to_mm).into(),
        map_mm: cell.map.map(to_mm).into(),
        bar_mm: [to_mm(cell.bar_min), to_mm(cell.bar_max)],
        blend_mm: to_mm(opts.blend),
        margin_mm: to_mm(opts.cell.margin),
        joint_margin_deg: to_deg(opts.cell.joint_margin),
        poses: plan.waypoints.iter().filter(|w| !w.support).count(),
        supports: plan.supports,
        sections: plan.sections(),
        identifiable: id.count(),
        cond,
        time_unsorted_s: path.time_unsorted,
        time_s: path.time_sorted,
        time_direct_s: path.time_direct,
        accelerations: robot.max_accelerations().map(to_deg),
        inputs_sha256: String::new(),
        joint_names: robot.joints.iter().map(|j| j.name.clone()).collect(),
        predicted_std_um: predicted.workspace_rms,
        bar_noise_um: predicted.bar_noise_um,
        bar_rate_hz: predicted.bar_rate_hz,
        program_name: opts.program_name.clone(),
        dialect: String::new(),
        controller: String::new(),
        axis_names: Vec::new(),
        axis_units: String::new(),
        axis_decimals: 0,
        dwell_s: 0.0,
        measure_mm: Vec::new(),
        plateau_samples: 0,
        predicted_continuous_std_um: 0.0,
    }
}

/// One move per waypoint; with a dwell, every measurement pose (all are made with the bar in
/// place: a section's first pose dwells after its mount pause) carries it.
fn moves(ck: &Checker, planned: &Planned, path: &Path, dwell: f64) -> Vec<Move> {
    let model = ck.model;
    let wps = &planned.plan.waypoints;
    let (mut pose_no, mut section) = (0, 0);
    wps.iter()
        .zip(&path.move_times)
        .enumerate()
        .map(|(k, (w, &t))| {
            let cruise = path.cruise_times.get(k).copied().unwrap_or(t);
            if !w.support {
                pose_no += 1;
            }
            // A transit's target without support flag is a section's first pose: the bar goes
            // in there; it comes out before the first transit move after a mounted stretch.
            let mount_after = w.transit && !w.support;
            if mount_after {
                section += 1;
            }
            Move {
                q_deg: w.q.map(|r| emit::round_deg(to_deg(r))),
                support: w.support,
                transit: w.transit,
                pose: if w.support { 0 } else { pose_no },
                blend_mm: to_mm(w.blend),
                time_s: t,
                cruise_s: cruise,
                blend_value: w.blend_value,
                length_mm: to_mm(model.reached_length(
                    &model.nominal,
                    &ck.robot.effects,
                    &w.q,
                    &[0.0; 6],
                )),
                note: String::new(),
                pause: String::new(),
                pause_before: String::new(),
                section: section.max(1),
                remove_before: k > 0 && w.transit && !(wps[k - 1].transit && wps[k - 1].support),
                mount_after,
                axes: [0.0; 6],
                speed_pct: 0.0,
                dwell_s: if w.support { 0.0 } else { dwell },
            }
        })
        .collect()
}

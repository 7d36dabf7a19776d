//! A compensation's report in; the text `compensate` prints out (what was compensated and how
//! well, the mastering offsets with their instructions, the accuracy of each route, the notes).

use super::offsets;
use super::Report;
use crate::units::fmt_fixed;

/// The lines `compensate` prints: what was compensated, the mastering offsets, the accuracy
/// each route gives, the notes.
pub fn text(r: &Report) -> String {
    let mut s = String::new();
    if let Some(t) = &r.targets {
        s += &format!(
            "{}: compensated {} of {} targets ({}); the calibrated robot missed them by {} µm RMS, {} µm max; at the written joints {} µm max\n",
            t.file,
            t.compensated,
            t.rows,
            t.kind,
            fmt_fixed(t.before_um.rms, 1),
            fmt_fixed(t.before_um.max, 1),
            fmt_fixed(t.residual_um.max, 3)
        );
        if t.orientation_free > 0 {
            s += &format!(
                "{} near a wrist singularity: position exact, orientation within {} deg\n",
                t.orientation_free,
                fmt_fixed(r.limits.orientation_tolerance_deg, 2)
            );
        }
        let mut reasons: Vec<(String, usize)> = Vec::new();
        for n in &t.not_compensated {
            let why = n.status.split(':').next().unwrap_or("").to_string();
            match reasons.iter_mut().find(|x| x.0 == why) {
                Some(x) => x.1 += 1,
                None => reasons.push((why, 1)),
            }
        }
        if !reasons.is_empty() {
            s += &format!(
                "not compensated (listed with the reason in the output): {}\n",
                reasons
                    .iter()
                    .map(|(w, n)| format!("{n} {w}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
    }
    if let Some(p) = &r.program {
        s += &format!(
            "{} ({}): {} moves compensated, axis values with {} decimals: TCP error at the printed values {} µm RMS, {} µm max{}\n",
            p.file,
            p.dialect,
            p.moves,
            p.decimals,
            fmt_fixed(p.printed_residual_um.rms, 3),
            fmt_fixed(p.printed_residual_um.max, 3),
            if p.retimed_lines.is_empty() {
                String::new()
            } else {
                format!(
                    "; {} moves slowed to stay within the axis speeds",
                    p.retimed_lines.len()
                )
            }
        );
    }
    if let Some(m) = &r.mastering {
        s += &format!(
            "mastering offsets (from the {}; {}):\n",
            match m.source {
                offsets::Source::CalibrationReport => "calibration report",
                offsets::Source::RobotFiles => "robot files' joint zeros",
            },
            m.controller
        );
        for (a, line) in m.axes.iter().zip(&m.instructions) {
            let std = match a.std {
                Some(v) => format!(" +/- {}", fmt_fixed(v, 6)),
                None => String::new(),
            };
            s += &format!(
                "  {}: {}{} {}   {}\n",
                a.axis,
                fmt_fixed(a.delta, 6),
                std,
                a.units,
                line
            );
        }
    }
    let acc = &r.accuracy;
    s += &format!(
        "TCP accuracy over the joint space ({} random poses, registered): nothing applied {} µm RMS, {} µm p95; offsets only {} µm RMS (model)",
        acc.poses,
        fmt_fixed(acc.uncompensated_um.rms, 1),
        fmt_fixed(acc.uncompensated_um.p95, 1),
        fmt_fixed(acc.offsets_only_model_um.rms, 1)
    );
    match (&acc.predicted_offsets_only_um, &acc.predicted_full_um) {
        (Some(o), Some(f)) => {
            s += &format!(
                ", {} µm RMS predicted; full compensation {} µm RMS, {} µm p95 predicted (the calibration's)\n",
                fmt_fixed(o.rms, 1),
                fmt_fixed(f.rms, 2),
                fmt_fixed(f.p95, 2)
            );
        }
        _ => s += "\n",
    }
    for n in &r.notes {
        s += &format!("note: {n}\n");
    }
    s
}

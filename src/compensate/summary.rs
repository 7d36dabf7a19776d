//! A compensation's report in; the text `compensate` prints out (what was compensated and how
//! well, the mastering offsets with their instructions, the accuracy of each route, the notes).

use super::offsets;
use super::Report;
use crate::units::{fmt_fixed, length_um};

/// The lines `compensate` prints: what was compensated, the mastering offsets, the accuracy
/// each route gives, the notes.
pub fn text(r: &Report) -> String {
    let mut s = String::new();
    if let Some(t) = &r.targets {
        s += &format!(
            "{}: compensated {} of {} targets ({}); the calibrated robot missed them by {} RMS, {} max; at the written joints {} max\n",
            t.file,
            t.compensated,
            t.rows,
            t.kind,
            length_um(t.before_um.rms),
            length_um(t.before_um.max),
            length_um(t.residual_um.max)
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
            "{} ({}): {} moves compensated, axis values with {} decimals: TCP error at the printed values {} RMS, {} max{}\n",
            p.file,
            p.dialect,
            p.moves,
            p.decimals,
            length_um(p.printed_residual_um.rms),
            length_um(p.printed_residual_um.max),
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
                Some(v) => format!(" ± {}", fmt_fixed(v, 6)),
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
        "TCP accuracy over the joint space ({} random poses, registered): nothing applied {} RMS, {} p95; offsets only {} RMS (model)",
        acc.poses,
        length_um(acc.uncompensated_um.rms),
        length_um(acc.uncompensated_um.p95),
        length_um(acc.offsets_only_model_um.rms)
    );
    match (&acc.predicted_offsets_only_um, &acc.predicted_full_um) {
        (Some(o), Some(f)) => {
            s += &format!(
                ", {} RMS predicted; full compensation {} RMS, {} p95 predicted (the calibration's)\n",
                length_um(o.rms),
                length_um(f.rms),
                length_um(f.p95)
            );
        }
        _ => s += "\n",
    }
    for n in &r.notes {
        s += &format!("note: {n}\n");
    }
    s
}

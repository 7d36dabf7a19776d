//! The limits `verify` checks a program with: the cell as flags and file state it, and the
//! program header's statements ([`HeaderLimits`]) in; the cell with every limit it does not
//! state taken from the header, where each limit came from, and notes where the header states
//! a looser one, out.

use super::HeaderLimits;
use crate::cell::CellSpec;
use crate::robot::Robot;
use crate::units::{fmt_fixed, to_mm, DEG, MM};

/// The limits `verify` checks with and where each came from (`--json`'s `limits`).
#[derive(serde::Serialize)]
pub struct Limits {
    pub bar_mm: [f64; 2],
    pub margin_mm: f64,
    pub joint_margin_deg: f64,
    /// The most any corner may blend: the header's statement (None: not stated).
    pub blend_mm: Option<f64>,
    /// The joint accelerations (deg/s², per joint) the move times are checked at: the robot
    /// file's or the cell's, never the header's (a note says where the header differs).
    pub accelerations_deg: [f64; 6],
    /// Per limit: "flag or cell", "header" or "default".
    pub from: std::collections::BTreeMap<&'static str, &'static str>,
}

/// Every limit the program header states is the one `verify` checks unless a flag or the cell
/// file states it: a program compiled with `--bar 150..300` or `--margin 5` verifies as it
/// was made. An explicit flag or cell value wins; where the header states a looser one, the
/// returned notes say so (the program was made to less than this check asks).
pub fn resolve(spec: &mut CellSpec, lim: &HeaderLimits, robot: &Robot) -> (Limits, Vec<String>) {
    let mut notes = Vec::new();
    let mut from = std::collections::BTreeMap::new();
    let source = |stated: bool, header: bool| match (stated, header) {
        (true, _) => "flag or cell",
        (false, true) => "header",
        (false, false) => "default",
    };
    let st = spec.stated;
    if let Some([lo, hi]) = lim.bar_mm {
        let cell = [to_mm(spec.bar_min), to_mm(spec.bar_max)];
        if !st.bar_min {
            spec.bar_min = lo * MM;
        }
        if !st.bar_max {
            spec.bar_max = hi * MM;
        }
        if (st.bar_min && lo < cell[0] - 0.05) || (st.bar_max && hi > cell[1] + 0.05) {
            notes.push(format!(
                "the program header states bar range {}..{} mm, wider than the {}..{} mm this check uses (flag or cell)",
                fmt_fixed(lo, 1), fmt_fixed(hi, 1), fmt_fixed(cell[0], 1), fmt_fixed(cell[1], 1)
            ));
        }
    }
    from.insert(
        "bar",
        match (st.bar_min, st.bar_max, lim.bar_mm.is_some()) {
            (true, true, _) => "flag or cell",
            (true, false, true) | (false, true, true) => "flag or cell and header",
            (_, _, header) => source(false, header),
        },
    );
    let mut scalar = |name: &'static str,
                      unit: &str,
                      stated: bool,
                      header: Option<f64>,
                      value: &mut f64,
                      scale: f64| {
        if let Some(h) = header {
            if !stated {
                *value = h * scale;
            } else if h < *value / scale - 0.05 {
                notes.push(format!(
                    "the program header states {name} {} {unit}, less than the {} {unit} this check uses (flag or cell)",
                    fmt_fixed(h, 1),
                    fmt_fixed(*value / scale, 1)
                ));
            }
        }
        from.insert(name, source(stated, header.is_some()));
    };
    scalar(
        "safety margin",
        "mm",
        st.margin,
        lim.margin_mm,
        &mut spec.margin,
        MM,
    );
    scalar(
        "joint margin",
        "deg",
        st.joint_margin,
        lim.joint_margin_deg,
        &mut spec.joint_margin,
        DEG,
    );
    from.insert(
        "corner blend",
        if lim.blend_mm.is_some() {
            "header"
        } else {
            "default"
        },
    );
    // The accelerations are the robot's (its file or the cell's `[robot] accelerations`): they
    // are what it does, whatever the program assumed. Where the header assumed others, the
    // program's times were made for another robot or cell: a note says so.
    let accelerations_deg = robot.max_accelerations().map(|a| a / DEG);
    if let Some((stated, half)) = lim.accelerations_deg {
        if (0..6).any(|i| (stated[i] - accelerations_deg[i]).abs() > half + 1e-9) {
            let list = |a: &[f64; 6]| a.map(|v| fmt_fixed(v, 1)).join(", ");
            notes.push(format!(
                "the program header states joint accelerations {} deg/s^2, but the robot{} has {} deg/s^2: the program's times were made for other accelerations (this check uses the robot's)",
                list(&stated),
                if spec.accelerations.is_some() { " (cell)" } else { " file" },
                list(&accelerations_deg)
            ));
        }
    }
    from.insert(
        "joint accelerations",
        if spec.accelerations.is_some() {
            "cell"
        } else {
            "robot file"
        },
    );
    (
        Limits {
            accelerations_deg,
            bar_mm: [to_mm(spec.bar_min), to_mm(spec.bar_max)],
            margin_mm: to_mm(spec.margin),
            joint_margin_deg: spec.joint_margin / DEG,
            blend_mm: lim.blend_mm,
            from,
        },
        notes,
    )
}

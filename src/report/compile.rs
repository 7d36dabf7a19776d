//! The compiler's report page: in = the robot and [`Compiled`] (every stage's result); out = a
//! [`Page`] with the paper's Figs. 4-7 and the stage counts, safety figures, identifiability and
//! warnings of the JSON report (`--json`).

use super::{Block, Page, ReportError, Section};
use crate::ir::Header;
use crate::model::identify::Status;
use crate::pipeline::{Compiled, Report};
use crate::plot::{Figure, Legend, Mark, Panel, Series};
use crate::robot::{kinematics::chain_frames, Robot};
use crate::units::{fmt_fixed, to_deg, to_mm};
use nalgebra::Vector3;

/// Palette indices (see `plot::PALETTE`).
const BLUE: usize = 0;
const RED: usize = 1;
const GREEN: usize = 2;
const PURPLE: usize = 3;
const ORANGE: usize = 4;
const SKY: usize = 5;
const BLACK: usize = 7;
const GREY: usize = 8;

/// At most this many pool poses are drawn as dots (a fixed stride over the pool; the caption
/// says so): beyond it the cloud looks the same and the page only grows.
const POOL_DOTS: usize = 600;
/// MAP samples per drawn move (joint-space moves curve in space).
const MOVE_SAMPLES: usize = 12;
/// Poses drawn as stick figures in Fig. 7.
const STICKS: usize = 4;

/// The three orthogonal views: (name, x axis, y axis) as coordinate indices.
const VIEWS: [(&str, usize, usize); 3] = [
    ("top (x-y)", 0, 1),
    ("front (x-z)", 0, 2),
    ("side (y-z)", 1, 2),
];
const AXIS: [&str; 3] = ["x", "y", "z"];

fn mm(v: &Vector3<f64>) -> [f64; 3] {
    [to_mm(v.x), to_mm(v.y), to_mm(v.z)]
}

fn project(points: &[[f64; 3]], view: (usize, usize)) -> Vec<(f64, f64)> {
    points.iter().map(|p| (p[view.0], p[view.1])).collect()
}

/// A circle of radius r (mm) around c in a view's plane: the outline of the bar's shell sphere.
fn circle(c: &[f64; 3], r: f64, view: (usize, usize)) -> Vec<(f64, f64)> {
    (0..=120)
        .map(|k| {
            let a = k as f64 / 120.0 * std::f64::consts::TAU;
            (c[view.0] + r * a.cos(), c[view.1] + r * a.sin())
        })
        .collect()
}

fn space_panel(title: String, view: (usize, usize), series: Vec<Series>) -> Panel {
    Panel {
        title,
        x_label: format!("{} [mm]", AXIS[view.0]),
        y_label: format!("{} [mm]", AXIS[view.1]),
        series,
        equal_aspect: true,
        legend: Legend::Outside,
        ..Panel::default()
    }
}

/// Joint trajectories over estimated time: poses joined by synchronous joint moves of the given
/// durations (Eq. 7), so every joint is linear in time between two poses.
fn joint_panel(title: &str, poses: &[[f64; 6]], times: &[f64]) -> Panel {
    let mut t = 0.0;
    let mut pts: [Vec<(f64, f64)>; 6] = Default::default();
    for (k, q) in poses.iter().enumerate() {
        t += times[k];
        for j in 0..6 {
            pts[j].push((t, to_deg(q[j])));
        }
    }
    Panel {
        title: title.to_string(),
        x_label: "estimated time [s]".into(),
        y_label: "joint angle [°]".into(),
        series: pts
            .into_iter()
            .enumerate()
            .map(|(j, p)| Series::line(format!("q{}", j + 1), j, p))
            .collect(),
        legend: Legend::Outside,
        ..Panel::default()
    }
}

/// The compiler's page.
pub fn page(robot: &Robot, out: &Compiled) -> Result<Page, ReportError> {
    let h = &out.program.header;
    let cell = &out.cell;
    let fixture = mm(&cell.fixture);
    let (fig4, stride) = poses_figure(out, &fixture);
    let fig5 = cond_figure(out);
    let fig6 = joints_figure(robot, out);
    let fig7 = path_figure(robot, out, &fixture);
    Ok(Page {
        title: format!("edbbgen — EDBB measurement program for {}", h.robot),
        kind: "compile".into(),
        tool_version: h.tool_version.clone(),
        inputs_sha256: h.inputs_sha256.clone(),
        facts: facts(h),
        warnings: out.warnings.clone(),
        sections: vec![
            Section {
                heading: "Poses around the fixture (Fig. 4)".into(),
                blocks: vec![Block::figure(
                    "fig-poses",
                    &format!(
                        "MAP positions of the pose pool ({} poses{}) and of the {} selected poses, in three orthogonal views of the robot base frame; circles: the bar's shell (ball-centre distance {} .. {} mm) around the fixture.",
                        out.pool.candidates.len(),
                        if stride > 1 { format!(", 1 in {stride} drawn") } else { String::new() },
                        out.selection.indices.len(),
                        fmt_fixed(to_mm(cell.bar_min), 0),
                        fmt_fixed(to_mm(cell.bar_max), 0)
                    ),
                    &fig4,
                )?],
            },
            Section {
                heading: "Pose count (Fig. 5)".into(),
                blocks: vec![Block::figure(
                    "fig-cond",
                    &format!("Condition number of the scaled identification Jacobian while the greedy elimination removes poses, down to n = m = {}; the dot marks the chosen count ({}).", out.selection.m, out.selection.rule),
                    &fig5,
                )?],
            },
            Section {
                heading: "Joint trajectories (Fig. 6)".into(),
                blocks: vec![Block::figure(
                    "fig-joints",
                    "Joint angles over the estimated time (each move with its acceleration ramps from rest to rest; the program's blends overlap moves, which its stated time takes off): the selected poses in pool order by direct moves, and the program in tour order with its support poses. Like for like, the ordering takes the direct-move time of the same poses from the first panel's to the one in the second panel's title.",
                    &fig6,
                )?],
            },
            Section {
                heading: "The measurement path (Fig. 7)".into(),
                blocks: vec![Block::figure(
                    "fig-path",
                    "MAP path of the program (joint-space moves sampled), measurement and support poses, corners with a blend; top row: the whole cell with the bar-free transits and the robot as a stick figure (base, DH frame origins, flange, MAP) at a few poses of the tour; bottom row: the measurement itself.",
                    &fig7,
                )?],
            },
            Section {
                heading: "Stages".into(),
                blocks: vec![Block::table(&["stage", "count"], stage_counts(&out.report))],
            },
            Section {
                heading: "Safety (as verified on the program text)".into(),
                blocks: vec![
                    Block::table(&["check", "value"], safety_rows(&out.report)),
                    Block::text("Body pairs excluded from the collision check, with the reason:"),
                    Block::table(&["body", "body", "reason"], excluded_rows(&out.report)),
                ],
            },
            Section {
                heading: "Identifiability (Section 2.1.2)".into(),
                blocks: vec![Block::table(&["parameter", "status"], identifiability_rows(out))],
            },
        ],
    })
}

/// Fig. 4 from the compiled pool and selection around the fixture (mm): the figure and the
/// stride the pool is drawn with.
fn poses_figure(out: &Compiled, fixture: &[f64; 3]) -> (Figure, usize) {
    let cell = &out.cell;
    let stride = out.pool.candidates.len().div_ceil(POOL_DOTS).max(1);
    let pool: Vec<[f64; 3]> = out
        .pool
        .candidates
        .iter()
        .step_by(stride)
        .map(|c| [to_mm(c.map[0]), to_mm(c.map[1]), to_mm(c.map[2])])
        .collect();
    let selected: Vec<[f64; 3]> = out
        .selection
        .indices
        .iter()
        .map(|&i| {
            let m = out.pool.candidates[i].map;
            [to_mm(m[0]), to_mm(m[1]), to_mm(m[2])]
        })
        .collect();
    let fig4 = Figure {
        title: String::new(),
        panels: VIEWS
            .iter()
            .map(|&(name, a, b)| {
                let v = (a, b);
                space_panel(
                    name.to_string(),
                    v,
                    vec![
                        Series::dots("pool", GREY, project(&pool, v)),
                        Series::dots("selected", BLUE, project(&selected, v)),
                        Series::dots("fixture", RED, project(&[*fixture], v)),
                        Series::line("bar max", SKY, circle(fixture, to_mm(cell.bar_max), v)),
                        Series::line("bar min", GREY, circle(fixture, to_mm(cell.bar_min), v)),
                    ],
                )
            })
            .collect(),
        columns: 3,
        panel_px: (330, 330),
    };
    (fig4, stride)
}

/// Fig. 5 from the compiled selection: the condition number over the pose count, whole and
/// near the end.
fn cond_figure(out: &Compiled) -> Figure {
    let sel_n = out.selection.indices.len();
    let curve: Vec<(f64, f64)> = out
        .selection
        .curve
        .iter()
        .map(|&(n, c)| (n as f64, c))
        .collect();
    let chosen: Vec<(f64, f64)> = curve
        .iter()
        .filter(|p| p.0 as usize == sel_n)
        .copied()
        .collect();
    let m = out.selection.m as f64;
    let zoom_to = (4 * sel_n).max(out.selection.m + 10) as f64;
    let cond_panel = |title: String, x_range: Option<(f64, f64)>, pts: Vec<(f64, f64)>| Panel {
        title,
        x_label: "number of poses n".into(),
        y_label: "condition number".into(),
        series: vec![
            Series::line("cond(n)", BLUE, pts),
            Series::dots("chosen", RED, chosen.clone()),
        ],
        x_range,
        y_log: true,
        legend: Legend::Outside,
        ..Panel::default()
    };
    Figure {
        title: String::new(),
        panels: vec![
            cond_panel(
                format!(
                    "whole elimination: {} → {} poses",
                    out.pool.candidates.len(),
                    out.selection.m
                ),
                None,
                curve.clone(),
            ),
            cond_panel(
                format!("near the end: chosen n = {sel_n}"),
                Some((m - 1.0, zoom_to)),
                curve.iter().filter(|p| p.0 <= zoom_to).copied().collect(),
            ),
        ],
        columns: 2,
        panel_px: (480, 320),
    }
}

/// Fig. 6 from the robot's limits and the compiled selection and path: the joint trajectories
/// unsorted and in tour order.
fn joints_figure(robot: &Robot, out: &Compiled) -> Figure {
    let lim = crate::timing::Limits::of(robot);
    let unsorted: Vec<[f64; 6]> = out
        .selection
        .indices
        .iter()
        .map(|&i| out.pool.candidates[i].q)
        .collect();
    let unsorted_t: Vec<f64> = (0..unsorted.len())
        .map(|k| {
            if k == 0 {
                0.0
            } else {
                // Timed as the header's unsorted time: direct, ramps, exact stops.
                crate::timing::move_time(&unsorted[k - 1], &unsorted[k], &lim, 1.0)
            }
        })
        .collect();
    Figure {
        title: String::new(),
        panels: vec![
            joint_panel(
                &format!(
                    "selected poses in pool order, direct moves: {} s",
                    fmt_fixed(out.path.time_unsorted, 1)
                ),
                &unsorted,
                &unsorted_t,
            ),
            joint_panel(
                &format!(
                    "the program in tour order, support poses included: {} s as programmed (the selected poses alone by direct moves: {} s)",
                    fmt_fixed(out.path.time_sorted, 1),
                    fmt_fixed(out.path.time_direct, 1)
                ),
                &out.path.poses,
                &out.path.move_times,
            ),
        ],
        columns: 1,
        panel_px: (960, 300),
    }
}

/// Fig. 7 from the robot and the compiled plan around the fixture (mm): the MAP path with
/// support poses, blends and the robot as stick figures.
fn path_figure(robot: &Robot, out: &Compiled, fixture: &[f64; 3]) -> Figure {
    let map_of = |q: &[f64; 6]| mm(&out.model.map_position(&out.model.nominal, q));
    let wps = &out.plan.waypoints;
    let mut path: Vec<[f64; 3]> = Vec::new();
    let mut transit: Vec<[f64; 3]> = Vec::new();
    for (k, w) in wps.iter().enumerate().skip(1) {
        let a = wps[k - 1].q;
        let seg: Vec<[f64; 3]> = (0..=MOVE_SAMPLES)
            .map(|s| {
                let f = s as f64 / MOVE_SAMPLES as f64;
                map_of(&std::array::from_fn(|j| a[j] + f * (w.q[j] - a[j])))
            })
            .collect();
        let target = if w.transit { &mut transit } else { &mut path };
        target.extend(seg);
        target.push([f64::NAN; 3]);
    }
    let measure: Vec<[f64; 3]> = wps
        .iter()
        .filter(|w| !w.support && !w.transit)
        .map(|w| map_of(&w.q))
        .collect();
    let support: Vec<[f64; 3]> = wps
        .iter()
        .filter(|w| w.support)
        .map(|w| map_of(&w.q))
        .collect();
    let blended: Vec<[f64; 3]> = wps
        .iter()
        .filter(|w| w.blend > 0.0)
        .map(|w| map_of(&w.q))
        .collect();
    // Stick figures: base, the DH frame origins, flange, MAP, at a few poses spread over the tour.
    let mut sticks: Vec<[f64; 3]> = Vec::new();
    let n_meas = out.path.poses.len();
    for k in 0..STICKS.min(n_meas) {
        let q = out.path.poses[k * n_meas / STICKS.min(n_meas)];
        let f = chain_frames(&robot.base, &robot.dh, &robot.flange, &q);
        let mut pts = vec![[0.0; 3]];
        pts.extend(f.iter().map(|fr| mm(&fr.t)));
        pts.push(map_of(&q));
        for w in pts.windows(2) {
            sticks.push(w[0]);
            sticks.push(w[1]);
        }
    }
    let view_series = |v: (usize, usize), whole: bool| {
        let mut s = vec![
            Series::line("path (bar on)", BLUE, project(&path, v)),
            Series::dots("measurement pose", GREEN, project(&measure, v)),
            Series::dots("support pose", RED, project(&support, v)),
            Series::dots("blended corner", PURPLE, project(&blended, v)),
            Series::dots("fixture", BLACK, project(&[*fixture], v)),
        ];
        if whole {
            s.push(Series::line(
                "transit (bar off)",
                ORANGE,
                project(&transit, v),
            ));
            s.push(Series {
                label: "robot (stick figure)".into(),
                points: project(&sticks, v),
                mark: Mark::Segments,
                colour: GREY,
            });
        }
        s
    };
    Figure {
        title: String::new(),
        panels: VIEWS
            .iter()
            .map(|&(name, a, b)| {
                space_panel(
                    format!("{name}: the cell"),
                    (a, b),
                    view_series((a, b), true),
                )
            })
            .chain(VIEWS.iter().map(|&(name, a, b)| {
                space_panel(
                    format!("{name}: the measurement"),
                    (a, b),
                    view_series((a, b), false),
                )
            }))
            .collect(),
        columns: 3,
        panel_px: (330, 330),
    }
}

/// The stage counts table's rows from the compiler's report.
fn stage_counts(r: &Report) -> Vec<Vec<String>> {
    let num = |v: u64| v.to_string();
    let mut counts = vec![
        vec!["joint grid".into(), num(r.grid_size)],
        vec![
            "evaluated (after q1 solution; reach, floor and cone pruning)".into(),
            num(r.evaluated),
        ],
        vec![
            "valid before collisions".into(),
            num(r.valid_before_collisions),
        ],
    ];
    for (why, n) in &r.rejected {
        counts.push(vec![format!("  rejected: {why}"), num(*n)]);
    }
    counts.extend([
        vec!["collision-checked".into(), r.collision_checked.to_string()],
        vec!["pool".into(), r.pool.to_string()],
        vec![
            "left out (not safely connected)".into(),
            r.disconnected.to_string(),
        ],
        vec![
            "connected groups (kept)".into(),
            format!("{} ({})", r.sections.groups, r.sections.kept_groups),
        ],
        vec![
            "sections (measurement poses each)".into(),
            format!(
                "{} ({})",
                r.sections.measured_per_section.len(),
                r.sections
                    .measured_per_section
                    .iter()
                    .map(|n| n.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ],
        vec![
            "replaced (unreachable)".into(),
            r.replaced_unreachable.to_string(),
        ],
        vec![
            "identifiable parameters m".into(),
            r.identifiable.to_string(),
        ],
        vec!["selected poses".into(), r.selected.to_string()],
        vec!["support poses".into(), r.support_poses.to_string()],
        vec!["dropped poses".into(), r.dropped.len().to_string()],
        vec![
            "exact stops (blend refused)".into(),
            r.exact_stops.to_string(),
        ],
    ]);
    counts
}

/// The safety table's rows from the compiler's report.
fn safety_rows(r: &Report) -> Vec<Vec<String>> {
    vec![
        vec![
            "minimum clearance".into(),
            format!(
                "{} mm ({} / {})",
                fmt_fixed(r.min_clearance_mm, 1),
                r.min_clearance_between[0],
                r.min_clearance_between[1]
            ),
        ],
        vec![
            "bar length used".into(),
            format!(
                "{} .. {} mm",
                fmt_fixed(r.bar_length_mm[0], 1),
                fmt_fixed(r.bar_length_mm[1], 1)
            ),
        ],
        vec![
            "largest socket angle".into(),
            format!("{}°", fmt_fixed(r.max_socket_angle_deg, 1)),
        ],
        vec![
            "largest cup angle".into(),
            format!("{}°", fmt_fixed(r.max_cup_angle_deg, 1)),
        ],
        vec![
            "body pairs checked".into(),
            r.collision_pairs_checked.to_string(),
        ],
        vec![
            "body pairs excluded".into(),
            r.excluded_pairs.len().to_string(),
        ],
    ]
}

/// The excluded body pairs' rows (body, body, reason) from the compiler's report.
fn excluded_rows(r: &Report) -> Vec<Vec<String>> {
    r.excluded_pairs
        .iter()
        .map(|p| vec![p.a.clone(), p.b.clone(), p.reason.clone()])
        .collect()
}

/// The identifiability table's rows (parameter, status) from the compiled model.
fn identifiability_rows(out: &Compiled) -> Vec<Vec<String>> {
    out.identifiability
        .params
        .iter()
        .map(|p| {
            let status = match &p.status {
                Status::Identifiable => "identifiable".to_string(),
                Status::Dependent { on } => format!("dependent on {}", on.join(", ")),
                Status::Negligible => "negligible".to_string(),
                Status::Known => "known (held)".to_string(),
            };
            vec![p.name.clone(), status]
        })
        .collect()
}

/// The page's facts (name, value) from the program's header.
fn facts(h: &Header) -> Vec<(String, String)> {
    vec![
        (
            "robot".to_string(),
            format!("{} [{}]", h.robot, h.robot_file),
        ),
        (
            "fixture (base frame)".into(),
            format!("{} mm", xyz(&h.fixture_mm)),
        ),
        (
            "MAP (flange frame)".into(),
            format!("{} mm", xyz(&h.map_mm)),
        ),
        (
            "bar range".into(),
            format!(
                "{} .. {} mm",
                fmt_fixed(h.bar_mm[0], 1),
                fmt_fixed(h.bar_mm[1], 1)
            ),
        ),
        (
            "poses".into(),
            format!(
                "{} measurement + {} support in {} section{}",
                h.poses,
                h.supports,
                h.sections,
                if h.sections == 1 { "" } else { "s" }
            ),
        ),
        ("identifiable parameters".into(), h.identifiable.to_string()),
        ("cond(J)".into(), fmt_fixed(h.cond, 2)),
        (
            "estimated time".into(),
            format!(
                "{} s as programmed (support poses and blends included; pauses not included)",
                fmt_fixed(h.time_s, 1),
            ),
        ),
        (
            "ordering (the measurement poses alone, direct moves with exact stops)".into(),
            format!(
                "{} s in tour order, {} s unsorted",
                fmt_fixed(h.time_direct_s, 1),
                fmt_fixed(h.time_unsorted_s, 1)
            ),
        ),
        (
            "corner blend / safety margin".into(),
            format!(
                "{} mm / {} mm",
                fmt_fixed(h.blend_mm, 1),
                fmt_fixed(h.margin_mm, 1)
            ),
        ),
    ]
}

fn xyz(v: &[f64; 3]) -> String {
    format!(
        "{}, {}, {}",
        fmt_fixed(v[0], 1),
        fmt_fixed(v[1], 1),
        fmt_fixed(v[2], 1)
    )
}

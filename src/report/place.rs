//! The placement page: in = the robot and the `edbbgen.place/1` report; out = a [`Page`] with
//! the candidate positions around the robot in three orthogonal views, coloured by their score
//! (classes relative to the best), the cell's fixture and the winners marked, and the ranking
//! table — the numbers of the JSON report.

use super::{Block, Page, ReportError, Section};
use crate::place::report::{row, shown, um, Report, ROW_HEAD};
use crate::plot::{Figure, Legend, Mark, Panel, Series};
use crate::robot::{kinematics::chain_frames, Robot};
use crate::units::{fmt_fixed, length_um, to_mm};

/// Palette indices (see `plot::PALETTE`).
const BLUE: usize = 0;
const RED: usize = 1;
const GREEN: usize = 2;
const PURPLE: usize = 3;
const ORANGE: usize = 4;
const SKY: usize = 5;
const BLACK: usize = 7;
const GREY: usize = 8;

/// Score classes: (upper bound of score / best score, colour, label).
const CLASSES: [(f64, usize, &str); 5] = [
    (1.25, BLUE, "within 1.25× of the best"),
    (2.0, SKY, "1.25-2×"),
    (4.0, GREEN, "2-4×"),
    (10.0, ORANGE, "4-10×"),
    (f64::INFINITY, RED, "more than 10× the best"),
];

const VIEWS: [(&str, usize, usize); 3] = [
    ("top (x-y)", 0, 1),
    ("front (x-z)", 0, 2),
    ("side (y-z)", 1, 2),
];
const AXIS: [&str; 3] = ["x", "y", "z"];

fn project(points: &[[f64; 3]], v: (usize, usize)) -> Vec<(f64, f64)> {
    points.iter().map(|p| (p[v.0], p[v.1])).collect()
}

/// A ring around a point in a view's plane (mm): marks a winner over its dot.
fn ring(c: &[f64; 3], r: f64, v: (usize, usize)) -> Vec<(f64, f64)> {
    let mut pts: Vec<(f64, f64)> = (0..=24)
        .map(|k| {
            let a = k as f64 / 24.0 * std::f64::consts::TAU;
            (c[v.0] + r * a.cos(), c[v.1] + r * a.sin())
        })
        .collect();
    pts.push((f64::NAN, f64::NAN));
    pts
}

pub fn page(robot: &Robot, rep: &Report, show: usize) -> Result<Page, ReportError> {
    let fig = candidates_figure(robot, rep);
    let rows: Vec<Vec<String>> = shown(rep, show)
        .into_iter()
        .map(|i| row(&rep.candidates[i]))
        .collect();
    let s = &rep.settings;
    let facts = facts(rep);
    let mut sections = vec![Section {
        heading: "Candidate positions".into(),
        blocks: vec![
            Block::figure(
                "fig-candidates",
                "Candidate fixture positions around the robot (at q = 0), coloured by their score relative to the best; grey: not usable (no room, out of reach, no valid pose). Rings: the winner(s); black: the cell's fixture.",
                &fig,
            )?,
            Block::text(format!(
                "Scores \"by compile\" come from a compile at the position (step {}°, at most {} candidates) and the prediction from its recording; \"by proxy\" from the proxy (step {}°, {} poses, one reading per selected pose) times {}, the median compile/proxy ratio. \"admitted\" is the number of poses the bar admits there at the proxy grid.",
                fmt_fixed(s.full.step_deg[0], 0),
                s.full.max_candidates,
                fmt_fixed(s.proxy.step_deg[0], 0),
                s.proxy.poses,
                fmt_fixed(s.proxy.scale, 3)
            )),
        ],
    }];
    let mut head: Vec<&str> = ROW_HEAD.to_vec();
    head[9] = "note";
    sections.push(Section {
        heading: "Ranking".into(),
        blocks: vec![Block::table(&head, rows)],
    });
    if let Some(c) = &rep.campaign {
        let rows = c
            .members
            .iter()
            .zip(&c.fixtures_mm)
            .enumerate()
            .map(|(k, (&i, f))| {
                let m = &rep.candidates[i];
                vec![
                    (k + 1).to_string(),
                    format!(
                        "{}, {}, {}",
                        fmt_fixed(f[0], 1),
                        fmt_fixed(f[1], 1),
                        fmt_fixed(f[2], 1)
                    ),
                    m.rank.map_or_else(|| "-".into(), |r| r.to_string()),
                    m.score_um.map_or_else(|| "-".into(), um),
                ]
            })
            .collect();
        sections.push(Section {
            heading: format!("Campaign of {} fixtures", c.count),
            blocks: vec![
                Block::table(&["run", "fixture [mm]", "rank alone", "alone [µm]"], rows),
                Block::text(format!(
                    "Calibrated together (shared robot parameters, each run's fixture known): {} µm RMS, {} µm p95 over the joint space ({} from the noise, {} from parameters held at their prior); {} parameters determined. Search: {}.",
                    um(c.predicted_um),
                    um(c.predicted_p95_um),
                    um(c.from_noise_um),
                    um(c.from_held_um),
                    c.determined,
                    c.search
                )),
            ],
        });
    }
    Ok(Page {
        title: "edbbgen — fixture placement".into(),
        kind: "place".into(),
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        inputs_sha256: String::new(),
        facts,
        warnings: rep.warnings.clone(),
        sections,
    })
}

/// The candidates in three views around the robot at q = 0, coloured by class; the winners ringed.
fn candidates_figure(robot: &Robot, rep: &Report) -> Figure {
    let best = rep
        .best
        .as_ref()
        .and_then(|b| b.score_um)
        .unwrap_or(f64::NAN);
    // Candidates by class; the unusable ones grey. Drawn worst first, so the best lie on top.
    let mut classes: Vec<Vec<[f64; 3]>> = vec![Vec::new(); CLASSES.len()];
    let mut unusable: Vec<[f64; 3]> = Vec::new();
    for c in &rep.candidates {
        match c.score_um {
            Some(s) => {
                let k = CLASSES
                    .iter()
                    .position(|(hi, _, _)| s <= hi * best)
                    .unwrap_or(CLASSES.len() - 1);
                classes[k].push(c.fixture_mm);
            }
            None => unusable.push(c.fixture_mm),
        }
    }
    let current: Vec<[f64; 3]> = rep.current.iter().map(|c| c.fixture_mm).collect();
    let winners: Vec<[f64; 3]> = match &rep.campaign {
        Some(c) => c.fixtures_mm.clone(),
        None => rep.best.iter().map(|b| b.fixture_mm).collect(),
    };
    // The robot at q = 0 as a stick figure: base, DH frame origins, flange, MAP.
    let frames = chain_frames(&robot.base, &robot.dh, &robot.flange, &[0.0; 6]);
    let map = rep.settings.map_mm;
    let mut chain: Vec<[f64; 3]> = vec![[0.0; 3]];
    chain.extend(
        frames
            .iter()
            .map(|f| [to_mm(f.t.x), to_mm(f.t.y), to_mm(f.t.z)]),
    );
    let tip = frames[7].apply(&nalgebra::Vector3::from(map).map(|v| v * 1e-3));
    chain.push([to_mm(tip.x), to_mm(tip.y), to_mm(tip.z)]);
    let sticks: Vec<[f64; 3]> = chain.windows(2).flat_map(|w| [w[0], w[1]]).collect();
    let span = |a: usize| {
        let r = [rep.region_mm.x, rep.region_mm.y, rep.region_mm.z][a];
        r[1] - r[0]
    };
    let ring_r = 0.03 * (0..3).map(span).fold(0.0, f64::max).max(100.0);

    let panel = |name: &str, v: (usize, usize)| {
        let mut series = vec![Series {
            label: "robot at q = 0".into(),
            points: project(&sticks, v),
            mark: Mark::Segments,
            colour: GREY,
        }];
        // Only the classes that occur: the legend names what is drawn.
        if !unusable.is_empty() {
            series.push(Series::dots("not usable", GREY, project(&unusable, v)));
        }
        for (k, (_, colour, label)) in CLASSES.iter().enumerate().rev() {
            if !classes[k].is_empty() {
                series.push(Series::dots(*label, *colour, project(&classes[k], v)));
            }
        }
        if !current.is_empty() {
            series.push(Series::dots(
                "the cell's fixture",
                BLACK,
                project(&current, v),
            ));
        }
        series.push(Series::line(
            if rep.campaign.is_some() {
                "campaign"
            } else {
                "best"
            },
            PURPLE,
            winners.iter().flat_map(|w| ring(w, ring_r, v)).collect(),
        ));
        Panel {
            title: name.to_string(),
            x_label: format!("{} [mm]", AXIS[v.0]),
            y_label: format!("{} [mm]", AXIS[v.1]),
            series,
            equal_aspect: true,
            legend: Legend::Outside,
            ..Panel::default()
        }
    };
    Figure {
        title: String::new(),
        panels: VIEWS.iter().map(|&(n, a, b)| panel(n, (a, b))).collect(),
        columns: 3,
        panel_px: (330, 330),
    }
}

/// The page's facts: the robot, the grid, what the score is, the best, the cell's fixture and the
/// campaign.
fn facts(rep: &Report) -> Vec<(String, String)> {
    let s = &rep.settings;
    let mut facts = vec![
        ("robot".to_string(), format!("{} [{}]", rep.robot, rep.robot_file)),
        (
            "candidates".into(),
            format!(
                "{} x {} x {} grid over x {}..{}, y {}..{}, z {}..{} mm; {} usable",
                rep.grid[0],
                rep.grid[1],
                rep.grid[2],
                fmt_fixed(rep.region_mm.x[0], 0),
                fmt_fixed(rep.region_mm.x[1], 0),
                fmt_fixed(rep.region_mm.y[0], 0),
                fmt_fixed(rep.region_mm.y[1], 0),
                fmt_fixed(rep.region_mm.z[0], 0),
                fmt_fixed(rep.region_mm.z[1], 0),
                rep.counts.usable
            ),
        ),
        (
            "score".into(),
            format!(
                "predicted MAP position uncertainty after calibration (1σ, RMS over {} joint poses, registered); bar noise {} at {} Hz; prior {} mm / {}°",
                s.workspace_poses,
                length_um(s.bar_noise_um),
                fmt_fixed(s.bar_rate_hz, 0),
                crate::units::fmt_given(s.prior.length_mm),
                crate::units::fmt_given(s.prior.angle_deg)
            ),
        ),
    ];
    if let Some(b) = &rep.best {
        facts.push((
            "best position".into(),
            format!(
                "{}, {}, {} mm: {} µm{}",
                fmt_fixed(b.fixture_mm[0], 1),
                fmt_fixed(b.fixture_mm[1], 1),
                fmt_fixed(b.fixture_mm[2], 1),
                b.score_um.map_or_else(|| "-".into(), um),
                b.ratio
                    .filter(|_| rep.current.as_ref().map(|c| c.index) != Some(b.index))
                    .map_or_else(String::new, |r| format!(
                        ", {}× better than the cell's fixture",
                        fmt_fixed(r, 2)
                    ))
            ),
        ));
    }
    if let Some(c) = &rep.current {
        facts.push((
            "the cell's fixture".into(),
            match c.rank {
                Some(r) => format!(
                    "{} µm, rank {r} of {}",
                    c.score_um.map_or_else(|| "-".into(), um),
                    rep.ranking.len()
                ),
                None => "not usable (see the table)".into(),
            },
        ));
    }
    if let Some(c) = &rep.campaign {
        facts.push((
            format!("campaign of {}", c.count),
            format!(
                "{} µm RMS ({} µm p95): {}× better than the best single position ({} µm; measured {} times: {} µm)",
                um(c.predicted_um),
                um(c.predicted_p95_um),
                fmt_fixed(c.gain_over_best_single, 2),
                um(c.best_single_um),
                c.count,
                um(c.best_single_repeated_um)
            ),
        ));
    }
    facts
}

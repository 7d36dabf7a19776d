//! The placement's report: in = a [`Placement`]; out = the `edbbgen.place/1` JSON structure
//! (mm, µm, deg) and the text summary the CLI prints. The HTML page
//! ([`crate::report::place`]) takes its numbers from the same structure.

use super::{Candidate, Placement, Source, Status, SCHEMA};
use crate::robot::Robot;
use crate::units::{fmt_fixed, fmt_given, length_um, to_deg, to_mm};
use serde::Serialize;

#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub robot: String,
    pub robot_file: String,
    pub region_mm: RegionMm,
    pub grid: [usize; 3],
    pub settings: Settings,
    /// How many positions ended in each status.
    pub counts: Counts,
    /// Every candidate, in candidate order (grid x fastest, then y, z; then `--at`, then the
    /// cell's fixture).
    pub candidates: Vec<CandidateReport>,
    /// Candidate indices of the usable positions, best first.
    pub ranking: Vec<usize>,
    pub best: Option<Ranked>,
    pub current: Option<Ranked>,
    pub campaign: Option<CampaignReport>,
    pub warnings: Vec<String>,
}

#[derive(Clone, Debug, Serialize)]
pub struct RegionMm {
    pub x: [f64; 2],
    pub y: [f64; 2],
    pub z: [f64; 2],
}

#[derive(Clone, Debug, Serialize)]
pub struct Settings {
    pub map_mm: [f64; 3],
    pub bar_mm: [f64; 2],
    pub stand_radius_mm: f64,
    pub bar_noise_um: f64,
    pub bar_rate_hz: f64,
    pub prior: PriorReport,
    pub workspace_poses: usize,
    pub seed: u64,
    pub proxy: ProxySettings,
    pub full: FullSettings,
}

#[derive(Clone, Debug, Serialize)]
pub struct PriorReport {
    pub length_mm: f64,
    pub angle_deg: f64,
    pub kappa: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct ProxySettings {
    pub step_deg: [f64; 6],
    pub poses: usize,
    /// The median ratio full / proxy that puts proxies on the full estimates' scale.
    pub scale: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct FullSettings {
    pub step_deg: [f64; 6],
    pub max_candidates: usize,
    pub top: usize,
}

#[derive(Clone, Debug, Default, Serialize)]
pub struct Counts {
    pub usable: usize,
    pub no_room: usize,
    pub out_of_reach: usize,
    pub no_valid_pose: usize,
    pub too_few_poses: usize,
    pub compile_failed: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct CandidateReport {
    pub index: usize,
    pub fixture_mm: [f64; 3],
    pub source: Source,
    pub grid: Option<[usize; 3]>,
    #[serde(flatten)]
    pub status: Status,
    pub rank: Option<usize>,
    /// The ranking's number (µm) and where it comes from: `compile` or `proxy` (scaled).
    pub score_um: Option<f64>,
    pub estimate: Option<&'static str>,
    pub proxy: Option<super::ProxyScore>,
    pub full: Option<super::FullScore>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Ranked {
    pub index: usize,
    pub fixture_mm: [f64; 3],
    pub rank: Option<usize>,
    pub score_um: Option<f64>,
    /// How many times better the best position's score is than this one's (best: than the
    /// cell's fixture); null without the other.
    pub ratio: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct CampaignReport {
    pub count: usize,
    pub fixtures_mm: Vec<[f64; 3]>,
    pub members: Vec<usize>,
    pub predicted_um: f64,
    pub predicted_p95_um: f64,
    pub from_noise_um: f64,
    pub from_held_um: f64,
    pub determined: usize,
    pub best_single_um: f64,
    pub best_single_repeated_um: f64,
    pub gain_over_best_single: f64,
    pub gain_over_current: Option<f64>,
    pub search: String,
}

fn mm3(v: &nalgebra::Vector3<f64>) -> [f64; 3] {
    [r(to_mm(v.x), 1), r(to_mm(v.y), 1), r(to_mm(v.z), 1)]
}

/// Rounded for the report (stable digits; no "-0").
fn r(v: f64, d: i32) -> f64 {
    if !v.is_finite() {
        return v;
    }
    let s = 10f64.powi(d);
    let x = (v * s).round() / s;
    if x == 0.0 {
        0.0
    } else {
        x
    }
}

/// Significant digits for µm figures that span orders of magnitude.
fn sig(v: f64) -> f64 {
    if !v.is_finite() || v == 0.0 {
        return v;
    }
    let d = 3 - v.abs().log10().floor() as i32;
    r(v, d.clamp(0, 9))
}

fn estimate_of(c: &Candidate) -> Option<&'static str> {
    match (&c.score_um, &c.full) {
        (None, _) => None,
        (Some(_), Some(_)) => Some("compile"),
        (Some(_), None) => Some("proxy"),
    }
}

fn rounded_proxy(p: &super::ProxyScore) -> super::ProxyScore {
    super::ProxyScore {
        cond: r(p.cond, 2),
        predicted_um: sig(p.predicted_um),
        ..p.clone()
    }
}

fn rounded_full(f: &super::FullScore) -> super::FullScore {
    super::FullScore {
        cond: r(f.cond, 2),
        time_s: r(f.time_s, 1),
        compile_predicted_um: sig(f.compile_predicted_um),
        predicted_um: sig(f.predicted_um),
        predicted_p95_um: sig(f.predicted_p95_um),
        from_noise_um: sig(f.from_noise_um),
        from_held_um: sig(f.from_held_um),
        ..f.clone()
    }
}

/// The `edbbgen.place/1` report.
pub fn report(robot: &Robot, p: &Placement) -> Report {
    let o = &p.options;
    let spec = &o.compile.cell;
    let (map, _) = crate::pipeline::resolve_map(robot, spec.map);
    let mut counts = Counts::default();
    for c in &p.candidates {
        match c.status {
            Status::Ok if c.score_um.is_some() => counts.usable += 1,
            Status::Ok => {}
            Status::NoRoom { .. } => counts.no_room += 1,
            Status::OutOfReach => counts.out_of_reach += 1,
            Status::NoValidPose { .. } => counts.no_valid_pose += 1,
            Status::TooFewPoses { .. } => counts.too_few_poses += 1,
            Status::CompileFailed { .. } => counts.compile_failed += 1,
        }
    }
    let candidates = p
        .candidates
        .iter()
        .enumerate()
        .map(|(i, c)| CandidateReport {
            index: i,
            fixture_mm: mm3(&c.fixture),
            source: c.source,
            grid: c.grid,
            status: c.status.clone(),
            rank: c.rank,
            score_um: c.score_um.map(sig),
            estimate: estimate_of(c),
            proxy: c.proxy.as_ref().map(rounded_proxy),
            full: c.full.as_ref().map(rounded_full),
        })
        .collect();
    let score = |i: usize| p.candidates[i].score_um;
    let best_i = p.ranking.first().copied();
    let ratio = |a: Option<f64>, b: Option<f64>| match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => Some(r(a / b, 3)),
        _ => None,
    };
    let ranked = |i: usize, other: Option<usize>| Ranked {
        index: i,
        fixture_mm: mm3(&p.candidates[i].fixture),
        rank: p.candidates[i].rank,
        score_um: score(i).map(sig),
        ratio: match other {
            // best: how much better than the current; current: how much worse than the best.
            Some(o) if Some(i) == best_i => ratio(score(o), score(i)),
            Some(o) => ratio(score(i), score(o)),
            None => None,
        },
    };
    let best = best_i.map(|b| ranked(b, p.current));
    let current = p.current.map(|c| ranked(c, best_i));
    let campaign = p.campaign.as_ref().map(|c| CampaignReport {
        count: c.members.len(),
        fixtures_mm: c
            .members
            .iter()
            .map(|&i| mm3(&p.candidates[i].fixture))
            .collect(),
        members: c.members.clone(),
        predicted_um: sig(c.predicted_um),
        predicted_p95_um: sig(c.predicted_p95_um),
        from_noise_um: sig(c.from_noise_um),
        from_held_um: sig(c.from_held_um),
        determined: c.determined,
        best_single_um: sig(c.best_single_um),
        best_single_repeated_um: sig(c.best_single_repeated_um),
        gain_over_best_single: r(c.best_single_um / c.predicted_um, 3),
        gain_over_current: p.current.and_then(score).map(|s| r(s / c.predicted_um, 3)),
        search: c.search.clone(),
    });
    let deg6 = |s: &[f64; 6]| s.map(|v| r(to_deg(v), 3));
    Report {
        schema: SCHEMA,
        robot: robot.name.clone(),
        robot_file: robot.source.clone(),
        region_mm: RegionMm {
            x: [r(to_mm(p.region.lo.x), 1), r(to_mm(p.region.hi.x), 1)],
            y: [r(to_mm(p.region.lo.y), 1), r(to_mm(p.region.hi.y), 1)],
            z: [r(to_mm(p.region.lo.z), 1), r(to_mm(p.region.hi.z), 1)],
        },
        grid: p.grid,
        settings: Settings {
            map_mm: mm3(&map),
            bar_mm: [r(to_mm(spec.bar_min), 3), r(to_mm(spec.bar_max), 3)],
            stand_radius_mm: r(to_mm(p.stand_radius), 3),
            bar_noise_um: r(o.compile.bar_noise * 1e6, 6),
            bar_rate_hz: o.compile.bar_rate,
            prior: PriorReport {
                length_mm: r(to_mm(o.prior.length), 6),
                angle_deg: r(to_deg(o.prior.angle), 6),
                kappa: o.prior.kappa,
            },
            workspace_poses: crate::pipeline::PREDICTION_POSES,
            seed: o.compile.seed,
            proxy: ProxySettings {
                step_deg: deg6(&o.proxy_step),
                poses: o.proxy_poses,
                scale: r(p.proxy_scale, 4),
            },
            full: FullSettings {
                step_deg: deg6(&o.compile.step),
                max_candidates: o.compile.max_candidates,
                top: o.top,
            },
        },
        counts,
        candidates,
        ranking: p.ranking.clone(),
        best,
        current,
        campaign,
        warnings: p.warnings.clone(),
    }
}

fn f3(v: &[f64; 3]) -> String {
    format!(
        "{}, {}, {}",
        fmt_fixed(v[0], 1),
        fmt_fixed(v[1], 1),
        fmt_fixed(v[2], 1)
    )
}

/// Micrometres for a table cell: three significant digits ([`crate::units::fmt_sig`]).
pub fn um(v: f64) -> String {
    crate::units::fmt_sig(v, 3)
}

/// One row of the ranking table (text and HTML share it): rank, fixture, score, estimate,
/// admitted pool, identifiable, cond, poses, time, source.
pub fn row(c: &CandidateReport) -> Vec<String> {
    let dash = || "-".to_string();
    let full = c.full.as_ref();
    let proxy = c.proxy.as_ref();
    vec![
        c.rank.map_or_else(dash, |r| r.to_string()),
        f3(&c.fixture_mm),
        c.score_um.map_or_else(dash, um),
        c.estimate.unwrap_or("-").to_string(),
        proxy.map_or_else(dash, |p| p.admitted.to_string()),
        full.map(|f| f.identifiable)
            .or(proxy.map(|p| p.identifiable))
            .map_or_else(dash, |n| n.to_string()),
        full.map(|f| f.cond)
            .or(proxy.map(|p| p.cond))
            .map_or_else(dash, |v| fmt_fixed(v, 1)),
        full.map_or_else(dash, |f| f.poses.to_string()),
        full.map_or_else(dash, |f| fmt_fixed(f.time_s, 1)),
        match c.source {
            Source::Grid => String::new(),
            Source::At => "--at".into(),
            Source::Current => "cell's fixture".into(),
        },
    ]
}

pub const ROW_HEAD: [&str; 10] = [
    "rank",
    "fixture [mm]",
    "score [µm]",
    "by",
    "admitted",
    "ident.",
    "cond",
    "poses",
    "time [s]",
    "",
];

/// The rows worth showing: the best `show`, the campaign's members and the cell's fixture.
pub fn shown(rep: &Report, show: usize) -> Vec<usize> {
    let mut out: Vec<usize> = rep.ranking.iter().take(show).copied().collect();
    let extra = rep
        .campaign
        .iter()
        .flat_map(|c| c.members.iter().copied())
        .chain(rep.current.as_ref().map(|c| c.index))
        .chain(
            rep.candidates
                .iter()
                .filter(|c| c.source == Source::At)
                .map(|c| c.index),
        );
    for i in extra {
        if !out.contains(&i) {
            out.push(i);
        }
    }
    out
}

/// The text summary: what was searched, the ranking's head, the cell's fixture, the winner(s).
pub fn text(rep: &Report, show: usize) -> String {
    let s = &rep.settings;
    let mut t = format!(
        "{} [{}]: {} positions on a {} x {} x {} grid over x {}..{}, y {}..{}, z {}..{} mm",
        rep.robot,
        rep.robot_file,
        rep.candidates
            .iter()
            .filter(|c| c.source == Source::Grid)
            .count(),
        rep.grid[0],
        rep.grid[1],
        rep.grid[2],
        fmt_fixed(rep.region_mm.x[0], 0),
        fmt_fixed(rep.region_mm.x[1], 0),
        fmt_fixed(rep.region_mm.y[0], 0),
        fmt_fixed(rep.region_mm.y[1], 0),
        fmt_fixed(rep.region_mm.z[0], 0),
        fmt_fixed(rep.region_mm.z[1], 0),
    );
    let extra = rep.candidates.len()
        - rep
            .candidates
            .iter()
            .filter(|c| c.source == Source::Grid)
            .count();
    if extra > 0 {
        t += &format!(" (+ {extra} given)");
    }
    t += "\n";
    let c = &rep.counts;
    t += &format!(
        "  usable {}; out of reach {}, no room {}, no valid pose {}, too few poses {}, compile failed {}\n",
        c.usable, c.out_of_reach, c.no_room, c.no_valid_pose, c.too_few_poses, c.compile_failed
    );
    t += &format!(
        "  score: predicted MAP position uncertainty after calibrating from a program compiled there (1 sigma, RMS over {} joint poses, after rigid registration; bar noise {} at {} Hz; held parameters at the prior {} mm / {} deg)\n",
        s.workspace_poses,
        length_um(s.bar_noise_um),
        fmt_fixed(s.bar_rate_hz, 0),
        fmt_given(s.prior.length_mm),
        fmt_given(s.prior.angle_deg),
    );
    t += &format!(
        "  by compile: step {} deg, at most {} candidates (the best {} by proxy); by proxy: step {} deg, {} poses, one reading per selected pose, x {} (median compile/proxy)\n\n",
        fmt_fixed(s.full.step_deg[0], 0),
        s.full.max_candidates,
        s.full.top,
        fmt_fixed(s.proxy.step_deg[0], 0),
        s.proxy.poses,
        fmt_fixed(s.proxy.scale, 3),
    );
    let rows: Vec<Vec<String>> = shown(rep, show)
        .into_iter()
        .map(|i| row(&rep.candidates[i]))
        .collect();
    let mut width = [0usize; 10];
    for r in std::iter::once(ROW_HEAD.map(String::from).to_vec()).chain(rows.iter().cloned()) {
        for (k, cell) in r.iter().enumerate() {
            width[k] = width[k].max(cell.chars().count());
        }
    }
    let line = |r: &[String]| -> String {
        let mut l = String::new();
        for (k, cell) in r.iter().enumerate() {
            let pad = width[k] - cell.chars().count();
            // Numbers right-aligned, the fixture and the labels left-aligned.
            if k == 1 || k == 3 || k == 9 {
                l += cell;
                l += &" ".repeat(pad);
            } else {
                l += &" ".repeat(pad);
                l += cell;
            }
            l += "  ";
        }
        l.trim_end().to_string() + "\n"
    };
    t += &line(&ROW_HEAD.map(String::from));
    for r in &rows {
        t += &line(r);
    }
    t += "\n";
    let usable = rep.ranking.len();
    if let Some(b) = &rep.best {
        let is_current = rep.current.as_ref().is_some_and(|c| c.index == b.index);
        t += &format!(
            "best: {}{} mm, {} (rank 1 of {usable})",
            if is_current {
                "the cell's fixture, "
            } else {
                ""
            },
            f3(&b.fixture_mm),
            b.score_um.map_or_else(|| "-".into(), length_um)
        );
        if let (false, Some(cur), Some(ratio)) = (is_current, &rep.current, b.ratio) {
            t += &format!(
                "; {} x better than the cell's fixture ({}, rank {} of {usable})",
                fmt_fixed(ratio, 2),
                cur.score_um.map_or_else(|| "-".into(), length_um),
                cur.rank.map_or_else(|| "-".into(), |r| r.to_string())
            );
        }
        t += "\n";
    }
    if let Some(cur) = &rep.current {
        if cur.rank.is_none() {
            let st = &rep.candidates[cur.index].status;
            t += &format!(
                "the cell's fixture {} mm is not usable: {}\n",
                f3(&cur.fixture_mm),
                super::status_text(st)
            );
        }
    }
    if let Some(c) = &rep.campaign {
        t += &format!(
            "campaign of {} fixtures (one run each, calibrated together: shared robot parameters, each run's fixture known):\n",
            c.count
        );
        for (k, (&i, f)) in c.members.iter().zip(&c.fixtures_mm).enumerate() {
            let m = &rep.candidates[i];
            t += &format!(
                "  {}  {} mm  (rank {}, {} alone)\n",
                k + 1,
                f3(f),
                m.rank.map_or_else(|| "-".into(), |r| r.to_string()),
                m.score_um.map_or_else(|| "-".into(), length_um)
            );
        }
        t += &format!(
            "  together: {} RMS, {} p95 over the joint space; {} x better than the best single fixture ({}; measured {} times: {})",
            length_um(c.predicted_um),
            um(c.predicted_p95_um),
            fmt_fixed(c.gain_over_best_single, 2),
            length_um(c.best_single_um),
            c.count,
            length_um(c.best_single_repeated_um)
        );
        if let Some(g) = c.gain_over_current {
            t += &format!(", {} x better than the cell's fixture", fmt_fixed(g, 2));
        }
        t += "\n";
    }
    t
}

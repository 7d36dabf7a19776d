//! Fixture placement: in = a robot, its cell and candidate fixture positions (a grid
//! over a region, positions the user names, the cell's own fixture); out = every candidate
//! scored by what a calibration from a compile there would buy, the ranking, and the best
//! campaign of K fixtures. No file I/O, no printing.
//!
//! The score of a position is the MAP position uncertainty a calibration from its measurement
//! program would state (RMS over the joint space, 1σ, after a rigid registration), predicted as
//! `calibrate` would make it ([`predict::expected`]): Type A from the bar noise over the
//! parameters the data determine, Type B from the prior of every parameter they do not. A
//! position that leaves a parameter undetermined therefore pays for it, instead of looking good
//! on the few parameters it does see.
//!
//! Cheap first, dear last:
//! 1. **Room** ([`crate::collision::Scene::fixture_room`]): the fixture ball and its stand clear
//!    the cell's obstacles and the robot's base, the ball the floor.
//! 2. **Proxy** ([`proxy`]): the compiler's own sampler at a coarse grid, its collision filter
//!    (on one scene whose fixture is moved, so no mesh is read twice), the identifiability of
//!    the admitted poses, the greedy selection's cond at the knee, and the prediction of one
//!    reading per selected pose. This gives reachability, the admitted pool size and cond(J).
//! 3. **Full estimate** for the best candidates by proxy (and for the cell's fixture and every
//!    `--at` position): literally a compile there ([`pipeline::compile`], coarse options), and
//!    the prediction from its recording (every move with the bar, at the bar's rate).
//!
//! Positions that differ only by a turn about joint 1 score alike when joint 1 turns the whole
//! arm (the program turns with them): the ranking keeps them all, in grid order on ties.
//!
//! A campaign ([`campaign`]) shares the robot's parameters between runs, each run with its own
//! known fixture, so the information of the runs adds up; it is searched greedily and then by
//! exchange, on the proxies over the best candidates, refined on full estimates.

pub mod campaign;
pub mod cellfile;
pub mod proxy;
pub mod report;

use crate::calibrate::predict::{self, Expected, Prior, RunInformation};
use crate::cell::CellSpec;
use crate::model::MeasurementModel;
use crate::pipeline::{self, CompileOptions, PipelineError};
use crate::robot::kinematics::chain_frames;
use crate::robot::Robot;
use crate::sample::Progress;
use crate::units::{fmt_fixed, to_mm, MM};
use nalgebra::Vector3;
use serde::Serialize;

/// The schema of the JSON report (`place --json`).
pub const SCHEMA: &str = "edbbgen.place/1";
/// A fixture stand assumed for placement when the cell models none (mm radius): a fixture
/// needs a support, and a robot that passes through it is no placement.
pub const DEFAULT_STAND_MM: f64 = 40.0;
/// Default grid over the region (x, y, z).
pub const DEFAULT_GRID: [usize; 3] = [10, 10, 5];
/// Candidates fully estimated (a compile each) by default.
pub const DEFAULT_TOP: usize = 6;
/// The proxy's admitted pool (poses). Its joint grid is the full estimate's: on the NJ-130
/// cell the proxy ranks 40 fully estimated positions with a Spearman correlation of 0.84 on
/// the same 20° grid, 0.50 on a 30° grid and 0.77 on a 15° one (the pools differ from the
/// compile's); 240 poses rank as well as 600 and better than 120 (0.80).
pub const DEFAULT_PROXY_POSES: usize = 240;
/// The full estimate's compile options (coarse, as the tests use them).
pub const DEFAULT_FULL_STEP_DEG: f64 = 20.0;
pub const DEFAULT_FULL_CANDIDATES: usize = 600;
/// Joint poses the proxies and the campaign search are judged over (a subset of the
/// prediction's 2,000: every 4th).
pub const SEARCH_POSES_STRIDE: usize = 4;
/// The campaign search looks at this many of the best candidates by single-run score.
pub const CAMPAIGN_POOL: usize = 40;

/// An axis-aligned box in the robot base frame (m).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Region {
    pub lo: Vector3<f64>,
    pub hi: Vector3<f64>,
}

/// Where a candidate comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// The grid over the region.
    Grid,
    /// Named by the user (`--at`).
    At,
    /// The cell's fixture: the one to compare with.
    Current,
}

#[derive(Clone, Debug)]
pub struct PlaceOptions {
    pub region: Region,
    /// Grid points per axis (x, y, z); 1 = the middle of the range.
    pub grid: [usize; 3],
    /// Positions scored besides the grid (m).
    pub at: Vec<Vector3<f64>>,
    /// The cell's fixture, if it has one: scored, fully estimated, its rank reported.
    pub current: Option<Vector3<f64>>,
    /// Fixture positions in the campaign (1 = a single placement).
    pub count: usize,
    /// Candidates fully estimated (a compile each), by proxy score.
    pub top: usize,
    pub proxy_step: [f64; 6],
    pub proxy_poses: usize,
    /// The full estimate's compile options (their fixture is replaced per candidate; their cell
    /// is the placement's, stand included).
    pub compile: CompileOptions,
    pub prior: Prior,
}

impl PlaceOptions {
    /// The defaults for a robot in a cell (resolved spec, SI), over `region`.
    pub fn new(spec: CellSpec, region: Region) -> Self {
        let mut compile = CompileOptions::new(Vector3::zeros());
        compile.cell = spec;
        compile.step = [DEFAULT_FULL_STEP_DEG.to_radians(); 6];
        compile.max_candidates = DEFAULT_FULL_CANDIDATES;
        PlaceOptions {
            region,
            grid: DEFAULT_GRID,
            at: Vec::new(),
            current: None,
            count: 1,
            top: DEFAULT_TOP,
            proxy_step: [DEFAULT_FULL_STEP_DEG.to_radians(); 6],
            proxy_poses: DEFAULT_PROXY_POSES,
            compile,
            prior: Prior::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PlaceError {
    #[error("--region {region}: no position in it can be measured from: {why}")]
    OutOfReach { region: String, why: String },
    #[error("no room for the fixture: each of the {n} positions in --region {region} collides with the cell (most often {what}); give a region clear of the obstacles, or fewer obstacles")]
    NoRoom {
        n: usize,
        region: String,
        what: String,
    },
    #[error("--region {region}: none of its {n} positions gives a measurement program ({why})")]
    Nothing {
        n: usize,
        region: String,
        why: String,
    },
    #[error("--count {count}: only {usable} usable positions to choose from (widen --region or refine --grid)")]
    Count { count: usize, usable: usize },
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
}

/// Why a candidate cannot be used, or that it can.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum Status {
    Ok,
    /// The ball or its stand collides with `with` (or the ball sits on the floor).
    NoRoom {
        with: String,
    },
    /// No joint pose brings the MAP within the bar's range of it above the floor.
    OutOfReach,
    /// Poses reach it, but every one breaks a cone, the harness or a collision: the counts.
    NoValidPose {
        why: String,
    },
    /// Too few admitted poses at the proxy grid to identify anything.
    TooFewPoses {
        admitted: usize,
    },
    /// The compile there failed (the full estimate): its message.
    CompileFailed {
        why: String,
    },
}

/// The proxy's findings (see [`proxy`]).
#[derive(Clone, Debug, Serialize)]
pub struct ProxyScore {
    /// Admitted poses at the proxy grid (valid poses × the collision pass rate of a uniform
    /// subset): how much room the bar has there.
    pub admitted: usize,
    pub identifiable: usize,
    /// Poses the greedy selection keeps (the knee) and its cond (scaled Jacobian, Fig. 5).
    pub selected: usize,
    pub cond: f64,
    /// Predicted MAP position uncertainty from one reading per selected pose (µm, workspace
    /// RMS): comparable between candidates, not with a program's.
    pub predicted_um: f64,
    pub determined: usize,
}

/// The full estimate: a compile at the candidate and what its recording buys.
#[derive(Clone, Debug, Serialize)]
pub struct FullScore {
    pub poses: usize,
    pub supports: usize,
    pub sections: usize,
    pub identifiable: usize,
    pub cond: f64,
    pub time_s: f64,
    /// The compile's pool (at most its max_candidates) and its valid poses before collisions.
    pub pool: usize,
    pub valid_before_collisions: u64,
    /// What the compiler itself prints (Type A over its identifiable parameters, µm).
    pub compile_predicted_um: f64,
    /// As calibrate would state it (Type A + B, µm): RMS and p95 over the joint space, and
    /// the two components (RMS).
    pub predicted_um: f64,
    pub predicted_p95_um: f64,
    pub from_noise_um: f64,
    pub from_held_um: f64,
    pub determined: usize,
    /// Parameters held at nominal that cost accuracy (not an exact dependency), dearest first.
    pub weak: Vec<Weak>,
}

/// One candidate position and everything known about it.
#[derive(Clone, Debug)]
pub struct Candidate {
    pub fixture: Vector3<f64>,
    pub source: Source,
    /// Grid indices (x, y, z) for grid candidates.
    pub grid: Option<[usize; 3]>,
    pub status: Status,
    pub proxy: Option<ProxyScore>,
    pub full: Option<FullScore>,
    /// The runs' information, for campaigns: the proxy's and the compile's.
    pub proxy_info: Option<RunInformation>,
    pub full_info: Option<RunInformation>,
    /// The number the ranking uses (µm): the full estimate where there is one, else the proxy
    /// scaled by the median full/proxy ratio of the fully estimated candidates.
    pub score_um: Option<f64>,
    pub rank: Option<usize>,
}

impl Candidate {
    fn new(fixture: Vector3<f64>, source: Source, grid: Option<[usize; 3]>) -> Self {
        Candidate {
            fixture,
            source,
            grid,
            status: Status::Ok,
            proxy: None,
            full: None,
            proxy_info: None,
            full_info: None,
            score_um: None,
            rank: None,
        }
    }
}

/// The best campaign of K fixtures.
#[derive(Clone, Debug, Serialize)]
pub struct Campaign {
    /// Candidate indices of the K fixtures, best single first.
    pub members: Vec<usize>,
    /// Predicted workspace uncertainty of a calibration over all K runs (µm): RMS, p95, and
    /// the two components.
    pub predicted_um: f64,
    pub predicted_p95_um: f64,
    pub from_noise_um: f64,
    pub from_held_um: f64,
    pub determined: usize,
    /// The best single fixture's full estimate (µm), and the best single fixture measured K
    /// times (the same information K-fold: its uncertainty / √K when nothing is held).
    pub best_single_um: f64,
    pub best_single_repeated_um: f64,
    /// How the search went: proxy evaluations, exchange swaps, full-estimate swaps.
    pub search: String,
}

/// The result of a placement search.
#[derive(Clone, Debug)]
pub struct Placement {
    pub region: Region,
    pub grid: [usize; 3],
    pub candidates: Vec<Candidate>,
    /// Candidate indices of the usable positions, best first.
    pub ranking: Vec<usize>,
    /// The index of the cell's fixture among the candidates.
    pub current: Option<usize>,
    pub campaign: Option<Campaign>,
    /// The factor that puts proxies on the full estimates' scale (median of full / proxy).
    pub proxy_scale: f64,
    pub stand_radius: f64,
    pub warnings: Vec<String>,
    pub options: PlaceOptions,
}

impl Placement {
    /// The winners: the campaign's fixtures, or the best single one.
    pub fn winners(&self) -> Vec<usize> {
        match &self.campaign {
            Some(c) => c.members.clone(),
            None => self.ranking.first().copied().into_iter().collect(),
        }
    }
}

fn mm_text(v: &Vector3<f64>) -> String {
    format!(
        "{}, {}, {}",
        fmt_fixed(to_mm(v.x), 1),
        fmt_fixed(to_mm(v.y), 1),
        fmt_fixed(to_mm(v.z), 1)
    )
}

/// The region as the flag writes it (mm).
pub fn region_text(r: &Region) -> String {
    let f = |a: f64, b: f64| format!("{}..{}", fmt_fixed(to_mm(a), 0), fmt_fixed(to_mm(b), 0));
    format!(
        "{},{},{}",
        f(r.lo.x, r.hi.x),
        f(r.lo.y, r.hi.y),
        f(r.lo.z, r.hi.z)
    )
}

/// A position in mm rounded to 0.1 mm, then to metres the way the cell file is read: a
/// position written to a cell file with one decimal reads back as exactly this value.
pub fn rounded(p_mm: [f64; 3]) -> Vector3<f64> {
    let r = |v: f64| (v * 10.0).round() / 10.0;
    Vector3::new(r(p_mm[0]), r(p_mm[1]), r(p_mm[2])) * MM
}

/// The default region: the volume in front of the robot from which the bar can reach its MAP,
/// above the floor. "In front" is the half-space on the side of the MAP at q = 0 of the plane
/// through joint 1's axis (for an arm whose joint 1 turns it fully, the back half repeats the
/// front). Its extent is the MAP's reach over random joint poses (the limits) plus the bar's
/// maximum length; its bottom leaves the ball and the safety margin above the floor.
pub fn default_region(robot: &Robot, map: &Vector3<f64>, spec: &CellSpec, seed: u64) -> Region {
    let model = MeasurementModel::new(robot, Vector3::zeros(), *map);
    let home = chain_frames(&robot.base, &robot.dh, &robot.flange, &[0.0; 6]);
    let (o, z) = (home[0].t, home[0].r.column(2).into_owned());
    let radial = |p: &Vector3<f64>| {
        let r = p - o;
        r - z * z.dot(&r)
    };
    let front = radial(&model.map_position(&model.nominal, &[0.0; 6]));
    let pts: Vec<Vector3<f64>> = predict::workspace(robot, 4000, seed)
        .iter()
        .map(|q| model.map_position(&model.nominal, q))
        .collect();
    let reach = pts.iter().map(|p| radial(p).norm()).fold(0.0, f64::max) + spec.bar_max;
    let top = pts.iter().map(|p| p.z).fold(f64::NEG_INFINITY, f64::max) + spec.bar_max;
    let bottom = spec.floor_z + 0.5 * spec.ball + spec.margin;
    let mut lo = Vector3::new(o.x - reach, o.y - reach, bottom);
    let mut hi = Vector3::new(o.x + reach, o.y + reach, top.max(bottom));
    // The front half along the horizontal axis closest to the front direction.
    let k = if front.x.abs() >= front.y.abs() { 0 } else { 1 };
    if front[k] >= 0.0 {
        lo[k] = o[k];
    } else {
        hi[k] = o[k];
    }
    // To 10 mm, outwards, except the bottom: upwards, to keep the floor clearance.
    let down = |v: f64| (to_mm(v) / 10.0).floor() * 10.0 * MM;
    let up = |v: f64| (to_mm(v) / 10.0).ceil() * 10.0 * MM;
    Region {
        lo: Vector3::new(down(lo.x), down(lo.y), up(lo.z)),
        hi: hi.map(up),
    }
}

/// The grid over the region: `n` points per axis including both ends (one point: the middle),
/// x fastest, then y, then z; each rounded to 0.1 mm.
pub fn grid_points(region: &Region, n: [usize; 3]) -> Vec<([usize; 3], Vector3<f64>)> {
    let at = |a: usize, i: usize| -> f64 {
        let (lo, hi) = (to_mm(region.lo[a]), to_mm(region.hi[a]));
        if n[a] <= 1 {
            0.5 * (lo + hi)
        } else {
            lo + (hi - lo) * i as f64 / (n[a] - 1) as f64
        }
    };
    let mut out = Vec::with_capacity(n[0] * n[1] * n[2]);
    for k in 0..n[2] {
        for j in 0..n[1] {
            for i in 0..n[0] {
                out.push(([i, j, k], rounded([at(0, i), at(1, j), at(2, k)])));
            }
        }
    }
    out
}

/// The placement's cell: the user's, with the fixture stand `stand` (m; 0 = none: the fixture
/// hangs, or sits on something the cell models) or, without it, the cell's stand, or
/// [`DEFAULT_STAND_MM`] where the cell models none. Returns the note that says so when a stand
/// was assumed.
pub fn placement_spec(spec: &CellSpec, stand: Option<f64>) -> (CellSpec, Option<String>) {
    let mut s = spec.clone();
    if let Some(r) = stand {
        s.stand_radius = r;
        return (s, None);
    }
    if s.stand_radius > 0.0 {
        return (s, None);
    }
    s.stand_radius = DEFAULT_STAND_MM * MM;
    (
        s,
        Some(format!(
            "the cell models no fixture stand: positions keep room for a stand of {} mm radius from the floor to the ball (--stand 0 for a fixture without one), and the cell files written for them declare it ([fixture] stand_radius)",
            fmt_fixed(DEFAULT_STAND_MM, 0)
        )),
    )
}

/// Scores every candidate and ranks them; with `count` > 1 also finds the best campaign.
/// `opts.compile.cell` must be the placement's spec ([`placement_spec`]).
pub fn run(
    robot: &Robot,
    opts: &PlaceOptions,
    progress: &dyn Progress,
) -> Result<Placement, PlaceError> {
    let spec = &opts.compile.cell;
    let (map, _) = pipeline::resolve_map(robot, spec.map);
    let mut cands: Vec<Candidate> = grid_points(&opts.region, opts.grid)
        .into_iter()
        .map(|(g, p)| Candidate::new(p, Source::Grid, Some(g)))
        .collect();
    let n_grid = cands.len();
    cands.extend(opts.at.iter().map(|p| Candidate::new(*p, Source::At, None)));
    let current = opts.current.map(|p| {
        cands.push(Candidate::new(p, Source::Current, None));
        cands.len() - 1
    });
    // The workspace the predictions are stated over (as the compiler's), and the subset the
    // proxies and the search use.
    let space = predict::workspace(robot, pipeline::PREDICTION_POSES, opts.compile.seed);
    let search: Vec<[f64; 6]> = space.iter().step_by(SEARCH_POSES_STRIDE).copied().collect();

    progress.start(cands.len() as u64 + opts.top as u64);
    let positions: Vec<Vector3<f64>> = cands.iter().map(|c| c.fixture).collect();
    let ctx = proxy::Context::new(robot, spec, &map, &positions, opts)?;
    proxy::score_all(&ctx, &mut cands, &search, progress);
    let grid_status: Vec<&Status> = cands[..n_grid].iter().map(|c| &c.status).collect();
    check_region(
        opts,
        &grid_status,
        cands.iter().any(|c| c.status == Status::Ok),
    )?;

    // Full estimates: the best by proxy until `top` of them compile, plus the cell's fixture
    // and the user's positions.
    let mut by_proxy: Vec<usize> = (0..cands.len())
        .filter(|&i| cands[i].proxy.is_some() && cands[i].status == Status::Ok)
        .collect();
    by_proxy.sort_by(|&a, &b| {
        proxy_um(&cands[a])
            .total_cmp(&proxy_um(&cands[b]))
            .then(a.cmp(&b))
    });
    let mut warnings = Vec::new();
    let mut done = 0;
    for &i in &by_proxy {
        if done >= opts.top {
            break;
        }
        if full_estimate(robot, opts, &space, &mut cands[i]) {
            done += 1;
        }
        progress.inc(1);
    }
    for i in 0..cands.len() {
        if cands[i].source != Source::Grid
            && cands[i].status == Status::Ok
            && cands[i].full.is_none()
        {
            full_estimate(robot, opts, &space, &mut cands[i]);
        }
    }
    let mut proxy_scale = scale_proxies(&mut cands);
    let mut ranking = rank(&mut cands);
    // The winner is always stated from a compile: a proxy-ranked first place is compiled
    // and everything ranked again.
    while let Some(&first) = ranking.first() {
        if cands[first].full.is_some() {
            break;
        }
        full_estimate(robot, opts, &space, &mut cands[first]);
        proxy_scale = scale_proxies(&mut cands);
        ranking = rank(&mut cands);
    }
    if ranking.is_empty() {
        return Err(PlaceError::Nothing {
            n: cands.len(),
            region: region_text(&opts.region),
            why: "every compile failed".into(),
        });
    }

    let campaign = if opts.count > 1 {
        Some(campaign::search(
            robot,
            opts,
            &space,
            &search,
            &mut cands,
            &ranking,
            proxy_scale,
            progress,
        )?)
    } else {
        None
    };
    progress.finish();
    if let Some(c) = current {
        if cands[c].status != Status::Ok {
            warnings.push(format!(
                "the cell's fixture ({} mm) cannot be used: {}",
                mm_text(&cands[c].fixture),
                status_text(&cands[c].status)
            ));
        }
    }
    Ok(Placement {
        region: opts.region,
        grid: opts.grid,
        candidates: cands,
        ranking,
        current,
        campaign,
        proxy_scale,
        stand_radius: spec.stand_radius,
        warnings,
        options: opts.clone(),
    })
}

fn proxy_um(c: &Candidate) -> f64 {
    c.proxy.as_ref().map_or(f64::INFINITY, |p| p.predicted_um)
}

/// A status in words (for messages and the text output).
pub fn status_text(s: &Status) -> String {
    match s {
        Status::Ok => "ok".into(),
        Status::NoRoom { with } => format!("no room: {with}"),
        Status::OutOfReach => "out of reach".into(),
        Status::NoValidPose { why } => format!("no valid pose ({why})"),
        Status::TooFewPoses { admitted } => format!("only {admitted} admitted poses"),
        Status::CompileFailed { why } => format!("compile failed: {why}"),
    }
}

/// Bad input: a region where nothing can be measured from is refused with the reason.
fn check_region(opts: &PlaceOptions, grid: &[&Status], any_ok: bool) -> Result<(), PlaceError> {
    if any_ok || grid.is_empty() {
        return Ok(());
    }
    let region = region_text(&opts.region);
    let n = grid.len();
    let no_room = grid
        .iter()
        .filter(|s| matches!(s, Status::NoRoom { .. }))
        .count();
    if no_room == n {
        // The obstacle named most often.
        let mut names: Vec<&str> = grid
            .iter()
            .filter_map(|s| match s {
                Status::NoRoom { with } => Some(with.as_str()),
                _ => None,
            })
            .collect();
        names.sort_unstable();
        let mut best = ("", 0);
        for g in names.chunk_by(|a, b| a == b) {
            if g.len() > best.1 {
                best = (g[0], g.len());
            }
        }
        return Err(PlaceError::NoRoom {
            n,
            region,
            what: best.0.to_string(),
        });
    }
    let out = grid
        .iter()
        .filter(|s| matches!(s, Status::OutOfReach))
        .count();
    if out + no_room == n {
        return Err(PlaceError::OutOfReach {
            region,
            why: format!(
                "{out} of its {n} positions are out of the bar's reach from any joint pose{}",
                if no_room > 0 {
                    format!(", {no_room} collide with the cell")
                } else {
                    String::new()
                }
            ),
        });
    }
    let mut why: Vec<String> = Vec::new();
    for s in grid {
        let t = match s {
            Status::NoValidPose { .. } => "no valid pose",
            Status::TooFewPoses { .. } => "too few admitted poses",
            Status::OutOfReach => "out of reach",
            Status::NoRoom { .. } => "no room",
            _ => continue,
        };
        if !why.iter().any(|w| w.starts_with(t)) {
            why.push(t.to_string());
        }
    }
    Err(PlaceError::Nothing {
        n,
        region,
        why: why.join(", "),
    })
}

/// Compiles at the candidate and predicts what its recording buys; false if the compile fails
/// (the candidate is then marked, not ranked).
fn full_estimate(
    robot: &Robot,
    opts: &PlaceOptions,
    space: &[[f64; 6]],
    c: &mut Candidate,
) -> bool {
    let copts = CompileOptions {
        fixture: c.fixture,
        ..opts.compile.clone()
    };
    let template = crate::emit::dialect("ngc").unwrap_or_default();
    let out = match pipeline::compile(robot, &copts, template, &crate::sample::NoProgress) {
        Ok(o) => o,
        Err(e) => {
            c.status = Status::CompileFailed { why: e.to_string() };
            return false;
        }
    };
    let segments = pipeline::recorded_segments(&out.path, &out.plan);
    let info = predict::recording_information(&out.model, &segments, opts.compile.bar_rate);
    let e = predict::expected(
        &out.model,
        &[&info],
        opts.compile.bar_noise,
        &opts.prior,
        space,
    );
    let h = &out.program.header;
    c.full = Some(FullScore {
        poses: h.poses,
        supports: h.supports,
        sections: h.sections,
        identifiable: h.identifiable,
        cond: h.cond,
        time_s: h.time_s,
        pool: out.pool.candidates.len(),
        valid_before_collisions: out.report.valid_before_collisions,
        compile_predicted_um: h.predicted_std_um,
        ..summary(&out.model, &e)
    });
    c.full_info = Some(info);
    true
}

/// The prediction's numbers as a [`FullScore`] (the compile's own fields left empty).
fn summary(model: &MeasurementModel, e: &Expected) -> FullScore {
    let um = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| x * 1e6).collect() };
    let total = predict::spread(&um(&e.combined));
    FullScore {
        poses: 0,
        supports: 0,
        sections: 0,
        identifiable: e.identifiable.len(),
        cond: f64::NAN,
        time_s: 0.0,
        pool: 0,
        valid_before_collisions: 0,
        compile_predicted_um: f64::NAN,
        predicted_um: total.rms,
        predicted_p95_um: total.p95,
        from_noise_um: predict::spread(&um(&e.from_noise)).rms,
        from_held_um: predict::spread(&um(&e.from_held)).rms,
        determined: e.determined.len(),
        weak: weak_names(model, e),
    }
}

/// The held parameters that cost accuracy (more than 1 % of the total, or 1 nm), dearest
/// first, with what each costs alone (µm): exact dependencies (d3 on d2) cost nothing.
fn weak_names(_model: &MeasurementModel, e: &Expected) -> Vec<Weak> {
    let total = predict::spread(&e.combined).rms;
    let mut w: Vec<Weak> = e
        .held
        .iter()
        .zip(&e.held_cost)
        .filter(|(_, &c)| c > (0.01 * total).max(1e-9))
        .map(|(&p, &c)| Weak {
            param: crate::model::PARAM_NAMES[p].to_string(),
            cost_um: (c * 1e6 * 1e4).round() / 1e4,
        })
        .collect();
    w.sort_by(|a, b| b.cost_um.total_cmp(&a.cost_um).then(a.param.cmp(&b.param)));
    w
}

/// A parameter held at nominal and what it costs alone (its prior through the fit, µm).
#[derive(Clone, Debug, Serialize)]
pub struct Weak {
    pub param: String,
    pub cost_um: f64,
}

/// Puts every proxy score on the full estimates' scale: the median ratio full / proxy over the
/// candidates that have both. Returns the factor (1 when no candidate has both).
fn scale_proxies(cands: &mut [Candidate]) -> f64 {
    let mut ratios: Vec<f64> = cands
        .iter()
        .filter_map(|c| match (&c.full, &c.proxy) {
            (Some(f), Some(p)) if p.predicted_um > 0.0 && f.predicted_um.is_finite() => {
                Some(f.predicted_um / p.predicted_um)
            }
            _ => None,
        })
        .collect();
    ratios.sort_by(f64::total_cmp);
    let scale = if ratios.is_empty() {
        1.0
    } else {
        let m = ratios.len();
        if m % 2 == 1 {
            ratios[m / 2]
        } else {
            0.5 * (ratios[m / 2 - 1] + ratios[m / 2])
        }
    };
    for c in cands.iter_mut() {
        c.score_um = match (&c.status, &c.full, &c.proxy) {
            (Status::Ok, Some(f), _) => Some(f.predicted_um),
            (Status::Ok, None, Some(p)) => Some(p.predicted_um * scale),
            _ => None,
        };
    }
    scale
}

/// Ranks the usable candidates by score (ties: candidate order); returns them best first.
fn rank(cands: &mut [Candidate]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..cands.len())
        .filter(|&i| cands[i].score_um.is_some())
        .collect();
    order.sort_by(|&a, &b| {
        cands[a]
            .score_um
            .unwrap_or(f64::INFINITY)
            .total_cmp(&cands[b].score_um.unwrap_or(f64::INFINITY))
            .then(a.cmp(&b))
    });
    for (r, &i) in order.iter().enumerate() {
        cands[i].rank = Some(r + 1);
    }
    order
}

//! The fast proxy of a fixture position: in = one candidate, the cell, a moved copy of one
//! collision scene; out = its status (room, reach, valid poses), the admitted pool size at a
//! coarse joint grid, the identifiable parameters, cond at the knee of the greedy selection
//! and the prediction from one reading per selected pose. The compiler's own stages do the
//! work ([`crate::sample::run`], [`crate::pipeline::collision_filter`], [`crate::model::analyse`],
//! [`crate::select::run`], [`crate::calibrate::predict::expected`]); nothing here is a copy of
//! them, only a coarser configuration.

use super::{Candidate, PlaceError, PlaceOptions, ProxyScore, Status};
use crate::calibrate::predict::{self, Prior, RunInformation};
use crate::cell::CellSpec;
use crate::collision::Scene;
use crate::ir::{Pool, Reason};
use crate::model::{self, IdentifyOptions, MeasurementModel, N_PARAMS};
use crate::pipeline::{self, RESERVOIR_FACTOR};
use crate::robot::kinematics::chain_frames;
use crate::robot::{Frame, Robot};
use crate::safety::Checker;
use crate::sample::{self, NoProgress, Progress, SampleConfig};
use crate::select::{self, SelectConfig};
use nalgebra::Vector3;
use rayon::prelude::*;

/// What every candidate shares: the robot, the cell, one collision scene (moved per
/// candidate) and the sampling configuration.
pub struct Context<'a> {
    robot: &'a Robot,
    spec: &'a CellSpec,
    map: Vector3<f64>,
    /// Built once, at the first candidate whose ball has room for a stand above the floor;
    /// None when none has.
    scene: Option<Scene>,
    home: [Frame; 8],
    cfg: SampleConfig,
    want: usize,
    noise: f64,
    prior: Prior,
}

impl<'a> Context<'a> {
    /// Checks the cell once (joint margin, bar, balls) and builds the scene.
    pub fn new(
        robot: &'a Robot,
        spec: &'a CellSpec,
        map: &Vector3<f64>,
        positions: &[Vector3<f64>],
        opts: &PlaceOptions,
    ) -> Result<Self, PlaceError> {
        // Errors of the cell itself (not of a position) are bad input at once.
        let anywhere = positions.first().copied().unwrap_or_else(Vector3::zeros);
        pipeline::make_cell(robot, anywhere, *map, spec)?;
        let scene = match positions.iter().find(|f| above_floor(spec, f)) {
            Some(f) => Some(pipeline::build_scene(robot, spec, f, map)?.0),
            None => None,
        };
        let model = MeasurementModel::new(robot, anywhere, *map);
        Ok(Context {
            robot,
            spec,
            map: *map,
            scene,
            home: chain_frames(&robot.base, &robot.dh, &robot.flange, &[0.0; 6]),
            cfg: SampleConfig {
                step: opts.proxy_step,
                max_candidates: opts.proxy_poses.saturating_mul(RESERVOIR_FACTOR),
                seed: opts.compile.seed,
                movable: model::movable_joints(&model, robot),
            },
            want: opts.proxy_poses,
            noise: opts.compile.bar_noise,
            prior: opts.prior,
        })
    }
}

/// The ball clears the floor by the margin, so a stand has height.
fn above_floor(spec: &CellSpec, f: &Vector3<f64>) -> bool {
    f.z - 0.5 * spec.ball - spec.floor_z >= spec.margin
}

/// Scores every candidate (in parallel; each result depends on its candidate alone, so the
/// output is the same on any thread count).
pub fn score_all(
    ctx: &Context,
    cands: &mut [Candidate],
    search: &[[f64; 6]],
    progress: &dyn Progress,
) {
    let results: Vec<(Status, Option<(ProxyScore, RunInformation)>)> = cands
        .par_iter()
        .map(|c| {
            let r = score(ctx, &c.fixture, search);
            progress.inc(1);
            r
        })
        .collect();
    for (c, (status, found)) in cands.iter_mut().zip(results) {
        c.status = status;
        if let Some((p, info)) = found {
            c.proxy = Some(p);
            c.proxy_info = Some(info);
        }
    }
}

/// What the proxy stages found at one position.
pub struct Found {
    pub model: MeasurementModel,
    /// Jacobian rows of the admitted poses (the proxy's pool).
    pub rows: Vec<[f64; N_PARAMS]>,
    pub admitted: usize,
    pub identifiable: usize,
    /// Indices into `rows` of the greedy selection (the knee) and its cond.
    pub selected: Vec<usize>,
    pub cond: f64,
}

/// Room, reach, the admitted pool at the proxy grid, identifiability and the greedy
/// selection at one fixture position; or why the position cannot be used.
pub fn evaluate(ctx: &Context, fixture: &Vector3<f64>) -> Result<Found, Status> {
    let spec = ctx.spec;
    let no_room = |with: &str| Status::NoRoom {
        with: with.to_string(),
    };
    if !above_floor(spec, fixture) {
        return Err(no_room("floor"));
    }
    let Some(base) = &ctx.scene else {
        return Err(no_room("floor"));
    };
    let Ok(scene) = base.with_fixture(spec, fixture) else {
        return Err(no_room("floor"));
    };
    if let Some(c) = scene.fixture_room(&ctx.home, spec.margin) {
        return Err(no_room(&c.b));
    }
    let Ok(cell) = pipeline::make_cell(ctx.robot, *fixture, ctx.map, spec) else {
        return Err(Status::NoValidPose {
            why: "the cell is invalid".into(),
        });
    };
    let model = MeasurementModel::new(ctx.robot, *fixture, ctx.map);
    let (sampled, rep) = sample::run(
        ctx.robot,
        &model,
        &pipeline::inset_cell(&cell),
        &ctx.cfg,
        &NoProgress,
    );
    if rep.valid == 0 {
        let reach_only = rep
            .rejected
            .keys()
            .all(|r| matches!(r, Reason::BarLength | Reason::Floor));
        if reach_only {
            return Err(Status::OutOfReach);
        }
        let why: Vec<String> = rep
            .rejected
            .iter()
            .map(|(r, n)| format!("{} {n}", r.name()))
            .collect();
        return Err(Status::NoValidPose {
            why: why.join(", "),
        });
    }
    let ck = Checker::new(ctx.robot, &model, &cell, &scene, spec.margin);
    // The first pose the filter checks, to name what it hits if every pose does.
    let first = sampled.candidates.iter().min_by_key(|c| c.key).map(|c| c.q);
    let (kept, checked, _) = pipeline::collision_filter(&ck, sampled.candidates, ctx.want);
    if kept.is_empty() {
        let example = first
            .and_then(|q| ck.pose(&q).err())
            .map_or_else(String::new, |v| format!(", e.g. {}", v.detail));
        return Err(Status::NoValidPose {
            why: format!("{checked} poses checked, every one collides{example}"),
        });
    }
    // The admitted pool at this grid: the valid poses times the pass rate of the uniform
    // subset that was checked.
    let admitted = (rep.valid as f64 * kept.len() as f64 / checked.max(1) as f64).round() as usize;
    if kept.len() < N_PARAMS {
        return Err(Status::TooFewPoses { admitted });
    }
    let qs: Vec<[f64; 6]> = kept.iter().map(|c| c.q).collect();
    let rows = model.rows(&qs);
    let id = model::analyse(&rows, &IdentifyOptions::default());
    let pool = Pool { candidates: kept };
    let Ok(sel) = select::run(&model, &pool, &id.identifiable, &SelectConfig::default()) else {
        return Err(Status::TooFewPoses { admitted });
    };
    let cond = sel
        .curve
        .iter()
        .find(|c| c.0 == sel.indices.len())
        .map_or(f64::NAN, |c| c.1);
    Ok(Found {
        model,
        rows,
        admitted,
        identifiable: id.count(),
        selected: sel.indices,
        cond,
    })
}

/// The proxy of one fixture position.
pub fn score(
    ctx: &Context,
    fixture: &Vector3<f64>,
    search: &[[f64; 6]],
) -> (Status, Option<(ProxyScore, RunInformation)>) {
    let f = match evaluate(ctx, fixture) {
        Ok(f) => f,
        Err(s) => return (s, None),
    };
    let chosen: Vec<[f64; N_PARAMS]> = f.selected.iter().map(|&i| f.rows[i]).collect();
    let info = predict::readings_information(&chosen);
    let e = predict::expected(&f.model, &[&info], ctx.noise, &ctx.prior, search);
    let um: Vec<f64> = e.combined.iter().map(|v| v * 1e6).collect();
    (
        Status::Ok,
        Some((
            ProxyScore {
                admitted: f.admitted,
                identifiable: f.identifiable,
                selected: f.selected.len(),
                cond: f.cond,
                predicted_um: predict::spread(&um).rms,
                determined: e.determined.len(),
            },
            info,
        )),
    )
}

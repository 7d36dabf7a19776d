//! The one place where stages are chained: in = a loaded robot and resolved options; out =
//! every intermediate result (the IR) plus the program text. No file I/O, no printing.

use crate::emit;
use crate::ir::{Cell, Header, Move, Path, Pool, Program, Selection};
use crate::model::{self, Identifiability, IdentifyOptions, MeasurementModel, N_PARAMS};
use crate::order;
use crate::robot::Robot;
use crate::sample::{self, Progress, SampleConfig, SampleReport};
use crate::select::{self, SelectConfig};
use crate::units::{fmt_fixed, to_deg, to_mm};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// Everything the compiler needs besides the robot, resolved and checked (SI units).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CompileOptions {
    pub fixture: Vector3<f64>,
    /// MAP in the flange frame; None = the robot file's tool, else the flange origin.
    pub tool: Option<Vector3<f64>>,
    pub bar_min: f64,
    pub bar_max: f64,
    pub floor_z: f64,
    pub step: [f64; 6],
    pub max_candidates: usize,
    pub seed: u64,
    pub poses: Option<usize>,
    pub blend: f64,
    /// Diameter of the EDBB's balls: their centres can come no closer than this.
    pub ball: f64,
    /// Start configuration; the tour starts at the selected pose nearest to it (Eq. 7).
    pub start: [f64; 6],
}

pub const DEFAULT_BAR_MM: (f64, f64) = (300.0, 520.0);
pub const DEFAULT_STEP_DEG: f64 = 10.0;
pub const DEFAULT_MAX_CANDIDATES: usize = 3400;
pub const DEFAULT_SEED: u64 = 1;
pub const DEFAULT_BLEND_MM: f64 = 10.0;
/// Ball diameter assumed when none is given (precision ball-bar balls are 12.7–25.4 mm).
pub const DEFAULT_BALL_MM: f64 = 25.0;

/// Millimetres with one decimal, for messages.
fn mm1(v_mm: f64) -> String {
    fmt_fixed(v_mm, 1)
}

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(
        "fixture at ({}, {}, {}) mm is out of reach: the MAP never comes closer than {} mm to it (bar range {}..{} mm)",
        mm1(fixture_mm[0]), mm1(fixture_mm[1]), mm1(fixture_mm[2]), mm1(*closest_mm), mm1(bar_mm[0]), mm1(bar_mm[1])
    )]
    OutOfReach {
        fixture_mm: [f64; 3],
        closest_mm: f64,
        bar_mm: [f64; 2],
    },
    #[error(
        "empty shell: no joint configuration on the grid puts the MAP within {}..{} mm of the fixture and above the floor (widen --bar or refine --step)",
        mm1(bar_mm[0]), mm1(bar_mm[1])
    )]
    EmptyShell { bar_mm: [f64; 2] },
    #[error(
        "empty shell: --bar {}..{} mm lies below {} mm, the closest the centres of two {} mm balls can come",
        mm1(bar_mm[0]), mm1(bar_mm[1]), mm1(*ball_mm), mm1(*ball_mm)
    )]
    BallsOverlap { bar_mm: [f64; 2], ball_mm: f64 },
    #[error(transparent)]
    Select(#[from] select::SelectError),
    #[error(transparent)]
    Order(#[from] order::OrderError),
    #[error("template: {0}")]
    Template(String),
}

impl PipelineError {
    /// The error for a shell no pose reaches: out of reach when even the closest MAP is too far.
    pub fn no_pose(cell: &Cell, closest: f64) -> Self {
        let bar_mm = [to_mm(cell.bar_min), to_mm(cell.bar_max)];
        if closest > cell.bar_max {
            PipelineError::OutOfReach {
                fixture_mm: cell.fixture.map(to_mm).into(),
                closest_mm: to_mm(closest),
                bar_mm,
            }
        } else {
            PipelineError::EmptyShell { bar_mm }
        }
    }
}

/// The MAP the cell uses and the warnings that go with it.
pub fn resolve_map(robot: &Robot, tool: Option<Vector3<f64>>) -> (Vector3<f64>, Vec<String>) {
    let mut warnings = Vec::new();
    let map = match tool.or(robot.tool) {
        Some(t) => t,
        None => {
            warnings.push(
                "no --tool and the robot file declares none: the MAP is the flange origin"
                    .to_string(),
            );
            Vector3::zeros()
        }
    };
    (map, warnings)
}

/// Warnings about the MAP's position relative to the wrist.
pub fn map_warnings(model: &MeasurementModel, id: &Identifiability) -> Vec<String> {
    let mut w = Vec::new();
    let off = model::map_offset_from_joint6_axis(model);
    if off < model::AXIS_TOLERANCE {
        let lost: Vec<&str> = id.names_with(|s| {
            matches!(
                s,
                model::Status::Dependent { .. } | model::Status::Negligible
            )
        });
        w.push(format!(
            "the MAP lies on the flange axis (axis of joint 6): q6 cannot move it, so theta6 is unobservable and fewer parameters are identifiable ({} instead of 22 for a spherical wrist; fixed: {}); use a tool cup off the flange axis",
            id.count(),
            lost.join(", ")
        ));
    } else if off < 0.02 {
        w.push(format!(
            "the MAP is only {} mm off the flange axis: the joint-6 parameters are weakly observable; an offset of 50 mm or more is better",
            fmt_fixed(to_mm(off), 1)
        ));
    }
    w
}

/// A rich pose set for identifiability: random configurations (movable joints only) whose MAP
/// lies in the shell. Returns the Jacobian rows, or the closest approach when none is found.
pub fn rich_rows(
    robot: &Robot,
    model: &MeasurementModel,
    cell: &Cell,
    count: usize,
    seed: u64,
) -> Result<Vec<[f64; N_PARAMS]>, f64> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let movable = model::movable_joints(model, robot);
    let (lo, hi) = robot.limits();
    let mut rows = Vec::with_capacity(count);
    let mut closest = f64::INFINITY;
    for _ in 0..(count * 2000) {
        let q: [f64; 6] = std::array::from_fn(|i| {
            if movable[i] {
                rng.random_range(lo[i]..=hi[i])
            } else {
                0.0f64.clamp(lo[i], hi[i])
            }
        });
        let p = model.map_position(&model.nominal, &q);
        closest = closest.min((p - cell.fixture).norm());
        if cell.admits(&p) {
            let mut row = [0.0; N_PARAMS];
            model.jacobian_row(&model.nominal, &q, &mut row);
            rows.push(row);
            if rows.len() == count {
                return Ok(rows);
            }
        }
    }
    if rows.len() >= N_PARAMS {
        Ok(rows)
    } else {
        Err(closest)
    }
}

/// Every stage's result, for reports and `--emit STAGE`.
#[derive(Clone, Debug, Serialize)]
pub struct Compiled {
    pub cell: Cell,
    pub model: MeasurementModel,
    pub identifiability: Identifiability,
    pub sample: SampleReport,
    pub pool: Pool,
    pub selection: Selection,
    pub path: Path,
    pub program: Program,
    pub text: String,
    pub warnings: Vec<String>,
}

/// load → model → sample → select → order → emit.
/// The cell, with the shell cut to what two balls of the given diameter allow.
pub fn make_cell(
    fixture: Vector3<f64>,
    map: Vector3<f64>,
    bar: (f64, f64),
    floor_z: f64,
    ball: f64,
) -> Result<Cell, PipelineError> {
    if bar.1 <= ball {
        return Err(PipelineError::BallsOverlap {
            bar_mm: [to_mm(bar.0), to_mm(bar.1)],
            ball_mm: to_mm(ball),
        });
    }
    Ok(Cell {
        fixture,
        map,
        bar_min: bar.0.max(ball),
        bar_max: bar.1,
        floor_z,
    })
}

pub fn compile(
    robot: &Robot,
    opts: &CompileOptions,
    template: &str,
    progress: &dyn Progress,
) -> Result<Compiled, PipelineError> {
    let (map, mut warnings) = resolve_map(robot, opts.tool);
    let cell = make_cell(
        opts.fixture,
        map,
        (opts.bar_min, opts.bar_max),
        opts.floor_z,
        opts.ball,
    )?;
    let model = MeasurementModel::new(robot, opts.fixture, map);

    let movable = model::movable_joints(&model, robot);
    let scfg = SampleConfig {
        step: opts.step,
        max_candidates: opts.max_candidates,
        seed: opts.seed,
        movable,
    };
    let (pool, sample) = sample::run(robot, &model, &cell, &scfg, progress);
    if pool.candidates.is_empty() {
        return Err(empty_pool_error(robot, &model, &cell, opts.seed));
    }

    // Identifiability over the poses the bar can actually measure: the pool itself.
    let rows: Vec<[f64; N_PARAMS]> = pool
        .candidates
        .iter()
        .map(|c| {
            let mut r = [0.0; N_PARAMS];
            model.jacobian_row(&model.nominal, &c.q, &mut r);
            r
        })
        .collect();
    let identifiability = model::analyse(&rows, &IdentifyOptions::default());
    warnings.extend(map_warnings(&model, &identifiability));

    let selection = select::run(
        &model,
        &pool,
        &identifiability.identifiable,
        &SelectConfig { poses: opts.poses },
    )?;
    let poses: Vec<[f64; 6]> = selection
        .indices
        .iter()
        .map(|&i| pool.candidates[i].q)
        .collect();
    let speeds = robot.max_speeds();
    let start = (0..poses.len())
        .map(|k| (k, order::move_time(&opts.start, &poses[k], &speeds)))
        .fold((0, f64::INFINITY), |b, c| if c.1 < b.1 { c } else { b })
        .0;
    let tour = order::solve(&poses, start, &speeds)?;
    let ordered: Vec<[f64; 6]> = tour.order.iter().map(|&k| poses[k]).collect();
    let move_times: Vec<f64> = std::iter::once(0.0)
        .chain(
            ordered
                .windows(2)
                .map(|w| order::move_time(&w[0], &w[1], &speeds)),
        )
        .collect();
    let path = Path {
        poses: ordered,
        move_times,
        time_unsorted: tour.time_unsorted,
        time_sorted: tour.time_sorted,
    };

    let cond = selection
        .curve
        .iter()
        .find(|c| c.0 == selection.indices.len())
        .map_or(f64::NAN, |c| c.1);
    let header = Header {
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        robot: robot.name.clone(),
        robot_file: robot.source.clone(),
        fixture_mm: opts.fixture.map(to_mm).into(),
        map_mm: map.map(to_mm).into(),
        bar_mm: [to_mm(opts.bar_min), to_mm(opts.bar_max)],
        blend_mm: to_mm(opts.blend),
        poses: path.poses.len(),
        identifiable: identifiability.count(),
        cond,
        time_unsorted_s: path.time_unsorted,
        time_s: path.time_sorted,
        inputs_sha256: inputs_hash(robot, opts, template),
        joint_names: robot.joints.iter().map(|j| j.name.clone()).collect(),
    };
    let moves = path
        .poses
        .iter()
        .zip(&path.move_times)
        .map(|(q, &t)| Move {
            q_deg: q.map(to_deg),
            time_s: t,
            length_mm: to_mm(model.length(&model.nominal, q)),
        })
        .collect();
    let program = Program { header, moves };
    let text = emit::render(template, &program).map_err(PipelineError::Template)?;
    Ok(Compiled {
        cell,
        model,
        identifiability,
        sample,
        pool,
        selection,
        path,
        program,
        text,
        warnings,
    })
}

fn empty_pool_error(
    robot: &Robot,
    model: &MeasurementModel,
    cell: &Cell,
    seed: u64,
) -> PipelineError {
    match rich_rows(robot, model, cell, 1, seed) {
        Ok(_) => PipelineError::EmptyShell {
            bar_mm: [to_mm(cell.bar_min), to_mm(cell.bar_max)],
        },
        Err(closest) => PipelineError::no_pose(cell, closest),
    }
}

/// SHA-256 of everything that determines the output: robot file, options, template.
pub fn inputs_hash(robot: &Robot, opts: &CompileOptions, template: &str) -> String {
    let mut h = Sha256::new();
    h.update(robot.digest.as_bytes());
    h.update(serde_json::to_string(opts).unwrap_or_default().as_bytes());
    h.update(template.as_bytes());
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

//! The one place where stages are chained: in = a loaded robot and resolved options; out =
//! every intermediate result (the IR) plus the program text. No file I/O, no printing.
//!
//! [`compile`] reads as its list of stages: cell, model and collision scene → admit (sample:
//! shell, cones, floor, harness; collision filter) → sections ([`sections`]) → identify →
//! select ⇄ order ⇄ plan (support poses, blends) → timed path → predict → program
//! ([`program`]) → emit → verify the emitted text. Each stage tells [`Progress::stage`] when it
//! starts (the CLI's `--timings`).

pub mod program;
pub mod sections;

pub use sections::{
    Sections, SectionsReport, COMPONENT_NEIGHBOURS, MAX_SECTIONS, MIN_POSES_PER_SECTION,
    MIN_SECTION_POSES,
};

use crate::cell::CellSpec;
use crate::collision::{self, Scene, SceneReport};
use crate::controller::ControllerMap;
use crate::dialect::{Dialect, MoveTime, Template};
use crate::emit;
use crate::ir::{Candidate, Cell, Path, Pool, Program, Reason, Selection};
use crate::model::{self, Identifiability, IdentifyOptions, MeasurementModel, N_PARAMS};
use crate::order;
use crate::robot::Robot;
use crate::safety::path::{self as safepath, Plan};
use crate::safety::{Checker, LineMemo};
use crate::sample::{self, Progress, SampleConfig, SampleReport};
use crate::select::{self, SelectConfig};
use crate::timing::{self, Limits};
use crate::units::{fmt_fixed, to_deg, to_mm};
use crate::verify;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;

/// Everything the compiler needs besides the robot, resolved and checked (SI units).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CompileOptions {
    pub fixture: Vector3<f64>,
    /// The cell with every CLI override applied (MAP: None = the robot file's tool).
    pub cell: CellSpec,
    pub step: [f64; 6],
    pub max_candidates: usize,
    pub seed: u64,
    pub poses: Option<usize>,
    pub blend: f64,
    /// Start configuration; the tour starts at the selected pose nearest to it (Eq. 7).
    pub start: [f64; 6],
    /// The bar's noise per reading (m) and its sample rate (Hz): what the predicted
    /// calibration uncertainty assumes.
    pub bar_noise: f64,
    pub bar_rate: f64,
    /// Stop-and-measure (`--dwell S`): an exact stop and a dwell of S seconds at every
    /// measurement pose. None: a continuous program (absent from the input hash, so continuous
    /// programs keep theirs).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dwell: Option<f64>,
    /// A short check program: the poses are chosen for these parameters only (Eq. 6 indices;
    /// those the pool cannot identify are left out), e.g. the ones that drifted last time and
    /// the joint zeros (`--focus`). None: every identifiable parameter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focus: Option<Vec<usize>>,
    /// The program's name (KRL's DEF, FANUC's /PROG, RAPID's MODULE): the output file's stem.
    /// Not part of the input hash: the text carries it.
    #[serde(skip)]
    pub program_name: String,
    /// What the tour minimises.
    #[serde(default)]
    pub tour_cost: TourCost,
}

/// The tour's cost per move (`--tour-cost`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TourCost {
    /// The move between exact stops with its acceleration ramps ([`crate::timing`]).
    #[default]
    Trapezoid,
    /// Eq. 7: the slowest joint at its maximum speed, no acceleration (the paper's).
    Eq7,
}

impl CompileOptions {
    /// The compiler's defaults for a fixture (the CLI's defaults, in SI units).
    pub fn new(fixture: Vector3<f64>) -> Self {
        CompileOptions {
            fixture,
            cell: CellSpec::default(),
            step: [DEFAULT_STEP_DEG.to_radians(); 6],
            max_candidates: DEFAULT_MAX_CANDIDATES,
            seed: DEFAULT_SEED,
            poses: None,
            blend: DEFAULT_BLEND_MM * 1e-3,
            start: [0.0; 6],
            bar_noise: DEFAULT_BAR_NOISE_UM * 1e-6,
            bar_rate: DEFAULT_BAR_RATE_HZ,
            dwell: None,
            focus: None,
            program_name: DEFAULT_PROGRAM_NAME.to_string(),
            tour_cost: TourCost::default(),
        }
    }
}

pub use crate::cell::{DEFAULT_BALL_MM, DEFAULT_BAR_MM};
pub const DEFAULT_STEP_DEG: f64 = 10.0;
pub const DEFAULT_MAX_CANDIDATES: usize = 3400;
pub const DEFAULT_SEED: u64 = 1;
pub const DEFAULT_BLEND_MM: f64 = 10.0;
/// The EDBB's stated accuracy (1 µm) as its noise per reading, and the twin's sample rate.
pub const DEFAULT_BAR_NOISE_UM: f64 = 1.0;
pub const DEFAULT_BAR_RATE_HZ: f64 = 50.0;
/// Random joint poses over which predicted accuracies are stated (seeded).
pub const PREDICTION_POSES: usize = 2000;
/// The program name when none is given.
pub const DEFAULT_PROGRAM_NAME: &str = "EDBB";
/// Measurement poses keep this far from the bar's ends and the cone edges, so that the joint
/// moves between them (which bow) have room; moves are checked against the full limits.
pub const POSE_INSET_BAR_MM: f64 = 5.0;
pub const POSE_INSET_CONE_DEG: f64 = 5.0;
/// The sampler keeps this many times `max_candidates` cheap-valid poses; the collision filter
/// then takes them in hash order until `max_candidates` pass.
pub const RESERVOIR_FACTOR: usize = 4;
/// Rounds of "take unreachable poses out and select again".
pub const REPAIR_ROUNDS: usize = 3;

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
    #[error(
        "joint {joint}: its range {}..{} deg leaves nothing inside the {} deg joint margin (lower --joint-margin or [safety] joint_margin)",
        mm1(range_deg[0]), mm1(range_deg[1]), mm1(*margin_deg)
    )]
    JointMargin {
        joint: String,
        range_deg: [f64; 2],
        margin_deg: f64,
    },
    #[error("no valid pose: every pose in the bar shell was rejected ({0}); check the cell, the cones and the harness limits")]
    AllRejected(String),
    #[error("only {0} valid poses in the cell, too few to identify the robot's parameters (30 or more are needed): refine --step, widen --bar or the cones, or move the fixture")]
    TooFewPoses(usize),
    #[error(
        "--step: {step_deg} deg gives {points:.1e} grid points on joints 2-6, more than the {GRID_LIMIT:.0e} the sampler enumerates in reasonable time: use a step of at least {min_step_deg:.2} deg"
    )]
    GridTooLarge {
        step_deg: String,
        points: f64,
        min_step_deg: f64,
    },
    #[error("collision model: {0}")]
    Collision(String),
    #[error(transparent)]
    Select(#[from] select::SelectError),
    #[error(transparent)]
    Order(#[from] order::OrderError),
    #[error("template: {0}")]
    Template(String),
    #[error(transparent)]
    Controller(#[from] crate::controller::ControllerError),
    #[error("refusing to write an unsafe program: {0}")]
    Unsafe(String),
    /// The compiler's own invariants caught a bug in it (never bad input): nothing is written.
    #[error("internal error, a bug in edbbgen (please report it with the command line; nothing was written): {0}")]
    Bug(String),
    #[error("--focus: {0}")]
    Focus(String),
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

    /// Exit code: 1 when the compiler's own safety check failed, 2 for bad input.
    pub fn exit_code(&self) -> i32 {
        match self {
            PipelineError::Unsafe(_) | PipelineError::Bug(_) => 1,
            _ => 2,
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
            "the MAP lies on the flange axis (axis of joint 6): q6 cannot move it and is held, so theta6 is unobservable and only {} parameters are identifiable (fixed: {}); use a tool cup off the flange axis",
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

/// The default tool-cup axis in the flange frame: along the axis of joint 6, pointing away from
/// the wrist (for a DH flange that is +z; REP-199 URDF flanges have it along x).
pub fn default_cup_axis(robot: &Robot) -> Vector3<f64> {
    // In DH frame 6, z is the joint-6 axis; the wrist (frame 5's origin) lies behind it.
    let t6 = crate::robot::kinematics::dh_transform(&robot.dh[5], 0.0);
    let wrist_in_6 = t6.inverse().t;
    let z = if wrist_in_6.z <= 0.0 {
        Vector3::z()
    } else {
        -Vector3::z()
    };
    robot.flange.r.transpose() * z
}

/// The cell the stages use: the spec's limits, with the shell cut at the ball diameter.
pub fn make_cell(
    robot: &Robot,
    fixture: Vector3<f64>,
    map: Vector3<f64>,
    spec: &CellSpec,
) -> Result<Cell, PipelineError> {
    for j in &robot.joints {
        if j.upper - j.lower < 2.0 * spec.joint_margin {
            return Err(PipelineError::JointMargin {
                joint: j.name.clone(),
                range_deg: [to_deg(j.lower), to_deg(j.upper)],
                margin_deg: to_deg(spec.joint_margin),
            });
        }
    }
    if spec.bar_max <= spec.ball {
        return Err(PipelineError::BallsOverlap {
            bar_mm: [to_mm(spec.bar_min), to_mm(spec.bar_max)],
            ball_mm: to_mm(spec.ball),
        });
    }
    Ok(Cell {
        fixture,
        map,
        bar_min: spec.bar_min.max(spec.ball),
        bar_max: spec.bar_max,
        floor_z: spec.floor_z,
        fixture_axis: spec.fixture_axis,
        fixture_cone_cos: spec.fixture_cone.cos(),
        tool_axis: spec.tool_axis.unwrap_or_else(|| default_cup_axis(robot)),
        tool_cone_cos: spec.tool_cone.cos(),
        cables: [spec.cable_q4, spec.cable_q6, spec.cable_q4_q6],
        joint_margin: spec.joint_margin,
    })
}

/// The cell for choosing measurement poses: the limits pulled in by the pose inset, and the
/// harness ranges by the joint margin, as the joint ranges are (a compensated program moves
/// its poses by a fraction of a degree: a pose on a harness limit would cross it).
pub fn inset_cell(cell: &Cell) -> Cell {
    let m = cell.joint_margin;
    let cables = cell.cables.map(|r| {
        r.map(|[lo, hi]| {
            if hi - lo > 2.0 * m {
                [lo + m, hi - m]
            } else {
                [0.5 * (lo + hi); 2]
            }
        })
    });
    let d = POSE_INSET_BAR_MM * 1e-3;
    let a = POSE_INSET_CONE_DEG.to_radians();
    let shrink = |c: f64| {
        if c <= -1.0 {
            c
        } else {
            (c.clamp(-1.0, 1.0).acos() - a).max(0.0).cos()
        }
    };
    let mid = 0.5 * (cell.bar_min + cell.bar_max);
    Cell {
        bar_min: (cell.bar_min + d).min(mid),
        bar_max: (cell.bar_max - d).max(mid),
        fixture_cone_cos: shrink(cell.fixture_cone_cos),
        tool_cone_cos: shrink(cell.tool_cone_cos),
        cables,
        ..cell.clone()
    }
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

/// Counts at every stage (`--json`).
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub schema: &'static str,
    pub grid_size: u64,
    pub evaluated: u64,
    pub valid_before_collisions: u64,
    pub rejected: BTreeMap<String, u64>,
    pub collision_checked: usize,
    pub pool: usize,
    /// Admitted poses outside the largest safely connected group (left out of the pool).
    pub disconnected: usize,
    /// Selected poses that no safe move reached, replaced by selecting again without them.
    pub replaced_unreachable: usize,
    pub identifiable: usize,
    pub selected: usize,
    pub support_poses: usize,
    pub dropped: Vec<safepath::Dropped>,
    pub exact_stops: usize,
    pub min_clearance_mm: f64,
    pub min_clearance_between: [String; 2],
    pub bar_length_mm: [f64; 2],
    pub max_socket_angle_deg: f64,
    pub max_cup_angle_deg: f64,
    /// The program's estimated time as planned (support poses, detours, blends), s.
    pub estimated_time_s: f64,
    /// The measurement poses in pool order by direct moves with exact stops, s.
    pub time_unsorted_s: f64,
    /// The measurement poses in tour order by the same direct moves, s (against
    /// `time_unsorted_s`: what the ordering gains).
    pub time_direct_s: f64,
    pub collision_pairs_checked: usize,
    pub excluded_pairs: Vec<collision::ExcludedPair>,
    pub warnings: Vec<String>,
    /// What the program buys: the predicted 1σ MAP position uncertainty after calibrating from
    /// its recording.
    pub predicted_position_std_um: Predicted,
    /// How the admitted poses split into groups that safe motions connect, and the sections
    /// the program measures.
    pub sections: SectionsReport,
}

/// The predicted MAP position uncertainty after calibration from a program's recording (µm):
/// Type A from the bar noise at the bar's rate along every move made with the bar, the
/// identifiable parameters free, over random joint poses, after a best rigid registration.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Predicted {
    pub workspace_rms: f64,
    pub workspace_p95: f64,
    pub bar_noise_um: f64,
    pub bar_rate_hz: f64,
    /// Stop-and-measure programs: `workspace_*` are from one reading per measurement pose (the
    /// plateau means of `plateau_samples` bar samples each); `continuous_workspace_rms` is the
    /// same program recorded continuously with a synchronous joint log (moves and dwells).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub plateau_samples: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub continuous_workspace_rms: Option<f64>,
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
    pub plan: Plan,
    pub program: Program,
    pub text: String,
    pub verified: verify::Summary,
    pub report: Report,
    pub warnings: Vec<String>,
}

/// The collision filter: candidates in key order, checked in parallel batches, until `want`
/// pass. Deterministic: the accepted set is the first `want` passing poses in key order.
/// Returns the accepted poses (grid order), how many were checked and how many rejected.
pub fn collision_filter(
    ck: &Checker,
    mut candidates: Vec<crate::ir::Candidate>,
    want: usize,
) -> (Vec<crate::ir::Candidate>, usize, u64) {
    candidates.sort_by_key(|c| c.key);
    let mut kept = Vec::with_capacity(want);
    let mut checked = 0;
    let mut rejected = 0u64;
    for batch in candidates.chunks(256) {
        let ok: Vec<bool> = batch.par_iter().map(|c| ck.pose(&c.q).is_ok()).collect();
        for (c, ok) in batch.iter().zip(ok) {
            checked += 1;
            if ok {
                kept.push(*c);
                if kept.len() == want {
                    break;
                }
            } else {
                rejected += 1;
            }
        }
        if kept.len() == want {
            break;
        }
    }
    kept.sort_by_key(|c| c.grid);
    (kept, checked, rejected)
}

pub fn build_scene(
    robot: &Robot,
    spec: &CellSpec,
    fixture: &Vector3<f64>,
    map: &Vector3<f64>,
) -> Result<(Scene, SceneReport), PipelineError> {
    collision::build(robot, spec, fixture, map).map_err(|e| PipelineError::Collision(e.to_string()))
}

/// The compiler, as its list of stages (each a function below, in this order): check the
/// template → cell, model, collision scene → admit (sample, collision filter) → sections →
/// identify → select ⇄ order ⇄ plan → timed path → predict → program → emit and verify.
pub fn compile(
    robot: &Robot,
    opts: &CompileOptions,
    template: &str,
    progress: &dyn Progress,
) -> Result<Compiled, PipelineError> {
    // The template and its controller mapping are checked before the long work starts.
    let template =
        Template::from_source(template).map_err(|e| PipelineError::Template(e.to_string()))?;
    let axes = controller_map(robot, opts, &template)?;
    let (map, mut warnings) = resolve_map(robot, opts.cell.map);
    warnings.extend(coupling_note(robot, opts, &template));
    warnings.extend(robot.notes.iter().cloned());
    let cell = make_cell(robot, opts.fixture, map, &opts.cell)?;
    let model = MeasurementModel::new(robot, opts.fixture, map);
    progress.stage("scene");
    let (scene, scene_report) = build_scene(robot, &opts.cell, &opts.fixture, &map)?;
    let ck = Checker::new(robot, &model, &cell, &scene, opts.cell.margin);
    let speeds = robot.max_speeds();

    progress.stage("sample");
    let admitted = admit(&ck, opts, progress)?;
    progress.stage("sections");
    let mut sections = Sections::group(&ck, &admitted.candidates, &speeds);
    warnings.extend(sections.warning());
    check_pool(&ck, opts.seed, &admitted, &sections.pool)?;
    progress.stage("identify");
    // Identifiability over the poses the bar can actually measure: the pool itself.
    let pool_q: Vec<[f64; 6]> = sections.pool.candidates.iter().map(|c| c.q).collect();
    // A stop-and-measure program has one reading per pose to share between the robot and
    // the set-up, which `calibrate` estimates by default: its poses are chosen for both (a
    // continuous recording learns the set-up along its moves).
    let identify = if opts.dwell.is_some() {
        IdentifyOptions {
            fixture_known: false,
            map_known: false,
        }
    } else {
        IdentifyOptions::default()
    };
    let mut identifiability = model::analyse(&model.rows(&pool_q), &identify);
    warnings.extend(map_warnings(&model, &identifiability));
    if let Some(focus) = &opts.focus {
        warnings.extend(focus_on(&mut identifiability, focus)?);
    }
    let mut planned = select_order_plan(&ck, &sections, &identifiability, opts, progress)?;
    if let Some(k) = planned.plan.repeated_pose() {
        return Err(PipelineError::Bug(format!(
            "the planner put the same pose twice in a row (waypoints {} and {}: a zero-length move)",
            k,
            k + 1
        )));
    }
    progress.stage("blend");
    blend(&ck, &mut planned.plan, opts, template.dialect, &axes);
    warnings.extend(planned.warnings());
    sections.report.measured_per_section = sections::measured_per_section(&planned.plan);
    let path = timed_path(
        &planned.plan,
        (planned.time_unsorted, planned.time_direct),
        &Limits::of(robot),
        template.dialect,
    );
    progress.stage("path, predict");
    let predicted = predict(&ck, &identifiability, &path, &planned.plan, opts);
    warnings.extend(dwell_warning(&predicted, opts));
    let mut base = program::base(&ck, opts, &identifiability, &planned, &path, &predicted);
    if opts.focus.is_some() {
        base.header.notes.push(format!(
            "check program: poses chosen for {} (--focus)",
            identifiability
                .identifiable
                .iter()
                .map(|&i| model::PARAM_NAMES[i])
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    progress.stage("emit, verify");
    // The compiler does not trust its own memory either: `finish` re-reads the text and checks it.
    let (program, text, verified) = finish(&ck, robot, opts, &base, &template, &axes)?;

    let report = Report {
        schema: "edbbgen.report/1",
        grid_size: admitted.sample.grid_size,
        evaluated: admitted.sample.evaluated,
        valid_before_collisions: admitted.sample.valid,
        rejected: admitted.rejected,
        collision_checked: admitted.collision_checked,
        pool: sections.pool.candidates.len(),
        disconnected: sections.report.disconnected,
        replaced_unreachable: planned.replaced,
        identifiable: identifiability.count(),
        selected: planned.selection.indices.len(),
        support_poses: planned.plan.supports,
        dropped: planned.plan.dropped.clone(),
        exact_stops: planned.plan.exact_stops,
        min_clearance_mm: to_mm(verified.min_clearance.distance),
        min_clearance_between: [
            verified.min_clearance.a.clone(),
            verified.min_clearance.b.clone(),
        ],
        bar_length_mm: [
            to_mm(verified.extremes.min_length),
            to_mm(verified.extremes.max_length),
        ],
        max_socket_angle_deg: to_deg(verified.extremes.max_socket_angle),
        max_cup_angle_deg: to_deg(verified.extremes.max_cup_angle),
        estimated_time_s: path.time_sorted + dwell_time(opts, &planned.plan),
        time_unsorted_s: path.time_unsorted + dwell_time(opts, &planned.plan),
        time_direct_s: path.time_direct + dwell_time(opts, &planned.plan),
        collision_pairs_checked: scene_report.pairs_checked,
        excluded_pairs: scene_report.excluded,
        warnings: warnings.clone(),
        predicted_position_std_um: predicted,
        sections: sections.report,
    };
    Ok(Compiled {
        cell,
        model,
        identifiability,
        sample: admitted.sample,
        pool: sections.pool,
        selection: planned.selection,
        path,
        plan: planned.plan,
        program,
        text,
        verified,
        report,
        warnings,
    })
}

/// `--focus`: the selection's columns become the focus parameters the pool identifies; the
/// others named are left out with a warning.
fn focus_on(id: &mut Identifiability, focus: &[usize]) -> Result<Vec<String>, PipelineError> {
    let keep: Vec<usize> = id
        .identifiable
        .iter()
        .copied()
        .filter(|i| focus.contains(i))
        .collect();
    let left: Vec<&str> = focus
        .iter()
        .filter(|i| !keep.contains(i))
        .map(|&i| model::PARAM_NAMES[i])
        .collect();
    if keep.is_empty() {
        return Err(PipelineError::Focus(format!(
            "none of {} is identifiable from the poses the bar can measure here",
            left.join(", ")
        )));
    }
    id.identifiable = keep;
    Ok((!left.is_empty())
        .then(|| {
            format!(
                "--focus: {} not identifiable from the poses the bar can measure here: left out of the check program",
                left.join(", ")
            )
        })
        .into_iter()
        .collect())
}

/// The poses that pass every check, in grid order, with the counts of the two stages.
struct Admitted {
    candidates: Vec<Candidate>,
    sample: SampleReport,
    collision_checked: usize,
    /// Rejections by reason, the collision filter's included.
    rejected: BTreeMap<String, u64>,
}

/// Samples the joint grid (shell, cones, floor, harness on the inset cell), then checks the
/// sampled poses for collisions in hash order until `max_candidates` pass.
fn admit(
    ck: &Checker,
    opts: &CompileOptions,
    progress: &dyn Progress,
) -> Result<Admitted, PipelineError> {
    let (robot, model, cell) = (ck.robot, ck.model, ck.cell);
    let scfg = SampleConfig {
        step: opts.step,
        max_candidates: opts.max_candidates.saturating_mul(RESERVOIR_FACTOR),
        seed: opts.seed,
        movable: model::movable_joints(model, robot),
    };
    check_grid_size(robot, cell, &scfg)?;
    let (sampled, sample) = sample::run(robot, model, &inset_cell(cell), &scfg, progress);
    let (candidates, collision_checked, collisions) =
        collision_filter(ck, sampled.candidates, opts.max_candidates);
    let mut rejected: BTreeMap<String, u64> = sample
        .rejected
        .iter()
        .map(|(r, n)| (r.name().to_string(), *n))
        .collect();
    if collisions > 0 {
        rejected.insert(Reason::Collision.name().to_string(), collisions);
    }
    Ok(Admitted {
        candidates,
        sample,
        collision_checked,
        rejected,
    })
}

/// Refuses a pool that is empty (saying which test rejected everything, or why the shell is
/// empty) or smaller than the parameter count.
fn check_pool(
    ck: &Checker,
    seed: u64,
    admitted: &Admitted,
    pool: &Pool,
) -> Result<(), PipelineError> {
    if pool.candidates.is_empty() {
        let sample = &admitted.sample;
        if sample.valid == 0
            && !sample
                .rejected
                .keys()
                .any(|r| !matches!(r, Reason::BarLength | Reason::Floor))
        {
            return Err(empty_pool_error(ck.robot, ck.model, ck.cell, seed));
        }
        let why: Vec<String> = admitted
            .rejected
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect();
        return Err(PipelineError::AllRejected(why.join(", ")));
    }
    if pool.candidates.len() < N_PARAMS {
        return Err(PipelineError::TooFewPoses(pool.candidates.len()));
    }
    Ok(())
}

/// The selection, its order and its safe plan.
pub struct Planned {
    pub selection: Selection,
    /// The selected poses in pool order by direct moves (ramps, exact stops), s.
    pub time_unsorted: f64,
    /// The same poses in tour order by the same direct moves, s.
    pub time_direct: f64,
    pub plan: Plan,
    /// Selected poses replaced because no safe move reached them or their section was too small.
    pub replaced: usize,
}

impl Planned {
    /// Replaced and dropped poses, and a program of several sections, as warnings.
    fn warnings(&self) -> Vec<String> {
        let mut w = Vec::new();
        if self.replaced > 0 {
            w.push(format!(
                "{} selected poses were replaced: no safe move reached them, or too few shared their section",
                self.replaced
            ));
        }
        for d in &self.plan.dropped {
            w.push(format!(
                "dropped tour pose {}: no safe move found ({})",
                d.index + 1,
                d.violation
            ));
        }
        let sections = self.plan.sections();
        if sections > 1 {
            w.push(format!(
                "the program has {sections} sections: the bar is removed and remounted between them (no safe motion joins their poses with the bar in place)"
            ));
        }
        w
    }
}

/// Selects, orders and makes the path safe, in one round: the selection measures every
/// section with at least [`MIN_POSES_PER_SECTION`] poses or not at all (a constraint of the
/// elimination, [`select::run_grouped`]), and the planner reaches every pose of a section
/// through the section's roadmap ([`safepath::plan_sections`]). Should a pose still be dropped
/// (no safe move reached it), it is taken out of the pool and the selection redone, for at
/// most [`REPAIR_ROUNDS`] rounds.
fn select_order_plan(
    ck: &Checker,
    sections: &Sections,
    id: &Identifiability,
    opts: &CompileOptions,
    progress: &dyn Progress,
) -> Result<Planned, PipelineError> {
    let pool = &sections.pool.candidates;
    let speeds = ck.robot.max_speeds();
    // Repair rounds plan mostly the same moves: the planner checks each once.
    let memo = LineMemo::default();
    let planner = ck.remembering(&memo);
    let mut usable: Vec<usize> = (0..pool.len()).collect();
    let mut replaced = 0;
    let mut round = 0;
    loop {
        progress.stage("select");
        let sub = Pool {
            candidates: usable.iter().map(|&i| pool[i]).collect(),
        };
        let label: Vec<usize> = usable.iter().map(|&i| sections.group[i]).collect();
        let mut selection = select::run_grouped(
            ck.model,
            &sub,
            &id.identifiable,
            &SelectConfig { poses: opts.poses },
            Some(select::Groups {
                label: &label,
                min: MIN_POSES_PER_SECTION,
            }),
        )?;
        // Indices into the pool, not into this round's part of it.
        let chosen: Vec<usize> = selection.indices.iter().map(|&k| usable[k]).collect();
        selection.indices.clone_from(&chosen);
        progress.stage("order");
        // The tour cost: each move with its acceleration ramps, or Eq. 7 as in the paper.
        let accel = ck.robot.max_accelerations();
        let (ordered, _) = sections.order(
            &chosen,
            &opts.start,
            &speeds,
            (opts.tour_cost == TourCost::Trapezoid).then_some(&accel),
        )?;
        progress.stage("plan");
        let plan = safepath::plan_sections(&planner, &ordered, &speeds, opts.seed);
        let (time_unsorted, time_direct) = direct_times(ck.robot, pool, &chosen, &plan);
        if plan.dropped.is_empty()
            || round == REPAIR_ROUNDS
            || usable.len() <= id.count() + plan.dropped.len()
        {
            return Ok(Planned {
                selection,
                time_unsorted,
                time_direct,
                plan,
                replaced,
            });
        }
        round += 1;
        // The plan holds the poses as the program carries them.
        let unreachable: Vec<[f64; 6]> = plan.dropped.iter().map(|d| d.q).collect();
        replaced += unreachable.len();
        usable.retain(|&i| !unreachable.contains(&emit::emitted(&pool[i].q)));
    }
}

/// The like-for-like pair that shows what the ordering gains (the paper's Fig. 6): the
/// program's measurement poses by direct moves, each with its ramps and an exact stop, no
/// support poses, in pool order (the "unsorted" time) and in the program's order (the tour, with
/// any pose the planner deferred where it went), s. The program's own time (support poses,
/// detours, blends) is another figure.
fn direct_times(robot: &Robot, pool: &[Candidate], chosen: &[usize], plan: &Plan) -> (f64, f64) {
    let lim = Limits::of(robot);
    let time = |qs: &[[f64; 6]]| -> f64 {
        qs.windows(2)
            .map(|w| timing::move_time(&w[0], &w[1], &lim, 1.0))
            .sum()
    };
    let near = |a: &[f64; 6], b: &[f64; 6]| (0..6).all(|j| (a[j] - b[j]).abs() < 1e-4);
    // A pose the planner dropped is in neither (the program does not visit it).
    let unsorted: Vec<[f64; 6]> = chosen
        .iter()
        .map(|&i| pool[i].q)
        .filter(|q| !plan.dropped.iter().any(|d| near(&d.q, q)))
        .collect();
    let program: Vec<[f64; 6]> = plan
        .waypoints
        .iter()
        .filter(|w| !w.support)
        .map(|w| w.q)
        .collect();
    (time(&unsorted), time(&program))
}

/// The blend stage: every corner of the plan blended or stopped by the dialect's corner model
/// (what its controller's blend instruction bounds), [`safepath::blend_corners`].
fn blend(
    ck: &Checker,
    plan: &mut Plan,
    opts: &CompileOptions,
    dialect: &Dialect,
    map: &ControllerMap,
) {
    safepath::blend_corners(
        ck,
        plan,
        &safepath::CornerSpec {
            corner: &dialect.corner,
            distance: opts.blend,
            map,
        },
    );
    // After the blends: a stop-and-measure program stops exactly at every measurement pose,
    // whatever the dialect's corner model would allow there.
    if opts.dwell.is_some() {
        stop_at_poses(plan);
    }
}

/// The resolution whole-move time words are timed in (s): RAPID prints `\T` to 1 ms, URScript
/// prints `t` to 0.1 ms (a whole millisecond exactly).
pub const WHOLE_MOVE_TICK: f64 = 1e-3;

/// The path on exactly the joint values the program carries (the 0.001° grid every dialect
/// prints), each move timed on those values (so the emitted feed never asks an axis for more
/// than its speed): its cruise at the slowest joint's speed (Eq. 7) and its duration with the
/// ramps at the joints' accelerations (the dialect's controller scales them on moves that
/// blend); the total takes the blends' overlaps off ([`crate::timing`]).
pub fn timed_path(
    plan: &Plan,
    (time_unsorted, time_direct): (f64, f64),
    lim: &Limits,
    dialect: &Dialect,
) -> Path {
    let wq: Vec<[f64; 6]> = plan
        .waypoints
        .iter()
        .map(|w| w.q.map(|r| emit::round_deg(to_deg(r)).to_radians()))
        .collect();
    let mut cruise_times: Vec<f64> = std::iter::once(0.0)
        .chain(wq.windows(2).map(|w| timing::eq7(&w[0], &w[1], &lim.speed)))
        .collect();
    let blended: Vec<bool> = plan.waypoints.iter().map(|w| w.blend > 0.0).collect();
    if dialect.move_time == MoveTime::Total {
        // A whole-move time word (RAPID `\T`, URScript `t`) is printed rounded up, and read
        // back (by the controller's model, `verify`, the twin) as the cruise that fills it,
        // [`timing::cruise_of`]. Near a triangle (T = 2·T_a) that cruise grows like
        // √(T_a·ε) with the rounding ε: 0.8 ms on \T made one move's cruise 13 ms longer and
        // let the blend before it overlap 13 ms more, so the text ran faster than the plan
        // stated. Each move is therefore timed as its printed word reads: its duration rounded
        // up to `WHOLE_MOVE_TICK`, its cruise the one that fills it.
        let m = timing::moves(
            &wq,
            &cruise_times,
            &blended,
            lim,
            dialect.corner.blend_acceleration,
        );
        for k in 1..wq.len() {
            if m[k].duration > 0.0 {
                let stated =
                    (m[k].duration / WHOLE_MOVE_TICK * (1.0 - 1e-12)).ceil() * WHOLE_MOVE_TICK;
                let ta = timing::accel_time(&wq[k - 1], &wq[k], &lim.accel);
                cruise_times[k] = timing::cruise_of(stated, ta).max(cruise_times[k]);
            }
        }
    }
    let (move_times, time_sorted) = timing::program(
        &wq,
        &cruise_times,
        &blended,
        lim,
        dialect.corner.blend_acceleration,
    );
    Path {
        poses: wq,
        move_times,
        cruise_times,
        time_unsorted,
        time_sorted,
        time_direct,
    }
}

/// Stop-and-measure: every measurement pose ends in an exact stop (its dwell follows); the
/// support poses keep their blends. An exact stop only removes a corner's blend, so every
/// checked move stays as checked (`verify` re-checks the text anyway).
fn stop_at_poses(plan: &mut Plan) {
    for w in plan.waypoints.iter_mut().filter(|w| !w.support) {
        w.blend = 0.0;
    }
}

/// The dwells' share of the program's time (s): one dwell per measurement pose.
fn dwell_time(opts: &CompileOptions, plan: &Plan) -> f64 {
    let poses = plan.waypoints.iter().filter(|w| !w.support).count();
    opts.dwell.unwrap_or(0.0) * poses as f64
}

/// What the program buys: the MAP position uncertainty after calibrating from its recording
/// (every move made with the bar, at the bar's rate), over the whole joint space. A
/// stop-and-measure program (`--dwell`) is calibrated from one reading per measurement pose,
/// the mean of a plateau's core ([`crate::logs::plateau_core_samples`] samples, so the noise
/// falls by its square root); the same program recorded continuously (moves and dwells, with
/// a synchronous joint log) is predicted alongside. Both as `calibrate` reads them by
/// default (the fixture and the MAP estimated); a continuous program's prediction keeps the
/// paper's convention (the set-up known, the identifiable parameters free).
fn predict(
    ck: &Checker,
    id: &Identifiability,
    path: &Path,
    plan: &Plan,
    opts: &CompileOptions,
) -> Predicted {
    use crate::calibrate::predict as p;
    let mut segments = recorded_segments(path, plan);
    let space = p::workspace(ck.robot, PREDICTION_POSES, opts.seed);
    let continuous = |segments: &[([f64; 6], [f64; 6], f64)]| {
        p::spread(&p::after_recording(
            ck.model,
            segments,
            &id.identifiable,
            opts.bar_noise,
            opts.bar_rate,
            &space,
        ))
    };
    let Some(dwell) = opts.dwell else {
        let spread = continuous(&segments);
        return Predicted {
            workspace_rms: spread.rms * 1e6,
            workspace_p95: spread.p95 * 1e6,
            bar_noise_um: opts.bar_noise * 1e6,
            bar_rate_hz: opts.bar_rate,
            plateau_samples: None,
            continuous_workspace_rms: None,
        };
    };
    let poses: Vec<[f64; 6]> = path
        .poses
        .iter()
        .zip(&plan.waypoints)
        .filter(|(_, w)| !w.support)
        .map(|(q, _)| *q)
        .collect();
    // Both forms are predicted as `calibrate` reads them by default: the fixture and the
    // tool point estimated where the data determine them (a stop-and-measure run has one
    // reading per pose to share between the robot and the set-up; its recording along the
    // moves is what the synchronous form adds).
    let calibrated = |info: &p::RunInformation, noise: f64| {
        let e = p::expected_setup_free(
            ck.model,
            info,
            noise,
            &p::Prior::default(),
            crate::calibrate::DEFAULT_PRIOR_SETUP_MM * crate::units::MM,
            &space,
        );
        p::spread(&e.combined)
    };
    // The continuous recording of the same run also holds every dwell: S seconds at the pose.
    segments.extend(poses.iter().map(|q| (*q, *q, dwell)));
    let recorded = calibrated(
        &p::recording_information(ck.model, &segments, opts.bar_rate),
        opts.bar_noise,
    );
    let n = crate::logs::plateau_core_samples(dwell, opts.bar_rate).max(1);
    let rows: Vec<[f64; N_PARAMS]> = poses
        .iter()
        .map(|q| {
            let mut row = [0.0; N_PARAMS];
            ck.model.jacobian_row(&ck.model.nominal, q, &mut row);
            row
        })
        .collect();
    let spread = calibrated(
        &p::readings_information(&rows),
        opts.bar_noise / (n as f64).sqrt(),
    );
    Predicted {
        workspace_rms: spread.rms * 1e6,
        workspace_p95: spread.p95 * 1e6,
        bar_noise_um: opts.bar_noise * 1e6,
        bar_rate_hz: opts.bar_rate,
        plateau_samples: Some(n),
        continuous_workspace_rms: Some(recorded.rms * 1e6),
    }
}

/// A stop-and-measure program whose plateau means predict more than twice the uncertainty of
/// the same run recorded synchronously: the dwell is too short for its readings to carry what
/// the continuous recording adds along the moves (each plateau mean averages the dwell's
/// core; a longer dwell narrows the gap).
fn dwell_warning(p: &Predicted, opts: &CompileOptions) -> Option<String> {
    let (dwell, cont) = (opts.dwell?, p.continuous_workspace_rms?);
    (p.workspace_rms > 2.0 * cont).then(|| {
        format!(
            "--dwell {}: the plateau means predict {} µm RMS over the joint space, more than twice the {} µm of the same run recorded with a synchronous joint log: a longer dwell averages more of each standstill",
            crate::units::fmt_fixed(dwell, 2),
            crate::units::fmt_fixed(p.workspace_rms, 2),
            crate::units::fmt_fixed(cont, 2)
        )
    })
}

/// The moves a program records: every move made with the bar (not the transits between
/// sections), as (from, to, duration in s) on the joint values the program text carries.
pub fn recorded_segments(path: &Path, plan: &Plan) -> Vec<([f64; 6], [f64; 6], f64)> {
    path.poses
        .windows(2)
        .zip(plan.waypoints.iter().skip(1))
        .zip(path.move_times.iter().skip(1))
        .filter(|((_, w), _)| !w.transit)
        .map(|((q, _), &t)| (q[0], q[1], t))
        .collect()
}

/// The controller mapping a template's programs use: the cell's `[controller]` over the
/// dialect's defaults.
pub fn controller_map(
    robot: &Robot,
    opts: &CompileOptions,
    template: &Template,
) -> Result<ControllerMap, PipelineError> {
    let d = template.dialect;
    Ok(ControllerMap::resolve(
        opts.cell.controller.as_ref(),
        &d.defaults(),
        &d.name,
        robot,
    )?)
}

/// How [`coupling_note`]s begin (a program's header notes are otherwise the program kind's).
const COUPLING_NOTE_PREFIX: &str = "J3: ";

/// What the user must know about the controller's axis 3 on a parallel-arm robot when the
/// cell does not state the J2/J3 coupling ([`ControllerMap::coupling_note`]).
pub fn coupling_note(robot: &Robot, opts: &CompileOptions, template: &Template) -> Option<String> {
    let d = template.dialect;
    ControllerMap::coupling_note(opts.cell.controller.as_ref(), &d.defaults(), &d.name, robot)
}

/// Writes the planned `base` program for one controller: fills the dialect's fields, renders
/// the template and checks the text with `verify` (the compiler refuses to hand out a program
/// that fails). Returns the program, its text and the verify summary. The header carries the
/// controller's J2/J3 note where the axis mapping is ambiguous.
pub fn finish(
    ck: &Checker,
    robot: &Robot,
    opts: &CompileOptions,
    base: &Program,
    template: &Template,
    map: &ControllerMap,
) -> Result<(Program, String, verify::Summary), PipelineError> {
    let hash = inputs_hash(robot, opts, &template.source);
    let mut base = base.clone();
    // A program written for another dialect (`retarget`) carries that dialect's note.
    base.header
        .notes
        .retain(|n| !n.starts_with(COUPLING_NOTE_PREFIX));
    base.header
        .notes
        .extend(coupling_note(robot, opts, template));
    emit_checked(ck, robot, &base, template, map, DEFAULT_PROGRAM_NAME, &hash)
}

/// Any program kind's last step (the compiler's, the LDBB circle's): fills the dialect's fields
/// of `base`, names it (`default_name` when its own name is not valid in the dialect), renders
/// the template and checks the text with `verify`. Nothing is returned that `verify` did not
/// pass.
pub fn emit_checked(
    ck: &Checker,
    robot: &Robot,
    base: &Program,
    template: &Template,
    map: &ControllerMap,
    default_name: &str,
    inputs_sha256: &str,
) -> Result<(Program, String, verify::Summary), PipelineError> {
    let mut program = emit::target(base, template.dialect, map, &robot.max_speeds());
    let h = &mut program.header;
    if !crate::dialect::valid_name(&h.program_name, template.dialect.name_max) {
        h.program_name = emit::ident(
            if h.program_name.is_empty() {
                default_name
            } else {
                &h.program_name
            },
            template.dialect.name_max,
        );
    }
    h.inputs_sha256 = inputs_sha256.to_string();
    // A timed move must take time: one that does not repeats the pose before it, and the
    // controllers read it as a move without speed (inverse-time F0, a zero \T, t=0). Only a
    // planner bug makes one, so it is named as such rather than left to the reader's "F0 must
    // be positive".
    if let Some((k, m)) = program.moves.iter().enumerate().skip(1).find(|(_, m)| {
        !m.transit && m.time_s.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
    }) {
        return Err(PipelineError::Bug(format!(
            "move {} of the program (to {} deg) takes {} s: the planner put the same pose twice in a row",
            k + 1,
            m.q_deg.map(|v| fmt_fixed(v, 3)).join(", "),
            fmt_fixed(m.time_s, 3)
        )));
    }
    let text = emit::render(template, &program).map_err(PipelineError::Template)?;
    let verified = verify::check_text(ck, robot, &text, template.dialect, map)
        .map_err(|f| PipelineError::Unsafe(f.to_string()))?;
    Ok((program, text, verified))
}

/// The compiled plan written for another dialect (or template): the same poses, order, blends
/// and times, verified like [`compile`]'s own text.
pub fn retarget(
    robot: &Robot,
    opts: &CompileOptions,
    compiled: &Compiled,
    template: &str,
) -> Result<(Program, String), PipelineError> {
    let template =
        Template::from_source(template).map_err(|e| PipelineError::Template(e.to_string()))?;
    let map = controller_map(robot, opts, &template)?;
    let (scene, _) = build_scene(robot, &opts.cell, &opts.fixture, &compiled.cell.map)?;
    let ck = Checker::new(
        robot,
        &compiled.model,
        &compiled.cell,
        &scene,
        opts.cell.margin,
    );
    // The same poses and order; the corners by this dialect's controller, timed for it.
    let mut planned = Planned {
        selection: compiled.selection.clone(),
        time_unsorted: compiled.path.time_unsorted,
        time_direct: compiled.path.time_direct,
        plan: compiled.plan.clone(),
        replaced: compiled.report.replaced_unreachable,
    };
    blend(&ck, &mut planned.plan, opts, template.dialect, &map);
    let path = timed_path(
        &planned.plan,
        (planned.time_unsorted, planned.time_direct),
        &Limits::of(robot),
        template.dialect,
    );
    let base = program::base(
        &ck,
        opts,
        &compiled.identifiability,
        &planned,
        &path,
        &compiled.report.predicted_position_std_um,
    );
    let (program, text, _) = finish(&ck, robot, opts, &base, &template, &map)?;
    Ok((program, text))
}

/// Grid points on joints 2-6 the sampler enumerates at most (joint 1 is solved in closed form).
/// Measured on the NJ-130 cell, 2 cores: 5° = 2.7e8 points in 16 s, 3° = 3.4e9 in 233 s; the
/// limit is ~6 minutes there (a step of ~2.7°).
pub const GRID_LIMIT: f64 = 5e9;

/// Refuses, before any work, a grid too fine to enumerate: the product of the grid sizes of
/// joints 2-6 (the nested enumeration; held joints count once) against [`GRID_LIMIT`], with the
/// uniform step that would fit.
fn check_grid_size(robot: &Robot, cell: &Cell, cfg: &SampleConfig) -> Result<(), PipelineError> {
    let (lo, hi) = robot.limits();
    let m = cell.joint_margin;
    let lens: Vec<f64> = (1..6)
        .map(|i| {
            sample::joint_grid(lo[i] + m, hi[i] - m, cfg.step[i], cfg.movable[i], true).len() as f64
        })
        .collect();
    let points: f64 = lens.iter().product();
    if points <= GRID_LIMIT {
        return Ok(());
    }
    // The grid shrinks like step^-k in the k joints that are enumerated.
    let k = lens.iter().filter(|&&n| n > 1.0).count().max(1) as f64;
    let coarsest = (1..6)
        .filter(|&i| cfg.movable[i])
        .map(|i| cfg.step[i])
        .fold(0.0, f64::max);
    let min_step = coarsest * (points / GRID_LIMIT).powf(1.0 / k);
    let step = cfg.step.map(to_deg);
    let step_deg = if step.iter().all(|s| *s == step[0]) {
        crate::units::fmt_fixed(step[0], 3)
    } else {
        step.map(|s| crate::units::fmt_fixed(s, 3)).join(",")
    };
    Err(PipelineError::GridTooLarge {
        step_deg,
        points,
        min_step_deg: to_deg(min_step).max(0.01),
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

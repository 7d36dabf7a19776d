//! The loaded circle test as a program (`ldbb-circle`): in = robot, setup, the cell around it
//! and a dialect template; out = the dialect-free [`Program`], its text, and `verify`'s summary
//! of that text. The LDBB's own small chain (build → emit → verify), like the compiler's
//! pipeline: nothing is returned that `verify` did not pass.
//!
//! The program, per load in ascending order: a transit to the start of the lead-in (a
//! standstill for every load after the first) and a pause to mount the LDBB and set the load;
//! then the tool ball runs the circle with the setup's constant tool orientation at the setup's
//! speed: `overshoot` of lead-in, `repeats` measured circles, `overshoot` of lead-out (with one
//! repeat and 180°: twice around, as in the paper). The first load's measured circles start at
//! angle 0. The path is joint-space moves between IK points `step` apart along the circle,
//! blended; the header states how far the chords and blends take the bar length from the
//! circle's.
//!
//! The instrument's cell: the table ball is the fixture, its socket axis the circle's axis
//! (+z), the tool cup axis the tool ball's direction in the end link frame; both cones open
//! 10° beyond the largest bar angle the circle needs. The bar range is the nominal length
//! ± the stroke (`--stroke`, default 2 mm: the compliance deflection of a large robot at
//! 625 N is a few tenths of a millimetre). Without a cell file the LDBB body is a 40 mm
//! capsule between the balls, the table link a 20 mm post from the floor, and the tool a
//! 20 mm capsule from the end link to the tool ball.

use super::kin::{Arm, CircleIk};
use super::setup::Setup;
use crate::cell::{CellSpec, Shape, ShapeKind};
use crate::ir::{Header, Move, Program};
use crate::model::MeasurementModel;
use crate::robot::{Frame, Robot};
use crate::units::{fmt_fixed, to_deg, to_mm, DEG, MM};
use nalgebra::Vector3;
use std::f64::consts::TAU;

#[derive(Clone, Debug, PartialEq)]
pub struct ProgramOptions {
    /// Angle between programmed points (rad).
    pub step: f64,
    /// Blend distance at the corners (m).
    pub blend: f64,
    /// The LVDT's usable range either side of the nominal bar length (m).
    pub stroke: f64,
    /// The program's name for the controller (the output file's stem; made a valid name for
    /// the dialect when it is not one).
    pub program_name: String,
}

impl Default for ProgramOptions {
    fn default() -> Self {
        ProgramOptions {
            step: 0.5 * DEG,
            blend: 0.5 * MM,
            stroke: 2.0 * MM,
            program_name: String::new(),
        }
    }
}

pub const LDBB_BAR_DIAMETER_MM: f64 = 40.0;
pub const LDBB_STAND_RADIUS_MM: f64 = 20.0;
pub const LDBB_TOOL_RADIUS_MM: f64 = 20.0;
/// How far the cones open beyond the largest bar angle of the circle.
pub const CONE_MARGIN_DEG: f64 = 10.0;

#[derive(Debug, thiserror::Error)]
pub enum ProgramError {
    #[error("{0}")]
    Input(String),
    #[error("template: {0}")]
    Template(String),
    /// The program's own check failed (exit 1): nothing is written.
    #[error("the LDBB program fails its own check: {0}")]
    Unsafe(String),
}

/// The LDBB program with what went into it.
pub struct Compiled {
    pub program: Program,
    pub text: String,
    pub verified: crate::verify::Summary,
    pub cell: CellSpec,
    /// Largest change of the bar length along the programmed path (chords and blends), m.
    pub path_deviation: f64,
}

/// The largest angles between the bar and the socket axis (+z) and the cup axis (base frame)
/// over the circle (rad).
fn bar_angles(setup: &Setup, cup_base: &Vector3<f64>) -> (f64, f64) {
    let (mut socket, mut cup) = (0.0f64, 0.0f64);
    for k in 0..720 {
        let u = setup.bar_direction(k as f64 * TAU / 720.0);
        socket = socket.max(u.z.clamp(-1.0, 1.0).acos());
        cup = cup.max((-u).dot(cup_base).clamp(-1.0, 1.0).acos());
    }
    (socket, cup)
}

/// The cell `verify` checks the LDBB program in: `base` (a cell file, or the defaults) with
/// the instrument's geometry from the setup (see the module doc).
pub fn cell(
    setup: &Setup,
    base: Option<CellSpec>,
    opts: &ProgramOptions,
) -> Result<CellSpec, String> {
    let (map, orientation) = setup.tool()?;
    let from_file = base.is_some();
    let mut c = base.unwrap_or_default();
    let cup = if map.norm() > 1e-9 {
        map.normalize()
    } else {
        Vector3::z()
    };
    let (socket, cup_angle) = bar_angles(setup, &(orientation * cup));
    let open = |a: f64| (a + CONE_MARGIN_DEG * DEG).min(179.0 * DEG);
    c.fixture = Some(setup.table_ball);
    c.fixture_axis = Vector3::z();
    c.fixture_cone = open(socket);
    c.tool_axis = Some(cup);
    c.tool_cone = open(cup_angle);
    c.map = Some(map);
    c.bar_min = setup.bar_length - opts.stroke;
    c.bar_max = setup.bar_length + opts.stroke;
    if !from_file {
        c.bar_diameter = LDBB_BAR_DIAMETER_MM * MM;
        c.stand_radius = LDBB_STAND_RADIUS_MM * MM;
        if map.norm() > 0.05 {
            c.tool_shapes = vec![Shape {
                name: "LDBB tool".into(),
                origin: Frame::IDENTITY,
                kind: ShapeKind::Capsule {
                    a: [0.0; 3],
                    b: (map * 0.8).into(),
                    radius: LDBB_TOOL_RADIUS_MM * MM,
                },
            }];
        }
    }
    Ok(c)
}

fn load_text(f: f64) -> String {
    let s = format!("{f}");
    s.strip_suffix(".0").map(str::to_string).unwrap_or(s)
}

/// Builds, renders and verifies the loaded circle program. `inputs_sha256` is the hash of
/// what went in (robot, setup, cell, options, template), for the header.
pub fn compile(
    robot: &Robot,
    setup: &Setup,
    spec: &CellSpec,
    opts: &ProgramOptions,
    template: &str,
    inputs_sha256: &str,
) -> Result<Compiled, ProgramError> {
    let input = |e: String| ProgramError::Input(e);
    if !(opts.step > 0.0 && opts.step <= 10.0 * DEG) {
        return Err(input(format!(
            "--step: {} deg must be in (0, 10]",
            to_deg(opts.step)
        )));
    }
    let template = crate::dialect::Template::from_source(template)
        .map_err(|e| ProgramError::Template(e.to_string()))?;
    // The chords' blends by the dialect's corner model: none where its blend instruction bounds
    // no corner region (URScript's movej blends, FANUC's CNT); a zone the controller may enlarge
    // (ABB: up to 10 %) written that much smaller; else the blend distance.
    let corner = &template.dialect.corner;
    let blend = if corner.kind == crate::dialect::CornerKind::Unbounded {
        0.0
    } else {
        opts.blend
    };
    let blend_value = if corner.kind == crate::dialect::CornerKind::TcpDistance {
        (to_mm(blend) / (1.0 + corner.tolerance.max(0.0)) * 1e3 * (1.0 - 1e-12)).floor() / 1e3
    } else {
        to_mm(blend)
    };
    let (map, orientation) = setup.tool().map_err(input)?;
    let arm = Arm { robot, map };
    let ik = CircleIk::new(arm.clone(), orientation, setup).map_err(input)?;
    let per_rev = (TAU / opts.step).round() as usize;
    let step = TAU / per_rev as f64;
    let over = (setup.circle.overshoot / step).round() as usize;
    let speeds = robot.max_speeds();
    let table = setup.table_ball;
    // Joint solutions of one revolution (the branch closes on itself).
    let qs: Vec<[f64; 6]> = (0..per_rev)
        .map(|k| {
            ik.at(setup, k as f64 * step)
                .map(|q| crate::emit::emitted(&q))
                .ok_or_else(|| {
                    input(format!(
                        "no IK at circle angle {:.2} deg",
                        k as f64 * step / DEG
                    ))
                })
        })
        .collect::<Result<_, _>>()?;
    let circle = Circle {
        setup,
        arm,
        table,
        qs,
        step,
        over,
        chord: 2.0 * setup.circle.radius * (0.5 * step).sin(),
        blend,
        blend_value,
    };
    let model = MeasurementModel::new(robot, table, map);
    let moves = circle.moves(&speeds);
    let dev = circle.path_deviation(&model);
    let header = ldbb_header(robot, spec, opts, &circle, dev, &moves, inputs_sha256);
    let base = Program { header, moves };
    let cmap = crate::controller::ControllerMap::resolve(
        spec.controller.as_ref(),
        &template.dialect.defaults(),
        &template.dialect.name,
        robot,
    )
    .map_err(|e| input(e.to_string()))?;
    // Check the text, not the memory: the same last step and `verify` as every program.
    let (scene, _) = crate::pipeline::build_scene(robot, spec, &table, &map)
        .map_err(|e| input(e.to_string()))?;
    let cellv =
        crate::pipeline::make_cell(robot, table, map, spec).map_err(|e| input(e.to_string()))?;
    let ck = crate::safety::Checker::new(robot, &model, &cellv, &scene, spec.margin);
    let (program, text, verified) = crate::pipeline::emit_checked(
        &ck,
        robot,
        &base,
        &template,
        &cmap,
        "LDBB_CIRCLE",
        inputs_sha256,
    )
    .map_err(|e| match e {
        crate::pipeline::PipelineError::Template(m) => ProgramError::Template(m),
        crate::pipeline::PipelineError::Unsafe(m) => ProgramError::Unsafe(m),
        e => input(e.to_string()),
    })?;
    Ok(Compiled {
        program,
        text,
        verified,
        cell: spec.clone(),
        path_deviation: dev,
    })
}

/// The programmed circle: the set-up, the arm with its tool ball, the table ball (m), the joint
/// solutions of one revolution `step` (rad) apart, the lead-in and lead-out (steps), the chord
/// (m) and the blend (m, and the value the dialect writes).
struct Circle<'a> {
    setup: &'a Setup,
    arm: Arm<'a>,
    table: Vector3<f64>,
    qs: Vec<[f64; 6]>,
    step: f64,
    over: usize,
    chord: f64,
    blend: f64,
    blend_value: f64,
}

impl Circle<'_> {
    /// The joint solution at step `k` of the circle, any revolution.
    fn at(&self, k: i64) -> [f64; 6] {
        let per_rev = self.qs.len();
        self.qs[k.rem_euclid(per_rev as i64) as usize]
    }

    /// The bar length (m) at joint position `q`.
    fn length(&self, q: &[f64; 6]) -> f64 {
        (self.arm.map_position(q) - self.table).norm()
    }

    /// Steps per load: the lead-in, the measured revolutions and the lead-out.
    fn per_load(&self) -> usize {
        2 * self.over + self.setup.repeats * self.qs.len()
    }

    /// The moves of every load in turn, timed with the joints' `speeds` (rad/s).
    fn moves(&self, speeds: &[f64; 6]) -> Vec<Move> {
        let setup = self.setup;
        let (per_rev, step, over, chord) = (self.qs.len(), self.step, self.over, self.chord);
        let (blend, blend_value) = (self.blend, self.blend_value);
        let at = |k: i64| self.at(k);
        let length = |q: &[f64; 6]| self.length(q);
        let per_load = self.per_load();
        let mut moves = Vec::new();
        let mut start: i64 = -(over as i64);
        for (j, &load) in setup.loads.iter().enumerate() {
            let f = load_text(load);
            let q0 = at(start);
            moves.push(Move {
                q_deg: q0.map(to_deg),
                support: false,
                transit: true,
                pose: moves.len() + 1,
                blend_mm: 0.0,
                time_s: 0.0,
                cruise_s: 0.0,
                blend_value: 0.0,
                length_mm: to_mm(length(&q0)),
                note: format!(
                    "{f} N: start of the lead-in, angle {} deg{}",
                    fmt_fixed((start.rem_euclid(per_rev as i64)) as f64 * step / DEG, 1),
                    if j == 0 { ", approach without the LDBB" } else { ", standstill" }
                ),
                pause: if j == 0 {
                    format!("mount the LDBB between the table ball and the tool ball, set the load to {f} N, then resume")
                } else {
                    format!("set the load to {f} N, then resume")
                },
                pause_before: if j == 0 {
                    String::new()
                } else {
                    "release the load; the LDBB may stay mounted, the next move is a standstill".into()
                },
                section: j + 1,
                remove_before: j > 0,
                mount_after: true,
                axes: [0.0; 6],
                speed_pct: 0.0,
                dwell_s: 0.0,
            });
            for s in 1..=per_load {
                let k = start + s as i64;
                let q = at(k);
                let angle = k.rem_euclid(per_rev as i64) as f64 * step / DEG;
                let phase = if s <= over {
                    "lead-in".to_string()
                } else if s > over + setup.repeats * per_rev {
                    "lead-out".to_string()
                } else {
                    format!("run {}", (s - over - 1) / per_rev + 1)
                };
                let starts =
                    s > over && (s - over) % per_rev == 0 && s < over + setup.repeats * per_rev;
                let note = if s == over {
                    format!(
                        "{f} N {phase} {} deg: run 1 starts here",
                        fmt_fixed(angle, 1)
                    )
                } else if starts {
                    format!(
                        "{f} N {phase} {} deg: run {} starts here",
                        fmt_fixed(angle, 1),
                        (s - over) / per_rev + 1
                    )
                } else {
                    format!("{f} N {phase} {} deg", fmt_fixed(angle, 1))
                };
                let prev = at(k - 1);
                let t =
                    (chord / setup.circle.speed).max(crate::order::move_time(&prev, &q, speeds));
                moves.push(Move {
                    q_deg: q.map(to_deg),
                    support: false,
                    transit: false,
                    pose: moves.len() + 1,
                    blend_mm: if s == per_load || blend_value <= 0.0 {
                        0.0
                    } else {
                        to_mm(blend)
                    },
                    time_s: t,
                    // The circle's constant speed is the cruise; its chords blend into each other.
                    cruise_s: t,
                    blend_value: if s == per_load || blend_value <= 0.0 {
                        0.0
                    } else {
                        blend_value
                    },
                    length_mm: to_mm(length(&q)),
                    note,
                    pause: String::new(),
                    pause_before: String::new(),
                    section: j + 1,
                    remove_before: false,
                    mount_after: false,
                    axes: [0.0; 6],
                    speed_pct: 0.0,
                    dwell_s: 0.0,
                });
            }
            start += per_load as i64;
        }
        moves
    }

    /// How far chords and blends take the bar length from the circle's over one revolution (m).
    fn path_deviation(&self, model: &MeasurementModel) -> f64 {
        let setup = self.setup;
        let at = |k: i64| self.at(k);
        let length = |q: &[f64; 6]| self.length(q);
        let blend = self.blend;
        let per_rev = self.qs.len();
        let mut dev = 0.0f64;
        for k in 0..per_rev as i64 {
            let (a, b, c) = (at(k - 1), at(k), at(k + 1));
            let mid: [f64; 6] = std::array::from_fn(|i| 0.5 * (a[i] + b[i]));
            dev = dev.max((length(&mid) - setup.bar_length).abs());
            dev = dev.max((length(&b) - setup.bar_length).abs());
            if let Some(bl) = crate::safety::blend::geometry(model, &a, &b, &c, blend) {
                dev = dev.max((length(&bl.point(0.5)) - setup.bar_length).abs());
            }
        }
        dev
    }
}

/// The program's header for `robot` in the cell `spec`: the circle's notes (with its path
/// deviation `dev`, m), the moves' count and time, the inputs' hash.
fn ldbb_header(
    robot: &Robot,
    spec: &CellSpec,
    opts: &ProgramOptions,
    c: &Circle,
    dev: f64,
    moves: &[Move],
    inputs_sha256: &str,
) -> Header {
    let setup = c.setup;
    let (table, map, blend) = (c.table, c.arm.map, c.blend);
    let total: f64 = moves.iter().map(|m| m.time_s).sum();
    let notes = header_notes(c, opts, dev, total);
    Header {
        title: "LDBB loaded circle test".into(),
        instrument: "LDBB".into(),
        notes,
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        robot: robot.name.clone(),
        robot_file: robot.source.clone(),
        fixture_mm: table.map(to_mm).into(),
        map_mm: map.map(to_mm).into(),
        bar_mm: [to_mm(spec.bar_min), to_mm(spec.bar_max)],
        accelerations: robot.max_accelerations().map(to_deg),
        blend_mm: to_mm(blend),
        margin_mm: to_mm(spec.margin),
        joint_margin_deg: to_deg(spec.joint_margin),
        poses: moves.len(),
        supports: 0,
        sections: setup.loads.len(),
        identifiable: 0,
        cond: 0.0,
        time_unsorted_s: total,
        time_s: total,
        time_direct_s: total,
        inputs_sha256: inputs_sha256.to_string(),
        joint_names: robot.joints.iter().map(|j| j.name.clone()).collect(),
        // The LDBB circle identifies no geometry: no calibration prediction (not rendered).
        predicted_std_um: 0.0,
        bar_noise_um: 0.0,
        bar_rate_hz: 0.0,
        program_name: opts.program_name.clone(),
        dialect: String::new(),
        controller: String::new(),
        axis_names: Vec::new(),
        axis_units: String::new(),
        axis_decimals: 0,
        dwell_s: 0.0,
        measure_mm: Vec::new(),
        plateau_samples: 0,
        predicted_continuous_std_um: 0.0,
    }
}

/// The header's notes of the `circle`: the circle, the bar, the tool orientation, the loads, the path (its
/// deviation `dev`, m) and the estimated time `total` (s).
fn header_notes(circle: &Circle, opts: &ProgramOptions, dev: f64, total: f64) -> Vec<String> {
    let setup = circle.setup;
    let (step, over, chord, blend) = (circle.step, circle.over, circle.chord, circle.blend);
    let per_load = circle.per_load();
    let run_time = per_load as f64 * chord / setup.circle.speed;
    let dir = match setup.circle.direction {
        super::setup::Direction::Clockwise => "clockwise",
        super::setup::Direction::Counterclockwise => "counterclockwise",
    };
    let c = &setup.circle;
    let r = setup
        .orientation
        .unwrap_or_else(nalgebra::Matrix3::identity);
    let row = |i: usize| {
        format!(
            "[{}, {}, {}]",
            fmt_fixed(r[(i, 0)], 6),
            fmt_fixed(r[(i, 1)], 6),
            fmt_fixed(r[(i, 2)], 6)
        )
    };
    vec![
        format!(
            "circle: centre {}, {}, {} mm, diameter {} mm, {dir} seen from +z, {} mm/s; angle 0 at +x of the circle, growing along the travel",
            fmt_fixed(to_mm(c.centre.x), 3),
            fmt_fixed(to_mm(c.centre.y), 3),
            fmt_fixed(to_mm(c.centre.z), 3),
            fmt_fixed(to_mm(2.0 * c.radius), 3),
            fmt_fixed(to_mm(c.speed), 1)
        ),
        format!(
            "table ball = fixture; nominal bar length {} mm, LVDT stroke +-{} mm",
            fmt_fixed(to_mm(setup.bar_length), 3),
            fmt_fixed(to_mm(opts.stroke), 1)
        ),
        format!("tool orientation [rows of base_R_end]: {}, {}, {}", row(0), row(1), row(2)),
        format!(
            "loads: {} N ascending; per load {} measured circle{} between {} deg of lead-in and of lead-out, {} s at speed",
            setup.loads.iter().map(|f| load_text(*f)).collect::<Vec<_>>().join(", "),
            setup.repeats,
            if setup.repeats == 1 { "" } else { "s" },
            fmt_fixed(over as f64 * step / DEG, 1),
            fmt_fixed(run_time, 1)
        ),
        format!(
            "path: joint moves {} deg apart, {}; they change the bar length by at most {} um against the circle",
            fmt_fixed(step / DEG, 3),
            if blend > 0.0 {
                format!("{} mm blends", fmt_fixed(to_mm(blend), 2))
            } else {
                "an exact stop at each (this controller's joint-move blends bound no corner region)"
                    .to_string()
            },
            fmt_fixed(dev * 1e6, 2)
        ),
        format!("estimated time: {} s of motion; pauses not included", fmt_fixed(total, 1)),
    ]
}

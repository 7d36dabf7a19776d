//! Verification: in = program text, robot and cell; out = a [`Summary`] of what the program
//! really does, or the first [`Failure`] (line, time, what hit what or which limit).
//!
//! `verify` never looks at the compiler's memory: it re-reads the text with the dialect's
//! reader ([`crate::dialect`]), undoing the controller mapping, reconstructs the motion the
//! controller will execute — straight joint moves, and at every blended corner the whole region
//! a controller following the dialect's documented corner model may execute
//! ([`crate::safety::blend::region`]) — and checks every pose, move and corner region
//! continuously with [`crate::safety::Checker`]. The bar is mounted at the first pause,
//! removed at the next, and so on; moves without it (the approach, transits between sections)
//! are checked for the robot's collisions, limits and harness. A program whose header declares
//! a controller mapping other than the one in force fails before anything else.

pub mod limits;
pub mod trace;

/// The RS274/NGC reader as `verify::gcode::parse` (ngc text with the identity mapping); the
/// readers live in [`crate::dialect`].
pub mod gcode {
    pub use crate::dialect::{Line, ParseError, Parsed, Step, Timing};

    /// Reads RS274/NGC text with model joints as X Y Z A B C (degrees), timed as LinuxCNC
    /// times it (the ngc dialect's [`crate::dialect::ProgramTiming`]).
    pub fn parse(text: &str) -> Result<Parsed, ParseError> {
        match crate::dialect::by_name("ngc") {
            Some(d) => d.read(text, &Parsed::default().map),
            None => crate::dialect::ngc::parse(text, &Parsed::default().map),
        }
    }
}

use crate::collision::Contact;
use crate::controller::ControllerMap;
use crate::dialect::{CornerKind, Dialect, MoveTime, Parsed, Step};
use crate::ir::Reason;
use crate::order::move_time;
use crate::robot::Robot;
use crate::safety::{blend, describe_contact, Checker, Extremes, Violation};
use crate::timing::{self, Limits};
use crate::units::{fmt_fixed, DEG};
use serde::{Deserialize, Serialize};

/// The limits a program's header states it was compiled to (the line `bar range: 300.0..520.0
/// mm; corner blend: 10.0 mm; safety margin: 10.0 mm; joint margin: 1.0 deg`, in every
/// dialect; FANUC separates the facts with commas), each None where the header does not state
/// it. Millimetres and degrees, as printed (0.1 mm and 0.1°). Also the line `joint
/// accelerations: a1, .., a6 deg/s^2` (or `rad/s^2`): the accelerations the program's times
/// assume, per controller axis in its units.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HeaderLimits {
    pub bar_mm: Option<[f64; 2]>,
    pub blend_mm: Option<f64>,
    pub margin_mm: Option<f64>,
    pub joint_margin_deg: Option<f64>,
    /// The joint accelerations the header states, in deg/s² (converted from rad/s² where the
    /// program counts in radians), with the resolution they were printed at (deg/s²).
    pub accelerations_deg: Option<([f64; 6], f64)>,
}

impl HeaderLimits {
    /// Reads the limits from a parsed program's header comments. A stated limit that does not
    /// read as a number is an error naming it (a header edited by hand must not be taken for
    /// one that states nothing).
    pub fn read(parsed: &Parsed) -> Result<HeaderLimits, String> {
        let bar = header_fact(&parsed.header, "bar range", "mm")?
            .map(|v| {
                let bad = || format!("program header: bar range '{v}' is not MIN..MAX mm");
                let (a, b) = v.split_once("..").ok_or_else(bad)?;
                let (a, b) = (number(a).ok_or_else(bad)?, number(b).ok_or_else(bad)?);
                if a > 0.0 && b > a {
                    Ok([a, b])
                } else {
                    Err(bad())
                }
            })
            .transpose()?;
        let scalar = |key: &str, unit: &str| -> Result<Option<f64>, String> {
            header_fact(&parsed.header, key, unit)?
                .map(|v| {
                    number(v).filter(|x| *x >= 0.0).ok_or_else(|| {
                        format!("program header: {key} '{v}' is not a number of {unit}")
                    })
                })
                .transpose()
        };
        Ok(HeaderLimits {
            bar_mm: bar,
            blend_mm: scalar("corner blend", "mm")?,
            margin_mm: scalar("safety margin", "mm")?,
            joint_margin_deg: scalar("joint margin", "deg")?,
            accelerations_deg: header_accelerations(&parsed.header)?,
        })
    }
}

/// The header's `joint accelerations: a1, .., a6 UNIT/s^2` in deg/s², and half the step of its
/// last printed digit (deg/s²): how far a value may lie from the printed one.
fn header_accelerations(header: &[String]) -> Result<Option<([f64; 6], f64)>, String> {
    for (unit, scale) in [("deg/s^2", 1.0), ("rad/s^2", 1.0 / DEG)] {
        let Some(v) = header_fact(header, "joint accelerations", unit)
            .ok()
            .flatten()
        else {
            continue;
        };
        let bad = || {
            format!(
                "program header: joint accelerations '{v}' are not six positive numbers of {unit}"
            )
        };
        let parts: Vec<&str> = v.split(',').map(str::trim).collect();
        let values: Vec<f64> = parts
            .iter()
            .filter_map(|p| number(p))
            .filter(|a| *a > 0.0)
            .collect();
        let a: [f64; 6] = values.try_into().map_err(|_| bad())?;
        let decimals = parts
            .iter()
            .map(|p| p.split_once('.').map_or(0, |(_, f)| f.len()))
            .max()
            .unwrap_or(0);
        let half = 0.5 * 10f64.powi(-(decimals as i32)) * scale;
        return Ok(Some((a.map(|x| x * scale), half)));
    }
    // Stated without a known unit: an error naming it, not a header that states nothing.
    if header
        .iter()
        .any(|h| h.trim_start().starts_with("joint accelerations:"))
    {
        return Err("program header: joint accelerations have no unit deg/s^2 or rad/s^2".into());
    }
    Ok(None)
}

fn number(s: &str) -> Option<f64> {
    s.trim().parse::<f64>().ok().filter(|v| v.is_finite())
}

/// The value of `key: VALUE UNIT` within a header comment: the key starts the comment or
/// follows a `;` or `,` separator, and the value runs to the unit. None when no comment has
/// the key; an error when the unit does not follow.
fn header_fact<'h>(header: &'h [String], key: &str, unit: &str) -> Result<Option<&'h str>, String> {
    for h in header {
        let mut from = 0;
        while let Some(at) = h[from..].find(key).map(|i| i + from) {
            let before = h[..at].trim_end();
            let starts = before.is_empty() || before.ends_with(';') || before.ends_with(',');
            if let Some(rest) = h[at + key.len()..].strip_prefix(':').filter(|_| starts) {
                let rest = rest.trim_start();
                let end = rest
                    .find(&format!(" {unit}"))
                    .filter(|&e| {
                        let after = &rest[e + 1 + unit.len()..];
                        after.is_empty() || after.starts_with([';', ',', ' '])
                    })
                    .ok_or_else(|| format!("program header: {key} '{rest}' has no unit {unit}"))?;
                return Ok(Some(rest[..end].trim()));
            }
            from = at + key.len();
        }
    }
    Ok(None)
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    /// Motion lines (including the approach).
    pub moves: usize,
    /// Measurement poses (motion lines without a `support` comment).
    pub poses: usize,
    pub supports: usize,
    /// Bar-mounted sections.
    pub sections: usize,
    pub blends: usize,
    /// Dwells (G4 and its kin) and their total (s): a stop-and-measure program's standstills.
    #[serde(default)]
    pub dwells: usize,
    #[serde(default)]
    pub dwell_s: f64,
    /// Program duration from the first move on (s), dwells included, pauses excluded.
    pub duration: f64,
    pub extremes: Extremes,
    /// Smallest clearance measured at the program's poses and blend midpoints.
    pub min_clearance: Contact,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Failure {
    /// 1-based program line of the motion that fails (0 = the program as a whole).
    pub line: usize,
    /// Program time at the failure (s), from the first move.
    pub time: f64,
    pub violation: Violation,
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "line {}, t = {} s: {}",
            self.line,
            fmt_fixed(self.time, 2),
            self.violation
        )
    }
}

pub(crate) fn fail(line: usize, time: f64, reason: Reason, detail: String) -> Failure {
    Failure {
        line,
        time,
        violation: Violation { reason, detail },
    }
}

struct Motion {
    line: usize,
    target: [f64; 6],
    /// The controller axes as the program states them.
    axes: [f64; 6],
    /// Its time at the cruise speed, and the whole move with its ramps.
    cruise: f64,
    duration: f64,
    /// The blend instruction's value (dialect unit) when the corner blends.
    blend: Option<f64>,
    corner: Option<CornerKind>,
    support: bool,
    /// Followed directly by another motion (no pause/dwell/end between): blendable corner.
    flows_on: bool,
    /// Followed by a pause.
    pause_after: bool,
    /// The dwells (s) that follow it before the next motion: the robot stands at its target.
    dwell_after: f64,
    /// The bar is in place during this move.
    mounted: bool,
}

/// Checks program text in `dialect`, read with the controller mapping `map`, against the
/// checker's robot and cell.
pub fn check_text(
    ck: &Checker,
    robot: &Robot,
    text: &str,
    dialect: &Dialect,
    map: &ControllerMap,
) -> Result<Summary, Failure> {
    let parsed = dialect.read(text, map).map_err(|e| {
        fail(
            e.line,
            0.0,
            Reason::Program,
            format!("cannot read the program: {}", e.msg),
        )
    })?;
    check(ck, robot, &parsed, dialect)
}

/// Checks a parsed program of `dialect` against the checker's robot and cell.
pub fn check(
    ck: &Checker,
    robot: &Robot,
    parsed: &Parsed,
    dialect: &Dialect,
) -> Result<Summary, Failure> {
    Ok(rebuild(ck, robot, parsed, dialect)?.0)
}

/// The motion a program commands, as `verify` rebuilt and checked it: per motion line (in
/// order) its line, target (model joints, rad), whether the bar is mounted during it, whether
/// it is a support pose, and its estimated start and end times (s from the first move).
#[derive(Clone, Debug, PartialEq)]
pub struct Executed {
    pub line: usize,
    pub target: [f64; 6],
    pub mounted: bool,
    pub support: bool,
    pub start: f64,
    pub end: f64,
    /// The move ends in a pause (the operator acts there).
    pub pause_after: bool,
}

/// [`check`], and the motions it rebuilt.
pub fn rebuild(
    ck: &Checker,
    robot: &Robot,
    parsed: &Parsed,
    dialect: &Dialect,
) -> Result<(Summary, Vec<Executed>), Failure> {
    // The joint values only mean what the mapping says: a program written for another
    // mapping (a wrong J2/J3 coupling, sign or offset) is refused before its poses are read.
    check_controller(parsed)?;
    let (motions, mount_at, blended, total) = timed_motions(robot, parsed, dialect)?;
    let n = motions.len();
    let free = ck.unmounted();
    let mut ext = Extremes::default();
    let mut time = 0.0;
    let mut min_clear = Contact {
        distance: f64::INFINITY,
        a: String::new(),
        b: String::new(),
    };
    let mut blends = 0;
    let note_clear = |q: &[f64; 6], min_clear: &mut Contact| {
        let c = ck.clearance(q);
        if c.distance < min_clear.distance {
            *min_clear = c;
        }
    };
    let mut executed = Vec::with_capacity(n);
    for j in 0..n {
        let m = &motions[j];
        let with = if m.mounted { ck } else { &free };
        let start = time;
        if j == 0 {
            // The approach starts wherever the robot is: only its target can be checked.
            with.pose(&m.target).map_err(|v| Failure {
                line: m.line,
                time,
                violation: v,
            })?;
        } else {
            let a = motions[j - 1].target;
            let mut e = Extremes::default();
            if let Err((s, v)) = with.line(&a, &m.target, &mut e) {
                return Err(Failure {
                    line: m.line,
                    time: time + s * m.duration,
                    violation: v,
                });
            }
            ext.merge(&e);
            time += m.duration;
        }
        executed.push(Executed {
            line: m.line,
            target: m.target,
            mounted: m.mounted,
            support: m.support,
            start,
            end: time,
            pause_after: m.pause_after,
        });
        time += m.dwell_after;
        // Where the bar goes in, the pose must hold it.
        if mount_at.contains(&(j + 1)) {
            ck.pose(&m.target).map_err(|v| Failure {
                line: m.line,
                time,
                violation: Violation {
                    reason: v.reason,
                    detail: format!("where the bar is mounted: {}", v.detail),
                },
            })?;
        }
        if m.mounted {
            note_clear(&m.target, &mut min_clear);
        }
        // The corner at the end of this move: the whole region the controller may execute.
        if blended[j] {
            let (e, middle) = check_corner(ck, dialect, &motions, j, time)?;
            ext.merge(&e);
            note_clear(&middle, &mut min_clear);
            blends += 1;
        }
    }
    debug_assert!((time - total).abs() >= 0.0);
    if min_clear.distance < ck.margin {
        return Err(fail(
            0,
            time,
            Reason::Collision,
            describe_contact(&min_clear, ck.margin),
        ));
    }
    Ok((
        Summary {
            moves: n,
            poses: motions.iter().filter(|m| !m.support).count(),
            supports: motions.iter().filter(|m| m.support).count(),
            sections: mount_at.len(),
            blends,
            dwells: motions.iter().filter(|m| m.dwell_after > 0.0).count(),
            dwell_s: motions.iter().map(|m| m.dwell_after).sum(),
            duration: total,
            extremes: ext,
            min_clearance: min_clear,
        },
        executed,
    ))
}

/// Refuses a program written for another controller mapping than the one in force.
fn check_controller(parsed: &Parsed) -> Result<(), Failure> {
    if let Some(declared) = parsed.header_value("controller") {
        let in_force = parsed.map.describe();
        if declared != in_force {
            return Err(fail(
                0,
                0.0,
                Reason::Program,
                format!(
                    "the program was written for the controller axes \"{declared}\", but the mapping in force is \"{in_force}\" (the cell's [controller] section, else the dialect's default)"
                ),
            ));
        }
    }
    Ok(())
}

/// Checks the corner at the end of motion `j` (at `time`): the whole region the controller may
/// execute. Returns the extremes met and the region's middle.
fn check_corner(
    ck: &Checker,
    dialect: &Dialect,
    motions: &[Motion],
    j: usize,
    time: f64,
) -> Result<(Extremes, [f64; 6]), Failure> {
    let m = &motions[j];
    let (a, b) = (&motions[j - 1], &motions[j + 1]);
    let len =
        |x: &[f64; 6], y: &[f64; 6]| (0..6).map(|i| (x[i] - y[i]).powi(2)).sum::<f64>().sqrt();
    let value = m.blend.unwrap_or(0.0);
    let at_corner = |v: Violation| Failure {
        line: m.line,
        time,
        violation: Violation {
            reason: v.reason,
            detail: format!(
                "in the corner region of its blend ({} {}{}): {}",
                dialect.corner.instruction,
                fmt_fixed(value, 3),
                if dialect.corner.unit.is_empty() {
                    String::new()
                } else {
                    format!(" {}", dialect.corner.unit)
                },
                v.detail
            ),
        },
    };
    let r = blend::region(
        ck,
        &dialect.corner,
        m.corner,
        &a.target,
        &m.target,
        &b.target,
        value,
        (len(&a.axes, &m.axes), len(&m.axes, &b.axes)),
    )
    .map_err(|why| {
        at_corner(Violation {
            reason: Reason::Program,
            detail: why.to_string(),
        })
    })?;
    let (e1, e2) = r.edges();
    let mut e = Extremes::default();
    ck.patch(&r.corner, &e1, &e2, &mut e)
        .map_err(|(_, v)| at_corner(v))?;
    Ok((e, r.point(0.5, 0.5)))
}

/// The program's estimated duration as `verify` times it (each move with its ramps at the robot's
/// accelerations, scaled where the dialect's controller blends; the blended corners' overlaps
/// taken off), without any safety check: what a recorded run of any program is compared with.
pub fn estimate(robot: &Robot, parsed: &Parsed, dialect: &Dialect) -> Result<f64, Failure> {
    Ok(timed_motions(robot, parsed, dialect)?.3)
}

/// The motions of a program with their mount state, the motions after which the bar goes in,
/// which corners blend, and the total time.
#[allow(clippy::type_complexity)]
fn timed_motions(
    robot: &Robot,
    parsed: &Parsed,
    dialect: &Dialect,
) -> Result<(Vec<Motion>, Vec<usize>, Vec<bool>, f64), Failure> {
    // The header's corner blend is the most the program may blend at any corner: a corner
    // blended more than the program states was not made by the compiler that wrote it.
    let stated_blend = HeaderLimits::read(parsed)
        .map_err(|e| fail(0, 0.0, Reason::Program, e))?
        .blend_mm;
    let speeds = robot.max_speeds();
    let lim = Limits::of(robot);
    // Collect the motions; the bar is mounted at the first pause, removed at the next, and so
    // on: a motion made while it is in place is checked with it.
    let mut motions: Vec<Motion> = Vec::new();
    let mut mounted = false;
    let mut mount_at: Vec<usize> = Vec::new();
    let mut prev: Option<([f64; 6], [f64; 6])> = None;
    for (k, l) in parsed.lines.iter().enumerate() {
        match &l.step {
            step @ Step::Move {
                target,
                axes,
                blend,
                ..
            } => {
                let q = target.map(|d| d * DEG);
                let cruise = match prev {
                    None => 0.0,
                    Some(from) => cruise_time(parsed, dialect, (&speeds, &lim), l, from, q)?,
                };
                let flows_on = matches!(
                    parsed.lines.get(k + 1).map(|n| &n.step),
                    Some(Step::Move { .. })
                );
                let support = l.comment.as_deref().is_some_and(|c| c.contains("support"));
                let corner = match step {
                    Step::Move { corner, .. } => *corner,
                    _ => None,
                };
                // Only a TCP distance is the header's kind of blend (mm at the MAP); the other
                // corner models' values are in their own units and bound other things.
                let tcp = corner.unwrap_or(dialect.corner.kind) == CornerKind::TcpDistance;
                if let (Some(b), Some(stated), true) = (blend, stated_blend, tcp) {
                    check_blend(l.line, *b, stated, corner.is_some())?;
                }
                motions.push(Motion {
                    line: l.line,
                    target: q,
                    axes: *axes,
                    cruise,
                    duration: 0.0,
                    blend: *blend,
                    corner,
                    support,
                    flows_on,
                    pause_after: matches!(
                        parsed.lines.get(k + 1).map(|n| &n.step),
                        Some(Step::Pause)
                    ),
                    mounted,
                    dwell_after: 0.0,
                });
                prev = Some((q, *axes));
            }
            Step::Pause => {
                mounted = !mounted;
                if mounted {
                    mount_at.push(motions.len());
                }
            }
            Step::Dwell(s) => {
                // The robot stands at the last motion's target; a dwell before the first motion
                // is before the program's time starts (from the first move).
                if let Some(m) = motions.last_mut() {
                    m.dwell_after += s;
                }
            }
            Step::End => {}
        }
    }
    if motions.is_empty() {
        return Err(fail(
            0,
            0.0,
            Reason::JointLimit,
            "the program commands no motion".into(),
        ));
    }
    if mount_at.is_empty() {
        // A program without pauses: the bar is taken as mounted throughout.
        motions.iter_mut().for_each(|m| m.mounted = true);
        mount_at.push(1);
    }
    let blended = blended_corners(&motions);
    let total = time_motions(&mut motions, &blended, &lim, dialect);
    Ok((motions, mount_at, blended, total))
}

/// A move's time at its cruise speed from `from` = (target, controller axes) to `q`, checked
/// against the robot's speeds (and accelerations, where the time word states the whole move).
fn cruise_time(
    parsed: &Parsed,
    dialect: &Dialect,
    (speeds, lim): (&[f64; 6], &Limits),
    l: &crate::dialect::Line,
    (p, from_axes): ([f64; 6], [f64; 6]),
    q: [f64; 6],
) -> Result<f64, Failure> {
    let step = &l.step;
    let min_time = move_time(&p, &q, speeds);
    // A standstill (the same target again, e.g. a pause for a load change) takes no time at
    // any speed.
    let standstill = (min_time == 0.0).then_some(0.0);
    let duration = parsed
        .duration(&from_axes, step, speeds)
        .or(standstill)
        .ok_or_else(|| {
            fail(
                l.line,
                0.0,
                Reason::JointSpeed,
                "the move's speed is left to the controller: only the approach (the first move) may do that".into(),
            )
        })?;
    // A whole-move time (RAPID `\T`, URScript `t`) must leave room for the ramps.
    let (min_time, what) = match (dialect.move_time, step) {
        (
            MoveTime::Total,
            Step::Move {
                timing: crate::dialect::Timing::Duration(_),
                ..
            },
        ) => (
            timing::move_time(&p, &q, lim, 1.0),
            "at its maximum speed and acceleration",
        ),
        _ => (min_time, "at its maximum speed"),
    };
    if duration < min_time * (1.0 - 1e-6) {
        return Err(fail(
            l.line,
            0.0,
            Reason::JointSpeed,
            format!(
                "move takes {} s but the slowest axis needs {} s {what}",
                fmt_fixed(duration, 3),
                fmt_fixed(min_time, 3)
            ),
        ));
    }
    // What the time word states: at the cruise (the ramps on top), or the whole move (its
    // cruise is what leaves the ramps room).
    Ok(match (dialect.move_time, step) {
        (
            MoveTime::Total,
            Step::Move {
                timing: crate::dialect::Timing::Duration(_),
                ..
            },
        ) => timing::cruise_of(duration, timing::accel_time(&p, &q, &lim.accel)),
        _ => duration,
    })
}

/// Refuses a TCP blend of `b` mm on line `line` beyond the header's `stated` corner blend
/// (`overrides`: the move overrides the dialect's own corner model).
fn check_blend(line: usize, b: f64, stated: f64, overrides: bool) -> Result<(), Failure> {
    // The header prints 0.1 mm; the program text the blend itself. A TCP blend that overrides
    // the dialect's own corner model (FANUC `CR` in a `CNT` dialect) is written in whole
    // millimetres: the stated blend rounded up.
    let allowed = if overrides {
        (stated - 1e-9).ceil()
    } else {
        stated + 0.05
    };
    if b > allowed + 1e-9 {
        return Err(fail(
            line,
            0.0,
            Reason::Program,
            format!(
                "the move blends its corner by {} mm, more than the {} mm corner blend the program header states",
                fmt_fixed(b, 3),
                fmt_fixed(stated, 1)
            ),
        ));
    }
    Ok(())
}

/// The corners that blend: into a move that follows directly, the bar in place on both.
fn blended_corners(motions: &[Motion]) -> Vec<bool> {
    let n = motions.len();
    (0..n)
        .map(|j| {
            let m = &motions[j];
            m.blend.is_some()
                && m.mounted
                && m.flows_on
                && j > 0
                && j + 1 < n
                && motions[j + 1].mounted
        })
        .collect()
}

/// The times: each move with its ramps (scaled where the controller blends), the blends'
/// overlaps off the total, as the compiler estimates them; the dwells on top. Sets each
/// motion's duration and returns the total.
fn time_motions(motions: &mut [Motion], blended: &[bool], lim: &Limits, dialect: &Dialect) -> f64 {
    let poses: Vec<[f64; 6]> = motions.iter().map(|m| m.target).collect();
    let cruise: Vec<f64> = motions.iter().map(|m| m.cruise).collect();
    let (durations, total) = timing::program(
        &poses,
        &cruise,
        blended,
        lim,
        dialect.corner.blend_acceleration,
    );
    for (m, d) in motions.iter_mut().zip(&durations) {
        m.duration = *d;
    }
    // The dwells: standstills at the moves' targets, on top of the moves.
    total + motions.iter().map(|m| m.dwell_after).sum::<f64>()
}

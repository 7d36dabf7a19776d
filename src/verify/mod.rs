//! Verification: in = program text, robot and cell; out = a [`Summary`] of what the program
//! really does, or the first [`Failure`] (line, time, what hit what or which limit).
//!
//! `verify` never looks at the compiler's memory: it re-reads the text with the dialect's
//! reader ([`crate::dialect`]), undoing the controller mapping, reconstructs the motion the
//! controller will execute — straight joint moves, and at every corner the blend of
//! [`crate::safety::blend`] with the blend distance in force — and checks every pose, move and
//! blend continuously with [`crate::safety::Checker`]. The bar is mounted at the first pause,
//! removed at the next, and so on; moves without it (the approach, transits between sections)
//! are checked for the robot's collisions, limits and harness. A program whose header declares
//! a controller mapping other than the one in force fails before anything else.

/// The RS274/NGC reader under its old path (`verify::gcode::parse` reads ngc text with the
/// identity mapping); the readers live in [`crate::dialect`].
pub mod gcode {
    pub use crate::dialect::{Line, ParseError, Parsed, Step, Timing};

    /// Reads RS274/NGC text with model joints as X Y Z A B C (degrees).
    pub fn parse(text: &str) -> Result<Parsed, ParseError> {
        crate::dialect::ngc::parse(text, &Parsed::default().map)
    }
}

use crate::collision::Contact;
use crate::controller::ControllerMap;
use crate::dialect::{Dialect, Parsed, Step};
use crate::ir::Reason;
use crate::order::move_time;
use crate::robot::Robot;
use crate::safety::{blend, describe_contact, Checker, Extremes, Violation};
use crate::units::{fmt_fixed, to_mm, DEG};
use serde::{Deserialize, Serialize};

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

fn fail(line: usize, time: f64, reason: Reason, detail: String) -> Failure {
    Failure {
        line,
        time,
        violation: Violation { reason, detail },
    }
}

struct Motion {
    line: usize,
    target: [f64; 6],
    duration: f64,
    blend: f64,
    support: bool,
    /// Followed directly by another motion (no pause/dwell/end between): blendable corner.
    flows_on: bool,
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
    check(ck, robot, &parsed)
}

/// Checks a parsed program (any dialect) against the checker's robot and cell.
pub fn check(ck: &Checker, robot: &Robot, parsed: &Parsed) -> Result<Summary, Failure> {
    // The joint values only mean what the mapping says: a program written for another
    // mapping (a wrong J2/J3 coupling, sign or offset) is refused before its poses are read.
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
    let speeds = robot.max_speeds();
    // Collect the motions; the bar is mounted at the first pause, removed at the next, and so
    // on: a motion made while it is in place is checked with it.
    let mut motions: Vec<Motion> = Vec::new();
    let mut mounted = false;
    let mut mount_at: Vec<usize> = Vec::new();
    let mut prev: Option<([f64; 6], [f64; 6])> = None;
    let (mut dwells, mut dwell_s) = (0usize, 0.0f64);
    for (k, l) in parsed.lines.iter().enumerate() {
        match &l.step {
            step @ Step::Move {
                target,
                axes,
                blend,
                ..
            } => {
                let q = target.map(|d| d * DEG);
                let duration = match prev {
                    None => 0.0,
                    Some((p, from_axes)) => {
                        let min_time = move_time(&p, &q, &speeds);
                        // A standstill (the same target again, e.g. a pause for a load
                        // change) takes no time at any speed.
                        let standstill = (min_time == 0.0).then_some(0.0);
                        let duration = parsed
                            .duration(&from_axes, step, &speeds)
                            .or(standstill)
                            .ok_or_else(|| {
                                fail(
                                    l.line,
                                    0.0,
                                    Reason::JointSpeed,
                                    "the move's speed is left to the controller: only the approach (the first move) may do that".into(),
                                )
                            })?;
                        if duration < min_time * (1.0 - 1e-6) {
                            return Err(fail(
                                l.line,
                                0.0,
                                Reason::JointSpeed,
                                format!(
                                    "move takes {} s but the slowest axis needs {} s at its maximum speed",
                                    fmt_fixed(duration, 3),
                                    fmt_fixed(min_time, 3)
                                ),
                            ));
                        }
                        duration
                    }
                };
                let flows_on = matches!(
                    parsed.lines.get(k + 1).map(|n| &n.step),
                    Some(Step::Move { .. })
                );
                let support = l.comment.as_deref().is_some_and(|c| c.contains("support"));
                motions.push(Motion {
                    line: l.line,
                    target: q,
                    duration,
                    blend: blend.unwrap_or(0.0) * 1e-3,
                    support,
                    flows_on,
                    mounted,
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
                dwells += 1;
                dwell_s += s;
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
    for j in 0..motions.len() {
        let m = &motions[j];
        let with = if m.mounted { ck } else { &free };
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
        // The corner at the end of this move, blended when the next motion follows directly.
        if m.mounted
            && m.blend > 0.0
            && m.flows_on
            && j > 0
            && j + 1 < motions.len()
            && motions[j + 1].mounted
        {
            let (a, b) = (motions[j - 1].target, motions[j + 1].target);
            if let Some(bl) = blend::geometry(ck.model, &a, &m.target, &b, m.blend) {
                let mut e = Extremes::default();
                if let Err((_, v)) = crate::safety::path::check_blend(ck, &bl, &mut e) {
                    let detail = format!(
                        "in the {} mm blend at the end of this move: {}",
                        fmt_fixed(to_mm(m.blend), 1),
                        v.detail
                    );
                    return Err(Failure {
                        line: m.line,
                        time,
                        violation: Violation {
                            reason: v.reason,
                            detail,
                        },
                    });
                }
                ext.merge(&e);
                note_clear(&bl.point(0.5), &mut min_clear);
                blends += 1;
            }
        }
    }
    if min_clear.distance < ck.margin {
        return Err(fail(
            0,
            time,
            Reason::Collision,
            describe_contact(&min_clear, ck.margin),
        ));
    }
    Ok(Summary {
        moves: motions.len(),
        poses: motions.iter().filter(|m| !m.support).count(),
        supports: motions.iter().filter(|m| m.support).count(),
        sections: mount_at.len(),
        blends,
        dwells,
        dwell_s,
        duration: time + dwell_s,
        extremes: ext,
        min_clearance: min_clear,
    })
}

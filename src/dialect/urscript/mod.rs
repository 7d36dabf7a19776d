//! Universal Robots URScript: in = a [`crate::ir::Program`] (through `urscript.j2`), a
//! `.script` text (through `reader`) or new joint values for a program read here; out = its
//! text, its [`crate::dialect::Parsed`] motions, or the [`Edit`]s that write the values.
//! Joints are a movej's list (radians); the controller's own kinematic calibration holds the
//! zeros.

mod reader;

pub use reader::parse;

use crate::controller::{ControllerMap, Units};
use crate::dialect::{werr, AxisZero, Edit, Language, NewValues, ParseError, Parsed, WriteError};
use crate::units::{ceil_fixed, fmt_fixed};

/// Universal Robots URScript.
pub struct UrScript;

impl Language for UrScript {
    fn name(&self) -> &'static str {
        "urscript"
    }

    fn template(&self) -> &'static str {
        include_str!("urscript.j2")
    }

    fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        parse(text, map)
    }

    /// The first statement is `def name():` in lower case (KRL's `DEF` in any case wins).
    fn recognises(&self, _text: &str, first_code: &str) -> u8 {
        if first_code.starts_with("def ") {
            3
        } else {
            0
        }
    }

    fn dwell_instruction(&self) -> &'static str {
        "sleep(seconds)"
    }

    /// Radians: 7 decimals (6e-6°); degrees 6.
    fn decimals(&self, units: Units) -> usize {
        match units {
            Units::Rad => 7,
            Units::Deg => 6,
        }
    }

    /// The movej's joint list becomes the new one; a named `t=` is rewritten when the move is
    /// slowed; the note is a comment after the def line. A movej to a name is refused (other
    /// moves may share it).
    fn write(
        &self,
        _text: &str,
        parsed: &Parsed,
        values: &[NewValues],
        note: &str,
        _map: &ControllerMap,
    ) -> Result<Vec<Edit>, WriteError> {
        let at = parsed
            .positions
            .header_at
            .ok_or_else(|| werr(0, "no def line"))?;
        let mut edits = vec![Edit::insert(at, format!("  # {note}\n"))];
        for (m, v) in parsed.positions.moves.iter().zip(values) {
            let list = m
                .axes
                .first()
                .ok_or_else(|| werr(m.line, "movej without its joint list"))?;
            edits.push(Edit::replace(
                list.clone(),
                format!("[{}]", v.axes.join(", ")),
            ));
            if let Some(t) = v.time {
                let r = m.time.clone().ok_or_else(|| {
                    werr(
                        m.line,
                        "the move's time must be slowed, but it is not given as t=: name it",
                    )
                })?;
                edits.push(Edit::replace(r, ceil_fixed(t, 4)));
            }
        }
        Ok(edits)
    }

    fn mastering(&self, z: &AxisZero) -> String {
        format!(
            "Universal Robots {}: calibration.conf [mounting] delta_theta += {} rad (the controller's own kinematic calibration)",
            z.axis,
            fmt_fixed(z.delta, 9)
        )
    }
}

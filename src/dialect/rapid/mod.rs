//! ABB RAPID: in = a [`crate::ir::Program`] (through `rapid.j2`), a program module (through
//! `reader`) or new joint values for a program read here; out = its text, its
//! [`crate::dialect::Parsed`] motions, or the [`Edit`]s that write the values. Joints are a
//! `MoveAbsJ`'s jointtarget (on the line or declared); the arm side's zero is the motor
//! calibration offset.

mod reader;

pub use reader::{parse, valid_name};

use crate::controller::{ControllerMap, Units};
use crate::dialect::{werr, AxisZero, Edit, Language, NewValues, ParseError, Parsed, WriteError};
use crate::units::{ceil_fixed, fmt_fixed};

/// ABB RAPID.
pub struct Rapid;

impl Language for Rapid {
    fn name(&self) -> &'static str {
        "rapid"
    }

    fn template(&self) -> &'static str {
        include_str!("rapid.j2")
    }

    fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        parse(text, map)
    }

    /// The first statement is `MODULE name`.
    fn recognises(&self, _text: &str, first_code: &str) -> u8 {
        if first_code.to_ascii_uppercase().starts_with("MODULE ") {
            4
        } else {
            0
        }
    }

    fn dwell_instruction(&self) -> &'static str {
        "WaitTime seconds;"
    }

    /// RAPID `num` is a 32-bit float (1.5e-5° at 180°): 5 decimals; radians 7.
    fn decimals(&self, units: Units) -> usize {
        match units {
            Units::Rad => 7,
            Units::Deg => 5,
        }
    }

    /// The jointtarget's robot axes become the new ones (the literal on the line, or a
    /// declared jointtarget's declaration: another move to the same name has the same nominal
    /// joints, so the same compensation); `\T` is rewritten when the move is slowed; the note
    /// is a comment after the MODULE line.
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
            .ok_or_else(|| werr(0, "no MODULE line"))?;
        let mut edits = vec![Edit::insert(at, format!("  ! {note}\n"))];
        for (m, v) in parsed.positions.moves.iter().zip(values) {
            let robax = m
                .axes
                .first()
                .ok_or_else(|| werr(m.line, "a jointtarget is [[robax], [extax]]"))?;
            edits.push(Edit::replace(
                robax.clone(),
                format!("[{}]", v.axes.join(", ")),
            ));
            if let Some(t) = v.time {
                let r = m
                    .time
                    .clone()
                    .ok_or_else(|| werr(m.line, "a timed MoveAbsJ without \\T"))?;
                edits.push(Edit::replace(r, ceil_fixed(t, 3)));
            }
        }
        Ok(edits)
    }

    fn mastering(&self, z: &AxisZero) -> String {
        format!(
            "ABB {}: {} deg on the arm side; the motor calibration offset (MOC.cfg, motor side, rad) changes by this times the axis's transmission ratio, with the motor's direction",
            z.axis,
            fmt_fixed(z.delta, 6)
        )
    }
}

//! SINUMERIK 840D part programs: in = a [`crate::ir::Program`] (through `sinumerik.j2`), a
//! program text (through `reader`) or new joint values for a program read here; out = its
//! text, its [`crate::dialect::Parsed`] motions, or the [`Edit`]s that write the values.
//! Joints are the machine axes `NAME=value`; an absolute encoder's zero is a machine datum.

mod reader;

pub use reader::parse;

use crate::controller::{ControllerMap, Units};
use crate::dialect::{
    werr, words_replaced, AxisZero, Edit, Language, NewValues, ParseError, Parsed, WriteError,
};
use crate::units::{fmt_fixed, inverse_time_feed};

/// SINUMERIK 840D.
pub struct Sinumerik;

impl Language for Sinumerik {
    fn name(&self) -> &'static str {
        "sinumerik"
    }

    fn template(&self) -> &'static str {
        include_str!("sinumerik.j2")
    }

    fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        parse(text, map)
    }

    /// Rounding with G641, or exact stop G60 in a text with `;` comments: more specific than a
    /// plain G-code start.
    fn recognises(&self, text: &str, _first_code: &str) -> u8 {
        if text.contains("G641") || text.contains("G60") && text.contains(';') {
            2
        } else {
            0
        }
    }

    fn dwell_instruction(&self) -> &'static str {
        "G4 F seconds"
    }

    /// SINUMERIK carries 4 decimals (the control resolves them with MD10210 INT_INCR_PER_DEG
    /// ≥ 10000, else it rounds to its resolution); radians 7.
    fn decimals(&self, units: Units) -> usize {
        match units {
            Units::Rad => 7,
            Units::Deg => 4,
        }
    }

    /// The block's axis words become all six new ones `NAME=value` (at the place of the
    /// first); a G93 F is rewritten when the move is slowed; the note is a comment on the
    /// first line. Refused after G91 (the words would be increments).
    fn write(
        &self,
        text: &str,
        parsed: &Parsed,
        values: &[NewValues],
        note: &str,
        map: &ControllerMap,
    ) -> Result<Vec<Edit>, WriteError> {
        if let Some(e) = &parsed.positions.unwritable {
            return Err(werr(e.line, e.msg.clone()));
        }
        let mut edits = vec![Edit::insert(0, format!("; {note}\n"))];
        for (m, v) in parsed.positions.moves.iter().zip(values) {
            let full = map
                .axis_names
                .iter()
                .zip(&v.axes)
                .map(|(n, x)| format!("{n}={x}"))
                .collect::<Vec<_>>()
                .join(" ");
            edits.extend(words_replaced(text, &m.axes, &full, m.line)?);
            if let Some(t) = v.time {
                let f = m
                    .time
                    .clone()
                    .ok_or_else(|| werr(m.line, "G93 move without F"))?;
                edits.push(Edit::replace(f, inverse_time_feed(t)));
            }
        }
        Ok(edits)
    }

    fn mastering(&self, z: &AxisZero) -> String {
        format!(
            "SINUMERIK {}: $MA_REFP_MOVE_DIST_CORR (MD34090, absolute encoder) += {} deg; check the sign on one axis (the offset's sign depends on the encoder's direction)",
            z.axis,
            fmt_fixed(z.delta, 6)
        )
    }
}

//! RS274/NGC (LinuxCNC, ISO CNC cores): in = a [`crate::ir::Program`] (through `ngc.j2`), a
//! program text (through `reader`) or new joint values for a program read here; out = its
//! text, its [`crate::dialect::Parsed`] motions, or the [`Edit`]s that write the values.
//! Joints are the axis words X Y Z A B C; LinuxCNC keeps a joint's zero in the INI file.

mod reader;

pub use reader::parse;

use crate::controller::{ControllerMap, Units};
use crate::dialect::{
    werr, words_replaced, AxisZero, Edit, Language, NewValues, ParseError, Parsed, WriteError,
};
use crate::units::{fmt_fixed, inverse_time_feed};

/// RS274/NGC.
pub struct Ngc;

const AXES: [char; 6] = ['X', 'Y', 'Z', 'A', 'B', 'C'];

impl Language for Ngc {
    fn name(&self) -> &'static str {
        "ngc"
    }

    fn template(&self) -> &'static str {
        include_str!("ngc.j2")
    }

    fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        parse(text, map)
    }

    /// A G-code program's first block starts with a G word or a block number (SINUMERIK's
    /// signs are more specific).
    fn recognises(&self, _text: &str, first_code: &str) -> u8 {
        u8::from(first_code.starts_with('G') || first_code.starts_with('N'))
    }

    fn dwell_instruction(&self) -> &'static str {
        "G4 P seconds"
    }

    /// G-code carries 6 decimals; radians 7 (6e-6°).
    fn decimals(&self, units: Units) -> usize {
        match units {
            Units::Rad => 7,
            Units::Deg => 6,
        }
    }

    /// The line's axis words become all six new ones (at the place of the first: a move may
    /// name only the axes that change); a G93 F is rewritten when the move is slowed; the note
    /// is a comment on the first line. Refused after G91 (the words would be increments).
    fn write(
        &self,
        text: &str,
        parsed: &Parsed,
        values: &[NewValues],
        note: &str,
        _map: &ControllerMap,
    ) -> Result<Vec<Edit>, WriteError> {
        if let Some(e) = &parsed.positions.unwritable {
            return Err(werr(e.line, e.msg.clone()));
        }
        let mut edits = vec![Edit::insert(
            0,
            format!("({})\n", note.replace(['(', ')'], "")),
        )];
        for (m, v) in parsed.positions.moves.iter().zip(values) {
            let full = AXES
                .iter()
                .zip(&v.axes)
                .map(|(a, x)| format!("{a}{x}"))
                .collect::<Vec<_>>()
                .join(" ");
            edits.extend(words_replaced(text, &m.axes, &full, m.line)?);
            if let Some(t) = v.time {
                let f = m
                    .time
                    .clone()
                    .ok_or_else(|| werr(m.line, "G93 move without F"))?;
                edits.push(Edit::replace(f, format!("F{}", inverse_time_feed(t))));
            }
        }
        Ok(edits)
    }

    fn mastering(&self, z: &AxisZero) -> String {
        format!(
            "LinuxCNC [JOINT_{}] HOME_OFFSET += {} (the joint's position at its home switch or index pulse)",
            z.index,
            fmt_fixed(z.delta, 6)
        )
    }
}

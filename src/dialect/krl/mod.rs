//! KUKA KRL (KSS 8.x): in = a [`crate::ir::Program`] (through `krl.j2`), a `.src` text (through
//! `reader`) or new joint values for a program read here; out = its text, its
//! [`crate::dialect::Parsed`] motions, or the [`Edit`]s that write the values. Joints are a
//! PTP's axis aggregate `{A1 …, A6 …}`; the controller keeps each axis's zero in `$MAMES`.

mod reader;

pub use reader::{parse, valid_name};

use crate::controller::{ControllerMap, Units};
use crate::dialect::{werr, AxisZero, Edit, Language, NewValues, ParseError, Parsed, WriteError};
use crate::units::fmt_fixed;

/// KUKA KRL.
pub struct Krl;

impl Language for Krl {
    fn name(&self) -> &'static str {
        "krl"
    }

    fn template(&self) -> &'static str {
        include_str!("krl.j2")
    }

    fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        parse(text, map)
    }

    /// The first statement is `DEF name( )` (in any case: it wins over URScript's `def`).
    fn recognises(&self, _text: &str, first_code: &str) -> u8 {
        if first_code.to_ascii_uppercase().starts_with("DEF ") {
            4
        } else {
            0
        }
    }

    fn dwell_instruction(&self) -> &'static str {
        "WAIT SEC seconds"
    }

    /// KRL `REAL` is a 32-bit float (1.5e-5° at 180°): 5 decimals; radians 7.
    fn decimals(&self, units: Units) -> usize {
        match units {
            Units::Rad => 7,
            Units::Deg => 5,
        }
    }

    /// The PTP's axis aggregate becomes all six new axes; a move that must be slower gets its
    /// lowered `$VEL_AXIS` set before it and the previous ones restored after it; the note is
    /// a comment after the DEF line. A PTP to a declared variable is refused (other moves may
    /// share it).
    fn write(
        &self,
        text: &str,
        parsed: &Parsed,
        values: &[NewValues],
        note: &str,
        _map: &ControllerMap,
    ) -> Result<Vec<Edit>, WriteError> {
        let at = parsed
            .positions
            .header_at
            .ok_or_else(|| werr(0, "no DEF line"))?;
        let mut edits = vec![Edit::insert(at, format!("; {note}\n"))];
        for (m, v) in parsed.positions.moves.iter().zip(values) {
            if let Some(p) = v.percent {
                let set = |to: &[f64; 6]| -> String {
                    (0..6)
                        .filter(|&i| p[i] != v.old_percent[i])
                        .map(|i| format!("$VEL_AXIS[{}] = {}\n", i + 1, to[i] as i64))
                        .collect()
                };
                let next_line = (m.line_range.end + 1).min(text.len());
                edits.push(Edit::insert(m.line_range.start, set(&p)));
                edits.push(Edit::insert(next_line, set(&v.old_percent)));
            }
            let agg = m
                .axes
                .first()
                .ok_or_else(|| werr(m.line, "no axis aggregate on the PTP line"))?;
            let list = v
                .axes
                .iter()
                .enumerate()
                .map(|(i, x)| format!("A{} {x}", i + 1))
                .collect::<Vec<_>>()
                .join(", ");
            edits.push(Edit::replace(agg.clone(), format!("{{{list}}}")));
        }
        Ok(edits)
    }

    fn mastering(&self, z: &AxisZero) -> String {
        format!(
            "KUKA $MACHINE.DAT: $MAMES[{}] += {} deg (the axis counter takes $MAMES at the mastering mark)",
            z.axis.get(1..).unwrap_or(""),
            fmt_fixed(z.delta, 6)
        )
    }
}

//! FANUC TP programs as LS text: in = a [`crate::ir::Program`] (through `fanuc.j2`), an LS text
//! (through `reader`) or new joint values for a program read here; out = its text, its
//! [`crate::dialect::Parsed`] motions, or the [`Edit`]s that write the values. Joints are the
//! J1..J6 of a move's position in `/POS`; the controller keeps each axis's zero as a master
//! count.

mod reader;

pub use reader::{parse, valid_name};

use crate::controller::{ControllerMap, Units};
use crate::dialect::{
    werr, wrap, AxisZero, Edit, Language, NewValues, ParseError, Parsed, WriteError,
};
use crate::units::{ceil_fixed, fmt_fixed};

/// FANUC LS.
pub struct Fanuc;

impl Language for Fanuc {
    fn name(&self) -> &'static str {
        "fanuc"
    }

    fn template(&self) -> &'static str {
        include_str!("fanuc.j2")
    }

    fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        parse(text, map)
    }

    /// The text starts with `/PROG`.
    fn recognises(&self, text: &str, _first_code: &str) -> u8 {
        if text.trim_start().starts_with("/PROG") {
            4
        } else {
            0
        }
    }

    fn dwell_instruction(&self) -> &'static str {
        "WAIT seconds(sec)"
    }

    /// FANUC LS positions resolve 0.001° (as printed); radians 7.
    fn decimals(&self, units: Units) -> usize {
        match units {
            Units::Rad => 7,
            Units::Deg => 3,
        }
    }

    /// The J1..J6 values of the move's position in `/POS` become the new ones (another move
    /// to the same position has the same nominal joints, so the same compensation); `n%` is
    /// lowered and a `sec`/`msec` time lengthened when the move must be slower; the note is
    /// remarks after `/MN`, the lines after them renumbered and `LINE_COUNT` grown.
    fn write(
        &self,
        text: &str,
        parsed: &Parsed,
        values: &[NewValues],
        note: &str,
        _map: &ControllerMap,
    ) -> Result<Vec<Edit>, WriteError> {
        let mut edits = note_edits(parsed, note)?;
        for (m, v) in parsed.positions.moves.iter().zip(values) {
            if m.axes.len() != 6 {
                return Err(werr(m.line, "the move's position lacks a joint value"));
            }
            for (r, x) in m.axes.iter().zip(&v.axes) {
                edits.push(Edit::replace(r.clone(), x.clone()));
            }
            if let Some(p) = v.percent {
                let r = m
                    .percent
                    .clone()
                    .ok_or_else(|| werr(m.line, "a J move without its speed n%"))?;
                edits.push(Edit::replace(r, format!("{}", p[0] as i64)));
            }
            if let Some(t) = v.time {
                let r = m
                    .time
                    .clone()
                    .ok_or_else(|| werr(m.line, "a timed J move without sec"))?;
                // As many decimals as the program wrote, at least 2.
                let digits = text[r.clone()]
                    .split_once('.')
                    .map_or(0, |(_, d)| d.len())
                    .max(2);
                edits.push(Edit::replace(r, ceil_fixed(t * m.time_per_s, digits)));
            }
        }
        Ok(edits)
    }

    fn mastering(&self, z: &AxisZero) -> String {
        let delta = fmt_fixed(z.delta, 6);
        match z.master_count_delta {
            Some(n) => format!(
                "FANUC $DMR_GRP[1].$MASTER_COUN[{}] += {n} (position = (encoder - master count) / pulses per deg; {delta} deg)",
                z.axis.get(1..).unwrap_or(""),
            ),
            None => format!(
                "FANUC {}: {delta} deg; give [controller] pulses_per_deg for the master count change ($DMR_GRP[1].$MASTER_COUN)",
                z.axis,
            ),
        }
    }
}

/// The note as remarks of at most 30 characters after `/MN`; the `/MN` lines after them
/// renumbered (each number right-aligned in the width it had) and `LINE_COUNT` grown.
fn note_edits(parsed: &Parsed, note: &str) -> Result<Vec<Edit>, WriteError> {
    let pos = &parsed.positions;
    let at = pos.header_at.ok_or_else(|| werr(0, "no /MN"))?;
    let chunks = wrap(note.replace(';', ","), 30);
    let n = chunks.len();
    let remarks: String = chunks
        .iter()
        .enumerate()
        .map(|(k, c)| format!("{:>4}:  !{c} ;\n", k + 1))
        .collect();
    let mut edits = vec![Edit::insert(at, remarks)];
    for (r, no) in &pos.line_numbers {
        let width = r.len();
        edits.push(Edit::replace(r.clone(), format!("{:>width$}", no + n)));
    }
    if let Some((r, v)) = &pos.line_count {
        edits.push(Edit::replace(r.clone(), format!("LINE_COUNT = {};", v + n)));
    }
    Ok(edits)
}

//! LDBB data files (DESIGN.md "LDBB loaded circle data"): in/out = CSV text; in memory SI.
//!
//! ```text
//! LOADED.csv  run,load_n,angle_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,deflection_um
//! LT.csv      angle_deg,error_um
//! ```
//! Read strictly: the header must be exactly the contract's, and every error names the line
//! and the column. The six joint columns are either all given or all empty, in every row alike.
//! Written with fixed decimals (deterministic bytes).

use crate::units::{fmt_fixed, DEG};

pub const LOADED_HEADER: &str =
    "run,load_n,angle_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,deflection_um";
pub const LT_HEADER: &str = "angle_deg,error_um";

const UM: f64 = 1e-6;

/// One LVDT sample (SI: rad, m, N).
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// Repeat number of its load, 1-based.
    pub run: usize,
    pub load: f64,
    /// Circle angle as recorded (rad, not wrapped).
    pub angle: f64,
    pub q: Option<[f64; 6]>,
    /// Bar length change (m), positive = longer.
    pub deflection: f64,
    /// 1-based line in the file (for messages).
    pub line: usize,
}

/// A loaded-circle recording.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Loaded {
    pub samples: Vec<Sample>,
}

impl Loaded {
    /// True when the rows carry joint angles.
    pub fn has_joints(&self) -> bool {
        self.samples.first().is_some_and(|s| s.q.is_some())
    }

    /// CSV text in the contract's form.
    pub fn to_csv(&self) -> String {
        let mut s = String::with_capacity(self.samples.len() * 100);
        s += LOADED_HEADER;
        s.push('\n');
        for x in &self.samples {
            s += &x.run.to_string();
            s.push(',');
            s += &fmt_fixed(x.load, 3);
            s.push(',');
            s += &fmt_fixed(x.angle / DEG, 6);
            for i in 0..6 {
                s.push(',');
                if let Some(q) = &x.q {
                    s += &fmt_fixed(q[i] / DEG, 6);
                }
            }
            s.push(',');
            s += &fmt_fixed(x.deflection / UM, 3);
            s.push('\n');
        }
        s
    }
}

/// A laser-tracker reference: unloaded kinematic error along the bar per angle (SI: rad, m).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Reference {
    pub angle: Vec<f64>,
    pub error: Vec<f64>,
}

impl Reference {
    pub fn to_csv(&self) -> String {
        let mut s = String::from(LT_HEADER);
        s.push('\n');
        for (a, e) in self.angle.iter().zip(&self.error) {
            s += &format!("{},{}\n", fmt_fixed(a / DEG, 6), fmt_fixed(e / UM, 3));
        }
        s
    }
}

use crate::twin::measured::err;
/// The measured-data contract's error: the same line, column and message as `diagnose` gives.
pub use crate::twin::measured::CsvError;

/// The data lines of a CSV text after its header, which must be exactly `header`.
fn body<'a>(
    text: &'a str,
    header: &str,
) -> Result<impl Iterator<Item = (usize, &'a str)>, CsvError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(k, l)| (k + 1, l.trim_end_matches('\r')))
        .filter(|(_, l)| !l.trim().is_empty());
    let (hl, h) = lines
        .next()
        .ok_or_else(|| err(1, "1", format!("empty file: expected the header {header}")))?;
    let got: Vec<&str> = h.split(',').map(str::trim).collect();
    let want: Vec<&str> = header.split(',').collect();
    if got != want {
        let col = got
            .iter()
            .zip(&want)
            .position(|(g, w)| g != w)
            .unwrap_or(got.len().min(want.len()));
        let name = want.get(col).copied().unwrap_or("(none)");
        return Err(err(
            hl,
            format!("{} ({name})", col + 1),
            format!(
                "the header must be exactly {header} (found '{}')",
                got.get(col).copied().unwrap_or("end of line")
            ),
        ));
    }
    Ok(lines)
}

fn number(line: usize, c: usize, name: &str, cell: &str) -> Result<f64, CsvError> {
    let col = || format!("{} ({name})", c + 1);
    let v: f64 = cell
        .parse()
        .map_err(|_| err(line, col(), format!("'{cell}' is not a number")))?;
    if !v.is_finite() {
        return Err(err(line, col(), format!("'{cell}' is not finite")));
    }
    Ok(v)
}

/// Parses LOADED.csv.
pub fn parse_loaded(text: &str) -> Result<Loaded, CsvError> {
    let names: Vec<&str> = LOADED_HEADER.split(',').collect();
    let mut out = Loaded::default();
    let mut joints: Option<bool> = None;
    for (line, raw) in body(text, LOADED_HEADER)? {
        let cells: Vec<&str> = raw.split(',').map(str::trim).collect();
        if cells.len() != names.len() {
            return Err(err(
                line,
                format!("{}", cells.len().min(names.len()) + 1),
                format!(
                    "{} cells, the header has {} columns",
                    cells.len(),
                    names.len()
                ),
            ));
        }
        let run: usize = cells[0].parse().ok().filter(|r| *r >= 1).ok_or_else(|| {
            err(
                line,
                "1 (run)",
                format!("'{}' is not a repeat number 1, 2, ...", cells[0]),
            )
        })?;
        let load = number(line, 1, names[1], cells[1])?;
        if load <= 0.0 {
            return Err(err(
                line,
                "2 (load_n)",
                format!("load {load} N is not positive"),
            ));
        }
        let angle = number(line, 2, names[2], cells[2])? * DEG;
        let empty = cells[3..9].iter().filter(|c| c.is_empty()).count();
        let q = match empty {
            6 => None,
            0 => {
                let mut q = [0.0; 6];
                for i in 0..6 {
                    q[i] = number(line, 3 + i, names[3 + i], cells[3 + i])? * DEG;
                }
                Some(q)
            }
            _ => {
                let c = 3 + cells[3..9].iter().position(|c| c.is_empty()).unwrap_or(0);
                return Err(err(
                    line,
                    format!("{} ({})", c + 1, names[c]),
                    "the six joint columns must be all given or all empty",
                ));
            }
        };
        match joints {
            None => joints = Some(q.is_some()),
            Some(j) if j != q.is_some() => {
                return Err(err(
                    line,
                    "4 (q1_deg)",
                    if j {
                        "joint angles missing here but given in the rows before"
                    } else {
                        "joint angles given here but empty in the rows before"
                    },
                ))
            }
            _ => {}
        }
        let deflection = number(line, 9, names[9], cells[9])? * UM;
        out.samples.push(Sample {
            run,
            load,
            angle,
            q,
            deflection,
            line,
        });
    }
    if out.samples.is_empty() {
        return Err(err(1, "1 (run)", "no data rows after the header"));
    }
    Ok(out)
}

/// Parses LT.csv (the laser-tracker reference).
pub fn parse_reference(text: &str) -> Result<Reference, CsvError> {
    let mut r = Reference::default();
    for (line, raw) in body(text, LT_HEADER)? {
        let cells: Vec<&str> = raw.split(',').map(str::trim).collect();
        if cells.len() != 2 {
            return Err(err(
                line,
                format!("{}", cells.len().min(2) + 1),
                format!("{} cells, the header has 2 columns", cells.len()),
            ));
        }
        r.angle.push(number(line, 0, "angle_deg", cells[0])? * DEG);
        r.error.push(number(line, 1, "error_um", cells[1])? * UM);
    }
    if r.angle.is_empty() {
        return Err(err(1, "1 (angle_deg)", "no data rows after the header"));
    }
    Ok(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_rejects_with_line_and_column() {
        let l = Loaded {
            samples: vec![
                Sample {
                    run: 1,
                    load: 125.0,
                    angle: 0.5 * DEG,
                    q: Some([0.1, -0.2, 0.3, 0.0, 1.0, -1.0]),
                    deflection: 12.345e-6,
                    line: 2,
                },
                Sample {
                    run: 2,
                    load: 250.0,
                    angle: 359.5 * DEG,
                    q: Some([0.1, -0.2, 0.3, 0.0, 1.0, -1.0]),
                    deflection: -1.5e-6,
                    line: 3,
                },
            ],
        };
        let back = parse_loaded(&l.to_csv()).unwrap();
        assert_eq!(back.samples.len(), 2);
        assert!((back.samples[0].deflection - 12.345e-6).abs() < 1e-12);
        assert!((back.samples[1].angle - 359.5 * DEG).abs() < 1e-12);

        let e = parse_loaded("run,load,angle_deg\n").unwrap_err();
        assert_eq!((e.line, e.column.as_str()), (1, "2 (load_n)"));
        let e = parse_loaded(&format!(
            "{LOADED_HEADER}\n1,125,0,,,,,,,3.0\n1,125,1,1,2,3,4,5,6,3\n"
        ))
        .unwrap_err();
        assert_eq!(e.line, 3, "{e}");
        let e = parse_loaded(&format!("{LOADED_HEADER}\n1,125,0,,,,,,,x\n")).unwrap_err();
        assert_eq!((e.line, e.column.as_str()), (2, "10 (deflection_um)"));
        let e = parse_loaded(&format!("{LOADED_HEADER}\n0,125,0,,,,,,,1\n")).unwrap_err();
        assert_eq!(e.column, "1 (run)");
        let e = parse_loaded(&format!("{LOADED_HEADER}\n1,125,0,1,,,,,,1\n")).unwrap_err();
        assert_eq!(e.column, "5 (q2_deg)");
        assert!(parse_reference("angle_deg,error_um\n0,1\n1,2\n").is_ok());
        assert_eq!(parse_reference("angle,error_um\n").unwrap_err().line, 1);
    }
}

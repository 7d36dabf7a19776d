//! The two log files (DESIGN.md, "Instrument and controller logs"): in/out = CSV text; in
//! memory SI units (s, m, rad).
//!
//! ```text
//! t_s,length_mm[,temp_c]          the bar's own recording, on its own clock
//! t_s,q1_deg,...,q6_deg           a controller's joint log, on its clock, in its axis values
//! ```
//! Written with fixed decimals (deterministic bytes); read strictly: every error names the line
//! and the column, and a header in other units (`length_m`, `t_ms`, `q1_rad`, ...) is refused
//! by name rather than read as if it were millimetres and seconds.

use crate::units::{fmt_fixed, DEG, MM};

/// The most rows a log may have (about 11 hours at 500 Hz): memory stays bounded.
pub const MAX_ROWS: usize = 20_000_000;

/// A bar log: the instrument's readings on its own clock (s), lengths (m), optional
/// temperatures (°C). Sorted by time; gaps allowed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BarLog {
    pub t: Vec<f64>,
    pub length: Vec<f64>,
    pub temp: Option<Vec<f64>>,
}

/// A joint log: a controller's axis values (rad, as the program writes them: the controller
/// mapping not undone) on its own clock (s). Sorted by time.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct JointLog {
    pub t: Vec<f64>,
    pub q: Vec<[f64; 6]>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
#[error("line {line}, column {column}: {msg}")]
pub struct LogError {
    pub line: usize,
    /// 1-based column number and, where known, its name.
    pub column: String,
    pub msg: String,
}

fn err(line: usize, column: impl Into<String>, msg: impl Into<String>) -> LogError {
    LogError {
        line,
        column: column.into(),
        msg: msg.into(),
    }
}

impl BarLog {
    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// CSV text: times to 1 µs, lengths to 0.1 µm, temperatures to 0.001 K.
    pub fn to_csv(&self) -> String {
        let mut s = String::with_capacity(self.len() * 32);
        s += "t_s,length_mm";
        if self.temp.is_some() {
            s += ",temp_c";
        }
        s.push('\n');
        for k in 0..self.len() {
            s += &fmt_fixed(self.t[k], 6);
            s.push(',');
            s += &fmt_fixed(self.length[k] / MM, 4);
            if let Some(t) = &self.temp {
                s.push(',');
                s += &fmt_fixed(t[k], 3);
            }
            s.push('\n');
        }
        s
    }
}

impl JointLog {
    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// CSV text: times to 1 µs, axis values to 1e-6 deg.
    pub fn to_csv(&self) -> String {
        let mut s = String::with_capacity(self.len() * 96);
        s += "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n";
        for k in 0..self.len() {
            s += &fmt_fixed(self.t[k], 6);
            for i in 0..6 {
                s.push(',');
                s += &fmt_fixed(self.q[k][i] / DEG, 6);
            }
            s.push('\n');
        }
        s
    }
}

/// A column the header must have; a name with the same stem in another unit is named.
fn find(names: &[&str], want: &str, line: usize) -> Result<usize, LogError> {
    if let Some(i) = names.iter().position(|n| *n == want) {
        return Ok(i);
    }
    let stem = want.rsplit_once('_').map_or(want, |(s, _)| s);
    let unit = want.rsplit_once('_').map_or("", |(_, u)| u);
    if let Some((i, other)) = names
        .iter()
        .enumerate()
        .find(|(_, n)| n.rsplit_once('_').is_some_and(|(s, _)| s == stem))
    {
        return Err(err(
            line,
            format!("{} ({other})", i + 1),
            format!("'{other}' is in another unit: the log's {stem} is '{want}' (in {unit})"),
        ));
    }
    Err(err(
        line,
        format!("{} ({want})", names.len() + 1),
        format!("missing column '{want}' in the header"),
    ))
}

/// The data lines of a CSV text: (1-based line number, cells), the header first.
fn rows(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(k, l)| (k + 1, l))
}

/// One parsed row: every cell a finite number, as many cells as the header has columns.
fn cells(line: usize, raw: &str, names: &[&str]) -> Result<Vec<f64>, LogError> {
    let at = |(c, m): (String, String)| err(line, c, m);
    let row = crate::files::csv_row(raw, names).map_err(at)?;
    (0..names.len())
        .map(|c| row.number(c).map_err(at))
        .collect()
}

fn sorted(line: usize, col: usize, t: f64, prev: Option<&f64>) -> Result<(), LogError> {
    if let Some(&p) = prev {
        if t <= p {
            return Err(err(
                line,
                format!("{} (t_s)", col + 1),
                format!(
                    "time {t} s is not after the previous row's {p} s (rows must be sorted by time)"
                ),
            ));
        }
    }
    Ok(())
}

fn too_many(line: usize) -> LogError {
    err(
        line,
        "1",
        format!("more than {MAX_ROWS} rows: split the run, or log at a lower rate"),
    )
}

/// Parses a bar log (`t_s,length_mm[,temp_c]`, further columns ignored). `min_rows`: fewer
/// rows are refused.
pub fn parse_bar_log(text: &str, min_rows: usize) -> Result<BarLog, LogError> {
    let mut it = rows(text);
    let (hl, header) = it
        .next()
        .ok_or_else(|| err(1, "1", "empty file: expected the header t_s,length_mm"))?;
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let ti = find(&names, "t_s", hl)?;
    let li = find(&names, "length_mm", hl)?;
    let temp = names.iter().position(|n| *n == "temp_c");
    let mut log = BarLog {
        temp: temp.map(|_| Vec::new()),
        ..BarLog::default()
    };
    for (line, raw) in it {
        if log.len() >= MAX_ROWS {
            return Err(too_many(line));
        }
        let v = cells(line, raw, &names)?;
        sorted(line, ti, v[ti], log.t.last())?;
        log.t.push(v[ti]);
        log.length.push(v[li] * MM);
        if let (Some(c), Some(temps)) = (temp, log.temp.as_mut()) {
            temps.push(v[c]);
        }
    }
    if log.len() < min_rows {
        return Err(err(
            text.lines().count().max(1),
            "1 (t_s)",
            format!(
                "{} data rows, fewer than the {min_rows} a bar log needs",
                log.len()
            ),
        ));
    }
    Ok(log)
}

/// Parses a joint log (`t_s,q1_deg,...,q6_deg`, further columns ignored).
pub fn parse_joint_log(text: &str, min_rows: usize) -> Result<JointLog, LogError> {
    let mut it = rows(text);
    let (hl, header) = it.next().ok_or_else(|| {
        err(
            1,
            "1",
            "empty file: expected the header t_s,q1_deg,...,q6_deg",
        )
    })?;
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let ti = find(&names, "t_s", hl)?;
    let mut qi = [0usize; 6];
    for (i, q) in qi.iter_mut().enumerate() {
        *q = find(&names, &format!("q{}_deg", i + 1), hl)?;
    }
    let mut log = JointLog::default();
    for (line, raw) in it {
        if log.len() >= MAX_ROWS {
            return Err(too_many(line));
        }
        let v = cells(line, raw, &names)?;
        sorted(line, ti, v[ti], log.t.last())?;
        log.t.push(v[ti]);
        log.q.push(std::array::from_fn(|i| v[qi[i]] * DEG));
    }
    if log.len() < min_rows {
        return Err(err(
            text.lines().count().max(1),
            "1 (t_s)",
            format!(
                "{} data rows, fewer than the {min_rows} a joint log needs",
                log.len()
            ),
        ));
    }
    Ok(log)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn logs_round_trip_through_their_csv() {
        let bar = BarLog {
            t: vec![12.5, 12.52, 13.0],
            length: vec![0.4123456, 0.41235, -0.0001],
            temp: Some(vec![20.0, 20.5, 21.25]),
        };
        let back = parse_bar_log(&bar.to_csv(), 1).unwrap();
        assert_eq!(back.t, bar.t);
        for (a, b) in back.length.iter().zip(&bar.length) {
            assert!((a - b).abs() < 1e-10, "{a} {b}");
        }
        assert_eq!(back.temp, bar.temp);
        let joints = JointLog {
            t: vec![0.0, 0.01],
            q: vec![[0.1, -0.2, 0.3, 0.0, 1.0, -1.0], [0.0; 6]],
        };
        let back = parse_joint_log(&joints.to_csv(), 1).unwrap();
        assert_eq!(back.t, joints.t);
        for (a, b) in back.q.iter().zip(&joints.q) {
            for i in 0..6 {
                assert!((a[i] - b[i]).abs() < 1e-7);
            }
        }
    }

    #[test]
    fn bad_logs_name_the_line_and_the_column() {
        let bad: &[(&str, usize, &str)] = &[
            ("", 1, "empty file"),
            ("t_s,length_m\n0,0.4\n", 1, "'length_m' is in another unit"),
            ("t_ms,length_mm\n0,400\n", 1, "'t_ms' is in another unit"),
            ("t_s,len\n0,400\n", 1, "missing column 'length_mm'"),
            ("t_s,length_mm\n0,400\n1,x\n", 3, "'x' is not a number"),
            ("t_s,length_mm\n1,400\n0.5,400\n", 3, "rows must be sorted"),
            ("t_s,length_mm\n0,400,3\n", 2, "3 cells"),
            ("t_s,length_mm\n0,NaN\n", 2, "not finite"),
        ];
        for (text, line, msg) in bad {
            let e = parse_bar_log(text, 1).unwrap_err();
            assert_eq!(e.line, *line, "{text:?}: {e}");
            assert!(e.msg.contains(msg), "{text:?}: {e}");
        }
        let e = parse_joint_log("t_s,q1_rad,q2_deg\n", 1).unwrap_err();
        assert!(e.msg.contains("'q1_rad' is in another unit"), "{e}");
        let e = parse_bar_log("t_s,length_mm\n0,400\n", 3).unwrap_err();
        assert!(e.msg.contains("fewer than the 3"), "{e}");
    }
}

//! Measured EDBB data (DESIGN.md's CSV contract): in/out = CSV text; in memory SI units.
//!
//! ```text
//! t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm[,temp_c]      continuous
//! q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm[,std_um][,n][,temp_c]   static
//! ```
//! The static form (no `t_s`) holds one reading per pose in the order taken; its rows get their
//! order (0, 1, 2, ...) as `t` and [`Form::Static`] `{ timed: false }`. `std_um` (the reading's
//! standard uncertainty) and `n` (bar samples averaged) are read in either form. Written with a
//! fixed number of decimals (deterministic bytes); read strictly: every error names the line and
//! the column.

use crate::units::{fmt_fixed, DEG, MM};

pub const COLUMNS: [&str; 8] = [
    "t_s",
    "q1_deg",
    "q2_deg",
    "q3_deg",
    "q4_deg",
    "q5_deg",
    "q6_deg",
    "length_mm",
];

/// How a run's readings were taken: the effects that can be fitted to it depend on it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Form {
    /// A continuous recording: one row per bar sample while the robot moves, joints
    /// interpolated to the bar's time stamps (the paper's Section 3.1).
    #[default]
    Continuous,
    /// One reading per pose at standstill (the static CSV form without `t_s`, or the plateaus
    /// of a stop-and-measure bar log). `timed`: `t` holds real times (plateau midpoints on the
    /// bar's clock); otherwise `t` is the row's order (0, 1, 2, ...) and no time-dependent
    /// effect may be fitted. Velocities are zero; the approach direction of a reading is
    /// the motion from the previous row.
    Static { timed: bool },
}

impl Form {
    /// True when `t` holds real times (a time-dependent effect may be fitted).
    pub fn timed(&self) -> bool {
        match self {
            Form::Continuous => true,
            Form::Static { timed } => *timed,
        }
    }

    /// The report's name of the form.
    pub fn name(&self) -> &'static str {
        match self {
            Form::Continuous => "continuous",
            Form::Static { timed: true } => "static, timed",
            Form::Static { timed: false } => "static",
        }
    }
}

/// One recorded run, in the order taken (sorted by time when timed). SI: s, rad, m, °C.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Measured {
    pub t: Vec<f64>,
    pub q: Vec<[f64; 6]>,
    pub length: Vec<f64>,
    pub temp: Option<Vec<f64>>,
    /// Per-reading standard uncertainty of `length` (m), where the data state it: the static
    /// form's `std_um`, a plateau's standard error. `None`: estimated from the residual.
    pub std: Option<Vec<f64>>,
    /// Bar samples averaged into each reading (the static form's `n`, a plateau's samples).
    pub samples: Option<Vec<u32>>,
    pub form: Form,
}

impl Measured {
    pub fn len(&self) -> usize {
        self.t.len()
    }

    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// CSV text: times to 1 ms, angles to 1e-6 deg, lengths to 0.1 µm, uncertainties to
    /// 1 nm, temperatures to 0.001 K. An untimed static run is written in the static form
    /// (no `t_s`).
    pub fn to_csv(&self) -> String {
        let timed = self.form.timed();
        let mut s = String::with_capacity(self.len() * 90);
        let cols = if timed { &COLUMNS[..] } else { &COLUMNS[1..] };
        s += &cols.join(",");
        if self.std.is_some() {
            s += ",std_um";
        }
        if self.samples.is_some() {
            s += ",n";
        }
        if self.temp.is_some() {
            s += ",temp_c";
        }
        s.push('\n');
        for k in 0..self.len() {
            if timed {
                s += &fmt_fixed(self.t[k], 3);
                s.push(',');
            }
            for i in 0..6 {
                s += &fmt_fixed(self.q[k][i] / DEG, 6);
                s.push(',');
            }
            s += &fmt_fixed(self.length[k] / MM, 4);
            if let Some(v) = &self.std {
                s.push(',');
                s += &fmt_fixed(v[k] * 1e6, 3);
            }
            if let Some(v) = &self.samples {
                s += &format!(",{}", v[k]);
            }
            if let Some(t) = &self.temp {
                s.push(',');
                s += &fmt_fixed(t[k], 3);
            }
            s.push('\n');
        }
        s
    }
}

#[derive(Debug, thiserror::Error, PartialEq)]
#[error("line {line}, column {column}: {msg}")]
pub struct CsvError {
    pub line: usize,
    /// 1-based column number and, where known, its name.
    pub column: String,
    pub msg: String,
}

pub(crate) fn err(line: usize, column: impl Into<String>, msg: impl Into<String>) -> CsvError {
    CsvError {
        line,
        column: column.into(),
        msg: msg.into(),
    }
}

/// The most rows a run may have (about 11 hours at 500 Hz): memory stays bounded (a few GB
/// through the fit) whatever the file claims.
pub const MAX_ROWS: usize = 20_000_000;

/// Parses measured data, continuous (with `t_s`) or static (without). `min_rows`: the fit
/// needs at least this many rows.
pub fn parse_csv(text: &str, min_rows: usize) -> Result<Measured, CsvError> {
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let (hl, header) = lines.next().ok_or_else(|| {
        err(
            1,
            "1",
            "empty file: expected the header t_s,q1_deg,...,length_mm (or q1_deg,...,length_mm for one reading per pose)",
        )
    })?;
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    // Without `t_s` the file is in the static form: one reading per pose, in the order taken.
    let timed = names.contains(&"t_s");
    let mut idx = [usize::MAX; 8];
    for (c, want) in COLUMNS.iter().enumerate() {
        if c == 0 && !timed {
            continue;
        }
        idx[c] = names.iter().position(|n| n == want).ok_or_else(|| {
            err(
                hl + 1,
                format!("{} ({want})", names.len() + 1),
                format!("missing column '{want}' in the header"),
            )
        })?;
    }
    let optional = |name: &str| names.iter().position(|n| *n == name);
    let (temp_idx, std_idx, n_idx) = (optional("temp_c"), optional("std_um"), optional("n"));
    let mut m = Measured {
        temp: temp_idx.map(|_| Vec::new()),
        std: std_idx.map(|_| Vec::new()),
        samples: n_idx.map(|_| Vec::new()),
        form: if timed {
            Form::Continuous
        } else {
            Form::Static { timed: false }
        },
        ..Measured::default()
    };
    for (l, raw) in lines {
        let line = l + 1;
        if m.t.len() >= MAX_ROWS {
            return Err(err(
                line,
                "1",
                format!("more than {MAX_ROWS} rows: split the run, or record at a lower rate"),
            ));
        }
        let at = |(c, m): (String, String)| err(line, c, m);
        // Only the columns used are read: an extra column may hold anything.
        let row = crate::files::csv_row(raw, &names).map_err(at)?;
        let col = |c: usize| row.column(c);
        let cell = |c: usize| -> Result<f64, CsvError> { row.number(c).map_err(at) };
        let t = if timed {
            let t = cell(idx[0])?;
            if let Some(&prev) = m.t.last() {
                if t <= prev {
                    return Err(err(
                        line,
                        format!("{} (t_s)", idx[0] + 1),
                        format!("time {t} s is not after the previous row's {prev} s (rows must be sorted by time)"),
                    ));
                }
            }
            t
        } else {
            m.t.len() as f64
        };
        let mut q = [0.0; 6];
        for i in 0..6 {
            q[i] = cell(idx[1 + i])? * DEG;
        }
        let len = cell(idx[7])?;
        if len <= 0.0 {
            return Err(err(
                line,
                format!("{} (length_mm)", idx[7] + 1),
                format!("length {len} mm is not positive"),
            ));
        }
        if let (Some(c), Some(v)) = (std_idx, m.std.as_mut()) {
            let s = cell(c)?;
            if s <= 0.0 {
                return Err(err(
                    line,
                    col(c),
                    format!("standard uncertainty {s} µm is not positive"),
                ));
            }
            v.push(s * 1e-6);
        }
        if let (Some(c), Some(v)) = (n_idx, m.samples.as_mut()) {
            let n = row
                .text(c)
                .parse::<u32>()
                .ok()
                .filter(|n| *n > 0)
                .ok_or_else(|| {
                    err(
                        line,
                        col(c),
                        format!(
                            "'{}' is not a positive whole number of samples",
                            row.text(c)
                        ),
                    )
                })?;
            v.push(n);
        }
        if let (Some(ti), Some(temps)) = (temp_idx, m.temp.as_mut()) {
            temps.push(cell(ti)?);
        }
        m.t.push(t);
        m.q.push(q);
        m.length.push(len * MM);
    }
    if m.len() < min_rows {
        let last = text.lines().count().max(1);
        return Err(err(
            last,
            if timed { "1 (t_s)" } else { "1 (q1_deg)" },
            format!(
                "{} data rows, fewer than the {min_rows} the fit needs (one per parameter at least)",
                m.len()
            ),
        ));
    }
    Ok(m)
}

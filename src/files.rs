//! Reading input files within limits: in = a path and the kind of file; out = its bytes or
//! text, or a one-line refusal when the file is larger than edbbgen reads.
//!
//! Inputs come from vendors, instruments and hand edits at a cell. A file far beyond any real
//! one of its kind (a 90 GB "measurement", a 5 GB "collision mesh") is refused by its size
//! before a byte is read, instead of exhausting the machine's memory. The limits are generous
//! multiples of real files and are named in the refusal, with what to do instead.

use std::path::Path;

/// The kinds of files edbbgen reads, each with its limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A URDF or DH spec (real ones: kilobytes to a megabyte).
    Robot,
    /// A cell, truth or setup TOML, or a template.
    Config,
    /// A collision mesh (real STL meshes of industrial arms: up to tens of megabytes).
    Mesh,
    /// Measured bar data (CSV): 2 GiB is about 20 million rows — 11 hours at 500 Hz.
    Measured,
    /// A program to verify or simulate.
    Program,
}

impl Kind {
    pub fn limit(self) -> u64 {
        const MIB: u64 = 1 << 20;
        match self {
            Kind::Robot => 64 * MIB,
            Kind::Config => 16 * MIB,
            Kind::Mesh => 512 * MIB,
            Kind::Measured => 2048 * MIB,
            Kind::Program => 256 * MIB,
        }
    }

    fn what(self) -> &'static str {
        match self {
            Kind::Robot => "a robot description",
            Kind::Config => "a configuration file",
            Kind::Mesh => "a collision mesh (decimate it, or use its convex hull)",
            Kind::Measured => "measured data (split the run, or record at a lower rate)",
            Kind::Program => "a program",
        }
    }
}

/// Why a file was not read.
#[derive(Debug)]
pub enum ReadError {
    Io(std::io::Error),
    TooLarge { bytes: u64, kind: Kind },
}

impl std::fmt::Display for ReadError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReadError::Io(e) => write!(f, "cannot read: {e}"),
            ReadError::TooLarge { bytes, kind } => write!(
                f,
                "{} is more than edbbgen reads as {} ({} at most)",
                size(*bytes),
                kind.what(),
                size(kind.limit())
            ),
        }
    }
}

fn size(bytes: u64) -> String {
    let b = bytes as f64;
    if b >= (1u64 << 30) as f64 {
        format!("{:.1} GiB", b / (1u64 << 30) as f64)
    } else {
        format!("{:.1} MiB", b / (1u64 << 20) as f64)
    }
}

fn check(path: &Path, kind: Kind) -> Result<(), ReadError> {
    let meta = std::fs::metadata(path).map_err(ReadError::Io)?;
    if meta.is_file() && meta.len() > kind.limit() {
        return Err(ReadError::TooLarge {
            bytes: meta.len(),
            kind,
        });
    }
    Ok(())
}

/// The file's bytes, if it is within its kind's limit.
pub fn read(path: &Path, kind: Kind) -> Result<Vec<u8>, ReadError> {
    check(path, kind)?;
    std::fs::read(path).map_err(ReadError::Io)
}

/// The file's text (UTF-8), if it is within its kind's limit.
pub fn read_text(path: &Path, kind: Kind) -> Result<String, ReadError> {
    check(path, kind)?;
    std::fs::read_to_string(path).map_err(ReadError::Io)
}

/// One CSV data row split into its cells (trimmed), checked to have as many cells as the
/// header `names` has columns. Errors are (column, message): the caller adds the file and
/// line in its own error type. Shared by the measured CSV and the instrument and controller
/// logs, so that both say the same about the same fault.
pub struct CsvRow<'a> {
    cells: Vec<&'a str>,
    names: &'a [&'a str],
}

/// Splits `raw` under the header `names`.
pub fn csv_row<'a>(raw: &'a str, names: &'a [&'a str]) -> Result<CsvRow<'a>, (String, String)> {
    let cells: Vec<&str> = raw.split(',').map(str::trim).collect();
    if cells.len() != names.len() {
        return Err((
            format!("{}", cells.len().min(names.len()) + 1),
            format!(
                "{} cells, the header has {} columns",
                cells.len(),
                names.len()
            ),
        ));
    }
    Ok(CsvRow { cells, names })
}

impl CsvRow<'_> {
    /// The column's name as messages give it: `3 (q2_deg)` (1-based).
    pub fn column(&self, c: usize) -> String {
        format!("{} ({})", c + 1, self.names[c])
    }

    /// Cell `c` (0-based) as written (trimmed).
    pub fn text(&self, c: usize) -> &str {
        self.cells[c]
    }

    /// Cell `c` (0-based) as a finite number.
    pub fn number(&self, c: usize) -> Result<f64, (String, String)> {
        let s = self.cells[c];
        let v: f64 = s
            .parse()
            .map_err(|_| (self.column(c), format!("'{s}' is not a number")))?;
        if !v.is_finite() {
            return Err((self.column(c), format!("'{s}' is not finite")));
        }
        Ok(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_over_its_limit_is_refused_before_reading_and_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("big.toml");
        let f = std::fs::File::create(&p).unwrap();
        // A sparse file: the size is what is checked, no byte is written or read.
        f.set_len(Kind::Config.limit() + (1 << 20)).unwrap();
        let e = read_text(&p, Kind::Config).unwrap_err();
        assert!(matches!(e, ReadError::TooLarge { .. }));
        assert_eq!(
            e.to_string(),
            "17.0 MiB is more than edbbgen reads as a configuration file (16.0 MiB at most)"
        );
        f.set_len(10).unwrap();
        assert_eq!(read(&p, Kind::Config).unwrap().len(), 10);
    }
}

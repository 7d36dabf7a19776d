//! The compensation targets file (DESIGN.md): in = CSV text; out = the targets in model
//! joints and SI units, and, given their compensations, the output CSV (the input columns
//! repeated, then `cq1_deg..cq6_deg`, `cx_mm,cy_mm,cz_mm,crx_deg,cry_deg,crz_deg`,
//! `residual_um`, `status`).
//!
//! Joint values (`q1_deg..q6_deg`, the seed's and the compensated ones) are controller axes as
//! the controller mapping in force says (the cell's `[controller]` over the dialect's
//! defaults; the identity without either), always in degrees. Orientations are fixed-axis
//! X-Y-Z in the base frame: R = Rz(rz)·Ry(ry)·Rx(rx) (KUKA's A, B, C are rz, ry, rx).

use super::{Compensated, Compensator, NotCompensated, Target, TargetsReport};
use crate::compensate::offsets::Um;
use crate::controller::{ControllerMap, Units};
use crate::robot::Frame;
use crate::units::{fmt_fixed, DEG, MM};
use nalgebra::Vector3;

/// Decimals of the written joint values (deg) and Cartesian values (mm, deg): 1e-6° moves a
/// point 2 m away by 0.03 µm, far below any calibration's accuracy.
pub const DECIMALS: usize = 6;

/// What the rows hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Joints,
    Pose,
    Position,
}

/// One row: its line, its fields as written, its name, and the target in user units
/// (controller axes in degrees, mm, deg).
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub line: usize,
    pub raw: Vec<String>,
    pub name: Option<String>,
    /// Joints (controller axes, deg), or the seed of a Cartesian row.
    pub q_deg: Option<[f64; 6]>,
    pub xyz_mm: Option<[f64; 3]>,
    pub rxyz_deg: Option<[f64; 3]>,
    /// The `approach` column: the direction each joint column moves into the target (+1, −1,
    /// 0 = not known), as the file's joint values count.
    pub approach: Option<[f64; 6]>,
}

/// How a target's joints come into it, where the file has no `approach` column: what a
/// backlash of the calibrated robot depends on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Approach {
    /// From the previous row (the file is the order the targets are visited in); the first
    /// row's joints are not known (the centre of the play).
    Order,
    /// Every joint moving positive into every target (a unidirectional approach).
    Positive,
    Negative,
    /// Not known: the centre of the play, half the play's error either way.
    Unknown,
}

impl Approach {
    /// The direction each joint approaches its target from: +1, −1, or 0 when not known.
    pub fn signs(self) -> [f64; 6] {
        match self {
            Approach::Positive => [1.0; 6],
            Approach::Negative => [-1.0; 6],
            Approach::Order | Approach::Unknown => [0.0; 6],
        }
    }

    pub fn parse(s: &str) -> Option<Approach> {
        match s {
            "order" => Some(Approach::Order),
            "positive" => Some(Approach::Positive),
            "negative" => Some(Approach::Negative),
            "unknown" => Some(Approach::Unknown),
            _ => None,
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct TargetFile {
    /// The header line as written.
    pub header: String,
    pub kind: Kind,
    pub rows: Vec<Row>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
#[error("line {line}: {msg}")]
pub struct CsvError {
    pub line: usize,
    pub msg: String,
}

fn err(line: usize, msg: impl Into<String>) -> CsvError {
    CsvError {
        line,
        msg: msg.into(),
    }
}

/// The fields of a CSV line as written (a quoted field keeps its quotes), and their values.
fn fields(line: usize, text: &str) -> Result<Vec<(String, String)>, CsvError> {
    let mut out = Vec::new();
    let mut raw = String::new();
    let mut value = String::new();
    let mut quoted = false;
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', false) if raw.trim().is_empty() => {
                quoted = true;
                raw.push(c);
            }
            ('"', true) => {
                raw.push(c);
                if chars.peek() == Some(&'"') {
                    chars.next();
                    raw.push('"');
                    value.push('"');
                } else {
                    quoted = false;
                }
            }
            (',', false) => {
                out.push((std::mem::take(&mut raw), std::mem::take(&mut value)));
            }
            _ => {
                raw.push(c);
                value.push(c);
            }
        }
    }
    if quoted {
        return Err(err(line, "a quoted field is not closed"));
    }
    out.push((raw, value));
    Ok(out)
}

const JOINTS: [&str; 6] = ["q1_deg", "q2_deg", "q3_deg", "q4_deg", "q5_deg", "q6_deg"];
const XYZ: [&str; 3] = ["x_mm", "y_mm", "z_mm"];
const RXYZ: [&str; 3] = ["rx_deg", "ry_deg", "rz_deg"];
const EXPECTED: &str =
    "name (optional), then q1_deg..q6_deg, or x_mm,y_mm,z_mm [rx_deg,ry_deg,rz_deg] [q1_deg..q6_deg as the seed], and optionally approach";

/// Parses a targets file (strict: unknown, repeated or incomplete columns, fields that are not
/// finite numbers, rows of the wrong width are errors naming the line and column).
pub fn parse(text: &str) -> Result<TargetFile, CsvError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(k, l)| (k + 1, l.strip_suffix('\r').unwrap_or(l)))
        .filter(|(_, l)| !l.trim().is_empty());
    let (hline, header) = lines
        .next()
        .ok_or_else(|| err(1, format!("empty file: expected a header ({EXPECTED})")))?;
    let cols = Columns::read(hline, header)?;
    let kind = cols.kind;
    let mut rows = Vec::new();
    for (line, text) in lines {
        rows.push(cols.row(line, text)?);
    }
    if rows.is_empty() {
        return Err(err(hline, "no targets after the header"));
    }
    Ok(TargetFile {
        header: header.to_string(),
        kind,
        rows,
    })
}

/// The header's columns: their names, the column of each target group that is there, the kind
/// of target they give and the name and approach columns.
struct Columns {
    names: Vec<String>,
    joints: Option<Vec<usize>>,
    xyz: Option<Vec<usize>>,
    rxyz: Option<Vec<usize>>,
    kind: Kind,
    name_col: Option<usize>,
    approach_col: Option<usize>,
}

impl Columns {
    /// The header `header` on line `hline`.
    fn read(hline: usize, header: &str) -> Result<Columns, CsvError> {
        let cols: Vec<String> = fields(hline, header)?
            .into_iter()
            .map(|(_, v)| v.trim().to_string())
            .collect();
        let known: Vec<&str> = ["name", "approach"]
            .into_iter()
            .chain(JOINTS)
            .chain(XYZ)
            .chain(RXYZ)
            .collect();
        for (k, c) in cols.iter().enumerate() {
            if !known.contains(&c.as_str()) {
                return Err(err(
                    hline,
                    format!("unknown column '{c}' (expected {EXPECTED})"),
                ));
            }
            if cols[..k].contains(c) {
                return Err(err(hline, format!("column '{c}' given twice")));
            }
        }
        let at = |name: &str| cols.iter().position(|c| c == name);
        let group = |names: &[&str]| -> Result<Option<Vec<usize>>, CsvError> {
            let found: Vec<Option<usize>> = names.iter().map(|n| at(n)).collect();
            match found.iter().filter(|f| f.is_some()).count() {
                0 => Ok(None),
                n if n == names.len() => Ok(Some(found.into_iter().flatten().collect())),
                _ => Err(err(
                    hline,
                    format!(
                        "columns {} come together: {} missing",
                        names.join(","),
                        names
                            .iter()
                            .zip(&found)
                            .filter(|(_, f)| f.is_none())
                            .map(|(n, _)| *n)
                            .collect::<Vec<_>>()
                            .join(", ")
                    ),
                )),
            }
        };
        let joints = group(&JOINTS)?;
        let xyz = group(&XYZ)?;
        let rxyz = group(&RXYZ)?;
        let kind = match (&xyz, &rxyz, &joints) {
            (Some(_), Some(_), _) => Kind::Pose,
            (Some(_), None, _) => Kind::Position,
            (None, Some(_), _) => {
                return Err(err(
                    hline,
                    "rx_deg,ry_deg,rz_deg need the position x_mm,y_mm,z_mm",
                ))
            }
            (None, None, Some(_)) => Kind::Joints,
            (None, None, None) => {
                return Err(err(
                    hline,
                    format!("no target columns (expected {EXPECTED})"),
                ))
            }
        };
        let name_col = at("name");
        let approach_col = at("approach");
        Ok(Columns {
            names: cols,
            joints,
            xyz,
            rxyz,
            kind,
            name_col,
            approach_col,
        })
    }

    /// The row `text` on line `line`.
    fn row(&self, line: usize, text: &str) -> Result<Row, CsvError> {
        let Columns {
            names: cols,
            joints,
            xyz,
            rxyz,
            ..
        } = self;
        let (kind, name_col, approach_col) = (self.kind, self.name_col, self.approach_col);
        let f = fields(line, text)?;
        if f.len() != cols.len() {
            return Err(err(
                line,
                format!("{} fields, the header has {}", f.len(), cols.len()),
            ));
        }
        let num = |c: usize| -> Result<Option<f64>, CsvError> {
            let v = f[c].1.trim();
            if v.is_empty() {
                return Ok(None);
            }
            match v.parse::<f64>() {
                Ok(x) if x.is_finite() => Ok(Some(x)),
                _ => Err(err(
                    line,
                    format!("column {}: '{v}' is not a finite number", cols[c]),
                )),
            }
        };
        // All of a group, or (a seed only) none of it.
        let take = |idx: &Option<Vec<usize>>,
                    may_be_empty: bool|
         -> Result<Option<Vec<f64>>, CsvError> {
            let Some(idx) = idx else { return Ok(None) };
            let vals: Vec<Option<f64>> = idx.iter().map(|&c| num(c)).collect::<Result<_, _>>()?;
            if vals.iter().all(Option::is_some) {
                return Ok(Some(vals.into_iter().flatten().collect()));
            }
            if may_be_empty && vals.iter().all(Option::is_none) {
                return Ok(None);
            }
            let missing = idx
                .iter()
                .zip(&vals)
                .find(|(_, v)| v.is_none())
                .map_or(0, |(c, _)| *c);
            Err(err(
                line,
                format!(
                    "column {}: a value is required{}",
                    cols[missing],
                    if may_be_empty {
                        " (a seed gives all six joints or none)"
                    } else {
                        ""
                    }
                ),
            ))
        };
        let q = take(joints, kind != Kind::Joints)?;
        let p = take(xyz, false)?;
        let r = take(rxyz, false)?;
        let approach = match approach_col {
            Some(c) => Some(parse_approach(f[c].1.trim()).ok_or_else(|| {
                err(
                    line,
                    format!(
                        "column approach: '{}' is not six signs, one per joint (+ moving positive into the target, - negative, 0 not known), e.g. ++-+0+",
                        f[c].1.trim()
                    ),
                )
            })?),
            None => None,
        };
        Ok(Row {
            line,
            raw: f.iter().map(|(raw, _)| raw.clone()).collect(),
            name: name_col.map(|c| f[c].1.trim().to_string()),
            q_deg: q.map(|v| std::array::from_fn(|i| v[i])),
            xyz_mm: p.map(|v| [v[0], v[1], v[2]]),
            rxyz_deg: r.map(|v| [v[0], v[1], v[2]]),
            approach,
        })
    }
}

/// The mapping with degree units (the file's joint columns are degrees in every dialect).
fn in_degrees(map: &ControllerMap) -> ControllerMap {
    ControllerMap {
        units: Units::Deg,
        ..map.clone()
    }
}

/// The rows as targets in model joints, SI.
pub fn to_targets(file: &TargetFile, map: &ControllerMap) -> Vec<Target> {
    let map = in_degrees(map);
    let model = |c: &[f64; 6]| map.undo(c).map(|d| d * DEG);
    file.rows
        .iter()
        .map(|r| {
            let seed = r.q_deg.as_ref().map(model);
            match (r.xyz_mm, r.rxyz_deg) {
                (Some(p), Some(rot)) => Target::Pose {
                    frame: Frame::from_xyz_rpy(p.map(|v| v * MM), rot.map(|v| v * DEG)),
                    seed,
                },
                (Some(p), None) => Target::Position {
                    position: Vector3::from(p) * MM,
                    seed,
                },
                _ => Target::Joints(seed.unwrap_or([0.0; 6])),
            }
        })
        .collect()
}

/// Six signs, one per joint: `+`, `-` or `0`.
fn parse_approach(s: &str) -> Option<[f64; 6]> {
    let v: Vec<f64> = s
        .chars()
        .map(|c| match c {
            '+' => Some(1.0),
            '-' => Some(-1.0),
            '0' => Some(0.0),
            _ => None,
        })
        .collect::<Option<_>>()?;
    (v.len() == 6).then(|| std::array::from_fn(|i| v[i]))
}

/// Each row's approach in model joints: the row's `approach` column, else the convention; with
/// [`Approach::Order`] the direction from the previous row's load-side joints to the row's
/// ([`approach_along`]; `load`: the joints the calibrated robot's load side must reach, model
/// joints; None for a row the robot does not visit).
pub fn approaches(
    file: &TargetFile,
    map: &ControllerMap,
    load: &[Option<[f64; 6]>],
    convention: Approach,
) -> Vec<[f64; 6]> {
    let by_order = approach_along(load, [0.0; 6]);
    file.rows
        .iter()
        .zip(by_order)
        .map(|(row, by_order)| match (row.approach, convention) {
            // The file counts the controller's axes: a flipped axis moves its joint the
            // other way.
            (Some(a), _) => std::array::from_fn(|j| a[j] * map.sign[j]),
            (None, Approach::Order) => by_order,
            (None, Approach::Positive) => [1.0; 6],
            (None, Approach::Negative) => [-1.0; 6],
            (None, Approach::Unknown) => [0.0; 6],
        })
        .collect()
}

/// The approach of each of a sequence of poses visited in order: per joint, the direction
/// from the load-side angle the previous visited pose reaches to this one's (a backlash's load
/// rests on the flank of the direction it was last pushed in, and to reach a new angle the
/// play must be pushed towards it); an unchanged angle keeps the last direction; before a
/// joint's first change, `first` (0: not known). `load`: None for a pose not visited.
pub fn approach_along(load: &[Option<[f64; 6]>], first: [f64; 6]) -> Vec<[f64; 6]> {
    let mut last = first;
    let mut prev: Option<[f64; 6]> = None;
    load.iter()
        .map(|q| {
            if let (Some(a), Some(b)) = (prev, q) {
                for j in 0..6 {
                    let d = b[j] - a[j];
                    if d != 0.0 {
                        last[j] = d.signum();
                    }
                }
            }
            if q.is_some() {
                prev = *q;
            }
            last
        })
        .collect()
}

/// The output CSV: every input row repeated with its compensation. A compensated row carries
/// the joints as printed (controller axes, deg), the nominal TCP pose at those joints (the
/// Cartesian target for a nominal-IK controller) and the calibrated robot's TCP position error
/// at those very printed joints; any other row only its residual (when one was computed) and
/// the reason.
pub fn write(
    file: &TargetFile,
    results: &[Compensated],
    comp: &Compensator,
    map: &ControllerMap,
) -> String {
    let map = in_degrees(map);
    let mut s = file.header.clone();
    s += ",cq1_deg,cq2_deg,cq3_deg,cq4_deg,cq5_deg,cq6_deg,cx_mm,cy_mm,cz_mm,crx_deg,cry_deg,crz_deg,residual_um,status\n";
    for (row, c) in file.rows.iter().zip(results) {
        s += &row.raw.join(",");
        match (c.status.is_ok(), c.q) {
            (true, Some(q)) => {
                let printed: [String; 6] = map
                    .apply(&q.map(|r| r / DEG))
                    .map(|v| fmt_fixed(v, DECIMALS));
                let axes: [f64; 6] =
                    std::array::from_fn(|i| printed[i].parse::<f64>().unwrap_or(f64::NAN));
                let qp = map.undo(&axes).map(|d| d * DEG);
                let pose = comp.controller_pose(&qp);
                let rpy = pose.rpy();
                for v in &printed {
                    s += ",";
                    s += v;
                }
                for v in pose.t.iter() {
                    s += ",";
                    s += &fmt_fixed(v / MM, DECIMALS);
                }
                for v in rpy {
                    s += ",";
                    s += &fmt_fixed(v / DEG, DECIMALS);
                }
                s += ",";
                s += &fmt_fixed(comp.residual(&c.target, &qp, &c.approach) * 1e6, 3);
            }
            _ => {
                s += &",".repeat(12);
                s += ",";
                if let Some(r) = c.residual {
                    s += &fmt_fixed(r * 1e6, 3);
                }
            }
        }
        s += ",";
        s += &c.status.to_string();
        s += "\n";
    }
    s
}

/// Every target of a file compensated. A backlash needs each target's approach; in file order
/// it follows the load-side joints (a first pass solves them) of the targets the robot will
/// visit: a row that cannot be compensated is not run, so the next one comes from the row
/// before it.
pub fn compensate_file(
    comp: &Compensator,
    file: &TargetFile,
    map: &ControllerMap,
    approach: Approach,
) -> Vec<Compensated> {
    let list = to_targets(file, map);
    let unknown: Vec<(Target, [f64; 6])> = list.iter().map(|t| (*t, [0.0; 6])).collect();
    // A backlash needs each target's approach; in file order it follows the load-side
    // joints (a first pass solves them) of the targets the robot will visit: a row that
    // cannot be compensated is not run, so the next one comes from the row before it.
    if comp.effects().backlash.is_empty() {
        comp.compensate_all(&unknown)
    } else {
        let load: Vec<Option<[f64; 6]>> = comp
            .compensate_all(&unknown)
            .iter()
            .map(|c| c.q.map(|q| comp.load(&q, &[0.0; 6])))
            .collect();
        let ap = approaches(file, map, &load, approach);
        let with: Vec<(Target, [f64; 6])> = list.iter().copied().zip(ap).collect();
        comp.compensate_all(&with)
    }
}

/// What the report says of a compensated target file (`name`: the file's).
pub fn report(
    name: String,
    file: &TargetFile,
    results: &[Compensated],
    comp: &Compensator,
    map: &ControllerMap,
) -> TargetsReport {
    // The residual at the printed joints, as the CSV states it.
    let printed = |q: &[f64; 6]| -> [f64; 6] {
        let m = ControllerMap {
            units: Units::Deg,
            ..map.clone()
        };
        let axes = m
            .apply(&q.map(|r| r / DEG))
            .map(|v| fmt_fixed(v, DECIMALS).parse::<f64>().unwrap_or(v));
        m.undo(&axes).map(|d| d * DEG)
    };
    let mut before = Vec::new();
    let mut after = Vec::new();
    let mut not = Vec::new();
    let mut free = 0;
    for (row, c) in file.rows.iter().zip(results) {
        match (c.status.is_ok(), c.q, c.nominal) {
            (true, Some(q), Some(qn)) => {
                before.push(comp.residual(&c.target, &qn, &c.approach) * 1e6);
                after.push(comp.residual(&c.target, &printed(&q), &c.approach) * 1e6);
                free += usize::from(c.orientation_free);
            }
            _ => not.push(NotCompensated {
                line: row.line,
                name: row.name.clone(),
                status: c.status.to_string(),
            }),
        }
    }
    let b: Um = crate::calibrate::predict::spread(&before).into();
    let r: Um = crate::calibrate::predict::spread(&after).into();
    before.sort_by(f64::total_cmp);
    after.sort_by(f64::total_cmp);
    TargetsReport {
        file: name,
        kind: match file.kind {
            Kind::Joints => "joints",
            Kind::Pose => "pose",
            Kind::Position => "position",
        },
        rows: file.rows.len(),
        compensated: before.len(),
        orientation_free: free,
        not_compensated: not,
        before_um: b,
        residual_um: r,
        sorted_um: (before, after),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_three_kinds_and_keeps_fields_as_written() {
        let f = parse("name,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n\"a, b\",1,2,3,4,5,6\n")
            .unwrap();
        assert_eq!(f.kind, Kind::Joints);
        assert_eq!(f.rows[0].raw[0], "\"a, b\"");
        assert_eq!(f.rows[0].name.as_deref(), Some("a, b"));
        assert_eq!(f.rows[0].q_deg, Some([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]));
        let f = parse("x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\r\n1,2,3,4,5,6\r\n\n").unwrap();
        assert_eq!(f.kind, Kind::Pose);
        assert_eq!(f.rows.len(), 1);
        let f = parse(
            "z_mm,x_mm,y_mm,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n3,1,2,,,,,,\n3,1,2,1,2,3,4,5,6\n",
        )
        .unwrap();
        assert_eq!(f.kind, Kind::Position);
        assert_eq!(f.rows[0].xyz_mm, Some([1.0, 2.0, 3.0]));
        assert_eq!(f.rows[0].q_deg, None);
        assert!(f.rows[1].q_deg.is_some());
    }

    #[test]
    fn bad_files_name_the_line_and_column() {
        for (text, needle) in [
            ("", "empty file"),
            ("name,q1_deg\n", "q2_deg, q3_deg"),
            ("x_mm,y_mm,z_mm,rx_deg\n", "ry_deg, rz_deg"),
            ("rx_deg,ry_deg,rz_deg\n1,2,3\n", "need the position"),
            ("name\nfoo\n", "no target columns"),
            (
                "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,speed\n",
                "unknown column 'speed'",
            ),
            ("q1_deg,q1_deg\n", "given twice"),
            ("q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n", "no targets"),
            (
                "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1,2,3,4,5\n",
                "line 2: 5 fields",
            ),
            (
                "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1,2,x,4,5,6\n",
                "line 2: column q3_deg: 'x' is not a finite number",
            ),
            (
                "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1,2,inf,4,5,6\n",
                "not a finite number",
            ),
            (
                "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1,2,,4,5,6\n",
                "column q3_deg: a value is required",
            ),
            (
                "x_mm,y_mm,z_mm,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1,2,3,1,,,,,\n",
                "all six joints or none",
            ),
            ("name,x_mm,y_mm,z_mm\n\"open,1,2,3\n", "not closed"),
        ] {
            let e = parse(text).unwrap_err().to_string();
            assert!(e.contains(needle), "{text:?}: {e}");
        }
    }
}

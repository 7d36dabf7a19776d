//! Controller dialects: in = a program text (and the [`ControllerMap`] in force); out =
//! [`Parsed`], the motions it commands in model joints. The other end of [`crate::emit`]: a
//! dialect is a template under `templates/` (how [`crate::ir::Program`] is written) and a
//! reader here (how that text is read back), side by side, one file per language.
//!
//! | name | language | file | reader |
//! |---|---|---|---|
//! | `ngc` | RS274/NGC (LinuxCNC, ISO CNC cores) | `templates/ngc.j2` | [`ngc`] |
//! | `sinumerik` | SINUMERIK 840D part program | `templates/sinumerik.j2` | [`sinumerik`] |
//! | `krl` | KUKA KRL (KSS 8.x) | `templates/krl.j2` | [`krl`] |
//! | `rapid` | ABB RAPID module | `templates/rapid.j2` | [`rapid`] |
//! | `urscript` | Universal Robots URScript | `templates/urscript.j2` | [`urscript`] |
//! | `fanuc` | FANUC TP as LS text | `templates/fanuc.j2` | [`fanuc`] |
//!
//! Every bundled template starts with its front matter: TOML inside a leading `{#- dialect`
//! … `-#}` comment (file extension, axis units and names, the default controller mapping,
//! program-name rules). A user template (`--template FILE`) declares the dialect it is read
//! back as with `{% extends "NAME" %}`, and inherits that dialect's front matter and reader.
//!
//! Readers are strict: they understand what a joint-space measurement program needs and name
//! the line of anything else. They never trust comments for motion, only for the header
//! facts (fixture, MAP, the controller mapping) and the `support` marks.

pub mod fanuc;
pub mod krl;
pub mod ngc;
pub mod rapid;
pub mod sinumerik;
pub mod urscript;

use crate::controller::{ControllerDefaults, ControllerMap, Coupling, Units};
use serde::{Deserialize, Serialize};
use std::sync::OnceLock;

/// The bundled dialects (name, template source), compiled into the binary.
pub const BUNDLED: &[(&str, &str)] = &[
    ("ngc", include_str!("../../templates/ngc.j2")),
    ("sinumerik", include_str!("../../templates/sinumerik.j2")),
    ("krl", include_str!("../../templates/krl.j2")),
    ("rapid", include_str!("../../templates/rapid.j2")),
    ("urscript", include_str!("../../templates/urscript.j2")),
    ("fanuc", include_str!("../../templates/fanuc.j2")),
];

/// A dialect's front matter.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Dialect {
    pub name: String,
    /// The language and controller, for people.
    pub title: String,
    /// File extensions, the usual one first (no dot).
    pub extensions: Vec<String>,
    pub units: Units,
    pub units_configurable: bool,
    pub axis_names: [String; 6],
    pub axis_names_configurable: bool,
    pub j3_coupling: Coupling,
    /// The coupling on a parallel-arm robot when the cell states none (see
    /// [`crate::controller::parallel_arm`]); absent: `j3_coupling`, with a warning.
    #[serde(default)]
    pub j3_coupling_parallel_arm: Option<Coupling>,
    /// Program names: at most this many characters (letters, digits, `_`, a letter first).
    pub name_max: usize,
    /// The program name must equal the file name (KRL's DEF, FANUC's /PROG, ...).
    pub name_must_match_file: bool,
    /// What the language cannot express exactly, for the docs and `edbbgen dialects`.
    pub approximations: Vec<String>,
    /// What a move's time word states on the controller.
    pub move_time: MoveTime,
    /// What the blend instruction bounds on the controller (front matter `[corner]`).
    pub corner: Corner,
}

/// What a move's time word (G93 F, `\T`, `t`, a speed percentage) states.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MoveTime {
    /// The time at the programmed speed: the controller's acceleration ramps come on top
    /// (inverse-time feed, `$VEL_AXIS`, FANUC `J n%`).
    Cruise,
    /// The whole move, ramps included (RAPID `\T`, URScript `t`).
    Total,
}

/// How a controller treats a blended corner, from its manual: what the blend instruction's value
/// bounds and what it leaves free. `verify` checks the corner region such a controller may execute
/// (the joint-space parallelogram spanned by the corner and the points where the blend may begin
/// and end, which holds every superposition of the two moves and every curve inside the triangle
/// of those three points), never edbbgen's intended blend.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Corner {
    pub kind: CornerKind,
    /// The blend instruction as the program writes it.
    pub instruction: String,
    /// The unit of its value as the program writes it ("mm", "m", "deg", "%", "" for none).
    pub unit: String,
    /// At most this fraction of each adjacent move is blended: 0.5 where the controller's
    /// documentation limits a blend to half a move (LinuxCNC), 1 where it documents no such
    /// limit (the blend may then reach anywhere along the move where the value allows).
    pub cap: f64,
    /// How far the controller may exceed the programmed value, as a fraction of it (ABB: in
    /// joint movement a zone's size "may differ somewhat from the one programmed"; 10 % is
    /// assumed): the region is checked at value × (1 + tolerance). 0 where nothing says so.
    #[serde(default)]
    pub tolerance: f64,
    /// The controller's acceleration on moves that blend, as a fraction of the joints' limits.
    pub blend_acceleration: f64,
    /// What the value bounds, and what it leaves free, in the vendor's words (for people).
    pub bounds: String,
    pub leaves_free: String,
}

/// What a blend instruction's value bounds on its controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CornerKind {
    /// A TCP distance: the blend begins where the TCP (set to the MAP) comes within the value of
    /// the corner and ends where it leaves it again (KRL `C_DIS`, RAPID zones).
    TcpDistance,
    /// A path distance over the controller axes in their units: the blend begins at most the
    /// value before the corner and ends at most the value after it (SINUMERIK `G641 ADIS` on
    /// the FGROUP axes, degrees of joint path).
    AxisPath,
    /// The value bounds only some axes (LinuxCNC `G64 P`: X Y Z), or nothing documented bounds
    /// it (FANUC `CR`): the blend may take up to `cap` of each adjacent move.
    Moves,
    /// No documented corner region (FANUC `CNT`, a continuity value; URScript `movej` blends,
    /// which Universal Robots says may deviate from the waypoints' course).
    Unbounded,
}

impl Dialect {
    pub fn defaults(&self) -> ControllerDefaults {
        ControllerDefaults {
            units: self.units,
            units_configurable: self.units_configurable,
            axis_names: self.axis_names.clone(),
            axis_names_configurable: self.axis_names_configurable,
            j3_coupling: self.j3_coupling,
            j3_coupling_parallel_arm: self.j3_coupling_parallel_arm,
        }
    }

    /// Reads a program in this dialect.
    pub fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        let mut p = match self.name.as_str() {
            "ngc" => ngc::parse(text, map),
            "sinumerik" => sinumerik::parse(text, map),
            "krl" => krl::parse(text, map),
            "rapid" => rapid::parse(text, map),
            "urscript" => urscript::parse(text, map),
            "fanuc" => fanuc::parse(text, map),
            other => Err(ParseError {
                line: 0,
                msg: format!("no reader for dialect '{other}'"),
            }),
        }?;
        p.map = map.clone();
        p.timing = ProgramTiming {
            move_time: self.move_time,
            blend_acceleration: self.corner.blend_acceleration,
        };
        Ok(p)
    }

    /// The default mapping of this dialect (no `[controller]` section), for robots whose
    /// joints 2 and 3 make `auto` coupling resolvable.
    pub fn default_map(&self, robot: &crate::robot::Robot) -> Result<ControllerMap, String> {
        ControllerMap::resolve(None, &self.defaults(), &self.name, robot).map_err(|e| e.to_string())
    }
}

fn front_matter(text: &str) -> Option<&str> {
    let rest = text.strip_prefix("{#- dialect\n")?;
    let end = rest.find("\n-#}")?;
    Some(&rest[..end])
}

/// Every bundled dialect, parsed once.
pub fn all() -> &'static [Dialect] {
    static ALL: OnceLock<Vec<Dialect>> = OnceLock::new();
    ALL.get_or_init(|| {
        BUNDLED
            .iter()
            .map(|(name, text)| {
                let fm = front_matter(text)
                    .unwrap_or_else(|| panic!("templates/{name}.j2 has no front matter"));
                let d: Dialect = toml::from_str(fm)
                    .unwrap_or_else(|e| panic!("templates/{name}.j2 front matter: {e}"));
                assert_eq!(&d.name, name, "templates/{name}.j2 names itself {}", d.name);
                d
            })
            .collect()
    })
}

pub fn by_name(name: &str) -> Option<&'static Dialect> {
    all().iter().find(|d| d.name == name)
}

/// How a dialect writes a dwell, as its reader takes it (for messages).
pub fn dwell_instruction(name: &str) -> &'static str {
    match name {
        "ngc" => "G4 P seconds",
        "sinumerik" => "G4 F seconds",
        "krl" => "WAIT SEC seconds",
        "rapid" => "WaitTime seconds;",
        "urscript" => "sleep(seconds)",
        "fanuc" => "WAIT seconds(sec)",
        _ => "a dwell",
    }
}

pub fn names() -> Vec<&'static str> {
    BUNDLED.iter().map(|(n, _)| *n).collect()
}

/// The bundled template source of a dialect.
pub fn source(name: &str) -> Option<&'static str> {
    BUNDLED.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// A template ready to render: its source and the dialect its programs are read back as.
#[derive(Clone, Debug)]
pub struct Template {
    pub source: String,
    pub dialect: &'static Dialect,
    /// True for a user's file (`--template`), false for a bundled dialect.
    pub user: bool,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum TemplateError {
    #[error("unknown dialect '{0}' (bundled: {1})")]
    Unknown(String, String),
    #[error("{0}")]
    Syntax(String),
    #[error("declares no dialect: start it with {{% extends \"ngc\" %}} (or another bundled dialect: {0}) so that verify and simulate can read its programs back")]
    NoDialect(String),
}

impl Template {
    pub fn bundled(name: &str) -> Result<Template, TemplateError> {
        let d = by_name(name)
            .ok_or_else(|| TemplateError::Unknown(name.to_string(), names().join(", ")))?;
        Ok(Template {
            source: source(name).unwrap_or_default().to_string(),
            dialect: d,
            user: false,
        })
    }

    /// A template from its source: a bundled one (front matter) or a user's, which must
    /// `{% extends "NAME" %}` a bundled dialect.
    pub fn from_source(source: &str) -> Result<Template, TemplateError> {
        if let Some(fm) = front_matter(source) {
            if let Some(d) = toml::from_str::<Dialect>(fm)
                .ok()
                .and_then(|d| by_name(&d.name))
            {
                return Ok(Template {
                    source: source.to_string(),
                    dialect: d,
                    user: source != self::source(&d.name).unwrap_or_default(),
                });
            }
        }
        let base = extends(source).ok_or_else(|| TemplateError::NoDialect(names().join(", ")))?;
        let d = by_name(&base)
            .ok_or_else(|| TemplateError::Unknown(base.clone(), names().join(", ")))?;
        // A syntax error is the file's, found before any work (not at the end of a compile).
        minijinja::Environment::new()
            .add_template("program", source)
            .map_err(|e| {
                TemplateError::Syntax(match e.line() {
                    Some(l) => format!("line {l}: {}", e.detail().unwrap_or("syntax error")),
                    None => e.to_string(),
                })
            })?;
        Ok(Template {
            source: source.to_string(),
            dialect: d,
            user: true,
        })
    }
}

/// The name in a template's `{% extends "NAME" %}` (its first tag), if any.
pub fn extends(source: &str) -> Option<String> {
    let mut rest = source;
    loop {
        let t = rest.trim_start();
        if let Some(r) = t.strip_prefix("{#") {
            rest = &r[r.find("#}")? + 2..];
            continue;
        }
        let r = t.strip_prefix("{%")?;
        let r = r.strip_prefix('-').unwrap_or(r).trim_start();
        let r = r.strip_prefix("extends")?.trim_start();
        let quote = r.chars().next().filter(|c| *c == '"' || *c == '\'')?;
        let r = &r[1..];
        return Some(r[..r.find(quote)?].to_string());
    }
}

/// The dialect of a program file: its extension, else what its text looks like.
pub fn detect(path: &std::path::Path, text: &str) -> Option<&'static Dialect> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    if let Some(ext) = ext {
        if let Some(d) = all().iter().find(|d| d.extensions.contains(&ext)) {
            return Some(d);
        }
    }
    let t = text.trim_start();
    let first_code = text
        .lines()
        .map(str::trim)
        .find(|l| {
            !l.is_empty()
                && !l.starts_with(';')
                && !l.starts_with('(')
                && !l.starts_with('!')
                && !l.starts_with('#')
                && !l.starts_with('&')
        })
        .unwrap_or("");
    let name = if t.starts_with("/PROG") {
        "fanuc"
    } else if first_code.to_ascii_uppercase().starts_with("DEF ") {
        "krl"
    } else if first_code.to_ascii_uppercase().starts_with("MODULE ") {
        "rapid"
    } else if first_code.starts_with("def ") {
        "urscript"
    } else if text.contains("G641") || text.contains("G60") && text.contains(';') {
        "sinumerik"
    } else if first_code.starts_with('G') || first_code.starts_with('N') {
        "ngc"
    } else {
        return None;
    };
    by_name(name)
}

// ---- what a reader returns ------------------------------------------------------------------

/// How long a motion line says its move takes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Timing {
    /// Every axis at its maximum speed, the slowest one leading (G0).
    Rapid,
    /// The move takes this long (s): G93 F, RAPID `\T`, URScript `t`.
    Duration(f64),
    /// G94: the joint-space path length (program units) over F (units per minute).
    PathFeed(f64),
    /// Each axis at most at this percentage of its maximum speed, all arriving together (KRL
    /// `$VEL_AXIS`, FANUC `J … n%`): the slowest axis leads.
    AxisPercent([f64; 6]),
    /// The leading axis at this speed (program units per second): URScript `v`.
    LeadSpeed(f64),
    /// Left to the controller (RAPID speed data without `\T`): only the approach may do that.
    Unknown,
}

impl Timing {
    /// The move's duration (s) between controller axis values `from` → `to` (program units),
    /// each axis's maximum speed `speeds` (program units per second); None when unknown.
    pub fn duration(&self, from: &[f64; 6], to: &[f64; 6], speeds: &[f64; 6]) -> Option<f64> {
        let d: [f64; 6] = std::array::from_fn(|i| (to[i] - from[i]).abs());
        let lead = |scale: &dyn Fn(usize) -> f64| {
            (0..6)
                .map(|i| {
                    if d[i] == 0.0 {
                        0.0
                    } else {
                        d[i] / (speeds[i] * scale(i))
                    }
                })
                .fold(0.0, f64::max)
        };
        match *self {
            Timing::Rapid => Some(lead(&|_| 1.0)),
            Timing::Duration(t) => Some(t),
            Timing::PathFeed(f) => Some(60.0 * d.iter().map(|x| x * x).sum::<f64>().sqrt() / f),
            Timing::AxisPercent(p) => Some(lead(&|i| p[i] / 100.0)),
            Timing::LeadSpeed(v) => Some(d.iter().fold(0.0, |m, x| f64::max(m, *x)) / v),
            Timing::Unknown => None,
        }
    }
}

/// What one program line commands.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Step {
    /// A joint-space move.
    Move {
        /// Target in model joints (deg): the controller mapping undone.
        target: [f64; 6],
        /// Target as the program states it: controller axes, program units.
        axes: [f64; 6],
        timing: Timing,
        /// The blend instruction's value at the corner this move ends in, in the dialect's
        /// unit (its front matter's `corner.unit`: mm at the MAP for a TCP distance, degrees of
        /// axis path for SINUMERIK's ADIS, LinuxCNC's G64 P); None = exact stop.
        blend: Option<f64>,
        /// What the blend bounds when it is not the dialect's usual instruction (FANUC `CR`
        /// in a `CNT` dialect); None = the dialect's `corner.kind`.
        #[serde(default)]
        corner: Option<CornerKind>,
    },
    /// Stand still for this many seconds.
    Dwell(f64),
    /// Program pause: the operator acts (mounts or removes the bar) and resumes.
    Pause,
    /// Program end.
    End,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Line {
    /// 1-based line number in the text.
    pub line: usize,
    pub step: Step,
    /// The comment that goes with the line (on it, or on the comment line just before it where
    /// the language keeps comments on lines of their own), if any.
    pub comment: Option<String>,
}

/// A parsed program: its steps, the header comments (before the first motion) and the
/// mapping it was read with.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Parsed {
    pub header: Vec<String>,
    pub lines: Vec<Line>,
    pub map: ControllerMap,
    /// How the dialect it was read in times moves (what its time words state, the
    /// acceleration of moves that blend): the twin runs the program on this timing.
    #[serde(default)]
    pub timing: ProgramTiming,
}

/// How a dialect's controller times a program's moves ([`crate::timing`]'s model): what a
/// move's time word states and the acceleration of moves that blend (the dialect's
/// `[corner] blend_acceleration`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProgramTiming {
    pub move_time: MoveTime,
    pub blend_acceleration: f64,
}

impl Default for ProgramTiming {
    /// A controller that states cruise times and blends at full acceleration.
    fn default() -> Self {
        ProgramTiming {
            move_time: MoveTime::Cruise,
            blend_acceleration: 1.0,
        }
    }
}

impl Default for Parsed {
    fn default() -> Self {
        Parsed {
            header: Vec::new(),
            lines: Vec::new(),
            map: ControllerMap::identity(Units::Deg, ["X", "Y", "Z", "A", "B", "C"]),
            timing: ProgramTiming::default(),
        }
    }
}

impl Parsed {
    /// Targets (model joints, deg) of all moves, with their line numbers.
    pub fn targets(&self) -> impl Iterator<Item = (usize, &[f64; 6])> {
        self.lines.iter().filter_map(|l| match &l.step {
            Step::Move { target, .. } => Some((l.line, target)),
            _ => None,
        })
    }

    /// The value of a `key: value` header comment, e.g. `header_value("fixture")`.
    pub fn header_value(&self, key: &str) -> Option<&str> {
        self.header.iter().find_map(|h| {
            h.strip_prefix(key)
                .and_then(|r| r.strip_prefix(':'))
                .map(str::trim)
        })
    }

    /// The duration (s) the move `from` → `step` commands (controller axes), with the robot
    /// file's joint speeds (rad/s) as each axis's 100 %; None for a move whose speed is left
    /// to the controller.
    pub fn duration(
        &self,
        from_axes: &[f64; 6],
        step: &Step,
        model_speeds: &[f64; 6],
    ) -> Option<f64> {
        match step {
            Step::Move { axes, timing, .. } => {
                timing.duration(from_axes, axes, &self.map.axis_speeds(model_speeds))
            }
            _ => None,
        }
    }
}

#[derive(Debug, thiserror::Error, PartialEq, Clone)]
#[error("line {line}: {msg}")]
pub struct ParseError {
    pub line: usize,
    pub msg: String,
}

pub(crate) fn perr(line: usize, msg: impl Into<String>) -> ParseError {
    ParseError {
        line,
        msg: msg.into(),
    }
}

/// A finite number, or an error naming it.
pub(crate) fn number(line: usize, what: &str, s: &str) -> Result<f64, ParseError> {
    let s = s.trim();
    let v: f64 = s
        .parse()
        .map_err(|_| perr(line, format!("{what}: '{s}' is not a number")))?;
    if !v.is_finite() {
        return Err(perr(line, format!("{what}: '{s}' is not finite")));
    }
    Ok(v)
}

/// Collects header comments into `key: value` lines, joining continuation lines to the line
/// before: `.. text` after a space, `..text` inside a cut word ([`crate::emit::wrap`] writes
/// them), for languages with short comment lines (FANUC's 32 characters).
pub fn push_header(header: &mut Vec<String>, comment: &str) {
    let c = comment.trim_end();
    let c = c.trim_start();
    if let Some(cont) = c.strip_prefix("..") {
        if let Some(last) = header.last_mut() {
            match cont.strip_prefix(' ') {
                Some(words) => {
                    last.push(' ');
                    last.push_str(words);
                }
                None => last.push_str(cont),
            }
            return;
        }
    }
    header.push(c.to_string());
}

/// A program name the dialect accepts: letters, digits and `_`, a letter first, at most `max`.
pub fn valid_name(name: &str, max: usize) -> bool {
    !name.is_empty()
        && name.len() <= max
        && name.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
        && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_bundled_template_has_front_matter_and_a_reader() {
        assert_eq!(all().len(), BUNDLED.len());
        for d in all() {
            let t = Template::from_source(source(&d.name).unwrap()).unwrap();
            assert_eq!(t.dialect.name, d.name);
            assert!(!t.user);
            assert!(!d.extensions.is_empty());
            let e = d
                .read(
                    "",
                    &ControllerMap::identity(d.units, ["A", "B", "C", "D", "E", "F"]),
                )
                .err();
            assert!(e.is_none_or(|e| !e.msg.contains("no reader")), "{}", d.name);
        }
    }

    #[test]
    fn user_templates_declare_what_they_extend() {
        let t = Template::from_source(
            "{# mine #}\n{% extends \"krl\" %}\n{% block header %}x{% endblock %}",
        )
        .unwrap();
        assert_eq!(t.dialect.name, "krl");
        assert!(t.user);
        assert!(matches!(
            Template::from_source("G0 X{{ 1 }}"),
            Err(TemplateError::NoDialect(_))
        ));
        assert!(matches!(
            Template::from_source("{%- extends 'kuka' %}"),
            Err(TemplateError::Unknown(..))
        ));
    }

    #[test]
    fn timing_durations() {
        let speeds = [100.0, 50.0, 100.0, 200.0, 200.0, 200.0];
        let a = [0.0; 6];
        let b = [10.0, 10.0, 0.0, 0.0, 0.0, 40.0];
        assert_eq!(Timing::Rapid.duration(&a, &b, &speeds), Some(0.2));
        assert_eq!(
            Timing::AxisPercent([50.0; 6]).duration(&a, &b, &speeds),
            Some(0.4)
        );
        assert_eq!(Timing::Duration(1.5).duration(&a, &b, &speeds), Some(1.5));
        assert_eq!(Timing::LeadSpeed(20.0).duration(&a, &b, &speeds), Some(2.0));
        let path = (10f64 * 10.0 + 10.0 * 10.0 + 40.0 * 40.0).sqrt();
        assert_eq!(Timing::PathFeed(60.0).duration(&a, &b, &speeds), Some(path));
        assert_eq!(Timing::Unknown.duration(&a, &b, &speeds), None);
    }
}

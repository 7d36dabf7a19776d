//! Controller dialects: in = a program text (and the [`ControllerMap`] in force); out =
//! [`Parsed`], the motions it commands in model joints and where each value sits in the text.
//! The other end of [`crate::emit`]: each dialect is one folder here, behind one trait
//! ([`Language`]): its template (how [`crate::ir::Program`] is written), its reader (how that
//! text is read back), its writer of new values (what `compensate` changes), its timing and
//! corner semantics (the template's front matter) and where its controller keeps joint zeros.
//!
//! | name | language | folder | template |
//! |---|---|---|---|
//! | `ngc` | RS274/NGC (LinuxCNC, ISO CNC cores) | [`ngc`] | `src/dialect/ngc/ngc.j2` |
//! | `sinumerik` | SINUMERIK 840D part program | [`sinumerik`] | `src/dialect/sinumerik/sinumerik.j2` |
//! | `krl` | KUKA KRL (KSS 8.x) | [`krl`] | `src/dialect/krl/krl.j2` |
//! | `rapid` | ABB RAPID module | [`rapid`] | `src/dialect/rapid/rapid.j2` |
//! | `urscript` | Universal Robots URScript | [`urscript`] | `src/dialect/urscript/urscript.j2` |
//! | `fanuc` | FANUC TP as LS text | [`fanuc`] | `src/dialect/fanuc/fanuc.j2` |
//!
//! Every bundled template starts with its front matter: TOML inside a leading `{#- dialect`
//! … `-#}` comment (file extension, axis units and names, the default controller mapping,
//! program-name rules, what a move's time states, the corner model). A user template
//! (`--template FILE`) declares the dialect it is read back as with `{% extends "NAME" %}`, and
//! inherits that dialect's front matter and reader.
//!
//! Readers are strict: they understand what a joint-space measurement program needs and name
//! the line of anything else. They never trust comments for motion, only for the header
//! facts (fixture, MAP, the controller mapping) and the `support` marks. They record where
//! every value they parsed sits ([`Positions`]), so a writer changes those bytes and nothing
//! else, and no second tokenizer has to agree with the reader.

pub mod fanuc;
pub mod krl;
pub mod ngc;
mod positions;
pub mod rapid;
pub mod sinumerik;
pub mod urscript;

pub(crate) use positions::{after_line, offset_in, shifted, span, werr, words_replaced};
pub use positions::{apply, Edit, MoveSpans, NewValues, Positions, WriteError};

use crate::controller::{ControllerDefaults, ControllerMap, Coupling, Units};
use serde::{Deserialize, Serialize};
use std::sync::OnceLock;

/// One controller language: everything edbbgen knows about it, in its own folder.
pub trait Language: Sync {
    /// The name programs, templates (`{% extends "NAME" %}`) and the command line use.
    fn name(&self) -> &'static str;

    /// The bundled template: its front matter ([`Dialect`]), then the blocks that write a
    /// program.
    fn template(&self) -> &'static str;

    /// Reads a program: its steps in model joints, and where each value sits in `text`.
    fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError>;

    /// How surely `text` is a program in this language when its file's extension does not
    /// say: 0 = not, higher = a more specific sign (the highest wins, ties in registry order).
    /// `first_code` is the text's first line that is not a comment in any bundled language.
    fn recognises(&self, text: &str, first_code: &str) -> u8;

    /// How the language writes a dwell, as its reader takes it (for messages).
    fn dwell_instruction(&self) -> &'static str;

    /// Decimals of compensated axis values: as many as the controller resolves, where the
    /// language carries them (a planned program lives on the 0.001° grid).
    fn decimals(&self, units: Units) -> usize;

    /// The edits that write `values` (one per move of `parsed`, in order) into `text` (which
    /// `parsed` was read from, with `map`; its lines end with `\n`, the last one too), and
    /// `note` as a header comment. Only the ranges the reader recorded change, besides whole
    /// lines the language needs around them.
    fn write(
        &self,
        text: &str,
        parsed: &Parsed,
        values: &[NewValues],
        note: &str,
        map: &ControllerMap,
    ) -> Result<Vec<Edit>, WriteError>;

    /// Where the controller keeps one axis's zero, and by how much to change it.
    fn mastering(&self, zero: &AxisZero) -> String;

    /// The template's front matter.
    fn dialect(&self) -> &'static Dialect {
        all()
            .iter()
            .find(|d| d.name == self.name())
            .unwrap_or_else(|| panic!("{} is not registered in dialect::LANGUAGES", self.name()))
    }

    /// How the controller times moves: what a time word states and the acceleration of moves
    /// that blend (front matter `move_time` and `[corner] blend_acceleration`).
    fn timing(&self) -> ProgramTiming {
        let d = self.dialect();
        ProgramTiming {
            move_time: d.move_time,
            blend_acceleration: d.corner.blend_acceleration,
        }
    }
}

/// One controller axis's zero offset, for [`Language::mastering`].
#[derive(Clone, Debug, PartialEq)]
pub struct AxisZero<'a> {
    /// The axis's name in the mapping (`A1`, `J1`, `X`, …).
    pub axis: &'a str,
    /// Its position among the six axes (0-based).
    pub index: usize,
    /// The change of its reading, in the program's units.
    pub delta: f64,
    /// The change of the master count (`[controller] pulses_per_deg` given).
    pub master_count_delta: Option<i64>,
}

/// Every bundled language, in the order `edbbgen dialects` lists them. A new dialect is a
/// folder beside these and one entry here.
pub const LANGUAGES: &[&dyn Language] = &[
    &ngc::Ngc,
    &sinumerik::Sinumerik,
    &krl::Krl,
    &rapid::Rapid,
    &urscript::UrScript,
    &fanuc::Fanuc,
];

/// A bundled language by name.
pub fn language(name: &str) -> Option<&'static dyn Language> {
    LANGUAGES.iter().copied().find(|l| l.name() == name)
}

/// The bundled dialects: (name, template source), in registry order.
pub fn bundled() -> impl Iterator<Item = (&'static str, &'static str)> {
    LANGUAGES.iter().map(|l| (l.name(), l.template()))
}

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

    /// The language this front matter belongs to (its reader, writer, mastering terms).
    pub fn language(&self) -> &'static dyn Language {
        language(&self.name).unwrap_or_else(|| panic!("dialect '{}' has no language", self.name))
    }

    /// Reads a program in this dialect.
    pub fn read(&self, text: &str, map: &ControllerMap) -> Result<Parsed, ParseError> {
        let mut p = self.language().read(text, map)?;
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
        bundled()
            .map(|(name, text)| {
                let fm = front_matter(text)
                    .unwrap_or_else(|| panic!("the {name} template has no front matter"));
                let d: Dialect = toml::from_str(fm)
                    .unwrap_or_else(|e| panic!("the {name} template's front matter: {e}"));
                assert_eq!(d.name, name, "the {name} template names itself {}", d.name);
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
    language(name).map_or("a dwell", |l| l.dwell_instruction())
}

pub fn names() -> Vec<&'static str> {
    LANGUAGES.iter().map(|l| l.name()).collect()
}

/// The bundled template source of a dialect.
pub fn source(name: &str) -> Option<&'static str> {
    language(name).map(|l| l.template())
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
    // The first line that is not a comment (or a KRL attribute line) in any bundled language.
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
    let mut best: Option<(u8, &dyn Language)> = None;
    for l in LANGUAGES {
        let sure = l.recognises(text, first_code);
        if sure > 0 && best.is_none_or(|(b, _)| sure > b) {
            best = Some((sure, *l));
        }
    }
    by_name(best?.1.name())
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
    /// Where each value the reader parsed sits in the text (not serialised: it belongs to
    /// the text it was read from).
    #[serde(skip)]
    pub positions: Positions,
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
            positions: Positions::default(),
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
/// before: `.. text` after a space, `..text` inside a cut word ([`wrap`] writes
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

/// Chunks of at most `width` characters, broken at spaces where possible. Every chunk after
/// the first starts with `..`: `.. text` continues after a space, `..text` continues a word
/// that was cut (the readers join them back exactly).
pub fn wrap(text: String, width: usize) -> Vec<String> {
    let width = width.max(8);
    let mut out: Vec<String> = Vec::new();
    let mut rest = text.as_str();
    let mut prefix = "";
    loop {
        let room = width - prefix.len();
        if rest.len() <= room {
            out.push(format!("{prefix}{rest}"));
            return out;
        }
        // Break at the last space that fits, else cut the word.
        let end = (0..=room + 1)
            .rev()
            .find(|&k| rest.is_char_boundary(k))
            .unwrap_or(0);
        match rest[..end].rfind(' ').filter(|&k| k > 0) {
            Some(k) => {
                out.push(format!("{prefix}{}", &rest[..k]));
                rest = &rest[k + 1..];
                prefix = ".. ";
            }
            None => {
                let cut = (1..=room)
                    .rev()
                    .find(|&k| rest.is_char_boundary(k))
                    .unwrap_or(room);
                out.push(format!("{prefix}{}", &rest[..cut]));
                rest = &rest[cut..];
                prefix = "..";
            }
        }
    }
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
        assert_eq!(all().len(), LANGUAGES.len());
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
    fn detect_takes_the_language_that_recognises_the_text_most_surely() {
        let path = std::path::Path::new("program.txt");
        for (text, name) in [
            ("/PROG  EDBB\n/MN\n", Some("fanuc")),
            ("&ACCESS RVP\nDEF edbb( )\nEND\n", Some("krl")),
            // KRL's DEF in any case: it wins over URScript's lower-case `def`.
            ("def edbb():\n  halt()\nend\n", Some("krl")),
            ("! note\nMODULE edbb\nENDMODULE\n", Some("rapid")),
            ("; note\nG71 G90 G60\nG0 X1=1\n", Some("sinumerik")),
            ("N10 G641 ADIS=1\n", Some("sinumerik")),
            ("(note)\nG21 G90\nG0 X1 Y2 Z3 A4 B5 C6\n", Some("ngc")),
            ("hello\n", None),
        ] {
            assert_eq!(
                detect(path, text).map(|d| d.name.as_str()),
                name,
                "{text:?}"
            );
        }
        let d = detect(std::path::Path::new("p.SCRIPT"), "").unwrap();
        assert_eq!(d.name, "urscript");
        assert_eq!(d.language().name(), "urscript");
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

//! Flags as clap parses them, close to argv; [`super::run`] resolves them once into checked,
//! SI-unit options.

use super::help;
use clap::{Args, Parser, Subcommand};
use std::path::PathBuf;

/// The compile stages `--emit` prints as JSON.
pub const EMIT_STAGES: [&str; 9] = [
    "model",
    "identifiability",
    "sample",
    "pool",
    "selection",
    "path",
    "plan",
    "program",
    "report",
];

#[derive(Parser, Debug)]
#[command(
    name = "edbbgen",
    version,
    about = "Compiles error-sensitive Extended Double Ball Bar (EDBB) measurement programs for 6-axis robots",
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true,
    allow_negative_numbers = true,
    after_help = help::COMPILE
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Option<Command>,
    #[command(flatten)]
    pub compile: CompileArgs,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Identifiability of the 30 model parameters and observability of a rich pose set.
    #[command(allow_negative_numbers = true, after_help = help::MODEL)]
    Model(ModelArgs),
    /// Re-read a program and re-check it: poses, moves and blends against every limit.
    #[command(allow_negative_numbers = true, after_help = help::VERIFY)]
    Verify(VerifyArgs),
    /// Digital twin: run a program on a virtual robot with the errors of TRUTH.toml and write
    /// what the EDBB and the encoders would record (CSV).
    #[command(allow_negative_numbers = true, after_help = help::SIMULATE)]
    Simulate(SimulateArgs),
    /// Compare measured EDBB data with the model: calibrate, name the missing effect, report.
    #[command(allow_negative_numbers = true, after_help = help::DIAGNOSE)]
    Diagnose(DiagnoseArgs),
    /// The extended circle test after ISO 230-4 as a program (the baseline for comparison).
    #[command(allow_negative_numbers = true, after_help = help::CIRCLE)]
    Circle(CircleArgs),
    /// Loaded double ball bar: compliance along the bar, the centring sine, the kinematic
    /// remainder and joint stiffness from loaded circle data (LOADED.csv).
    #[command(allow_negative_numbers = true, after_help = help::LDBB)]
    Ldbb(LdbbArgs),
    /// The LDBB loaded circle test as a program (every load, lead-in, measured circles,
    /// lead-out), checked by verify.
    #[command(allow_negative_numbers = true, after_help = help::LDBB_CIRCLE)]
    LdbbCircle(LdbbCircleArgs),
    /// LDBB digital twin: loaded circle data (and a laser-tracker reference) from a truth.
    #[command(allow_negative_numbers = true, after_help = help::SIMULATE_LDBB)]
    SimulateLdbb(SimulateLdbbArgs),
    /// List the bundled controller dialects (templates) and what each approximates.
    #[command(after_help = help::DIALECTS)]
    Dialects(DialectsArgs),
    /// Calibrate: from measured EDBB runs to a calibrated robot file, with the parameters the
    /// data determine, their uncertainties and the predicted MAP position accuracy.
    #[command(allow_negative_numbers = true, after_help = help::CALIBRATE)]
    Calibrate(CalibrateArgs),
    /// Where to put the fixture: candidate positions scored by the MAP position uncertainty a
    /// calibration from a program compiled there would reach; the best campaign of K positions.
    #[command(allow_negative_numbers = true, after_help = help::PLACE)]
    Place(Box<PlaceArgs>),
    /// Apply a calibration: compensated joint and Cartesian targets (CSV) or a compensated
    /// joint-move program for any controller, the mastering offsets, and the accuracy each
    /// route gives over the joint space.
    #[command(allow_negative_numbers = true, after_help = help::COMPENSATE)]
    Compensate(CompensateArgs),
    /// Print a shell completion script (bash, zsh, fish, elvish, powershell) on stdout.
    #[command(after_help = help::COMPLETIONS)]
    Completions(CompletionsArgs),
    /// Print the manual page (roff, `man -l -` reads it) on stdout.
    #[command(after_help = help::MAN)]
    Man(ManArgs),
}

#[derive(Args, Debug)]
pub struct DialectsArgs {
    /// Write the report as JSON (schema edbbgen.dialects/1) to FILE; `-`, or the flag alone, prints it
    /// on stdout in place of the summary.
    #[arg(long, value_name = "FILE", num_args = 0..=1, default_missing_value = "-")]
    pub json: Option<PathBuf>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct CompletionsArgs {
    /// The shell to complete for.
    #[arg(value_name = "SHELL")]
    pub shell: clap_complete::Shell,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct ManArgs {
    /// A subcommand's page (`edbbgen-verify(1)`, ...) instead of the compiler's.
    #[arg(value_name = "SUBCOMMAND")]
    pub subcommand: Option<String>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Robot, cell and instrument: shared by the compiler and `model`.
#[derive(Args, Debug, Clone)]
pub struct CellArgs {
    /// Cell description (fixture, bar, tool, environment, cables, margin); flags override it.
    #[arg(long, value_name = "CELL.toml")]
    pub cell: Option<PathBuf>,
    /// MAP (tool ball centre) in the flange frame, mm [default: the robot file's tool, else the
    /// flange origin].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub tool: Option<Xyz>,
    /// Usable bar length range (ball-centre distance), mm [default: 300..520].
    #[arg(long, value_name = "MIN..MAX", value_parser = range)]
    pub bar: Option<Range>,
    /// Diameter of the EDBB's balls, mm: their centres can come no closer than this [default: 25].
    #[arg(long, value_name = "MM", value_parser = number)]
    pub ball: Option<f64>,
    /// Floor height in the robot base frame, mm [default: 0].
    #[arg(long, value_name = "MM", allow_hyphen_values = true, value_parser = number)]
    pub floor: Option<f64>,
    /// Safety margin: minimum clearance between any two bodies, mm [default: 10].
    #[arg(long, value_name = "MM", value_parser = number)]
    pub margin: Option<f64>,
    /// Distance kept from every joint limit by poses and motions, deg [default: 1].
    #[arg(long, value_name = "DEG", value_parser = number)]
    pub joint_margin: Option<f64>,
    /// URDF: the link that ends the chain [default: flange, tool0, or the chain's last link].
    #[arg(long, value_name = "LINK")]
    pub flange: Option<String>,
    /// URDF: directory searched for package:// paths (repeatable).
    #[arg(long = "package-path", value_name = "DIR")]
    pub package_path: Vec<PathBuf>,
    /// Seed of every random choice (the pool subset, the model's pose set).
    #[arg(long, value_name = "N", default_value_t = crate::pipeline::DEFAULT_SEED)]
    pub seed: u64,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct CompileArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT", required = true)]
    pub robot: Option<PathBuf>,
    /// Fixture ball centre in the robot base frame, mm [default: the cell file's].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Option<Xyz>,
    /// Output program.
    #[arg(short, long, value_name = "PATH.nc", required = true)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub cell: CellArgs,
    /// Joint grid step, degrees: one value for all joints or six comma-separated values.
    #[arg(long, value_name = "DEG", default_value = "10", value_parser = steps)]
    pub step: Steps,
    /// Keep at most this many valid poses for pruning (a seeded uniform subset).
    #[arg(long, value_name = "N", default_value_t = crate::pipeline::DEFAULT_MAX_CANDIDATES)]
    pub max_candidates: usize,
    /// Number of measurement poses [default: the knee of the cond(n) curve].
    #[arg(long, value_name = "N")]
    pub poses: Option<usize>,
    /// Corner blend distance at the MAP, mm.
    #[arg(long, value_name = "MM", default_value = "10", value_parser = number)]
    pub blend: f64,
    /// What the tour minimises: each move with its acceleration ramps (trapezoid), or Eq. 7 (the
    /// slowest joint at its maximum speed, the paper's).
    #[arg(long, value_name = "COST", default_value = "trapezoid", value_parser = ["trapezoid", "eq7"])]
    pub tour_cost: String,
    /// The bar's noise per reading, µm: what the predicted calibration uncertainty assumes.
    #[arg(long, value_name = "UM", default_value = "1.0", value_parser = number)]
    pub bar_noise: f64,
    /// The bar's sample rate, Hz: readings along every move made with the bar.
    #[arg(long, value_name = "HZ", default_value = "50", value_parser = number)]
    pub bar_rate: f64,
    /// Stop-and-measure: an exact stop and a dwell of S seconds at every measurement pose, for
    /// controllers without a synchronous joint log (calibrate reads the bar's own log with
    /// --bar-log and --program); rounded to 0.01 s.
    #[arg(long, value_name = "S", value_parser = number)]
    pub dwell: Option<f64>,
    /// A short check program: the poses are chosen for these parameters only (names such as
    /// theta2,a3), or for a calibration report's (calibrate --json, e.g. of a --baseline
    /// run): the parameters its drift section found moved, then the six joint zeros.
    #[arg(long, value_name = "PARAMS|REPORT.json")]
    pub focus: Option<String>,
    /// Start configuration, degrees: the tour starts at the selected pose nearest to it.
    #[arg(long, value_name = "Q1,..,Q6", allow_hyphen_values = true, value_parser = joints)]
    pub start: Option<Joints>,
    /// Output dialect: ngc, sinumerik, krl, rapid, urscript, fanuc (`edbbgen dialects`).
    #[arg(long, value_name = "NAME", default_value = "ngc")]
    pub dialect: String,
    /// Use this template file instead of a bundled dialect; it must start with
    /// {% extends "NAME" %} (the dialect its programs are read back as).
    #[arg(long, value_name = "FILE", conflicts_with = "dialect")]
    pub template: Option<PathBuf>,
    /// Golden-file mode: compile, compare with the file at -o, write nothing; exit 1 with a
    /// unified diff when they differ.
    #[arg(long)]
    pub check: bool,
    /// Also print a stage's result as JSON on stdout.
    #[arg(long, value_name = "STAGE", value_parser = EMIT_STAGES)]
    pub emit: Option<String>,
    /// Write the counts of every stage as JSON (schema edbbgen.report/1).
    #[arg(long, value_name = "REPORT.json")]
    pub json: Option<PathBuf>,
    /// The former spelling of --json (still read, with a warning).
    #[arg(long, value_name = "REPORT.json", hide = true, conflicts_with = "json")]
    pub report: Option<PathBuf>,
    /// Write a self-contained HTML report (figures of the pool, pose count, trajectories and
    /// path; the stage counts, safety and identifiability tables).
    #[arg(long, value_name = "REPORT.html")]
    pub html: Option<PathBuf>,
    /// Print the wall time of every compile stage on stderr (load, scene, sample, sections,
    /// identify, select/order/plan, predict, emit/verify; no output file changes).
    #[arg(long)]
    pub timings: bool,
}

#[derive(Args, Debug)]
pub struct VerifyArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// The program to check.
    #[arg(value_name = "PROGRAM.nc")]
    pub program: PathBuf,
    /// Fixture ball centre, mm [default: the cell file's, else the program header's].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Option<Xyz>,
    /// The program's dialect [default: from the file extension, else from its text].
    #[arg(long, value_name = "NAME")]
    pub dialect: Option<String>,
    #[command(flatten)]
    pub cell: CellArgs,
    /// Write the report as JSON (schema edbbgen.verify/1, or edbbgen.verify-trace/1 with --trace) to FILE; `-`, or the flag alone, prints it
    /// on stdout in place of the summary.
    #[arg(long, value_name = "FILE", num_args = 0..=1, default_missing_value = "-")]
    pub json: Option<PathBuf>,
    /// A recorded run of the program (t_s,q1_deg,...,q6_deg in the controller's axis values):
    /// check the executed path, how close it passed each measurement pose, and its time.
    #[arg(long, value_name = "TRACE.csv")]
    pub trace: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct ModelArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// Fixture ball centre in the robot base frame, mm [default: the cell file's].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Option<Xyz>,
    #[command(flatten)]
    pub cell: CellArgs,
    /// Size of the random pose set the analysis uses.
    #[arg(long, value_name = "N", default_value_t = 400)]
    pub samples: usize,
    /// The bar's noise per reading, µm: what the predicted calibration uncertainty assumes.
    #[arg(long, value_name = "UM", default_value = "1.0", value_parser = number)]
    pub bar_noise: f64,
    /// Write the report as JSON (schema edbbgen.model/1) to FILE; `-`, or the flag alone, prints it
    /// on stdout in place of the summary.
    #[arg(long, value_name = "FILE", num_args = 0..=1, default_missing_value = "-")]
    pub json: Option<PathBuf>,
}

#[derive(Args, Debug)]
pub struct SimulateArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// The program to run (any bundled dialect, as `edbbgen` or `edbbgen circle` emit it).
    #[arg(value_name = "PROGRAM.nc")]
    pub program: PathBuf,
    /// The program's dialect [default: from the file extension, else from its text].
    #[arg(long, value_name = "NAME")]
    pub dialect: Option<String>,
    /// The real robot: geometric errors, effects and noise.
    #[arg(long, value_name = "TRUTH.toml")]
    pub truth: PathBuf,
    /// Output CSV (measured-data contract).
    #[arg(short, long, value_name = "MEASURED.csv")]
    pub output: PathBuf,
    /// Fixture ball centre, mm [default: the program's header].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Option<Xyz>,
    /// MAP in the flange frame, mm [default: the program's header, else the robot file's tool].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub tool: Option<Xyz>,
    /// Cell file: its `[controller]` section maps the program's axes to the model's joints
    /// (the twin needs nothing else from it).
    #[arg(long, value_name = "CELL.toml")]
    pub cell: Option<PathBuf>,
    /// The bar's sample rate, Hz.
    #[arg(long, value_name = "HZ", default_value = "50", value_parser = number)]
    pub bar_rate: f64,
    /// The former spelling of --bar-rate (still read, with a warning).
    #[arg(long, value_name = "HZ", hide = true, value_parser = number)]
    pub rate: Option<f64>,
    /// Noise seed.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// Also write the bar's own log (t_s,length_mm on its own clock, with what it reads while
    /// unmounted); -o then holds the same mounted samples with the true joints (the
    /// synchronous reference).
    #[arg(long, value_name = "BAR.csv")]
    pub bar_log: Option<PathBuf>,
    /// Also write the controller's joint log (t_s,q1_deg..q6_deg in the controller's axis
    /// values, on its own clock); needs --bar-log.
    #[arg(long, value_name = "JOINTS.csv", requires = "bar_log")]
    pub joint_log: Option<PathBuf>,
    /// The joint log's rate, Hz.
    #[arg(long, value_name = "HZ", default_value = "100", value_parser = number)]
    pub joint_rate: f64,
    /// The bar's clock: t_bar = OFFSET + (1 + DRIFT·1e-6)·t_controller, s.
    #[arg(
        long,
        value_name = "S",
        default_value = "0",
        allow_hyphen_values = true
    , value_parser = number)]
    pub clock_offset: f64,
    /// The bar's clock drift against the controller's, ppm.
    #[arg(
        long,
        value_name = "PPM",
        default_value = "0",
        allow_hyphen_values = true
    , value_parser = number)]
    pub clock_drift: f64,
    /// How long the operator takes at each pause (mounting, removing the bar), s: uniform.
    #[arg(long, value_name = "MIN..MAX", default_value = "5..20", value_parser = range)]
    pub pause: Range,
    /// The bar's reading minus the ball-centre distance (a bar whose zero is not it), mm.
    #[arg(
        long,
        value_name = "MM",
        default_value = "0",
        allow_hyphen_values = true
    , value_parser = number)]
    pub bar_zero: f64,
    /// Random gaps (0.5..3 s) in the bar log.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub gaps: usize,
    /// Probability that a bar sample is lost.
    #[arg(long, value_name = "P", default_value = "0", value_parser = number)]
    pub dropout: f64,
    /// Poses (1-based, in dwell order) whose plateau the bar log loses.
    #[arg(long, value_name = "K,..")]
    pub missing: Option<String>,
    /// The controller's moves take this many times the program's time (acceleration ramps, a
    /// speed override); dwells are exact.
    #[arg(long, value_name = "F", default_value = "1", value_parser = number)]
    pub move_scale: f64,
    /// Controller stops (0.5..3 s) in moves made with the bar: plateaus of no pose.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub holds: usize,
    /// Poses (1-based) whose plateau a decaying 15 Hz vibration (10 µm) disturbs.
    #[arg(long, value_name = "K,..")]
    pub vibration: Option<String>,
    /// The bar logs nothing while unmounted (default: it reads what a handled bar reads).
    #[arg(long)]
    pub no_handling: bool,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct DiagnoseArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// Fixture ball centre in the robot base frame, mm [default with --program: its header's].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Option<Xyz>,
    /// MAP in the flange frame, mm [default: the program header's, else the robot file's tool].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub tool: Option<Xyz>,
    /// Measured EDBB data (CSV contract).
    #[arg(
        long,
        value_name = "MEASURED.csv",
        required_unless_present = "bar_log",
        conflicts_with = "bar_log"
    )]
    pub measured: Option<PathBuf>,
    /// Instead of --measured: the bar's own log, with --program (stop-and-measure) or
    /// --joint-log (continuous).
    #[arg(long, value_name = "BAR.csv")]
    pub bar_log: Option<PathBuf>,
    /// The program the bar log recorded.
    #[arg(long, value_name = "PROG", requires = "bar_log")]
    pub program: Option<PathBuf>,
    /// The controller's joint log (t_s,q1_deg..q6_deg on its clock).
    #[arg(long, value_name = "JOINTS.csv", requires = "bar_log")]
    pub joint_log: Option<PathBuf>,
    /// Write the JSON report here.
    #[arg(long, value_name = "REPORT.json")]
    pub json: Option<PathBuf>,
    /// Write the residual plot (SVG) here.
    #[arg(long, value_name = "REPORT.svg")]
    pub plot: Option<PathBuf>,
    /// Write a self-contained HTML report here (Figs. 11-12, steps, parameters, verdict).
    #[arg(long, value_name = "REPORT.html")]
    pub html: Option<PathBuf>,
    /// One reading's noise, µm (the instrument's specification, or its spread at standstill):
    /// what the residual is judged against [default: from the data: repeated or neighbouring
    /// poses of static readings, the high-frequency part of a continuous recording].
    #[arg(long, value_name = "UM", value_parser = positive_um)]
    pub noise: Option<f64>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct CircleArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// Fixture ball centre (circle centre) in the robot base frame, mm.
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Xyz,
    /// MAP in the flange frame, mm [default: the robot file's tool].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub tool: Option<Xyz>,
    /// Output program.
    #[arg(short, long, value_name = "CIRCLE.nc")]
    pub output: PathBuf,
    /// Circle diameter, mm (ISO 230-4 test of the paper: 700).
    #[arg(long, value_name = "MM", default_value = "700", value_parser = number)]
    pub diameter: f64,
    /// MAP speed along the circle, mm/s.
    #[arg(long, value_name = "MM_S", default_value = "50", value_parser = number)]
    pub speed: f64,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct LdbbArgs {
    /// Loaded circle data: run,load_n,angle_deg,q1_deg..q6_deg,deflection_um.
    #[arg(value_name = "LOADED.csv")]
    pub loaded: PathBuf,
    /// The setup: circle, table ball, tool, loads (mm, deg, N, s).
    #[arg(long, value_name = "SETUP.toml")]
    pub setup: PathBuf,
    /// Robot description for the stiffness (.urdf or .dh.toml) [default: the setup's robot].
    #[arg(long, value_name = "ROBOT")]
    pub robot: Option<PathBuf>,
    /// Laser-tracker reference: angle_deg,error_um (unloaded kinematic error along the bar).
    #[arg(long, value_name = "LT.csv")]
    pub reference: Option<PathBuf>,
    /// Write the report as JSON (schema edbbgen.ldbb/1).
    #[arg(long, value_name = "REPORT.json")]
    pub json: Option<PathBuf>,
    /// Write the figures (Figs. 13-15 and the compliance) as one SVG.
    #[arg(long, value_name = "LDBB.svg")]
    pub plot: Option<PathBuf>,
    /// Write a self-contained HTML report.
    #[arg(long, value_name = "REPORT.html")]
    pub html: Option<PathBuf>,
    /// Angle grid the runs are resampled onto, deg (must divide 360).
    #[arg(long, value_name = "DEG", default_value = "1", value_parser = number)]
    pub grid_step: f64,
    /// The sine the kinematic remainder subtracts: linear (b = 1, the centring offset's) or
    /// nonlinear (the paper's Eq. 9 with b free).
    #[arg(long, value_name = "MODEL", default_value = "linear", value_parser = ["linear", "nonlinear"])]
    pub sine: String,
    /// Start of the nonlinear fit: the linear solution, or the paper's guess (a = 0.8 mm,
    /// b = 1, phi = 22.5 deg).
    #[arg(long, value_name = "START", default_value = "linear", value_parser = ["linear", "paper"])]
    pub sine_start: String,
    /// URDF: directory searched for package:// paths (repeatable).
    #[arg(long = "package-path", value_name = "DIR")]
    pub package_path: Vec<PathBuf>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct LdbbCircleArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// The setup: circle, table ball, tool, loads.
    #[arg(long, value_name = "SETUP.toml")]
    pub setup: PathBuf,
    /// Output program.
    #[arg(short, long, value_name = "PROGRAM")]
    pub output: PathBuf,
    /// Cell file (environment, tool shapes, hoses, floor, cables, speeds, margins); the
    /// instrument's geometry comes from the setup.
    #[arg(long, value_name = "CELL.toml")]
    pub cell: Option<PathBuf>,
    /// Angle between programmed points along the circle, deg.
    #[arg(long, value_name = "DEG", default_value = "0.5", value_parser = number)]
    pub step: f64,
    /// Corner blend distance at the tool ball, mm.
    #[arg(long, value_name = "MM", default_value = "0.5", value_parser = number)]
    pub blend: f64,
    /// The LVDT's range either side of the nominal bar length, mm.
    #[arg(long, value_name = "MM", default_value = "2", value_parser = number)]
    pub stroke: f64,
    /// Safety margin: minimum clearance between any two bodies, mm [default: the cell's, 10].
    #[arg(long, value_name = "MM", value_parser = number)]
    pub margin: Option<f64>,
    /// Distance kept from every joint limit, deg [default: the cell's, 1].
    #[arg(long, value_name = "DEG", value_parser = number)]
    pub joint_margin: Option<f64>,
    /// Output dialect (a bundled template, `edbbgen dialects` lists them).
    #[arg(long, value_name = "NAME", default_value = "ngc")]
    pub dialect: String,
    /// Use this template file instead of a bundled dialect.
    #[arg(long, value_name = "FILE")]
    pub template: Option<PathBuf>,
    /// URDF: directory searched for package:// paths (repeatable).
    #[arg(long = "package-path", value_name = "DIR")]
    pub package_path: Vec<PathBuf>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct SimulateLdbbArgs {
    /// The setup: circle, table ball, tool, loads, samples per circle.
    #[arg(long, value_name = "SETUP.toml")]
    pub setup: PathBuf,
    /// The real robot and instrument: stiffness, centring offset, joint-origin errors, gear
    /// nonlinearity, gravity, per-circle offsets, noise.
    #[arg(long, value_name = "LDBB_TRUTH.toml")]
    pub truth: PathBuf,
    /// Output: loaded circle data (the LOADED.csv contract).
    #[arg(short, long, value_name = "LOADED.csv")]
    pub output: PathBuf,
    /// Also write the laser-tracker reference (angle_deg,error_um).
    #[arg(long, value_name = "LT.csv")]
    pub reference: Option<PathBuf>,
    /// Robot description [default: the setup's robot].
    #[arg(long, value_name = "ROBOT")]
    pub robot: Option<PathBuf>,
    /// Noise seed.
    #[arg(long, value_name = "N", default_value_t = 1)]
    pub seed: u64,
    /// URDF: directory searched for package:// paths (repeatable).
    #[arg(long = "package-path", value_name = "DIR")]
    pub package_path: Vec<PathBuf>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct CalibrateArgs {
    /// Robot description: a .urdf or a .dh.toml file (the nominal robot).
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// Measured EDBB data of one run (CSV contract); repeat for a campaign of runs, in pairs
    /// with --fixture.
    #[arg(long, value_name = "M.csv", required_unless_present = "bar_log")]
    pub measured: Vec<PathBuf>,
    /// Fixture ball centre of the run, mm, robot base frame; repeat in pairs with --measured
    /// (then --bar-log), or give it once for every run [default for a --bar-log run: its
    /// program's header].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Vec<Xyz>,
    /// A run without a synchronous joint log: the bar's own log (t_s,length_mm on its clock);
    /// with --program (stop-and-measure: its plateaus matched to the program's poses) or
    /// --joint-log (continuous: the clocks synchronised). Repeatable: one run each.
    #[arg(long, value_name = "BAR.csv")]
    pub bar_log: Vec<PathBuf>,
    /// The program a --bar-log run recorded (once for every --bar-log, or once each).
    #[arg(long, value_name = "PROG")]
    pub program: Vec<PathBuf>,
    /// The controller's joint log of a --bar-log run (t_s,q1_deg..q6_deg on its clock; once
    /// each).
    #[arg(long, value_name = "JOINTS.csv")]
    pub joint_log: Vec<PathBuf>,
    /// MAP in the flange frame, mm [default: the robot file's tool].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub tool: Option<Xyz>,
    /// The calibrated robot: a .dh.toml for a DH robot, a .urdf for a URDF robot.
    #[arg(short, long, value_name = "CALIBRATED.dh.toml|CALIBRATED.urdf")]
    pub output: PathBuf,
    /// Write the JSON report here (schema edbbgen.calibrate/1).
    #[arg(long, value_name = "REPORT.json")]
    pub json: Option<PathBuf>,
    /// Write the residual plot (SVG) here: measured − model before and after, per run.
    #[arg(long, value_name = "REPORT.svg")]
    pub plot: Option<PathBuf>,
    /// Write a self-contained HTML report here.
    #[arg(long, value_name = "REPORT.html")]
    pub html: Option<PathBuf>,
    /// Effects fitted together with the geometry: auto (those the diagnosis names), none, or
    /// a list such as cyclic_error:2,servo_lag (joint numbers 1-based).
    #[arg(long, value_name = "auto|none|LIST", default_value = "auto")]
    pub effects: String,
    /// Write the geometry only: the robot file leaves out the effects fitted with it (every
    /// command then evaluates the geometry alone), and the prediction includes what they do
    /// over the joint space.
    #[arg(long)]
    pub geometry_only: bool,
    /// The step the joints were logged to, deg (0.1 for a controller that logs tenths of a
    /// degree; 0: exact). Each reading is then weighted by its own uncertainty: the
    /// instrument's noise with what rounding the joints does to the length at its pose
    /// [default: read from the logged values].
    #[arg(long, value_name = "DEG", allow_negative_numbers = true)]
    pub joint_resolution: Option<f64>,
    /// Estimate each run's fixture position where the data determine it (the default; the
    /// given position is a prior).
    #[arg(long, conflicts_with = "fixture_known")]
    pub fixture_free: bool,
    /// Hold each run's fixture at the given position (known in the robot's frame to a
    /// micrometre).
    #[arg(long)]
    pub fixture_known: bool,
    /// Hold the MAP at the given position (--tool or the robot file's) instead of
    /// estimating it.
    #[arg(long)]
    pub tool_known: bool,
    /// The bar's zero: the reading minus the ball-centre distance, mm, or `free` (unknown:
    /// estimated per run, e.g. a draw-wire or a bar zeroed anywhere) [default: 0].
    #[arg(long, value_name = "MM|free", allow_hyphen_values = true)]
    pub length_offset: Option<String>,
    /// Standard uncertainty of a length and an angle of the robot before calibration, mm,deg,
    /// and optionally of the given set-up (fixture, MAP, length zero), mm: what a
    /// parameter's calibrated uncertainty is judged against [default: 1,0.05,10].
    #[arg(long, value_name = "MM,DEG[,SETUP_MM]", allow_hyphen_values = true, value_parser = prior)]
    pub prior: Option<Prior>,
    /// One reading's noise, µm (the instrument's specification, or its spread at standstill):
    /// what the residual is judged against [default: from the data: repeated or neighbouring
    /// poses of static readings, the high-frequency part of a continuous recording].
    #[arg(long, value_name = "UM", value_parser = positive_um)]
    pub noise: Option<f64>,
    /// A previous calibration report (calibrate --json) of the same nominal robot: the fit
    /// starts from it (what these data do not determine keeps its values), and the report
    /// says what moved since, beyond the combined uncertainty, with a verdict.
    #[arg(long, value_name = "PREVIOUS.json")]
    pub baseline: Option<PathBuf>,
    /// URDF: the link that ends the chain [default: flange, tool0, or the chain's last link].
    #[arg(long, value_name = "LINK")]
    pub flange: Option<String>,
    /// URDF: directory searched for package:// paths (repeatable).
    #[arg(long = "package-path", value_name = "DIR")]
    pub package_path: Vec<PathBuf>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct CompensateArgs {
    /// The calibrated robot (calibrate -o): a .dh.toml or a .urdf file.
    #[arg(value_name = "CALIBRATED")]
    pub calibrated: PathBuf,
    /// The nominal robot the controller computes with (the file calibrate was given).
    #[arg(long, value_name = "ROBOT")]
    pub nominal: PathBuf,
    /// Targets to compensate (CSV: name, then q1_deg..q6_deg, or x_mm,y_mm,z_mm with optional
    /// rx_deg,ry_deg,rz_deg and an optional seed q1_deg..q6_deg).
    #[arg(long, value_name = "T.csv")]
    pub targets: Option<PathBuf>,
    /// A joint-move program to write again with compensated joints (any bundled dialect).
    #[arg(long, value_name = "PROGRAM")]
    pub program: Option<PathBuf>,
    /// The compensated targets (CSV) or program.
    #[arg(short, long, value_name = "OUT")]
    pub output: Option<PathBuf>,
    /// The TCP to compensate, in the flange frame, mm, optionally with its orientation
    /// (fixed-axis X-Y-Z, deg) [default: each robot file's MAP].
    #[arg(long, value_name = "X,Y,Z[,RX,RY,RZ]", allow_hyphen_values = true, value_parser = tcp_frame)]
    pub tcp: Option<crate::robot::Frame>,
    /// Cell file: its `[controller]` section maps the joint values (targets, program, mastering)
    /// to the controller's axes.
    #[arg(long, value_name = "CELL.toml")]
    pub cell: Option<PathBuf>,
    /// The controller family (a dialect name): the mapping's defaults and how the mastering
    /// offsets are written [default: the program's dialect; model joints for targets].
    #[arg(long, value_name = "NAME")]
    pub dialect: Option<String>,
    /// The calibration report (calibrate --json): the joint zero offsets with their
    /// uncertainties and the predicted accuracy [default: the robot files' joint zeros].
    #[arg(long, value_name = "REPORT.json")]
    pub calibration: Option<PathBuf>,
    /// How each target's joints come into it, for a backlash of the calibrated robot, where
    /// the targets file has no `approach` column: order (from the previous row), positive,
    /// negative, unknown (the centre of the play). A program's moves come from the move before;
    /// positive or negative says how the robot comes into its first move.
    #[arg(
        long,
        value_name = "order|positive|negative|unknown",
        default_value = "order"
    )]
    pub approach: String,
    /// The temperature (°C) to compensate a thermal drift referred to a logged temperature at
    /// [default: the calibration's reference state].
    #[arg(
        long,
        value_name = "C",
        allow_hyphen_values = true,
        conflicts_with = "elapsed"
    )]
    pub temperature: Option<f64>,
    /// The time since the reference state (s) to compensate a thermal drift at (a drift
    /// identified as a warm-up lag) [default: the reference state].
    #[arg(long, value_name = "S")]
    pub elapsed: Option<f64>,
    /// A payload different from the calibration's: mass (kg) and its centre in the flange
    /// frame (mm; default the TCP), for a joint compliance identified with a mass
    /// model (form known_masses).
    #[arg(long, value_name = "KG[,X,Y,Z]")]
    pub payload: Option<String>,
    /// Write the report here (schema edbbgen.compensate/1).
    #[arg(long, value_name = "REPORT.json")]
    pub json: Option<PathBuf>,
    /// Write a self-contained HTML report here.
    #[arg(long, value_name = "REPORT.html")]
    pub html: Option<PathBuf>,
    /// URDF: the link that ends the chain [default: flange, tool0, or the chain's last link].
    #[arg(long, value_name = "LINK")]
    pub flange: Option<String>,
    /// URDF: directory searched for package:// paths (repeatable).
    #[arg(long = "package-path", value_name = "DIR")]
    pub package_path: Vec<PathBuf>,
    /// Quiet: no progress and no summary; warnings and errors only (on stderr). Output asked for
    /// by a flag (a file, `--emit`, `--json -`) is still written.
    #[arg(short, long)]
    pub quiet: bool,
}

#[derive(Args, Debug)]
pub struct PlaceArgs {
    /// Robot description: a .urdf or a .dh.toml file.
    #[arg(value_name = "ROBOT")]
    pub robot: PathBuf,
    /// The fixture to compare with, mm [default: the cell file's, if it has one].
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub fixture: Option<Xyz>,
    #[command(flatten)]
    pub cell: CellArgs,
    /// The box searched, mm, robot base frame [default: the reachable volume in front of the
    /// robot above the floor].
    #[arg(long, value_name = "X0..X1,Y0..Y1,Z0..Z1", allow_hyphen_values = true)]
    pub region: Option<String>,
    /// Radius of the fixture's stand, a column from the floor to the ball, mm; 0 = no stand
    /// (a fixture on a bracket or hung from above) [default: the cell's, else 40].
    #[arg(long, value_name = "MM", value_parser = number)]
    pub stand: Option<f64>,
    /// Grid points per axis over the region (ends included).
    #[arg(long, value_name = "NX,NY,NZ", default_value = "10,10,5")]
    pub grid: String,
    /// Also score this position, mm (repeatable): spots the cell offers.
    #[arg(long, value_name = "X,Y,Z", allow_hyphen_values = true, value_parser = xyz)]
    pub at: Vec<Xyz>,
    /// Fixture positions in the campaign: the best K, calibrated together.
    #[arg(long, value_name = "K", default_value_t = 1)]
    pub count: usize,
    /// Positions estimated in full (a compile each), the best by proxy.
    #[arg(long, value_name = "N", default_value_t = crate::place::DEFAULT_TOP)]
    pub top: usize,
    /// Joint grid step of the proxies and the full estimate's compiles, degrees (one value or
    /// six).
    #[arg(long, value_name = "DEG", default_value = "20", value_parser = steps)]
    pub step: Steps,
    /// Pool size of the full estimate's compiles.
    #[arg(long, value_name = "N", default_value_t = crate::place::DEFAULT_FULL_CANDIDATES)]
    pub max_candidates: usize,
    /// The bar's noise per reading, µm.
    #[arg(long, value_name = "UM", default_value = "1.0", value_parser = number)]
    pub bar_noise: f64,
    /// The bar's sample rate, Hz.
    #[arg(long, value_name = "HZ", default_value = "50", value_parser = number)]
    pub bar_rate: f64,
    /// Standard uncertainty of a length and an angle before calibration, mm,deg: what a
    /// parameter the data do not determine costs [default: 1,0.05]. The grammar is
    /// calibrate's; a set-up value has nothing to act on here (the score takes the set-up as
    /// given) and is refused.
    #[arg(long, value_name = "MM,DEG[,SETUP_MM]", allow_hyphen_values = true, value_parser = prior)]
    pub prior: Option<Prior>,
    /// Ranked positions printed (the cell's fixture, --at positions and the campaign are
    /// printed too).
    #[arg(long, value_name = "N", default_value_t = 10)]
    pub show: usize,
    /// Write the JSON report here (schema edbbgen.place/1).
    #[arg(long, value_name = "REPORT.json")]
    pub json: Option<PathBuf>,
    /// Write a self-contained HTML report here (the candidates around the robot, the ranking).
    #[arg(long, value_name = "REPORT.html")]
    pub html: Option<PathBuf>,
    /// Write the cell file of each winner: into a directory (DIR/place-K.cell.toml) or as
    /// PREFIX-K.cell.toml.
    #[arg(long, value_name = "DIR_or_PREFIX")]
    pub write_cell: Option<PathBuf>,
}

/// `--tcp X,Y,Z[,RX,RY,RZ]` (mm, deg): the tool frame in the flange frame (clap's error
/// otherwise, exit 2).
fn tcp_frame(s: &str) -> Result<crate::robot::Frame, String> {
    use crate::units::{DEG, MM};
    let v = finite_list(s)?;
    match v.len() {
        3 => Ok(crate::robot::Frame::translation(
            nalgebra::Vector3::new(v[0], v[1], v[2]) * MM,
        )),
        6 => Ok(crate::robot::Frame::from_xyz_rpy(
            [v[0] * MM, v[1] * MM, v[2] * MM],
            [v[3] * DEG, v[4] * DEG, v[5] * DEG],
        )),
        n => Err(format!(
            "'{s}' has {n} values, expected X,Y,Z or X,Y,Z,RX,RY,RZ (mm, deg)"
        )),
    }
}

/// A noise figure in µm: positive and finite (clap's error otherwise, exit 2).
fn positive_um(v: &str) -> Result<f64, String> {
    match v.parse::<f64>() {
        Ok(x) if x.is_finite() && x > 0.0 => Ok(x),
        _ => Err(format!("'{v}' is not a positive number of micrometres")),
    }
}

// ---- value parsers: numbers, vectors and ranges, in clap's error form (exit 2) -------------

/// `X,Y,Z` in mm: three finite numbers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Xyz(pub [f64; 3]);

impl Xyz {
    /// The point in metres.
    pub fn m(&self) -> nalgebra::Vector3<f64> {
        nalgebra::Vector3::from(self.0) * crate::units::MM
    }
}

/// `MIN..MAX`: two finite numbers, MIN ≤ MAX.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Range(pub f64, pub f64);

/// A joint grid step in degrees: one for every joint or six, each 0.1 to 180.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Steps(pub [f64; 6]);

impl Steps {
    /// The steps in radians.
    pub fn rad(&self) -> [f64; 6] {
        self.0.map(|x| x * crate::units::DEG)
    }
}

/// Six joint values in degrees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Joints(pub [f64; 6]);

/// `--prior MM,DEG[,SETUP_MM]`: the standard uncertainty of a length and an angle of the robot
/// before calibration and, optionally, of the given set-up (fixture, MAP, length zero).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Prior {
    pub length_mm: f64,
    pub angle_deg: f64,
    pub setup_mm: Option<f64>,
}

fn finite_list(s: &str) -> Result<Vec<f64>, String> {
    s.split(',')
        .map(|x| x.trim().parse::<f64>().ok().filter(|x| x.is_finite()))
        .collect::<Option<_>>()
        .ok_or_else(|| "not a comma-separated list of finite numbers".to_string())
}

/// A finite number.
pub(super) fn number(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(x) if x.is_finite() => Ok(x),
        _ => Err("not a finite number".into()),
    }
}

pub(super) fn xyz(s: &str) -> Result<Xyz, String> {
    match finite_list(s)?.as_slice() {
        &[x, y, z] => Ok(Xyz([x, y, z])),
        v => Err(format!("{} values, expected X,Y,Z (mm)", v.len())),
    }
}

pub(super) fn range(s: &str) -> Result<Range, String> {
    let (a, b) = s.split_once("..").ok_or("not MIN..MAX")?;
    let (a, b) = (number(a)?, number(b)?);
    if a <= b {
        Ok(Range(a, b))
    } else {
        Err("needs MIN <= MAX".into())
    }
}

pub(super) fn steps(s: &str) -> Result<Steps, String> {
    let v = finite_list(s)?;
    let v: [f64; 6] = match v.len() {
        1 => [v[0]; 6],
        6 => std::array::from_fn(|i| v[i]),
        n => return Err(format!("{n} values, expected 1 or 6")),
    };
    if v.iter().any(|x| !(0.1..=180.0).contains(x)) {
        return Err("each step must be between 0.1 and 180 degrees".into());
    }
    Ok(Steps(v))
}

pub(super) fn joints(s: &str) -> Result<Joints, String> {
    let v = finite_list(s)?;
    if v.len() != 6 {
        return Err(format!("{} values, expected Q1,..,Q6 (deg)", v.len()));
    }
    Ok(Joints(std::array::from_fn(|i| v[i])))
}

pub(super) fn prior(s: &str) -> Result<Prior, String> {
    let v = finite_list(s)?;
    if !(v.len() == 2 || v.len() == 3) || v.iter().any(|x| *x <= 0.0) {
        return Err(
            "needs a positive length (mm) and angle (deg) of the robot, and optionally of the set-up (mm)"
                .into(),
        );
    }
    Ok(Prior {
        length_mm: v[0],
        angle_deg: v[1],
        setup_mm: v.get(2).copied(),
    })
}

#[cfg(test)]
mod value_tests {
    use super::*;

    #[test]
    fn numbers_vectors_and_ranges_parse_and_bad_ones_are_named() {
        assert_eq!(xyz("-1, 2,3.5"), Ok(Xyz([-1.0, 2.0, 3.5])));
        assert!(xyz("1,2").unwrap_err().contains("2 values"));
        assert!(xyz("1,2,inf").is_err());
        assert_eq!(range("300..520"), Ok(Range(300.0, 520.0)));
        assert!(range("520..300").is_err() && range("300").is_err() && range("5..5").is_ok());
        assert_eq!(steps("20"), Ok(Steps([20.0; 6])));
        assert!(steps("-5").is_err() && steps("10,10").is_err());
        assert!(joints("1,2,3,4,5").is_err());
        assert_eq!(number("NaN"), Err("not a finite number".into()));
        let p = prior("1,0.05").unwrap();
        assert_eq!((p.length_mm, p.angle_deg, p.setup_mm), (1.0, 0.05, None));
        assert_eq!(prior("1,0.05,10").unwrap().setup_mm, Some(10.0));
        assert!(prior("1").is_err() && prior("0,1").is_err());
    }
}

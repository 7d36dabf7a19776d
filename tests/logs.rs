//! Measuring on any controller: stop-and-measure programs read back from the bar's
//! own log, continuous runs synchronised with a controller's joint log, and bad logs.
//!
//! The runs are the twin's ([`edbbgen::twin::logsim`]): its own clocks, pauses, holds, gaps
//! and handling; the matcher sees only the bar log and the program. Every match is checked
//! against the simulation's truth (which standstill each plateau really is).

use crate::common::*;
use edbbgen::logs;
use edbbgen::model::{MeasurementModel, A, ALPHA, D, THETA};
use edbbgen::twin::logsim::{self, LogOptions};
use edbbgen::twin::{Trajectory, Truth};
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use std::sync::OnceLock;

const DEG: f64 = std::f64::consts::PI / 180.0;

/// A compiled stop-and-measure program and what reads it back.
pub struct Dwell {
    pub robot: edbbgen::robot::Robot,
    pub model: MeasurementModel,
    pub compiled: edbbgen::pipeline::Compiled,
    pub parsed: edbbgen::dialect::Parsed,
}

/// A small stop-and-measure program for the NJ-130 (coarse grid, 2 s dwell), compiled once.
pub fn dwell_program() -> &'static Dwell {
    static D: OnceLock<Dwell> = OnceLock::new();
    D.get_or_init(|| compile_dwell(2.0))
}

/// The same with a 5 s dwell: plateaus long enough to carry what the synchronous recording
/// adds along the moves (the compiler's two predictions within 2x of each other).
pub fn dwell_program_5() -> &'static Dwell {
    static D: OnceLock<Dwell> = OnceLock::new();
    D.get_or_init(|| compile_dwell(5.0))
}

fn compile_dwell(dwell: f64) -> Dwell {
    let robot = load(&nj130_dh());
    let mut opts = edbbgen::pipeline::CompileOptions::new(Vector3::new(0.258, 1.468, 0.708));
    opts.step = [20.0 * DEG; 6];
    opts.max_candidates = 600;
    opts.dwell = Some(dwell);
    let compiled = edbbgen::pipeline::compile(
        &robot,
        &opts,
        edbbgen::emit::dialect("ngc").unwrap(),
        &edbbgen::sample::NoProgress,
    )
    .expect("compile");
    let parsed = edbbgen::verify::gcode::parse(&compiled.text).expect("read back");
    let model = compiled.model.clone();
    Dwell {
        robot,
        model,
        compiled,
        parsed,
    }
}

/// A robot with random geometric errors (±0.2 mm, ±0.02°).
fn random_truth(rng: &mut impl Rng, noise: f64) -> Truth {
    let mut truth = Truth {
        noise,
        ..Truth::default()
    };
    for i in 0..6 {
        truth.geometric[A + i] = rng.random_range(-0.2..0.2) * 1e-3;
        truth.geometric[D + i] = rng.random_range(-0.2..0.2) * 1e-3;
        truth.geometric[ALPHA + i] = rng.random_range(-0.02..0.02) * DEG;
        truth.geometric[THETA + i] = rng.random_range(-0.02..0.02) * DEG;
    }
    truth
}

#[test]
fn the_program_lists_its_measurement_poses_and_every_dwell_follows_an_exact_stop() {
    let d = dwell_program();
    let h = &d.compiled.program.header;
    assert_eq!(h.dwell_s, 2.0);
    assert_eq!(h.measure_mm.len(), h.poses);
    // The header's list, read back from the text, is the poses' own nominal lengths in the
    // order the program dwells at them, computed here from the joint values it commands.
    let traj = Trajectory::from_program(&d.robot, &d.model, &d.parsed).unwrap();
    let tpl = logsim::template(&traj, &d.model);
    assert_eq!(tpl.slots.len(), h.poses);
    for (s, l) in tpl.slots.iter().zip(&h.measure_mm) {
        assert!(
            (s.length * 1e3 - l).abs() < 1e-9,
            "{} vs {l}",
            s.length * 1e3
        );
    }
    // Every dwell comes right after a move without a blend, or after the mount pause.
    let lines = &d.parsed.lines;
    for (k, l) in lines.iter().enumerate() {
        if let edbbgen::dialect::Step::Dwell(s) = l.step {
            assert_eq!(s, 2.0);
            match &lines[k - 1].step {
                edbbgen::dialect::Step::Move { blend, .. } => {
                    assert_eq!(
                        *blend, None,
                        "line {}: a dwell after a blended move",
                        l.line
                    )
                }
                edbbgen::dialect::Step::Pause => {}
                other => panic!("line {}: a dwell after {other:?}", l.line),
            }
        }
    }
    // The estimated time includes the dwells; verify counts them.
    let dwells = 2.0 * h.poses as f64;
    assert!((h.time_s - d.compiled.path.time_sorted - dwells).abs() < 1e-9);
    assert_eq!(d.compiled.verified.dwells, h.poses);
    // Both predictions: the plateaus' and the same run's synchronous recording.
    assert!(h.predicted_std_um > 0.0 && h.predicted_continuous_std_um > 0.0);
    assert!(h.plateau_samples >= 80, "{}", h.plateau_samples);
}

/// The acceptance test: offsets up to ±30 s, drift up to ±200 ppm, a lost plateau and a
/// controller stop in every run, plus random pauses, handling, a vibration, dropouts, a
/// controller that runs moves 0.9..1.3 times the program's time, any bar zero. Every match
/// must be the right standstill; a lost plateau must be reported missing; a refusal must name
/// a pose. 200 runs.
#[test]
#[ignore = "slow tier: `make test` runs it"]
fn randomised_runs_are_matched_right_or_refused_naming_the_pose() {
    let d = dwell_program();
    let traj = Trajectory::from_program(&d.robot, &d.model, &d.parsed).unwrap();
    let tpl = logsim::template(&traj, &d.model);
    let n = tpl.slots.len();
    let (mut refused, mut missing_found, mut holds_seen) = (0, 0, 0);
    // ONLY_RUN=k replays one run (with EDBB_DEBUG=1 the matcher prints its passes).
    let only: Option<u64> = std::env::var("ONLY_RUN").ok().and_then(|v| v.parse().ok());
    for run in 0..200u64 {
        if only.is_some_and(|o| o != run) {
            continue;
        }
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1000 + run);
        let truth = random_truth(&mut rng, 0.5e-6);
        let lost = rng.random_range(1..=n);
        let opts = LogOptions {
            bar_rate: [25.0, 50.0, 100.0][rng.random_range(0..3)],
            offset: rng.random_range(-30.0..30.0),
            drift: rng.random_range(-200e-6..200e-6),
            pause: (2.0, 25.0),
            zero: rng.random_range(-50e-3..50e-3),
            dropout: 0.005,
            missing: vec![lost],
            holds: 1,
            move_scale: rng.random_range(0.9..1.3),
            vibration: if run % 2 == 0 {
                vec![rng.random_range(1..=n)]
            } else {
                Vec::new()
            },
            seed: run,
            ..LogOptions::default()
        };
        let logs = logsim::simulate_logs(&d.robot, &d.model, &traj, &truth, &opts).unwrap();
        holds_seen += logs.truth.holds.len();
        if only.is_some() {
            eprintln!(
                "truth: holds {:?} mounted {:?} lost {lost}\nstandstills {:?}",
                logs.truth.holds, logs.truth.mounted, logs.truth.standstills
            );
        }
        let got = match logs::stop_and_measure(&tpl, &logs.bar) {
            Ok(g) => g,
            Err(e) => {
                let msg = e.to_string();
                assert!(
                    msg.contains(&format!("/{n} ")) && msg.contains("pose "),
                    "run {run}: a refusal that names no pose: {msg}"
                );
                assert!(!msg.contains('\n'), "one line: {msg}");
                eprintln!("run {run} refused: {msg}");
                refused += 1;
                continue;
            }
        };
        for (k, m) in got.alignment.matched.iter().enumerate() {
            let (x, y) = logs.truth.standstills[k];
            match m {
                Some(j) => {
                    let p = &got.plateaus[*j];
                    let mid = 0.5 * (p.from + p.to);
                    assert!(
                        mid > x && mid < y,
                        "run {run}: pose {} matched to the plateau {}..{} s, its standstill is {x}..{y} s",
                        k + 1,
                        p.from,
                        p.to
                    );
                }
                None => {
                    assert!(
                        !logs.truth.intact[k],
                        "run {run}: pose {}'s plateau is whole in the log ({x}..{y} s) but reported missing",
                        k + 1
                    );
                    if k + 1 == lost {
                        missing_found += 1;
                    }
                }
            }
        }
        // The lost plateau is the one reported missing, and listed as such.
        assert!(got.missing.contains(&lost), "run {run}: {:?}", got.missing);
        // The bar's zero is found within the robot's own errors.
        assert!((got.zero - opts.zero).abs() < 1e-3, "run {run}");
    }
    assert!(
        holds_seen >= 190,
        "{holds_seen} controller stops in 200 runs"
    );
    eprintln!(
        "randomised matching: {} of 200 runs matched (every plateau the right standstill, the lost one reported missing), {refused} refused with one line naming the pose",
        200 - refused
    );
    // At most 3 % refused (6 of 200): a refusal is safe, but a matcher that refuses often is
    // no use. Every run here has a controller stop at a random time of a random move, and a
    // few land within a sample or two of a pose's standstill: two plateaus 0.1-0.2 s apart,
    // both about a dwell long and within 2 mm, that no timing or length can tell apart (at
    // seeds 1000+: runs 87, 154, 168, 194, and 116 where the lost pose's gap follows a handling
    // plateau 3.7 length sigmas from the pose). Runs with one replayed: ONLY_RUN=k.
    assert!(
        refused <= 6,
        "{refused} of 200 runs refused: the matcher gives up too easily"
    );
    assert_eq!(missing_found, 200 - refused);
}

/// A dwell program written to `dir` and a clean simulated run of it through the CLI: the
/// program's path, the bar log, the joint log and the synchronous recording.
fn simulated_run(
    d: &Dwell,
    dir: &std::path::Path,
    truth: &str,
    extra: &[&str],
) -> (
    std::path::PathBuf,
    std::path::PathBuf,
    std::path::PathBuf,
    std::path::PathBuf,
) {
    let prog = dir.join("prog.nc");
    std::fs::write(&prog, &d.compiled.text).unwrap();
    let t = dir.join("truth.toml");
    std::fs::write(&t, truth).unwrap();
    let (bar, joints, sync) = (
        dir.join("bar.csv"),
        dir.join("joints.csv"),
        dir.join("sync.csv"),
    );
    let mut args = vec![
        "simulate".to_string(),
        nj130_dh().display().to_string(),
        prog.display().to_string(),
        "--truth".into(),
        t.display().to_string(),
        "-o".into(),
        sync.display().to_string(),
        "--bar-log".into(),
        bar.display().to_string(),
        "--joint-log".into(),
        joints.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let r = edbbgen(&args);
    assert_eq!(r.code, 0, "{}", r.stderr);
    (prog, bar, joints, sync)
}

const TRUTH: &str =
    "noise_um = 1.0\n[geometric]\na2 = 0.15\ntheta3 = 0.01\nd4 = -0.08\nalpha2 = 0.005\n";

/// Bad logs exit 2 with one line naming the file and what is wrong, and nothing is written:
/// unsorted time, no plateau, lengths in metres, times in milliseconds, a log shorter than
/// the program, another unit in the header.
#[test]
fn bad_logs_exit_2_with_one_line_and_write_nothing() {
    let dir = tempdir();
    let (prog, bar, _, _) = simulated_run(
        dwell_program(),
        dir.path(),
        TRUTH,
        &["--clock-offset", "7.5", "--clock-drift", "80"],
    );
    let good = std::fs::read_to_string(&bar).unwrap();
    let rows: Vec<&str> = good.lines().collect();
    let mut cases: Vec<(&str, String, &str)> = Vec::new();
    // Two rows swapped.
    let mut swapped = rows.clone();
    swapped.swap(100, 101);
    cases.push(("unsorted", swapped.join("\n") + "\n", "sorted by time"));
    // A bar that never stands still: a continuous motion over the same time span.
    let moving: String = std::iter::once("t_s,length_mm".to_string())
        .chain(rows[1..].iter().map(|r| {
            let t: f64 = r.split(',').next().unwrap().parse().unwrap();
            format!("{t:.6},{:.4}", 400.0 + 80.0 * (0.7 * t).sin())
        }))
        .collect::<Vec<_>>()
        .join("\n");
    cases.push(("moving", moving + "\n", "no plateau"));
    // Lengths in metres under a millimetre header.
    let metres: String = std::iter::once(rows[0].to_string())
        .chain(rows[1..].iter().map(|r| {
            let (t, l) = r.split_once(',').unwrap();
            format!("{t},{:.7}", l.parse::<f64>().unwrap() / 1000.0)
        }))
        .collect::<Vec<_>>()
        .join("\n");
    cases.push(("metres", metres + "\n", "another unit"));
    // Times in milliseconds under a seconds header.
    let millis: String = std::iter::once(rows[0].to_string())
        .chain(rows[1..].iter().map(|r| {
            let (t, l) = r.split_once(',').unwrap();
            format!("{:.3},{l}", t.parse::<f64>().unwrap() * 1000.0)
        }))
        .collect::<Vec<_>>()
        .join("\n");
    cases.push(("millis", millis + "\n", "another unit"));
    // The first third of the run only.
    let short = rows[..rows.len() / 3].join("\n") + "\n";
    cases.push(("short", short, "shorter than the program"));
    // A header in another unit.
    cases.push((
        "header",
        good.replacen("t_s,length_mm", "t_s,length_um", 1),
        "'length_um' is in another unit",
    ));
    for (name, text, needle) in cases {
        let path = dir.path().join(format!("{name}.csv"));
        std::fs::write(&path, text).unwrap();
        let out = dir.path().join(format!("{name}.cal.dh.toml"));
        let json = dir.path().join(format!("{name}.json"));
        let r = edbbgen([
            "calibrate",
            nj130_dh().to_str().unwrap(),
            "--bar-log",
            path.to_str().unwrap(),
            "--program",
            prog.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--json",
            json.to_str().unwrap(),
        ]);
        assert_eq!(r.code, 2, "{name}: {}{}", r.stdout, r.stderr);
        let line = r.stderr.trim();
        assert_eq!(line.lines().count(), 1, "{name}: {line}");
        assert!(
            line.contains(&format!("{name}.csv")) && line.contains(needle),
            "{name}: {line}"
        );
        assert!(
            !out.exists() && !json.exists(),
            "{name}: a file was written"
        );
        // diagnose refuses the same log the same way.
        let d = edbbgen([
            "diagnose",
            nj130_dh().to_str().unwrap(),
            "--bar-log",
            path.to_str().unwrap(),
            "--program",
            prog.to_str().unwrap(),
            "--json",
            json.to_str().unwrap(),
        ]);
        assert_eq!(d.code, 2, "{name}: {}", d.stderr);
        assert!(d.stderr.contains(needle), "{name}: {}", d.stderr);
        assert!(!json.exists());
    }
}

fn map_positions(cal: &std::path::Path, space: &[[f64; 6]]) -> Vec<Vector3<f64>> {
    let robot = load(cal);
    let model = MeasurementModel::new(
        &robot,
        Vector3::new(0.258, 1.468, 0.708),
        robot.tool.expect("calibrated tool"),
    );
    space
        .iter()
        .map(|q| model.map_position(&model.nominal, q))
        .collect()
}

fn rms_um(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> f64 {
    (a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).norm_squared())
        .sum::<f64>()
        / a.len() as f64)
        .sqrt()
        * 1e6
}

/// `--joint-log` at 10 ms with an unknown offset and drift: the offset within 0.5 ms (and
/// inside its stated uncertainty's reach), and the calibrated robot the synchronous one within
/// 1 µm RMS over the joint space. The continuous program, its logs written by the twin.
#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_joint_log_synchronises_to_a_fraction_of_a_millisecond() {
    let dir = tempdir();
    let robot = load(&nj130_dh());
    let mut opts = edbbgen::pipeline::CompileOptions::new(Vector3::new(0.258, 1.468, 0.708));
    opts.step = [20.0 * DEG; 6];
    opts.max_candidates = 600;
    let compiled = edbbgen::pipeline::compile(
        &robot,
        &opts,
        edbbgen::emit::dialect("ngc").unwrap(),
        &edbbgen::sample::NoProgress,
    )
    .unwrap();
    let prog = dir.path().join("cont.nc");
    std::fs::write(&prog, &compiled.text).unwrap();
    let truth = dir.path().join("truth.toml");
    std::fs::write(&truth, TRUTH).unwrap();
    let (bar, joints, sync) = (
        dir.path().join("bar.csv"),
        dir.path().join("joints.csv"),
        dir.path().join("sync.csv"),
    );
    let offset = -17.3125;
    let r = edbbgen([
        "simulate",
        nj130_dh().to_str().unwrap(),
        prog.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
        "-o",
        sync.to_str().unwrap(),
        "--bar-log",
        bar.to_str().unwrap(),
        "--joint-log",
        joints.to_str().unwrap(),
        "--joint-rate",
        "100",
        "--clock-offset",
        &offset.to_string(),
        "--clock-drift",
        "150",
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let (a, b) = (
        dir.path().join("logs.dh.toml"),
        dir.path().join("sync.dh.toml"),
    );
    let (ja, jb) = (dir.path().join("logs.json"), dir.path().join("sync.json"));
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--bar-log",
        bar.to_str().unwrap(),
        "--joint-log",
        joints.to_str().unwrap(),
        "--program",
        prog.to_str().unwrap(),
        "-o",
        a.to_str().unwrap(),
        "--json",
        ja.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--measured",
        sync.to_str().unwrap(),
        "--fixture",
        "258,1468,708",
        "-o",
        b.to_str().unwrap(),
        "--json",
        jb.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&ja).unwrap()).unwrap();
    let clock = &report["runs"][0]["clock"];
    let got = clock["offset_s"].as_f64().unwrap();
    let std = clock["offset_std_s"].as_f64().unwrap();
    assert!(
        (got - offset).abs() < 0.5e-3,
        "offset {got} s, truth {offset} s"
    );
    assert!(std < 0.5e-3 && std > 0.0, "{std}");
    let drift = clock["drift_ppm"].as_f64().unwrap();
    assert!((drift - 150.0).abs() < 1.0, "drift {drift} ppm");
    assert_eq!(report["runs"][0]["form"], "continuous");
    // The calibrated robots over the joint space.
    let space = edbbgen::calibrate::predict::workspace(&robot, 2000, 7);
    let d = rms_um(&map_positions(&a, &space), &map_positions(&b, &space));
    assert!(d < 1.0, "the two calibrated robots differ by {d} um RMS");
}

/// The stop-and-measure program's plateaus calibrate the robot within twice the accuracy of
/// the same run recorded synchronously: predicted by the compiler (the header states both),
/// predicted by calibrate, and realised against the twin's true robot.
#[test]
fn stop_and_measure_calibrates_within_twice_the_synchronous_accuracy() {
    let dir = tempdir();
    let (prog, bar, _, sync) = simulated_run(
        dwell_program_5(),
        dir.path(),
        TRUTH,
        &[
            "--clock-offset",
            "-21.7",
            "--clock-drift",
            "-120",
            "--holds",
            "1",
            "--missing",
            "5",
        ],
    );
    let h = &dwell_program_5().compiled.program.header;
    let compiled_ratio = h.predicted_std_um / h.predicted_continuous_std_um;
    assert!(
        (0.5..=2.0).contains(&compiled_ratio),
        "header: {} vs {}",
        h.predicted_std_um,
        h.predicted_continuous_std_um
    );
    let (a, b) = (
        dir.path().join("plateaus.dh.toml"),
        dir.path().join("sync.dh.toml"),
    );
    let (ja, jb) = (
        dir.path().join("plateaus.json"),
        dir.path().join("sync.json"),
    );
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--bar-log",
        bar.to_str().unwrap(),
        "--program",
        prog.to_str().unwrap(),
        "-o",
        a.to_str().unwrap(),
        "--json",
        ja.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stdout.contains("missing: pose 5"), "{}", r.stdout);
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--measured",
        sync.to_str().unwrap(),
        "--fixture",
        "258,1468,708",
        "-o",
        b.to_str().unwrap(),
        "--json",
        jb.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let read = |p: &std::path::Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
    };
    let (ra, rb) = (read(&ja), read(&jb));
    // The report keeps every plateau, the missing pose and the clock.
    let run = &ra["runs"][0];
    assert_eq!(run["form"], "stop_and_measure");
    assert_eq!(run["missing"], serde_json::json!([5]));
    let plateaus = run["plateaus"].as_array().unwrap();
    let matched = plateaus.iter().filter(|p| !p["pose"].is_null()).count();
    assert_eq!(matched, h.poses - 1);
    assert!(
        plateaus.len() > matched,
        "the controller's stop is listed, unmatched"
    );
    for p in plateaus {
        for key in [
            "t_from_s",
            "t_to_s",
            "rows",
            "samples",
            "mean_mm",
            "spread_um",
            "std_um",
        ] {
            assert!(!p[key].is_null(), "{key}");
        }
    }
    assert_eq!(run["clock"]["reference"], "program");
    // Predicted by calibrate.
    let pa = ra["predicted_position_std_um"]["workspace_rms"]
        .as_f64()
        .unwrap();
    let pb = rb["predicted_position_std_um"]["workspace_rms"]
        .as_f64()
        .unwrap();
    assert!(
        pa <= 2.0 * pb,
        "predicted {pa} um from the plateaus, {pb} um synchronous"
    );
    // Realised: against the true robot, after a best rigid registration (as any external
    // validation would).
    let robot = load(&nj130_dh());
    let truth = Truth::from_toml(TRUTH).unwrap();
    let model = MeasurementModel::new(
        &robot,
        Vector3::new(0.258, 1.468, 0.708),
        robot.tool.unwrap(),
    );
    let mut tp = model.nominal.to_array();
    for (v, g) in tp.iter_mut().zip(&truth.geometric) {
        *v += g;
    }
    let tp = edbbgen::model::Params::from_array(&tp);
    let space = edbbgen::calibrate::predict::workspace(&robot, 2000, 11);
    let truep: Vec<_> = space.iter().map(|q| model.map_position(&tp, q)).collect();
    let err = |cal: &std::path::Path| {
        edbbgen::calibrate::predict::register(&map_positions(cal, &space), &truep).0 * 1e6
    };
    let (ea, eb) = (err(&a), err(&b));
    assert!(
        ea <= 2.0 * eb.max(0.05),
        "realised {ea} um from the plateaus, {eb} um synchronous"
    );
}

/// The stop-and-measure clock against the twin's: `simulate --bar-log` writes the bar's clock
/// as t_bar = offset + (1 + drift)·t_c, t_c the controller's time from the program's start.
/// With every pause 12 s long, the first (the bar's mounting) taken out of t_ref, the report's
/// offset is offset + (1 + drift)·12 s, each later section follows its removal and mount
/// pauses (24 s), and the drift is the clock's (the twin runs moves in the program's times).
/// Each within 4 of its stated standard uncertainties, which are below 20 ms and 300 ppm: the
/// drift is seen only within a section (the pauses' lengths are unknown), some 30 s of edges
/// to a sample interval (20 ms), so a stop-and-measure run tells it to some 100 ppm.
#[test]
fn the_stop_and_measure_clock_is_the_bar_to_controller_offset_and_drift() {
    let dir = tempdir();
    let (offset, drift_ppm) = (-13.25, 150.0);
    let (prog, bar, _, _) = simulated_run(
        dwell_program(),
        dir.path(),
        TRUTH,
        &[
            "--clock-offset",
            &offset.to_string(),
            "--clock-drift",
            &drift_ppm.to_string(),
            "--pause",
            "12..12",
        ],
    );
    let json = dir.path().join("cal.json");
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--bar-log",
        bar.to_str().unwrap(),
        "--program",
        prog.to_str().unwrap(),
        "-o",
        dir.path().join("cal.dh.toml").to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let clock = &report["runs"][0]["clock"];
    eprintln!("{clock}");
    assert_eq!(clock["reference"], "program");
    let rate = 1.0 + drift_ppm * 1e-6;
    let want = offset + rate * 12.0;
    let (got, std) = (
        clock["offset_s"].as_f64().unwrap(),
        clock["offset_std_s"].as_f64().unwrap(),
    );
    assert!(std > 0.0 && std < 0.02, "offset std {std} s");
    assert!(
        (got - want).abs() <= 4.0 * std,
        "offset {got} +- {std} s, truth {want} s"
    );
    let (d, dstd) = (
        clock["drift_ppm"].as_f64().unwrap(),
        clock["drift_std_ppm"].as_f64().unwrap(),
    );
    assert!(dstd > 0.0 && dstd < 300.0, "drift std {dstd} ppm");
    assert!(
        (d - drift_ppm).abs() <= 4.0 * dstd,
        "drift {d} +- {dstd} ppm, truth {drift_ppm} ppm"
    );
    let pauses = clock["pauses_s"].as_array().unwrap();
    let stds = clock["pauses_std_s"].as_array().unwrap();
    let sections = dwell_program().compiled.program.header.sections;
    assert_eq!(pauses.len(), sections - 1);
    // A pause is two sections' offsets apart; a section of three to five poses has four to
    // eight program-timed edges, each moved by a smooth stop or start by up to ~0.2 s
    // depending on how fast the bar's length changes near the pose (25 ms RMS about the
    // timeline here): a few hundredths of a second is what the edges can say.
    for (p, s) in pauses.iter().zip(stds) {
        let (p, s) = (p.as_f64().unwrap(), s.as_f64().unwrap());
        assert!(
            (p - 24.0).abs() <= 4.0 * s && s < 0.05,
            "pause {p} +- {s} s, truth 24 s"
        );
    }
}

/// A dwell too short for its plateaus: the compiler says so before anyone measures, when the
/// plateau means predict more than twice the same run recorded synchronously (its two header
/// figures), and says nothing when they are within 2x.
#[test]
fn a_dwell_too_short_for_its_plateaus_is_warned_about_at_compile_time() {
    let warned = |d: &Dwell| {
        d.compiled
            .warnings
            .iter()
            .any(|w| w.starts_with("--dwell ") && w.contains("more than twice"))
    };
    let short = compile_dwell(0.3);
    let h = &short.compiled.program.header;
    assert!(
        h.predicted_std_um > 2.0 * h.predicted_continuous_std_um,
        "0.3 s: {} vs {} um",
        h.predicted_std_um,
        h.predicted_continuous_std_um
    );
    assert!(warned(&short), "{:?}", short.compiled.warnings);
    let long = dwell_program_5();
    let h = &long.compiled.program.header;
    assert!(h.predicted_std_um <= 2.0 * h.predicted_continuous_std_um);
    assert!(!warned(long), "{:?}", long.compiled.warnings);
}

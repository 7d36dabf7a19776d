//! Digital twin + diagnosis: hidden-effect tests. Data come from `twin::simulate` on
//! random robots (random geometric errors) with one hidden effect; `diagnose::run` is not told
//! which. Library calls for speed; a few CLI-level checks at the end.

use crate::common::{self, edbbgen, nj130_dh, shared_robot};
use edbbgen::diagnose::{self, Report};
use edbbgen::model::{MeasurementModel, A, ALPHA, D, THETA};
use edbbgen::robot::Robot;
use edbbgen::twin::truth::{Backlash, Compliance, Cyclic, Slip, Thermal};
use edbbgen::twin::{self, SimOptions, Truth};
use edbbgen::verify::gcode;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const DEG: f64 = std::f64::consts::PI / 180.0;

/// A compiled short program for a robot (small grid, few candidates) and its model.
pub struct Cell {
    pub robot: Robot,
    pub model: MeasurementModel,
    pub program: gcode::Parsed,
    pub text: String,
}

pub fn cell(robot: Robot, fixture_mm: [f64; 3]) -> Cell {
    cell_with(robot, fixture_mm, Some(80))
}

pub fn cell_with(robot: Robot, fixture_mm: [f64; 3], poses: Option<usize>) -> Cell {
    let fixture = Vector3::from(fixture_mm) * 1e-3;
    // A rich program for the diagnosis to work on: wide cones (a cell whose socket and cup
    // allow 85°) and 80 poses, so every joint and the whole bar range are exercised.
    let spec = edbbgen::cell::CellSpec {
        fixture_cone: 85.0 * DEG,
        tool_cone: 85.0 * DEG,
        ..Default::default()
    };
    let opts = edbbgen::pipeline::CompileOptions {
        step: [20.0 * DEG; 6],
        max_candidates: 600,
        poses,
        cell: spec,
        ..edbbgen::pipeline::CompileOptions::new(fixture)
    };
    let template = edbbgen::emit::dialect("ngc").expect("ngc dialect");
    let out = edbbgen::pipeline::compile(&robot, &opts, template, &edbbgen::sample::NoProgress)
        .expect("compiles");
    let model = out.model.clone();
    let program = gcode::parse(&out.text).expect("parses");
    Cell {
        robot,
        model,
        program,
        text: out.text,
    }
}

pub fn nj130_cell() -> Cell {
    cell(common::load(&nj130_dh()), [258.0, 1468.0, 708.0])
}

pub fn urdf_cell() -> Cell {
    let mut robot = common::load(&shared_robot("kuka_kr210_l150"));
    robot.tool = Some(Vector3::new(0.06, 0.03, 0.12));
    assert!(!robot.masses.is_empty(), "KR 210 URDF has inertials");
    cell(robot, [1400.0, 400.0, 700.0])
}

/// Random geometric errors of the DH parameters (up to 0.2 mm, 0.02°) and the fixture.
pub fn random_geometry(rng: &mut ChaCha8Rng) -> [f64; 30] {
    let mut g = [0.0; 30];
    for i in 0..6 {
        g[A + i] = rng.random_range(-0.2..0.2) * 1e-3;
        g[D + i] = rng.random_range(-0.2..0.2) * 1e-3;
        g[ALPHA + i] = rng.random_range(-0.02..0.02) * DEG;
        g[THETA + i] = rng.random_range(-0.02..0.02) * DEG;
    }
    for v in g.iter_mut().take(3) {
        *v = rng.random_range(-0.1..0.1) * 1e-3;
    }
    g
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Hidden {
    None,
    Compliance,
    Thermal(bool),
    Cyclic(usize),
    Backlash(usize),
    Servo,
    Slip,
}

pub fn truth_with(h: Hidden, rng: &mut ChaCha8Rng) -> Truth {
    let mut t = Truth {
        geometric: random_geometry(rng),
        ..Truth::default()
    };
    let s = rng.random_range(0.5..2.0);
    match h {
        Hidden::None => {}
        Hidden::Compliance => {
            t.compliance = Some(Compliance {
                stiffness: [1e7, 4e6 * s, 4e6 * s, 1.5e6 * s, 1.5e6 * s, 1.5e6 * s],
                masses: Vec::new(),
            })
        }
        Hidden::Thermal(log) => {
            t.thermal = Some(Thermal {
                alpha: 11.5e-6,
                rise: 1.5 * s,
                time_constant: rng.random_range(30.0..200.0),
                temp_log: log,
            })
        }
        Hidden::Cyclic(j) => {
            let a = 0.0015 * s * DEG;
            let h = rng.random_range(0..3);
            let mut c = Cyclic {
                joint: j,
                cos: [0.0; 3],
                sin: [0.0; 3],
            };
            c.cos[h] = a * rng.random_range(-1.0..1.0);
            c.sin[h] = a * rng.random_range(0.5..1.0);
            t.cyclic = Some(c);
        }
        Hidden::Backlash(j) => {
            t.backlash = Some(Backlash {
                joint: j,
                play: 0.004 * s * DEG,
            })
        }
        Hidden::Servo => t.servo_lag = Some(0.001 * s),
        Hidden::Slip => {
            t.fixture_slip = Some(Slip {
                at_s: rng.random_range(8.0..20.0),
                shift: Vector3::new(30e-6, 0.0, 0.0),
            })
        }
    }
    t
}

fn expected(h: Hidden) -> Option<(&'static str, Option<usize>)> {
    match h {
        Hidden::None | Hidden::Slip => None,
        Hidden::Compliance => Some(("joint_compliance", None)),
        Hidden::Thermal(_) => Some(("thermal_drift", None)),
        Hidden::Cyclic(j) => Some(("cyclic_error", Some(j + 1))),
        Hidden::Backlash(j) => Some(("backlash", Some(j + 1))),
        Hidden::Servo => Some(("servo_lag", None)),
    }
}

fn run_case(c: &Cell, h: Hidden, seed: u64) -> (Report, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let truth = truth_with(h, &mut rng);
    let m = twin::simulate(
        &c.robot,
        &c.model,
        &c.program,
        &truth,
        &SimOptions { rate: 50.0, seed },
    )
    .expect("simulates");
    let d = diagnose::run(&c.model, &m, &Default::default()).expect("diagnoses");
    (d.report, truth.noise * 1e6)
}

fn hidden_cases() -> Vec<Hidden> {
    let mut v = Vec::new();
    for j in 0..6 {
        v.push(Hidden::Cyclic(j));
        v.push(Hidden::Backlash(j));
    }
    v.extend([
        Hidden::Compliance,
        Hidden::Compliance,
        Hidden::Thermal(true),
        Hidden::Thermal(false),
        Hidden::Servo,
        Hidden::Servo,
    ]);
    v
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn hidden_effects_are_named_with_their_joint() {
    let cells = [nj130_cell(), urdf_cell()];
    let mut total = 0;
    let mut right = 0;
    let mut worst_ratio: f64 = 0.0;
    let mut failures = Vec::new();
    for (ci, c) in cells.iter().enumerate() {
        // Two magnitudes/seeds per effect and joint on each robot: 2 × 18 × 2 = 72 cases.
        for rep in 0..2u64 {
            for (k, h) in hidden_cases().into_iter().enumerate() {
                let seed = 1000 * ci as u64 + 100 * rep + k as u64;
                let (r, noise) = run_case(c, h, seed);
                let (name, joint) = expected(h).expect("modelled");
                let named: Vec<(&str, Option<usize>)> = r
                    .named_effects
                    .iter()
                    .map(|e| (e.effect, e.joint))
                    .collect();
                let ok = named == vec![("geometric", None), (name, joint)] && !r.unexplained;
                total += 1;
                if ok {
                    right += 1;
                    worst_ratio = worst_ratio.max(r.rms_final_um / noise);
                    assert!(
                        r.rms_final_um <= 3.0 * noise,
                        "{h:?} seed {seed}: rms_final {} um > 3x noise",
                        r.rms_final_um
                    );
                } else {
                    failures.push(format!(
                        "cell {ci} {h:?} seed {seed}: {named:?} unexplained {} rms {}",
                        r.unexplained, r.rms_final_um
                    ));
                }
            }
        }
    }
    eprintln!(
        "hidden-effect accuracy: {right}/{total}; worst rms_final/noise {worst_ratio:.2}; failures: {failures:#?}"
    );
    assert!(total >= 60);
    assert!(
        right * 100 >= 95 * total,
        "{right}/{total} named correctly: {failures:#?}"
    );
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn geometric_errors_only_name_no_further_effect() {
    let c = nj130_cell();
    for seed in 0..4 {
        let (r, noise) = run_case(&c, Hidden::None, 500 + seed);
        assert_eq!(r.named_effects.len(), 1, "{:?}", r.named_effects);
        assert_eq!(r.named_effects[0].effect, "geometric");
        assert!(!r.unexplained);
        assert!(r.rms_final_um <= 3.0 * noise);
    }
}

#[test]
fn fixture_slip_is_flagged_unexplained() {
    // The compiler's own choice of pose count (the knee rule).
    let c = cell_with(common::load(&nj130_dh()), [258.0, 1468.0, 708.0], None);
    for seed in 0..3 {
        let (r, _) = run_case(&c, Hidden::Slip, 700 + seed);
        assert!(r.unexplained, "{:?}", r.named_effects);
        assert!(r.where_.is_some());
        assert_eq!(r.named_effects.len(), 1, "{:?}", r.named_effects);
    }
}

// ---- CLI ----------------------------------------------------------------------------------

fn header() -> &'static str {
    "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm\n"
}

fn good_rows(n: usize) -> String {
    (0..n)
        .map(|k| format!("{}.0,{k},1,2,3,4,5,400.0\n", k))
        .collect()
}

fn diagnose_csv(text: &str) -> common::Run {
    let dir = common::tempdir();
    let p = dir.path().join("m.csv");
    std::fs::write(&p, text).expect("write");
    let nj = nj130_dh();
    edbbgen([
        "diagnose".as_ref(),
        nj.as_os_str(),
        "--fixture".as_ref(),
        "258,1468,708".as_ref(),
        "--measured".as_ref(),
        p.as_os_str(),
    ])
}

#[test]
fn malformed_csv_exits_2_naming_line_and_column() {
    let cases: Vec<(String, &str)> = vec![
        (
            "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n".to_string() + "0,1,2,3,4,5,6\n",
            "line 1, column 8 (length_mm): missing column 'length_mm'",
        ),
        (
            format!("{}{}99.5,1,2,x,4,5,6,400\n", header(), good_rows(40)),
            "line 42, column 4 (q3_deg): 'x' is not a number",
        ),
        (
            format!("{}{}99.5,1,2,3,4,5,6,NaN\n", header(), good_rows(40)),
            "line 42, column 8 (length_mm): 'NaN' is not finite",
        ),
        (
            format!("{}{}3.0,1,2,3,4,5,6,400\n", header(), good_rows(40)),
            "line 42, column 1 (t_s): time 3 s is not after",
        ),
        (
            format!("{}{}", header(), good_rows(10)),
            "10 data rows, fewer than the 32",
        ),
    ];
    for (text, want) in cases {
        let r = diagnose_csv(&text);
        assert_eq!(r.code, 2, "{want}: {}", r.stderr);
        assert_eq!(r.stderr.trim().lines().count(), 1, "{}", r.stderr);
        assert!(r.stderr.contains(want), "want '{want}' in: {}", r.stderr);
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn compile_simulate_diagnose_through_the_cli() {
    let dir = common::tempdir();
    let p = |n: &str| dir.path().join(n);
    let nj = nj130_dh();
    let c = nj130_cell();
    std::fs::write(p("prog.nc"), &c.text).expect("write");
    std::fs::write(
        p("truth.toml"),
        "[geometric]\na2 = 0.12\ntheta3 = 0.01\n[cyclic_error]\njoint = 4\ncos_deg = [0.002]\n",
    )
    .expect("write");
    let r = edbbgen([
        "simulate".as_ref(),
        nj.as_os_str(),
        p("prog.nc").as_os_str(),
        "--truth".as_ref(),
        p("truth.toml").as_os_str(),
        "-o".as_ref(),
        p("m.csv").as_os_str(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let csv = std::fs::read_to_string(p("m.csv")).expect("csv");
    assert!(csv.starts_with(header()));
    let r = edbbgen([
        "diagnose".as_ref(),
        nj.as_os_str(),
        "--fixture".as_ref(),
        "258,1468,708".as_ref(),
        "--measured".as_ref(),
        p("m.csv").as_os_str(),
        "--json".as_ref(),
        p("r.json").as_os_str(),
        "--plot".as_ref(),
        p("r.svg").as_os_str(),
        "--html".as_ref(),
        p("r.html").as_os_str(),
        "-q".as_ref(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(p("r.json")).expect("json")).expect("parse");
    assert_eq!(v["schema"], "edbbgen.diagnose/1");
    for key in [
        "rms_nominal_um",
        "named_effects",
        "unexplained",
        "where",
        "rms_final_um",
        "steps",
    ] {
        assert!(v.get(key).is_some(), "report lacks {key}");
    }
    assert_eq!(v["named_effects"][1]["effect"], "cyclic_error");
    assert_eq!(v["named_effects"][1]["joint"], 4);
    assert_eq!(v["unexplained"], false);
    let svg = std::fs::read_to_string(p("r.svg")).expect("svg");
    // One residual trace per diagnosis step, drawn in the first palette colour.
    let traces = svg
        .lines()
        .filter(|l| l.starts_with("<polyline") && l.contains("stroke=\"#0072B2\""))
        .count();
    // One panel per step; a recording in sections breaks each trace at the same pauses.
    let panels = svg.matches(" µm\n</text>").count();
    assert!(svg.starts_with("<svg") && panels == 3, "{panels} panels");
    assert!(traces >= 3 && traces % 3 == 0, "{traces} traces");
    crate::report::assert_page_draws(&p("r.html"), "diagnose", &["fig-length", "fig-residual"]);
    crate::snapshots::assert_golden(
        "html@nj130_diagnosis",
        &std::fs::read_to_string(p("r.html")).expect("html"),
    );

    // The circle test is a program the twin can run too.
    let r = edbbgen([
        "circle".as_ref(),
        nj.as_os_str(),
        "--fixture".as_ref(),
        "258,1468,708".as_ref(),
        "-o".as_ref(),
        p("circle.nc").as_os_str(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(p("circle.nc")).expect("circle");
    let parsed = gcode::parse(&text).expect("circle parses");
    let robot = common::load(&nj);
    let fix = Vector3::new(0.258, 1.468, 0.708);
    for (_, q) in parsed.targets() {
        let q = q.map(|d| d * DEG);
        let l = (robot.point(&q, &c.model.nominal.map) - fix).norm();
        assert!((l - 0.35).abs() < 1e-5, "circle point off the sphere: {l}");
    }
}

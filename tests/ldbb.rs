//! The loaded double ball bar: `simulate-ldbb`, `ldbb` and `ldbb-circle` as users
//! call them. The analysis is checked against the truth of edbbgen's own simulator and, so
//! that it does not merely invert that simulator, against data made here by an independent
//! forward model: its own URDF kinematics (urdf-rs), its own IK, perturbed URDF joint origins
//! instead of DH deviations, a different gear nonlinearity, no fixed point for the bar
//! direction, a counterclockwise circle, other sampling, unwrapped angles and shuffled rows.

use crate::common::*;
use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use std::path::{Path, PathBuf};

const UM: f64 = 1e-6;

fn abb() -> PathBuf {
    shared_robot("abb_irb6700_200_260")
}

/// The paper's setup (DESIGN.md's example) with the shared ABB IRB 6700.
fn setup_text(direction: &str, samples: usize, loads: &str, repeats: usize) -> String {
    format!(
        r#"robot = "{robot}"
base_link = "base_link"
end_link = "tool0"
[circle]
centre_mm = [1350.0, -125.0, 1250.0]
diameter_mm = 250.0
direction = "{direction}"
speed_mm_s = 50.0
overshoot_deg = 180.0
samples_per_circle = {samples}
[table_ball]
position_mm = [1350.0, -125.0, 1205.805826]
bar_length_mm = 132.582521
[tool]
map_offset_mm = [0.0, 0.0, 150.0]
orientation_matrix = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]
lt_map_offset_mm = [6.0, 0.0, 150.0]
[loads]
loads_n = [{loads}]
repeats = {repeats}
"#,
        robot = abb().display()
    )
}

const TRUTH: &str = r#"
noise_um = 1.0
run_offset_um = 3.0
stiffness_nm_per_rad = [6.0e6, 4.5e6, 3.5e6, 8.0e5, 6.0e5, 3.0e5]
centring_offset_mm = [0.3, 0.1, 0.0]
[geometric]
theta2 = 0.01
theta3 = -0.015
a2 = 0.2
d4 = -0.15
alpha3 = 0.01
theta5 = 0.02
"#;

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

fn nums(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_f64().expect("number"))
        .collect()
}

/// The least-squares mean and first harmonic of a curve on the uniform grid `angles` (rad):
/// (curve without them, amplitude, phase of a·sin(θ − φ)).
fn first_harmonic(angles: &[f64], v: &[f64]) -> (Vec<f64>, f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let s = 2.0 / n * v.iter().zip(angles).map(|(y, t)| y * t.sin()).sum::<f64>();
    let c = 2.0 / n * v.iter().zip(angles).map(|(y, t)| y * t.cos()).sum::<f64>();
    let rest = v
        .iter()
        .zip(angles)
        .map(|(y, t)| y - m - s * t.sin() - c * t.cos())
        .collect();
    (rest, s.hypot(c), (-c).atan2(s))
}

fn angle_diff_deg(a: f64, b: f64) -> f64 {
    ((a - b + 180.0).rem_euclid(360.0) - 180.0).abs()
}

/// Runs `ldbb` and returns its JSON report.
fn analyse(dir: &Path, loaded: &Path, setup: &Path, extra: &[&str]) -> serde_json::Value {
    let json = dir.join("report.json");
    let mut args: Vec<String> = vec![
        "ldbb".into(),
        loaded.display().to_string(),
        "--setup".into(),
        setup.display().to_string(),
        "--json".into(),
        json.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let r = edbbgen(&args);
    assert_eq!(r.code, 0, "ldbb: {}", r.stderr);
    serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap()
}

/// What the acceptance compares, measured against a truth.
struct Figures {
    compliance_rel_rms: f64,
    amplitude_error_mm: f64,
    phase_error_deg: f64,
    kinematic_rms_error_um: f64,
}

fn compare(report: &serde_json::Value, c_true: &[f64], y0_true: &[f64]) -> Figures {
    let angles: Vec<f64> = nums(&report["compliance"]["angle_deg"])
        .iter()
        .map(|d| d.to_radians())
        .collect();
    assert_eq!(angles.len(), c_true.len());
    let c: Vec<f64> = nums(&report["compliance"]["um_per_n"])
        .iter()
        .map(|x| x * UM)
        .collect();
    let dc: Vec<f64> = c.iter().zip(c_true).map(|(a, b)| a - b).collect();
    let (k_true, a_true, phi_true) = first_harmonic(&angles, y0_true);
    let k: Vec<f64> = nums(&report["kinematic_error"]["um"])
        .iter()
        .map(|x| x * UM)
        .collect();
    let dk: Vec<f64> = k.iter().zip(&k_true).map(|(a, b)| a - b).collect();
    let s = &report["sine_fit"];
    assert_eq!(
        s["b"].as_f64(),
        Some(1.0),
        "the default sine is the linear one"
    );
    Figures {
        compliance_rel_rms: rms(&dc) / rms(c_true),
        amplitude_error_mm: (s["a_mm"].as_f64().unwrap() - a_true * 1e3).abs(),
        phase_error_deg: angle_diff_deg(s["phi_deg"].as_f64().unwrap(), phi_true.to_degrees()),
        kinematic_rms_error_um: rms(&dk) / UM,
    }
}

fn assert_acceptance(case: &str, f: &Figures) {
    eprintln!(
        "{case}: compliance {:.2} % RMS, amplitude {:.4} mm, phase {:.2} deg, kinematic {:.2} um RMS",
        f.compliance_rel_rms * 100.0,
        f.amplitude_error_mm,
        f.phase_error_deg,
        f.kinematic_rms_error_um
    );
    assert!(
        f.compliance_rel_rms < 0.05,
        "{case}: compliance {:.3}",
        f.compliance_rel_rms
    );
    assert!(
        f.amplitude_error_mm < 0.02,
        "{case}: amplitude {}",
        f.amplitude_error_mm
    );
    assert!(
        f.phase_error_deg < 3.0,
        "{case}: phase {}",
        f.phase_error_deg
    );
    assert!(
        f.kinematic_rms_error_um < 10.0,
        "{case}: kinematic {}",
        f.kinematic_rms_error_um
    );
}

/// Determined stiffnesses within 10 % of the truth, the others null with a reason.
fn assert_stiffness(case: &str, report: &serde_json::Value, truth: &[f64; 6]) -> usize {
    let k = report["stiffness_nm_per_rad"].as_array().unwrap();
    let why = report["stiffness"]["why"].as_array().unwrap();
    let mut determined = 0;
    for i in 0..6 {
        match k[i].as_f64() {
            Some(v) => {
                determined += 1;
                eprintln!(
                    "{case}: k{} {v:.4e} against {:.4e} ({:+.2} %)",
                    i + 1,
                    truth[i],
                    (v / truth[i] - 1.0) * 100.0
                );
                assert!(
                    (v / truth[i] - 1.0).abs() < 0.10,
                    "{case}: k{} = {v} vs {}",
                    i + 1,
                    truth[i]
                );
                assert!(why[i].is_null());
            }
            None => {
                let w = why[i]
                    .as_str()
                    .unwrap_or_else(|| panic!("{case}: k{} null without a reason", i + 1));
                assert!(w.len() > 20, "{w}");
            }
        }
    }
    assert!(
        why[5].as_str().unwrap().starts_with("no lever"),
        "{case}: k6 {}",
        why[5]
    );
    determined
}

#[test]
fn acceptance_on_simulated_loaded_circles() {
    use edbbgen::ldbb::{setup::Setup, sim};
    let robot = edbbgen::robot::load(
        &abb(),
        &edbbgen::robot::LoadOptions {
            flange_link: Some("tool0".into()),
            ..Default::default()
        },
    )
    .unwrap();
    let gears = "[nonlinearity]\nhardening_torque_nm = [0.0, 3000.0, 2000.0, 0.0, 0.0, 0.0]\n[gravity]\nmasses_kg = [0.0, 400.0, 250.0, 60.0, 20.0, 10.0]\n";
    let cases: [(&str, String); 4] = [
        ("linear", TRUTH.to_string()),
        (
            "gear nonlinearity on joints 2 and 3",
            format!("{TRUTH}{gears}"),
        ),
        (
            "per-run offsets of 5 um",
            TRUTH.replace("run_offset_um = 3.0", "run_offset_um = 5.0"),
        ),
        (
            "centring offset of 0.3 mm only",
            TRUTH.replace(
                "centring_offset_mm = [0.3, 0.1, 0.0]",
                "centring_offset_mm = [0.0, -0.3, 0.0]",
            ),
        ),
    ];
    let dir = tempdir();
    let setup_path = dir.path().join("setup.toml");
    let text = setup_text(
        "clockwise seen from +z",
        2000,
        "125.0, 250.0, 375.0, 500.0, 625.0",
        3,
    );
    std::fs::write(&setup_path, &text).unwrap();
    let setup = Setup::from_toml(&text, dir.path()).unwrap();
    for (k, (case, truth_text)) in cases.iter().enumerate() {
        let truth_path = dir.path().join("truth.toml");
        std::fs::write(&truth_path, truth_text).unwrap();
        let loaded = dir.path().join("loaded.csv");
        let r = edbbgen([
            "simulate-ldbb",
            "--setup",
            setup_path.to_str().unwrap(),
            "--truth",
            truth_path.to_str().unwrap(),
            "-o",
            loaded.to_str().unwrap(),
            "--seed",
            &(k + 1).to_string(),
        ]);
        assert_eq!(r.code, 0, "{case}: {}", r.stderr);
        let report = analyse(dir.path(), &loaded, &setup_path, &[]);
        let truth = sim::Truth::from_toml(truth_text).unwrap();
        let angles: Vec<f64> = nums(&report["compliance"]["angle_deg"])
            .iter()
            .map(|d| d.to_radians())
            .collect();
        let (c, y0) = sim::truth_on_grid(&robot, &setup, &truth, &angles).unwrap();
        assert_acceptance(case, &compare(&report, &c, &y0));
        let determined = assert_stiffness(case, &report, &truth.stiffness);
        if k == 0 {
            assert!(
                determined >= 1,
                "the linear case determines k1 (the DESIGN example's)"
            );
        }
    }
}

// ---- an independent forward model ---------------------------------------------------------

/// The URDF's chain from `base_link` to `tool0`, walked with urdf-rs joint origins, with
/// perturbed joint origins (the real robot's kinematic error).
struct Chain {
    /// (origin, revolute axis) from the base to tool0.
    steps: Vec<(Isometry3<f64>, Option<Vector3<f64>>)>,
}

impl Chain {
    fn new(path: &Path, perturb: &[(&str, [f64; 3], [f64; 3])]) -> Chain {
        let doc = urdf_rs::read_file(path).unwrap();
        let mut link = "tool0".to_string();
        let mut steps = Vec::new();
        while link != "base_link" {
            let j = doc.joints.iter().find(|j| j.child.link == link).unwrap();
            let (mut x, mut r) = (j.origin.xyz.0, j.origin.rpy.0);
            for (name, dx, dr) in perturb {
                if *name == j.name {
                    for i in 0..3 {
                        x[i] += dx[i];
                        r[i] += dr[i];
                    }
                }
            }
            let origin = Isometry3::from_parts(
                Translation3::new(x[0], x[1], x[2]),
                UnitQuaternion::from_euler_angles(r[0], r[1], r[2]),
            );
            let axis = matches!(j.joint_type, urdf_rs::JointType::Revolute)
                .then(|| Vector3::from(j.axis.xyz.0).normalize());
            steps.push((origin, axis));
            link = j.parent.link.clone();
        }
        steps.reverse();
        assert_eq!(steps.iter().filter(|s| s.1.is_some()).count(), 6);
        Chain { steps }
    }

    /// tool0 in the base frame.
    fn fk(&self, q: &[f64; 6]) -> Isometry3<f64> {
        let mut f = Isometry3::identity();
        let mut k = 0;
        for (origin, axis) in &self.steps {
            f *= origin;
            if let Some(a) = axis {
                f *= UnitQuaternion::from_scaled_axis(a * q[k]);
                k += 1;
            }
        }
        f
    }
}

const MAP: [f64; 3] = [0.0, 0.0, 0.15];

fn ball(chain: &Chain, q: &[f64; 6]) -> Vector3<f64> {
    chain.fk(q).transform_point(&MAP.into()).coords
}

/// Newton on position and orientation with a finite-difference Jacobian.
fn ik(chain: &Chain, p: &Vector3<f64>, r: &Matrix3<f64>, seed: [f64; 6]) -> [f64; 6] {
    // (not `from_matrix`: its iteration starts at the identity and cannot leave it for a
    // half-turn like this tool's)
    let target =
        UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(*r));
    let err = |q: &[f64; 6]| -> Vector6<f64> {
        let f = chain.fk(q);
        let ep = p - f.transform_point(&MAP.into()).coords;
        let eo = (target * f.rotation.inverse()).scaled_axis();
        Vector6::new(ep.x, ep.y, ep.z, eo.x, eo.y, eo.z)
    };
    let mut q = seed;
    for _ in 0..100 {
        let e = err(&q);
        if e.norm() < 1e-12 {
            return q;
        }
        let mut jm = Matrix6::zeros();
        for i in 0..6 {
            let mut d = q;
            d[i] += 1e-7;
            jm.set_column(i, &((e - err(&d)) / 1e-7));
        }
        let dq = jm.lu().solve(&e).expect("IK step");
        // Short steps: Newton's full step can jump to another branch of the arm.
        let scale = (0.1 / dq.amax()).min(1.0);
        for i in 0..6 {
            q[i] += dq[i] * scale;
        }
    }
    q
}

/// The bar reading under `load`: one linear step of joint compliance with an arctangent
/// gear law (stiffness grows with the square of the torque) on the given joints.
fn reading(
    chain: &Chain,
    q: &[f64; 6],
    table: &Vector3<f64>,
    load: f64,
    k: &[f64; 6],
    tau0: &[f64; 6],
) -> f64 {
    let p = ball(chain, q);
    let u = (p - table).normalize();
    let mut ql = *q;
    for i in 0..6 {
        let mut d = *q;
        d[i] += 1e-7;
        let ji = (ball(chain, &d) - p) / 1e-7;
        let tau = ji.dot(&u) * load;
        ql[i] += if tau0[i] > 0.0 {
            tau0[i] / k[i] * (tau / tau0[i]).atan()
        } else {
            tau / k[i]
        };
    }
    (ball(chain, &ql) - table).norm()
}

#[test]
fn analysis_recovers_data_made_by_an_independent_forward_model() {
    let stiffness = [7.0e6, 5.0e6, 3.0e6, 9.0e5, 7.0e5, 4.0e5];
    let perturb: &[(&str, [f64; 3], [f64; 3])] = &[
        ("joint_2", [0.0002, 0.0, -0.0001], [0.0, 0.0002, 0.0]),
        ("joint_3", [0.0, 0.0001, 0.0003], [0.0001, -0.0003, 0.0]),
        ("joint_5", [-0.0002, 0.0, 0.0], [0.0, 0.0, 0.0002]),
    ];
    let nominal = Chain::new(&abb(), &[]);
    let real = Chain::new(&abb(), perturb);
    let r = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
    let (centre, radius) = (Vector3::new(1.35, -0.125, 1.25), 0.125);
    // Counterclockwise seen from +z: P(θ) = centre + R·[cos θ, sin θ, 0].
    let point = |t: f64| centre + radius * Vector3::new(t.cos(), t.sin(), 0.0);
    let table = Vector3::new(1.35, -0.125, 1.205805826) + Vector3::new(0.00025, -0.0001, 0.0);
    let bar = 0.132582521;
    // The joint path: continued around the circle from a seed near the ABB's elbow-up pose.
    let grid: Vec<f64> = (0..360).map(|k| (k as f64).to_radians()).collect();
    // A pose near the ABB's elbow-up branch, then in small steps to the circle's start (so that
    // Newton stays on the branch).
    let seed = [-0.085, -0.14, 0.56, std::f64::consts::PI, -1.15, 3.05];
    let from = ball(&nominal, &seed);
    let mut q = seed;
    for k in 1..=20 {
        let tp = from + (point(0.0) - from) * (k as f64 / 20.0);
        q = ik(&nominal, &tp, &r, q);
    }
    let mut path = Vec::new();
    for &t in &grid {
        q = ik(&nominal, &point(t), &r, q);
        path.push(q);
    }
    // The branch the ABB takes here: elbow up, wrist within its ±130°.
    for q in &path {
        assert!(
            q[4].to_degrees().abs() < 125.0 && q[2].to_degrees().abs() < 70.0,
            "{q:?}"
        );
    }
    let joints_at = |t: f64| -> [f64; 6] {
        let k = ((t.rem_euclid(std::f64::consts::TAU)).to_degrees().round() as usize) % 360;
        ik(&nominal, &point(t), &r, path[k])
    };
    for (cname, tau0) in [
        ("independent, linear gears", [0.0; 6]),
        (
            "independent, arctan gears on joints 2 and 3",
            [0.0, 1500.0, 1200.0, 0.0, 0.0, 0.0],
        ),
    ] {
        let loads = [150.0, 300.0, 450.0, 600.0];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut rows: Vec<String> = Vec::new();
        for &f in &loads {
            for run in 1..=2 {
                let n = 1500;
                let start = rng.random_range(0.0..360.0f64);
                let offset = rng.random_range(-4.0..4.0) * UM;
                for k in 0..n {
                    // Unwrapped angles from the run's own origin, irregular spacing.
                    let deg = start + 360.0 * (k as f64 + rng.random_range(0.0..0.8)) / n as f64;
                    let t = deg.to_radians();
                    let qk = joints_at(t);
                    let l = reading(&real, &qk, &table, f, &stiffness, &tau0);
                    let noise =
                        0.8 * UM * (rng.random_range(-1.0..1.0) + rng.random_range(-1.0..1.0));
                    let qd: Vec<String> = qk
                        .iter()
                        .map(|v| format!("{:.6}", v.to_degrees()))
                        .collect();
                    rows.push(format!(
                        "{run},{f:.1},{deg:.6},{},{:.4}",
                        qd.join(","),
                        (l - bar + offset + noise) / UM
                    ));
                }
            }
        }
        // Rows in no particular order: the analysis groups them itself.
        for i in (1..rows.len()).rev() {
            let j = rng.random_range(0..=i);
            rows.swap(i, j);
        }
        let dir = tempdir();
        let loaded = dir.path().join("loaded.csv");
        std::fs::write(
            &loaded,
            format!(
                "run,load_n,angle_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,deflection_um\n{}\n",
                rows.join("\n")
            ),
        )
        .unwrap();
        let setup = dir.path().join("setup.toml");
        std::fs::write(
            &setup,
            setup_text(
                "counterclockwise seen from +z",
                1500,
                "150.0, 300.0, 450.0, 600.0",
                2,
            ),
        )
        .unwrap();
        let report = analyse(dir.path(), &loaded, &setup, &[]);
        // The truth, noise-free, on the report's grid.
        let mut c_true = Vec::new();
        let mut y0 = Vec::new();
        for (k, &t) in grid.iter().enumerate() {
            let ys: Vec<f64> = loads
                .iter()
                .map(|&f| reading(&real, &path[k], &table, f, &stiffness, &tau0))
                .collect();
            let fm = loads.iter().sum::<f64>() / 4.0;
            let ym = ys.iter().sum::<f64>() / 4.0;
            let sxy: f64 = loads
                .iter()
                .zip(&ys)
                .map(|(f, y)| (f - fm) * (y - ym))
                .sum();
            let sxx: f64 = loads.iter().map(|f| (f - fm).powi(2)).sum();
            c_true.push(sxy / sxx);
            y0.push(reading(&real, &path[k], &table, 0.0, &stiffness, &tau0) - bar);
            let _ = t;
        }
        assert_acceptance(cname, &compare(&report, &c_true, &y0));
        if tau0 == [0.0; 6] {
            let n = assert_stiffness(cname, &report, &stiffness);
            assert!(n >= 1, "{cname}: no stiffness determined");
        } else {
            // With nonlinear gears the stiffness is load dependent: nothing may be claimed
            // beyond 10 % of the small-torque stiffness.
            assert_stiffness(cname, &report, &stiffness);
        }
    }
}

// ---- the program, the report, bad input ---------------------------------------------------

/// A short test for programs: two loads, one circle each, 30° of lead-in and lead-out.
fn short_setup(dir: &Path) -> PathBuf {
    let p = dir.join("short.toml");
    let text = setup_text("clockwise seen from +z", 720, "125.0, 250.0", 1)
        .replace("overshoot_deg = 180.0", "overshoot_deg = 30.0");
    std::fs::write(&p, text).unwrap();
    p
}

fn ldbb_circle(setup: &Path, out: &Path, extra: &[&str]) -> Run {
    let mut args: Vec<String> = vec![
        "ldbb-circle".into(),
        abb().display().to_string(),
        "--setup".into(),
        setup.display().to_string(),
        "-o".into(),
        out.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    edbbgen(&args)
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn ldbb_circle_program_is_verified_read_back_golden_and_interpreted() {
    let dir = tempdir();
    let setup = short_setup(dir.path());
    let out = dir.path().join("ldbb.nc");
    let r = ldbb_circle(&setup, &out, &["--step", "5"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(&out).unwrap();
    // The program's name is the file's stem: the same name in another directory.
    let dir2 = tempdir();
    let again = dir2.path().join("ldbb.nc");
    assert_eq!(ldbb_circle(&setup, &again, &["--step", "5"]).code, 0);
    assert!(
        text == std::fs::read_to_string(&again).unwrap(),
        "not byte-identical"
    );
    assert!(!text.contains("/work") && !text.contains(env!("CARGO_MANIFEST_DIR")));
    crate::snapshots::assert_golden("gcode@ldbb_circle", &text);

    // Read back independently: every target on the circle with the setup's tool orientation.
    let robot = edbbgen::robot::load(
        &abb(),
        &edbbgen::robot::LoadOptions {
            flange_link: Some("tool0".into()),
            ..Default::default()
        },
    )
    .unwrap();
    let poses = program_poses(&text);
    let table = Vector3::new(1.35, -0.125, 1.205805826);
    let want = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
    let mut travel = 0.0;
    let mut last: Option<f64> = None;
    // The header's bound on how far the printed path takes the bar length from the circle's
    // (chords, blends and the 0.001° grid of the printed joints) holds at every target.
    let stated: f64 = text
        .split("they change the bar length by at most ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|v| v.parse().ok())
        .expect("the header states the path deviation");
    assert!(stated < 150.0, "{stated} um");
    for q in &poses {
        let q = q.map(|d| d.to_radians());
        let f = robot.fk(&q);
        let p = f.apply(&Vector3::new(0.0, 0.0, 0.15));
        let dl = ((p - table).norm() - 0.132582521).abs();
        assert!(dl <= stated * 1e-6 + 1e-9, "bar length at {q:?}: {dl} m");
        // 0.0005° of rounding per joint moves the ball by up to ~40 µm on this arm.
        assert!(dl < 5e-5, "bar length at {q:?}: {dl} m");
        assert!(
            (p.z - 1.25).abs() < 5e-5
                && ((p.xy() - Vector3::new(1.35, -0.125, 0.0).xy()).norm() - 0.125).abs() < 5e-5
        );
        assert!((f.r - want).abs().max() < 5e-5, "tool orientation");
        // Clockwise seen from +z: the angle of P(θ) = c + R[cos θ, −sin θ] grows clockwise.
        let theta = (-(p.y + 0.125)).atan2(p.x - 1.35);
        if let Some(l) = last {
            let d = (theta - l).rem_euclid(std::f64::consts::TAU);
            // Forward (clockwise) in steps of 5° or standing (the load change).
            assert!(d < 0.1, "steps of 5° clockwise, not {d} rad");
            travel += d;
        }
        last = Some(theta);
    }
    // Per load: 30° lead-in, one circle, 30° lead-out (the ends off by the grid's ~40 µm at
    // most: 0.02° of the circle).
    assert!(
        (travel.to_degrees() - 2.0 * 420.0).abs() < 0.05,
        "{}",
        travel.to_degrees()
    );
    assert_eq!(
        text.matches("\nM0 (").count(),
        4,
        "mount + load, release, load, remove"
    );
    assert!(text.contains("set the load to 125 N") && text.contains("set the load to 250 N"));

    // `verify` on its own, with the cell the program was checked in.
    let v = edbbgen([
        "verify",
        abb().to_str().unwrap(),
        out.to_str().unwrap(),
        "--flange",
        "tool0",
        "--cell",
        root().join("examples/ldbb/cell.toml").to_str().unwrap(),
    ]);
    assert_eq!(v.code, 0, "{}{}", v.stdout, v.stderr);
    // LinuxCNC's interpreter reads it as written.
    crate::linuxcnc::check("ldbb-circle", &text);

    // Every bundled dialect writes the loaded circle with its own pauses and messages, and
    // the compiler's own read-back (verify) passes on it: the same targets to the grid.
    for (dialect, file) in [
        ("sinumerik", "LDBB.MPF"),
        ("krl", "ldbb.src"),
        ("rapid", "ldbb.mod"),
        ("urscript", "ldbb.script"),
        ("fanuc", "LDBB.LS"),
    ] {
        let p = dir2.path().join(file);
        let r = ldbb_circle(&setup, &p, &["--step", "5", "--dialect", dialect]);
        assert_eq!(r.code, 0, "{dialect}: {}", r.stderr);
        let t = std::fs::read_to_string(&p).unwrap();
        assert!(
            t.contains("125 N") && t.contains("250 N"),
            "{dialect}: the load changes"
        );
        assert!(
            t.contains("LDBB") && !t.contains("EDBB"),
            "{dialect}: the instrument"
        );
        let d = edbbgen::dialect::by_name(dialect).unwrap();
        let map = edbbgen::controller::ControllerMap::resolve(None, &d.defaults(), &d.name, &robot)
            .unwrap();
        let parsed = d.read(&t, &map).unwrap();
        let back: Vec<[f64; 6]> = parsed.targets().map(|(_, q)| *q).collect();
        assert_eq!(back.len(), poses.len(), "{dialect}: every target");
        for (a, b) in back.iter().zip(&poses) {
            assert!(
                (0..6).all(|i| (a[i] - b[i]).abs() < 1e-4),
                "{dialect}: {a:?} against ngc's {b:?}"
            );
        }
    }

    // The default step: the path keeps the bar within ~20 µm of its length: the chords' share
    // is ~1 µm at 0.5°, the rest is the 0.001° grid every dialect prints (the same joint values,
    // hence the same deviation, at every load: load differences do not see it).
    let fine = dir.path().join("fine.nc");
    let r = ldbb_circle(&setup, &fine, &[]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(&fine).unwrap();
    let dev: f64 = text
        .lines()
        .find_map(|l| l.split("by at most ").nth(1))
        .and_then(|s| s.split(' ').next())
        .and_then(|s| s.parse().ok())
        .expect("the header states the path's deviation");
    assert!(dev < 20.0, "{dev} um");
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn report_json_is_golden_and_the_html_draws_in_a_browser() {
    let dir = tempdir();
    let setup = dir.path().join("setup.toml");
    std::fs::write(
        &setup,
        setup_text(
            "clockwise seen from +z",
            720,
            "125.0, 250.0, 375.0, 500.0, 625.0",
            2,
        ),
    )
    .unwrap();
    let truth = dir.path().join("truth.toml");
    std::fs::write(&truth, TRUTH).unwrap();
    let (loaded, lt) = (dir.path().join("loaded.csv"), dir.path().join("lt.csv"));
    let r = edbbgen([
        "simulate-ldbb",
        "--setup",
        setup.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
        "-o",
        loaded.to_str().unwrap(),
        "--reference",
        lt.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let (page, svg) = (dir.path().join("ldbb.html"), dir.path().join("ldbb.svg"));
    let report = analyse(
        dir.path(),
        &loaded,
        &setup,
        &[
            "--reference",
            lt.to_str().unwrap(),
            "--grid-step",
            "10",
            "--html",
            page.to_str().unwrap(),
            "--plot",
            svg.to_str().unwrap(),
        ],
    );
    // DESIGN.md's keys first, in its order (top-level keys of the pretty JSON text).
    let json = std::fs::read_to_string(dir.path().join("report.json")).unwrap();
    let keys: Vec<&str> = json
        .lines()
        .filter(|l| l.starts_with("  \"") && !l.starts_with("   "))
        .filter_map(|l| l.trim().strip_prefix('"')?.split('"').next())
        .collect();
    assert_eq!(
        keys[..7],
        [
            "schema",
            "compliance",
            "sine_fit",
            "kinematic_error",
            "stiffness_nm_per_rad",
            "linearity_spread_um",
            "reference"
        ]
    );
    assert_eq!(report["schema"], "edbbgen.ldbb/1");
    assert!(
        report["reference"]["mean_abs_difference_um"]
            .as_f64()
            .unwrap()
            < 40.0
    );
    crate::snapshots::assert_golden("json@ldbb_simulated", &json);
    assert!(std::fs::read_to_string(&svg).unwrap().starts_with("<svg"));
    crate::report::assert_page_draws(
        &page,
        "ldbb",
        &[
            "fig-raw",
            "fig-deflection",
            "fig-compliance",
            "fig-compensated",
            "fig-average",
            "fig-kinematic",
        ],
    );
}

/// Exit 2, one line naming `needle`, and no report written.
fn rejected(args: &[String], needle: &str) {
    let r = edbbgen(args);
    assert_eq!(r.code, 2, "{args:?}: {}", r.stderr);
    let lines: Vec<&str> = r.stderr.lines().collect();
    assert_eq!(lines.len(), 1, "one line: {}", r.stderr);
    assert!(
        lines[0].starts_with("edbbgen: error: ") && lines[0].contains(needle),
        "'{}' should name '{needle}'",
        lines[0]
    );
}

#[test]
fn bad_input_is_one_line_naming_file_and_place() {
    let dir = tempdir();
    let d = dir.path();
    let setup = d.join("setup.toml");
    let text = setup_text("clockwise seen from +z", 360, "125.0, 250.0, 375.0", 2);
    std::fs::write(&setup, &text).unwrap();
    let truth = d.join("truth.toml");
    std::fs::write(&truth, TRUTH).unwrap();
    let loaded = d.join("loaded.csv");
    let s = |p: &Path| p.display().to_string();
    let r = edbbgen([
        "simulate-ldbb",
        "--setup",
        &s(&setup),
        "--truth",
        &s(&truth),
        "-o",
        &s(&loaded),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let csv = std::fs::read_to_string(&loaded).unwrap();
    let json = d.join("r.json");
    let run = |data: &Path, setup: &Path| -> Vec<String> {
        vec![
            "ldbb".into(),
            s(data),
            "--setup".into(),
            s(setup),
            "--json".into(),
            s(&json),
        ]
    };
    let write = |name: &str, text: &str| -> PathBuf {
        let p = d.join(name);
        std::fs::write(&p, text).unwrap();
        p
    };
    // Wrong header.
    let p = write("header.csv", &csv.replacen("load_n", "load", 1));
    rejected(&run(&p, &setup), "header.csv: line 1, column 2 (load_n)");
    // A load with one repeat missing.
    let p = write(
        "missing.csv",
        &csv.lines()
            .filter(|l| !l.starts_with("2,375.000,"))
            .collect::<Vec<_>>()
            .join("\n"),
    );
    rejected(
        &run(&p, &setup),
        "missing.csv: load 375 N: run(s) 2 missing",
    );
    // Angles not covering the circle.
    let p = write(
        "hole.csv",
        &csv.lines()
            .filter(|l| {
                let c: Vec<&str> = l.split(',').collect();
                !(c[0] == "1"
                    && c[1] == "250.000"
                    && c[2].parse::<f64>().is_ok_and(|a| (40.0..55.0).contains(&a)))
            })
            .collect::<Vec<_>>()
            .join("\n"),
    );
    rejected(
        &run(&p, &setup),
        "hole.csv: load 250 N, run 1: the angles do not cover the circle",
    );
    // A load the setup does not list, a bad number.
    let p = write("load.csv", &csv.replacen("\n1,125.000,", "\n1,130.000,", 1));
    rejected(
        &run(&p, &setup),
        "load.csv: line 2, column 2 (load_n): load 130 N is not one of the setup's loads",
    );
    let p = write("nan.csv", &csv.replacen("\n1,125.000,", "\n1,x,", 1));
    rejected(
        &run(&p, &setup),
        "nan.csv: line 2, column 2 (load_n): 'x' is not a number",
    );
    // A setup key typo, a setup without its tool for the robot.
    let bad = write("typo.toml", &text.replace("bar_length_mm", "bar_lenght_mm"));
    rejected(&run(&loaded, &bad), "typo.toml: line");
    let bad = write(
        "notool.toml",
        &text.replace("map_offset_mm = [0.0, 0.0, 150.0]\n", ""),
    );
    rejected(&run(&loaded, &bad), "notool.toml: [tool] map_offset_mm");
    // Options and the reference.
    let mut args = run(&loaded, &setup);
    args.extend(["--grid-step".into(), "7".into()]);
    rejected(&args, "--grid-step");
    let lt = write("lt.csv", "angle,error_um\n0,1\n");
    let mut args = run(&loaded, &setup);
    args.extend(["--reference".into(), s(&lt)]);
    rejected(&args, "lt.csv: line 1, column 1 (angle_deg)");
    assert!(!json.exists(), "no report on bad input");
    // The simulator's truth and the program's reach.
    let t = write(
        "t.toml",
        &TRUTH.replace("stiffness_nm_per_rad", "stifness_nm_per_rad"),
    );
    rejected(
        &[
            "simulate-ldbb",
            "--setup",
            &s(&setup),
            "--truth",
            &s(&t),
            "-o",
            &s(&d.join("x.csv")),
        ]
        .map(String::from),
        "t.toml: line",
    );
    let far = write(
        "far.toml",
        &text.replace("[1350.0, -125.0, 1250.0]", "[4350.0, -125.0, 1250.0]"),
    );
    let out = d.join("far.nc");
    let r = ldbb_circle(&far, &out, &[]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(
        r.stderr.contains("far.toml: the circle is out of reach"),
        "{}",
        r.stderr
    );
    assert!(!out.exists());
    let leftovers: Vec<_> = std::fs::read_dir(d)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with(".edbbgen-"))
        .collect();
    assert!(leftovers.is_empty(), "no temp files left behind");
}

//! Applying a calibration: the numerical inverse kinematics against closed forms
//! written here (a spherical-wrist arm — the NJ-130's table — and a UR-type offset wrist), the
//! compensation against the calibrated arm's closed form, the targets file and compensated
//! programs in every dialect (golden, read back, verified in their cells), and, on twin robots
//! with known truth, the accuracy the compensated targets and the mastering offsets deliver
//! against what was predicted.

use crate::calibrate::{dh_errors, joint_space, workdir};
use crate::common::*;
use crate::snapshots::assert_golden;
use edbbgen::compensate::ik::{self, Chain, Goal};
use edbbgen::compensate::{Compensator, Status, Target};
use edbbgen::model::{MeasurementModel, Params, N_PARAMS};
use edbbgen::robot::{Frame, Robot};
use edbbgen::twin::{self, SimOptions, Truth};
use nalgebra::{Matrix3, Matrix4, Vector3, Vector4};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;
use std::path::{Path, PathBuf};

const DEG: f64 = PI / 180.0;

// ---- an independent kinematics for the tests ------------------------------------------------

/// A DH row (α, a, d, θ), SI.
type Row = [f64; 4];

fn table(robot: &Robot) -> [Row; 6] {
    std::array::from_fn(|i| {
        let d = robot.dh[i];
        [d.alpha, d.a, d.d, d.theta]
    })
}

fn dh_matrix(r: &Row, q: f64) -> Matrix4<f64> {
    let (st, ct) = (r[3] + q).sin_cos();
    let (sa, ca) = r[0].sin_cos();
    Matrix4::new(
        ct,
        -st * ca,
        st * sa,
        r[1] * ct,
        st,
        ct * ca,
        -ct * sa,
        r[1] * st,
        0.0,
        sa,
        ca,
        r[2],
        0.0,
        0.0,
        0.0,
        1.0,
    )
}

/// The flange of a DH-file robot (no base or flange transform) at q, as a 4 × 4 matrix.
fn fk(t: &[Row; 6], q: &[f64; 6]) -> Matrix4<f64> {
    (0..6).fold(Matrix4::identity(), |m, i| m * dh_matrix(&t[i], q[i]))
}

fn rot(m: &Matrix4<f64>) -> Matrix3<f64> {
    m.fixed_view::<3, 3>(0, 0).into_owned()
}

fn pos(m: &Matrix4<f64>) -> Vector3<f64> {
    Vector3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)])
}

fn wrap(a: f64) -> f64 {
    let mut x = a % (2.0 * PI);
    if x > PI {
        x -= 2.0 * PI;
    }
    if x <= -PI {
        x += 2.0 * PI;
    }
    x
}

/// Angle difference modulo 2π.
fn adiff(a: f64, b: f64) -> f64 {
    wrap(a - b).abs()
}

/// The closed-form solutions that reproduce the pose (each checked by the forward kinematics).
fn checked(t: &[Row; 6], target: &Matrix4<f64>, cands: Vec<[f64; 6]>) -> Vec<[f64; 6]> {
    cands
        .into_iter()
        .map(|q| q.map(wrap))
        .filter(|q| {
            let f = fk(t, q);
            (pos(&f) - pos(target)).norm() < 1e-9 && (rot(&f) - rot(target)).norm() < 1e-9
        })
        .collect()
}

/// Closed-form IK of arms with joints 2 and 3 parallel and a spherical wrist: α1, α3, α4 = ±90°,
/// α2 = 0° or 180°, α5 = −α4, α6 = 0; d2 = d3 = d5 = 0; a4 = a5 = a6 = 0 (the NJ-130's table,
/// KUKA- and ABB-like arms). Up to 8 solutions for the flange pose `target`.
fn spherical_ik(t: &[Row; 6], target: &Matrix4<f64>) -> Vec<[f64; 6]> {
    let s1 = t[0][0].sin().round();
    let e2 = t[1][0].cos().round();
    let s3 = t[2][0].sin().round();
    let s4 = t[3][0].sin().round();
    let (a1, a2, a3) = (t[0][1], t[1][1], t[2][1]);
    let (d1, d4, d6) = (t[0][2], t[3][2], t[5][2]);
    let r = rot(target);
    let p = pos(target);
    let w = p - r.column(2) * d6;
    let mut out = Vec::new();
    for phi1 in [w.y.atan2(w.x), w.y.atan2(w.x) + PI] {
        let x1 = Vector3::new(phi1.cos(), phi1.sin(), 0.0);
        let y1 = Vector3::new(0.0, 0.0, s1);
        let o1 = Vector3::new(a1 * phi1.cos(), a1 * phi1.sin(), d1);
        let (u, v) = ((w - o1).dot(&x1), (w - o1).dot(&y1));
        // The forearm from joint 3 to the wrist centre: a3 along x3, ±d4 along z3.
        let d4p = -s3 * e2 * d4;
        let l3 = a3.hypot(d4p);
        let beta = d4p.atan2(a3);
        let c = (u * u + v * v - a2 * a2 - l3 * l3) / (2.0 * a2 * l3);
        if c.abs() > 1.0 + 1e-12 {
            continue;
        }
        for gamma in [c.clamp(-1.0, 1.0).acos(), -c.clamp(-1.0, 1.0).acos()] {
            let phi2 = v.atan2(u) - (l3 * gamma.sin()).atan2(a2 + l3 * gamma.cos());
            let phi3 = e2 * (gamma - beta);
            let q3: [f64; 3] = [phi1 - t[0][3], phi2 - t[1][3], phi3 - t[2][3]];
            let r3 = rot(&(0..3).fold(Matrix4::identity(), |m, i| m * dh_matrix(&t[i], q3[i])));
            let m = r3.transpose() * r;
            // Rz(φ4) · Ry(−s4 φ5) · Rz(φ6).
            for sign in [1.0, -1.0] {
                let sb = sign * (m[(0, 2)].powi(2) + m[(1, 2)].powi(2)).sqrt();
                if sb.abs() < 1e-9 {
                    continue;
                }
                let b = sb.atan2(m[(2, 2)]);
                let phi4 = (m[(1, 2)] / sb).atan2(m[(0, 2)] / sb);
                let phi6 = (m[(2, 1)] / sb).atan2(-m[(2, 0)] / sb);
                let phi5 = -s4 * b;
                out.push([
                    q3[0],
                    q3[1],
                    q3[2],
                    phi4 - t[3][3],
                    phi5 - t[4][3],
                    phi6 - t[5][3],
                ]);
            }
        }
    }
    checked(t, target, out)
}

fn inv(m: &Matrix4<f64>) -> Matrix4<f64> {
    m.try_inverse().unwrap()
}

/// Closed-form IK of the Universal Robots arms (Hawkins, "Analytic inverse kinematics for the
/// Universal Robots UR-5/UR-10 arms", 2013): α = (90°, 0, 0, 90°, −90°, 0), a = (0, a2, a3, 0,
/// 0, 0), d = (d1, 0, 0, d4, d5, d6). Up to 8 solutions.
fn ur_ik(t: &[Row; 6], target: &Matrix4<f64>) -> Vec<[f64; 6]> {
    let (a2, a3) = (t[1][1], t[2][1]);
    let (d4, d6) = (t[3][2], t[5][2]);
    let p05 = target * Vector4::new(0.0, 0.0, -d6, 1.0);
    let p06 = pos(target);
    let mut out = Vec::new();
    let rxy = p05.x.hypot(p05.y);
    if rxy < d4.abs() {
        return out;
    }
    let phi = p05.y.atan2(p05.x);
    let psi = (d4 / rxy).acos();
    for th1 in [phi + psi + PI / 2.0, phi - psi + PI / 2.0] {
        let (s1, c1) = th1.sin_cos();
        let c5 = (p06.x * s1 - p06.y * c1 - d4) / d6;
        if c5.abs() > 1.0 + 1e-12 {
            continue;
        }
        for th5 in [c5.clamp(-1.0, 1.0).acos(), -c5.clamp(-1.0, 1.0).acos()] {
            let s5 = th5.sin();
            if s5.abs() < 1e-9 {
                continue;
            }
            // x and y axes of the base frame seen from frame 6: the rows of R06.
            let r = rot(target);
            let th6 = ((-r[(0, 1)] * s1 + r[(1, 1)] * c1) / s5)
                .atan2((r[(0, 0)] * s1 - r[(1, 0)] * c1) / s5);
            let t01 = dh_matrix(&t[0], th1 - t[0][3]);
            let t45 = dh_matrix(&t[4], th5 - t[4][3]);
            let t56 = dh_matrix(&t[5], th6 - t[5][3]);
            let t14 = inv(&t01) * target * inv(&t56) * inv(&t45);
            let p13 = t14 * Vector4::new(0.0, -d4, 0.0, 1.0);
            let p13 = Vector3::new(p13.x, p13.y, p13.z);
            let c3 = (p13.norm_squared() - a2 * a2 - a3 * a3) / (2.0 * a2 * a3);
            if c3.abs() > 1.0 + 1e-12 {
                continue;
            }
            for th3 in [c3.clamp(-1.0, 1.0).acos(), -c3.clamp(-1.0, 1.0).acos()] {
                let th2 = -p13.y.atan2(-p13.x) + (a3 * th3.sin() / p13.norm()).asin();
                let t12 = dh_matrix(&t[1], th2 - t[1][3]);
                let t23 = dh_matrix(&t[2], th3 - t[2][3]);
                let t34 = inv(&t23) * inv(&t12) * t14;
                let th4 = t34[(1, 0)].atan2(t34[(0, 0)]);
                out.push([
                    th1 - t[0][3],
                    th2 - t[1][3],
                    th3 - t[2][3],
                    th4 - t[3][3],
                    th5 - t[4][3],
                    th6 - t[5][3],
                ]);
            }
        }
    }
    checked(t, target, out)
}

/// A DH file of six joints (α, a, d, θ in deg and mm), limits ±`lim` deg, written to `dir`.
fn dh_file(
    dir: &Path,
    name: &str,
    rows: &[[f64; 4]; 6],
    lim: [[f64; 2]; 6],
    tool: [f64; 3],
) -> PathBuf {
    let mut s = format!(
        "name = \"{name}\"\nconvention = \"dh\"\nlength_unit = \"mm\"\nangle_unit = \"deg\"\ntool = [{}, {}, {}]\n",
        tool[0], tool[1], tool[2]
    );
    for (i, r) in rows.iter().enumerate() {
        s += &format!(
            "\n[[joints]]\nname = \"j{}\"\nalpha = {:?}\na = {:?}\nd = {:?}\ntheta = {:?}\nlimits = [{:?}, {:?}]\nmax_speed = 180.0\n",
            i + 1,
            r[0],
            r[1],
            r[2],
            r[3],
            lim[i][0],
            lim[i][1]
        );
    }
    let p = dir.join(format!("{name}.dh.toml"));
    std::fs::write(&p, s).unwrap();
    p
}

/// The UR5e's published DH table (mm, deg).
const UR5E: [[f64; 4]; 6] = [
    [90.0, 0.0, 162.5, 0.0],
    [0.0, -425.0, 0.0, 0.0],
    [0.0, -392.2, 0.0, 0.0],
    [90.0, 0.0, 133.3, 0.0],
    [-90.0, 0.0, 99.7, 0.0],
    [0.0, 0.0, 99.6, 0.0],
];

const UR_LIMITS: [[f64; 2]; 6] = [[-360.0, 360.0]; 6];

/// The NJ-130's table as mm/deg rows.
fn nj130_rows() -> [[f64; 4]; 6] {
    let r = load(&nj130_dh());
    std::array::from_fn(|i| {
        let d = r.dh[i];
        [d.alpha / DEG, d.a * 1e3, d.d * 1e3, d.theta / DEG]
    })
}

fn nj130_limits() -> [[f64; 2]; 6] {
    let r = load(&nj130_dh());
    std::array::from_fn(|i| [r.joints[i].lower / DEG, r.joints[i].upper / DEG])
}

fn random_q(robot: &Robot, rng: &mut ChaCha8Rng) -> [f64; 6] {
    let (lo, hi) = robot.limits();
    std::array::from_fn(|i| rng.random_range(lo[i]..hi[i]))
}

#[test]
fn the_closed_forms_hold_and_the_numerical_ik_finds_each_of_their_branches() {
    let dir = tempdir();
    let arms = [
        (
            "spherical (NJ-130)",
            dh_file(dir.path(), "nj", &nj130_rows(), nj130_limits(), [0.0; 3]),
            spherical_ik as fn(&[Row; 6], &Matrix4<f64>) -> Vec<[f64; 6]>,
        ),
        (
            "UR5e",
            dh_file(dir.path(), "ur", &UR5E, UR_LIMITS, [0.0; 3]),
            ur_ik,
        ),
    ];
    for (what, path, closed) in arms {
        let robot = load(&path);
        let t = table(&robot);
        let chain = Chain::new(&robot, &Frame::IDENTITY);
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (mut branches, mut poses) = (0, 0);
        for _ in 0..150 {
            let q = random_q(&robot, &mut rng);
            if ik::conditioning(&chain, &q, false) < 0.02 {
                continue;
            }
            poses += 1;
            let target = fk(&t, &q);
            let sols = closed(&t, &target);
            // The closed form is right: the pose's own joints are among its solutions.
            assert!(
                sols.iter()
                    .any(|s| (0..6).all(|i| adiff(s[i], q[i]) < 1e-7)),
                "{what}: {q:?} not among {sols:?}"
            );
            // The library's forward kinematics agrees with the independent one.
            let f = chain.pose(&q);
            assert!((f.t - pos(&target)).norm() < 1e-12 && (f.r - rot(&target)).norm() < 1e-12);
            for s in &sols {
                if ik::conditioning(&chain, s, false) < 0.02 {
                    continue;
                }
                // Seeded 3° off a branch, the numerical IK returns that branch.
                let seed: [f64; 6] =
                    std::array::from_fn(|i| s[i] + rng.random_range(-3.0..3.0) * DEG);
                let goal = Goal::Pose(Frame::new(rot(&target), pos(&target)));
                let n = ik::solve(&chain, &goal, &seed, &ik::Options::default());
                assert!(n.converged, "{what}: {s:?} from {seed:?}: {n:?}");
                for i in 0..6 {
                    assert!(
                        adiff(n.q[i], s[i]) < 1e-7,
                        "{what}: branch {s:?}, got {:?}",
                        n.q
                    );
                }
                branches += 1;
            }
        }
        eprintln!("{what}: {branches} branches of {poses} poses");
        assert!(
            poses > 100 && branches > 4 * poses,
            "{what}: {branches} / {poses}"
        );
    }
}

/// Deviations that keep an arm in its closed form's family (θ, and lengths along the links).
fn structural_deviation(rows: &[[f64; 4]; 6], rng: &mut ChaCha8Rng, ur: bool) -> [[f64; 4]; 6] {
    let mut out = *rows;
    for (i, r) in out.iter_mut().enumerate() {
        r[3] += rng.random_range(-0.03..0.03);
        let (da, dd) = (rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3));
        if ur {
            if i == 1 || i == 2 {
                r[1] += da;
            }
            if i == 0 || i >= 3 {
                r[2] += dd;
            }
        } else {
            if i < 3 {
                r[1] += da;
            }
            if i == 0 || i == 3 || i == 5 {
                r[2] += dd;
            }
        }
    }
    out
}

#[test]
fn compensated_joints_are_the_calibrated_arms_closed_form_solution_on_the_same_branch() {
    let dir = tempdir();
    let mut rng = ChaCha8Rng::seed_from_u64(24);
    for (what, rows, limits, closed, ur) in [
        (
            "spherical (NJ-130)",
            nj130_rows(),
            nj130_limits(),
            spherical_ik as fn(&[Row; 6], &Matrix4<f64>) -> Vec<[f64; 6]>,
            false,
        ),
        ("UR5e", UR5E, UR_LIMITS, ur_ik, true),
    ] {
        let nominal = load(&dh_file(dir.path(), "n", &rows, limits, [0.0; 3]));
        let cal_rows = structural_deviation(&rows, &mut rng, ur);
        let calibrated = load(&dh_file(dir.path(), "c", &cal_rows, limits, [0.0; 3]));
        let tc = table(&calibrated);
        let comp = Compensator::new(&nominal, &calibrated, &Frame::IDENTITY, &Frame::IDENTITY);
        let (mut checked_joints, mut checked_poses) = (0, 0);
        for _ in 0..200 {
            let q = random_q(&nominal, &mut rng);
            let target = comp.nominal.pose(&q);
            let m = Matrix4::new(
                target.r[(0, 0)],
                target.r[(0, 1)],
                target.r[(0, 2)],
                target.t.x,
                target.r[(1, 0)],
                target.r[(1, 1)],
                target.r[(1, 2)],
                target.t.y,
                target.r[(2, 0)],
                target.r[(2, 1)],
                target.r[(2, 2)],
                target.t.z,
                0.0,
                0.0,
                0.0,
                1.0,
            );
            // The calibrated arm's closed-form solution on the nominal joints' branch.
            let Some(want) = closed(&tc, &m).into_iter().min_by(|a, b| {
                let d = |s: &[f64; 6]| (0..6).map(|i| adiff(s[i], q[i])).fold(0.0, f64::max);
                d(a).total_cmp(&d(b))
            }) else {
                continue;
            };
            for (kind, t) in [
                ("joints", Target::Joints(q)),
                (
                    "pose",
                    Target::Pose {
                        frame: target,
                        seed: Some(std::array::from_fn(|i| {
                            q[i] + rng.random_range(-2.0..2.0) * DEG
                        })),
                    },
                ),
            ] {
                let c = comp.compensate(&t, &[0.0; 6]);
                match (c.status, c.q) {
                    (Status::Ok, Some(cq)) if !c.orientation_free => {
                        for i in 0..6 {
                            assert!(
                                adiff(cq[i], want[i]) < 1e-7,
                                "{what} {kind}: {q:?}: {cq:?} against {want:?}"
                            );
                        }
                        if kind == "joints" {
                            checked_joints += 1;
                        } else {
                            checked_poses += 1;
                        }
                    }
                    (Status::Ok, _) => {}
                    (s, _) => {
                        // Only near singularities (where a compensation may also swing to
                        // another branch) or limits may a target be refused.
                        assert!(
                            matches!(
                                s,
                                Status::Singular { .. }
                                    | Status::Limit { .. }
                                    | Status::Branch { .. }
                            ),
                            "{what} {kind}: {q:?}: {s}"
                        );
                    }
                }
            }
        }
        eprintln!("{what}: {checked_joints} joint and {checked_poses} pose targets against the closed form");
        assert!(checked_joints > 150 && checked_poses > 150, "{what}");
    }
}

#[test]
fn a_stretched_arm_is_refused_as_singular() {
    // The UR5e with its elbow straight (q3 = 0): the position Jacobian loses rank, no
    // compensation can be trusted there.
    let dir = tempdir();
    let nominal = load(&dh_file(dir.path(), "n", &UR5E, UR_LIMITS, [0.0; 3]));
    let mut rows = UR5E;
    rows[1][1] += 0.2;
    rows[2][3] += 0.02;
    let calibrated = load(&dh_file(dir.path(), "c", &rows, UR_LIMITS, [0.0; 3]));
    let comp = Compensator::new(&nominal, &calibrated, &Frame::IDENTITY, &Frame::IDENTITY);
    let q = [0.3, -1.2, 0.0, -1.0, 1.2, 0.4];
    let c = comp.compensate(&Target::Joints(q), &[0.0; 6]);
    assert!(matches!(c.status, Status::Singular { .. }), "{}", c.status);
    assert!(c.q.is_none());
    assert!(c.status.to_string().starts_with("near a singularity"));
    // Bent by 20°, the same target is fine.
    let c = comp.compensate(
        &Target::Joints([0.3, -1.2, 0.35, -1.0, 1.2, 0.4]),
        &[0.0; 6],
    );
    assert_eq!(c.status, Status::Ok);
}

// ---- the CLI: targets, programs, bad input --------------------------------------------------

fn cases() -> PathBuf {
    root().join("tests/cases/compensate")
}

fn cal_file() -> PathBuf {
    cases().join("nj130.cal.dh.toml")
}

#[test]
fn the_compensated_targets_file_is_golden_and_every_refusal_names_its_reason() {
    let dir = tempdir();
    let t = dir.path().join("t.csv");
    // Joint targets (one at the wrist singularity q5 = 0, one beyond a limit), poses and
    // positions (one out of reach, one with no seed).
    std::fs::write(
        &t,
        "name,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n\
         p1,60,0,-40,80,-80,-20\n\
         \"home, wrist straight\",0,0,0,0,0,0\n\
         p3,80,-20,-40,160,20,-160\n\
         beyond q2,10,86,0,0,30,0\n\
         at the limit,0,-60,-80,0,30,0\n",
    )
    .unwrap();
    let out = dir.path().join("t.comp.csv");
    let r = edbbgen([
        "compensate",
        cal_file().to_str().unwrap(),
        "--nominal",
        nj130_dh().to_str().unwrap(),
        "--targets",
        t.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let joints = std::fs::read_to_string(&out).unwrap();
    let p = dir.path().join("p.csv");
    std::fs::write(
        &p,
        "name,x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n\
         seeded,1500,300,1200,180,0,90,10,10,-10,0,60,0\n\
         no seed,1500,300,1200,180,0,90,,,,,,\n\
         far away,5000,0,1000,180,0,0,0,0,0,0,60,0\n",
    )
    .unwrap();
    let pout = dir.path().join("p.comp.csv");
    let r = edbbgen([
        "compensate",
        cal_file().to_str().unwrap(),
        "--nominal",
        nj130_dh().to_str().unwrap(),
        "--targets",
        p.to_str().unwrap(),
        "-o",
        pout.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let poses = std::fs::read_to_string(&pout).unwrap();
    let x = dir.path().join("x.csv");
    std::fs::write(
        &x,
        "x_mm,y_mm,z_mm,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1500,300,1200,10,10,-10,0,60,0\n1500,300,1200,10,10,-10,0,0.2,0\n",
    )
    .unwrap();
    let xout = dir.path().join("x.comp.csv");
    let r = edbbgen([
        "compensate",
        cal_file().to_str().unwrap(),
        "--nominal",
        nj130_dh().to_str().unwrap(),
        "--targets",
        x.to_str().unwrap(),
        "-o",
        xout.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let positions = std::fs::read_to_string(&xout).unwrap();
    assert_golden(
        "compensated@targets",
        &format!("{joints}\n{poses}\n{positions}"),
    );

    // Every row: the input repeated, ok rows fully written, the others with the reason only.
    let status = |text: &str| -> Vec<String> {
        text.lines()
            .skip(1)
            .map(|l| l.rsplit(',').next().unwrap().to_string())
            .collect()
    };
    let js = status(&joints);
    assert_eq!(js[0], "ok");
    assert_eq!(
        js[1], "ok",
        "the wrist singularity: position exact, orientation free"
    );
    assert!(
        js[3].starts_with("joint limit: the target's joint 2"),
        "{}",
        js[3]
    );
    // At joint 2's lower limit: the compensated joint would leave the range.
    assert!(
        js[4].starts_with("joint limit: joint 2 at -60.0"),
        "{}",
        js[4]
    );
    let ps = status(&poses);
    assert_eq!(ps[0], "ok");
    assert_eq!(ps[1], "ok");
    assert!(
        ps[2].starts_with("out of reach: the nominal robot"),
        "{}",
        ps[2]
    );
    for l in joints.lines().skip(1).chain(poses.lines().skip(1)) {
        let fields: Vec<&str> = l.split(',').collect();
        if l.ends_with(",ok") {
            continue;
        }
        // 12 compensated columns left empty.
        let n = fields.len();
        assert!(fields[n - 14..n - 2].iter().all(|f| f.is_empty()), "{l}");
    }
    // Without a seed, the solution nearest the middle of the joint ranges: here the other
    // wrist configuration than the seed's.
    let rows: Vec<&str> = poses.lines().skip(1).collect();
    let cq = |l: &str| -> Vec<f64> {
        l.split(',')
            .skip(13)
            .take(6)
            .map(|v| v.parse().unwrap())
            .collect()
    };
    let lim = nj130_limits();
    let spread = |q: &[f64]| -> f64 {
        (0..6)
            .map(|i| ((q[i] - 0.5 * (lim[i][0] + lim[i][1])) / (lim[i][1] - lim[i][0])).powi(2))
            .sum()
    };
    assert!(spread(&cq(rows[1])) <= spread(&cq(rows[0])));
    assert!(
        (cq(rows[0])[4] + cq(rows[1])[4]).abs() < 0.1,
        "the wrist flipped: q5 → −q5"
    );
    assert_eq!(status(&positions), ["ok", "ok"]);
}

#[test]
fn compensate_writes_the_same_bytes_on_one_and_two_threads() {
    let dir = tempdir();
    let t = dir.path().join("t.csv");
    let mut text = "x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg\n".to_string();
    for k in 0..40 {
        let a = k as f64;
        text += &format!(
            "{},{},{},180,{},{}\n",
            1200.0 + 10.0 * a,
            -300.0 + 15.0 * a,
            1000.0 + 5.0 * a,
            a * 0.5,
            90.0 - a
        );
    }
    std::fs::write(&t, text).unwrap();
    let run = |threads: &str| {
        let (out, json) = (
            dir.path().join(format!("o{threads}.csv")),
            dir.path().join(format!("r{threads}.json")),
        );
        let r = edbbgen_env(
            [
                "compensate",
                cal_file().to_str().unwrap(),
                "--nominal",
                nj130_dh().to_str().unwrap(),
                "--targets",
                t.to_str().unwrap(),
                "-o",
                out.to_str().unwrap(),
                "--json",
                json.to_str().unwrap(),
            ],
            &[("RAYON_NUM_THREADS", threads)],
        );
        assert_eq!(r.code, 0, "{}", r.stderr);
        (
            std::fs::read_to_string(out).unwrap(),
            std::fs::read_to_string(json).unwrap(),
            r.stdout.replace(&format!("o{threads}.csv"), ""),
        )
    };
    let one = run("1");
    assert!(one.0.lines().skip(1).filter(|l| l.ends_with(",ok")).count() > 30);
    assert_eq!(one, run("2"));
}

#[test]
fn bad_target_files_exit_2_with_one_line_and_write_nothing() {
    let dir = tempdir();
    for (text, needle) in [
        ("q1_deg,q2_deg\n1,2\n", "line 1: columns q1_deg"),
        (
            "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n1,2,x,4,5,6\n",
            "line 2: column q3_deg: 'x'",
        ),
        ("x_mm,y_mm,z_mm,w\n1,2,3,4\n", "unknown column 'w'"),
        ("", "empty file"),
    ] {
        let t = dir.path().join("bad.csv");
        std::fs::write(&t, text).unwrap();
        let out = dir.path().join("out.csv");
        let r = edbbgen([
            "compensate",
            cal_file().to_str().unwrap(),
            "--nominal",
            nj130_dh().to_str().unwrap(),
            "--targets",
            t.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ]);
        assert_eq!(r.code, 2, "{text:?}: {}", r.stderr);
        assert_eq!(r.stderr.lines().count(), 1, "{}", r.stderr);
        assert!(
            r.stderr.contains("bad.csv") && r.stderr.contains(needle),
            "{}",
            r.stderr
        );
        assert!(!out.exists());
    }
}

const USER_PROGRAMS: [(&str, &str); 6] = [
    ("ngc", "user.nc"),
    ("sinumerik", "user.mpf"),
    ("krl", "user.src"),
    ("rapid", "user.mod"),
    ("urscript", "user.script"),
    ("fanuc", "user.ls"),
];

/// Model joints (deg) of every move of a program file, read with its dialect's default mapping.
fn read_moves(path: &Path, robot: &Robot) -> Vec<[f64; 6]> {
    let text = std::fs::read_to_string(path).unwrap();
    let d = edbbgen::dialect::detect(path, &text).unwrap();
    let parsed = d.read(&text, &d.default_map(robot).unwrap()).unwrap();
    parsed.targets().map(|(_, t)| *t).collect()
}

#[test]
fn a_users_program_in_every_dialect_is_rewritten_with_compensated_joints_and_golden() {
    let nominal = load(&nj130_dh());
    let calibrated = load(&cal_file());
    let tcp = |r: &Robot| Frame::translation(r.tool.unwrap());
    let comp = Compensator::new(&nominal, &calibrated, &tcp(&nominal), &tcp(&calibrated));
    let dir = tempdir();
    for (d, file) in USER_PROGRAMS {
        let input = cases().join(file);
        let out = dir.path().join(file);
        let r = edbbgen([
            "compensate",
            cal_file().to_str().unwrap(),
            "--nominal",
            nj130_dh().to_str().unwrap(),
            "--program",
            input.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ]);
        assert_eq!(r.code, 0, "{d}: {}", r.stderr);
        let text = std::fs::read_to_string(&out).unwrap();
        assert_golden(&format!("compensated@user_{d}"), &text);
        // Read back: every move is the compensated joint target of the original, to the
        // printed precision (and the same number of moves).
        let before = read_moves(&input, &nominal);
        let after = read_moves(&out, &nominal);
        assert_eq!(before.len(), after.len(), "{d}");
        let tol = match d {
            "fanuc" => 0.0006,
            "sinumerik" => 0.00006,
            "krl" | "rapid" => 0.000006,
            // 1e-7 rad, cut toward zero.
            "urscript" => 0.000006,
            _ => 0.000002,
        };
        for (b, a) in before.iter().zip(&after) {
            let c = comp.compensate(&Target::Joints(b.map(|v| v * DEG)), &[0.0; 6]);
            let cq = c.q.unwrap().map(|r| r / DEG);
            for i in 0..6 {
                // J3 of the FANUC text is q3 − q2: the model joint carries both roundings.
                let t = if d == "fanuc" && i == 2 {
                    2.0 * tol
                } else {
                    tol
                };
                assert!((a[i] - cq[i]).abs() <= t, "{d}: {a:?} vs {cq:?}");
            }
        }
        // The rest of the text is the input's: a line that is not a move (or, in RAPID, the
        // declaration of a jointtarget) is the same line; FANUC renumbers its lines.
        if d != "fanuc" {
            let input_text = std::fs::read_to_string(&input).unwrap();
            let dialect = edbbgen::dialect::detect(&input, &input_text).unwrap();
            let parsed = dialect
                .read(&input_text, &dialect.default_map(&nominal).unwrap())
                .unwrap();
            let moves: Vec<usize> = parsed.targets().map(|(l, _)| l).collect();
            let kept: Vec<&str> = text
                .lines()
                .filter(|l| !l.contains("compensated by"))
                .collect();
            let given: Vec<&str> = input_text.lines().collect();
            assert_eq!(kept.len(), given.len(), "{d}");
            for (k, (a, b)) in given.iter().zip(&kept).enumerate() {
                if !moves.contains(&(k + 1)) && !a.contains("jointtarget") {
                    assert_eq!(a, b, "{d}: line {}", k + 1);
                }
            }
        }
    }
}

#[test]
fn a_move_that_cannot_be_compensated_or_an_incremental_program_writes_nothing() {
    let dir = tempdir();
    let run = |text: &str, name: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        let out = dir.path().join(format!("out_{name}"));
        let r = edbbgen([
            "compensate",
            cal_file().to_str().unwrap(),
            "--nominal",
            nj130_dh().to_str().unwrap(),
            "--program",
            p.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ]);
        assert!(!out.exists(), "{name}: nothing written");
        r
    };
    // A move beyond joint 2's limit (85°): listed with its line, exit 1.
    let r = run(
        "G21 G90\nG0 X0 Y0 Z0 A0 B30 C0\nG0 X0 Y86 Z0 A0 B30 C0\nM2\n",
        "limit.nc",
    );
    assert_eq!(r.code, 1, "{}", r.stderr);
    assert!(
        r.stderr
            .contains("line 3: cannot be compensated: joint limit: the target's joint 2"),
        "{}",
        r.stderr
    );
    // Incremental moves are outside what compensate rewrites: exit 2, the line named.
    let r = run("G21 G90\nG0 X0 Y0 Z0 A0 B30 C0\nG91\nG0 X1\nM2\n", "inc.nc");
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("line 3: G91"), "{}", r.stderr);
    assert_eq!(r.stderr.lines().count(), 1);
    // A line the reader does not take: its line and the reader's reason.
    let r = run("G21 G90\nG0 X0 Y0 Z0 A0 B30 C0\nG2 X1\nM2\n", "arc.nc");
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("line 3"), "{}", r.stderr);
}

#[test]
fn a_move_at_its_speed_limit_is_slowed_by_the_ratio_of_its_times() {
    // A joint-4-only move planned at joint 4's full speed, in the direction in which the
    // compensation lengthens it: its G93 F must come down so that no axis exceeds its speed.
    let nominal = load(&nj130_dh());
    let calibrated = load(&cal_file());
    let tcp = |r: &Robot| Frame::translation(r.tool.unwrap());
    let comp = Compensator::new(&nominal, &calibrated, &tcp(&nominal), &tcp(&calibrated));
    let c = |q: &[f64; 6]| {
        comp.compensate(&Target::Joints(q.map(|v| v * DEG)), &[0.0; 6])
            .q
            .unwrap()
    };
    // A pose pair whose compensation lengthens joint 4's travel (it shortens it as often).
    let (from, to) = (0..40)
        .map(|k| {
            let a = [60.0, 0.0, -40.0, 80.0, -70.0 + 5.0 * k as f64, -20.0];
            let mut b = a;
            b[3] = 140.0;
            (a, b)
        })
        .find(|(a, b)| (c(b)[3] - c(a)[3]).abs() > 60.0 * DEG)
        .expect("a move the compensation lengthens");
    let line = |q: [f64; 6]| {
        format!(
            "X{} Y{} Z{} A{} B{} C{}",
            q[0], q[1], q[2], q[3], q[4], q[5]
        )
    };
    // 60° at 180°/s: 1/3 s, F = 180.
    let text = format!(
        "G21 G90\nG0 {}\nG93\nG1 {} F180\nM2\n",
        line(from),
        line(to)
    );
    let dir = tempdir();
    let p = dir.path().join("fast.nc");
    std::fs::write(&p, &text).unwrap();
    let out = dir.path().join("slow.nc");
    let r = edbbgen([
        "compensate",
        cal_file().to_str().unwrap(),
        "--nominal",
        nj130_dh().to_str().unwrap(),
        "--program",
        p.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--json",
        dir.path().join("r.json").to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(&out).unwrap();
    let f: f64 = text
        .lines()
        .find(|l| l.starts_with("G1 "))
        .unwrap()
        .split_whitespace()
        .find_map(|w| w.strip_prefix('F'))
        .unwrap()
        .parse()
        .unwrap();
    // The compensated joint-4 travel at 180°/s.
    let travel = ((c(&to)[3] - c(&from)[3]) / DEG).abs();
    let min_time = travel / 180.0;
    assert!(
        travel > 60.0 && 60.0 / f >= min_time * (1.0 - 1e-9),
        "F{f}: {travel} deg"
    );
    assert!(
        60.0 / f < min_time * 1.001,
        "slowed by the ratio, not more: F{f}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("r.json")).unwrap()).unwrap();
    assert_eq!(report["program"]["retimed_lines"], serde_json::json!([4]));
}

// ---- programs the compiler wrote, compensated and verified in their cells --------------------

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn compiled_programs_of_every_dialect_compensated_still_verify_in_their_cells() {
    // The NJ-130 in its cell (DH), and the R-2000iC (URDF) whose FANUC J3 follows J2 through the
    // controller mapping: the compensation works on model joints, the text carries axes.
    for case in ["nj130_cell", "fanuc_r2000ic_165f"] {
        let c = crate::dialects::cell(case);
        let dir = workdir(&c.robot_path);
        // A calibrated robot file of the cell's robot: the nominal with small deviations.
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let g = dh_errors(&mut rng);
        let cal_path = write_calibrated(dir.path(), &c.robot_path, &c.robot, &g);
        for (d, program, text) in &c.programs {
            let input = crate::dialects::file_for(dir.path(), d, program);
            std::fs::write(&input, text).unwrap();
            let ext = input.extension().unwrap().to_string_lossy().into_owned();
            let out = dir.path().join(format!("COMP.{ext}"));
            let json = dir.path().join("comp.json");
            let r = edbbgen([
                "compensate",
                cal_path.to_str().unwrap(),
                "--nominal",
                c.robot_path.to_str().unwrap(),
                "--program",
                input.to_str().unwrap(),
                "-o",
                out.to_str().unwrap(),
                "--cell",
                c.cell_path.to_str().unwrap(),
                "--json",
                json.to_str().unwrap(),
            ]);
            assert_eq!(r.code, 0, "{d}@{case}: {}", r.stderr);
            // A pose planned at the joint margin's edge may cross it by the compensation:
            // compensate says so, and verify takes the program with the margin less that.
            let rep: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
            let change = rep["program"]["largest_change_deg"].as_f64().unwrap();
            assert!(change > 0.0 && change < 1.0, "{d}@{case}: {change} deg");
            let beyond = rep["program"]["beyond_joint_margin"].as_array().unwrap();
            let margin = c.opts.cell.joint_margin / DEG;
            let mut args = vec![
                "verify".to_string(),
                c.robot_path.display().to_string(),
                out.display().to_string(),
                "--cell".into(),
                c.cell_path.display().to_string(),
            ];
            if !beyond.is_empty() {
                assert!(
                    r.stdout.contains("leave the cell's joint margin"),
                    "{}",
                    r.stdout
                );
                for b in beyond {
                    assert!(b[2].as_f64().unwrap() <= change + 1e-9, "{b}");
                }
                args.push("--joint-margin".into());
                args.push(format!("{:.4}", margin - change - 1e-4));
            }
            let r = edbbgen(&args);
            assert_eq!(r.code, 0, "verify {d}@{case}: {} {}", r.stdout, r.stderr);
        }
    }
}

/// A calibrated file of `robot` with the Eq. 6 deviations `g` applied (DH or URDF, by the
/// library's writers).
fn write_calibrated(dir: &Path, path: &Path, robot: &Robot, g: &[f64; N_PARAMS]) -> PathBuf {
    let map = robot.tool.unwrap_or_else(|| Vector3::new(0.06, 0.03, 0.12));
    let mut p = Params {
        fix: Vector3::zeros(),
        dh: robot.dh,
        map,
    }
    .to_array();
    for k in 3..N_PARAMS {
        p[k] += g[k];
    }
    let p = Params::from_array(&p);
    let text = std::fs::read_to_string(path).unwrap();
    if path.extension().unwrap() == "urdf" {
        let out = dir.join("cal.urdf");
        let t = edbbgen::robot::urdf::calibrated(
            &text,
            path,
            &Default::default(),
            robot,
            &p.dh,
            &p.map,
            &["test".to_string()],
        )
        .unwrap();
        std::fs::write(&out, t).unwrap();
        out
    } else {
        let out = dir.join("cal.dh.toml");
        let t =
            edbbgen::robot::dh::calibrated(&text, path, &p.dh, &p.map, &["test".to_string()], "")
                .unwrap();
        std::fs::write(&out, t).unwrap();
        out
    }
}

// ---- twin robots: compensation, offsets, against the truth ----------------------------------

/// The twin's truth robot: the nominal parameters plus the truth's deviations.
fn truth_params(model: &MeasurementModel, truth: &Truth) -> Params {
    let mut p = model.nominal.to_array();
    for k in 0..N_PARAMS {
        p[k] += truth.geometric[k];
    }
    Params::from_array(&p)
}

fn registered(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> f64 {
    edbbgen::calibrate::predict::register(a, b).0 * 1e6
}

/// The compensated joints (model, rad) of an output file's ok rows, by row.
fn compensated_rows(path: &Path) -> Vec<Option<([f64; 6], [f64; 6])>> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap();
    let cq: Vec<usize> = (1..=6).map(|i| col(&format!("cq{i}_deg"))).collect();
    let cart: Vec<usize> = ["cx_mm", "cy_mm", "cz_mm", "crx_deg", "cry_deg", "crz_deg"]
        .iter()
        .map(|n| col(n))
        .collect();
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[f.len() - 1] == "ok").then(|| {
                (
                    std::array::from_fn(|i| f[cq[i]].parse::<f64>().unwrap() * DEG),
                    std::array::from_fn(|i| f[cart[i]].parse::<f64>().unwrap()),
                )
            })
        })
        .collect()
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn on_a_twin_the_truth_robot_reaches_the_nominal_targets_as_predicted() {
    let c = crate::diagnose::cell_with(load(&nj130_dh()), [258.0, 1468.0, 708.0], None);
    let dir = tempdir();
    let mut rng = ChaCha8Rng::seed_from_u64(2024);
    let truth = Truth {
        geometric: dh_errors(&mut rng),
        noise: 1e-6,
        ..Truth::default()
    };
    let m = twin::simulate(
        &c.robot,
        &c.model,
        &c.program,
        &truth,
        &SimOptions {
            rate: 50.0,
            seed: 3,
        },
    )
    .unwrap();
    let csv = dir.path().join("m.csv");
    std::fs::write(&csv, m.to_csv()).unwrap();
    let (cal, json) = (dir.path().join("cal.dh.toml"), dir.path().join("cal.json"));
    let r = edbbgen([
        "calibrate",
        nj130_dh().to_str().unwrap(),
        "--measured",
        csv.to_str().unwrap(),
        "--fixture",
        "258,1468,708",
        "-o",
        cal.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
        "--effects",
        "none",
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let predicted = report["predicted_position_std_um"]["workspace_rms"]
        .as_f64()
        .unwrap();

    // 2000 random targets in reach: the nominal robot's MAP at random joints within the limits.
    let qs = joint_space(&c.robot, 2000, 99);
    let nominal_chain = Chain::new(&c.robot, &Frame::translation(c.model.nominal.map));
    let poses: Vec<Frame> = qs.iter().map(|q| nominal_chain.pose(q)).collect();
    let fmt = |v: f64| format!("{v:.9}");
    let seed = |q: &[f64; 6], rng: &mut ChaCha8Rng| -> String {
        q.iter()
            .map(|v| fmt(v / DEG + rng.random_range(-2.0..2.0)))
            .collect::<Vec<_>>()
            .join(",")
    };
    let mut joints = "q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n".to_string();
    let mut full =
        "x_mm,y_mm,z_mm,rx_deg,ry_deg,rz_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n"
            .to_string();
    let mut position = "x_mm,y_mm,z_mm,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg\n".to_string();
    for (q, p) in qs.iter().zip(&poses) {
        joints += &(q.iter().map(|v| fmt(v / DEG)).collect::<Vec<_>>().join(",") + "\n");
        let xyz =
            p.t.iter()
                .map(|v| fmt(v * 1e3))
                .collect::<Vec<_>>()
                .join(",");
        let rpy = p
            .rpy()
            .iter()
            .map(|v| fmt(v / DEG))
            .collect::<Vec<_>>()
            .join(",");
        full += &format!("{xyz},{rpy},{}\n", seed(q, &mut rng));
        position += &format!("{xyz},{}\n", seed(q, &mut rng));
    }
    let tp = truth_params(&c.model, &truth);
    let truth_at = |q: &[f64; 6]| c.model.map_position(&tp, q);
    let mut realised = Vec::new();
    for (kind, text) in [
        ("joints", &joints),
        ("pose", &full),
        ("position", &position),
    ] {
        let t = dir.path().join(format!("{kind}.csv"));
        std::fs::write(&t, text).unwrap();
        let out = dir.path().join(format!("{kind}.comp.csv"));
        let rj = dir.path().join(format!("{kind}.json"));
        let html = dir.path().join(format!("{kind}.html"));
        let r = edbbgen([
            "compensate",
            cal.to_str().unwrap(),
            "--nominal",
            nj130_dh().to_str().unwrap(),
            "--targets",
            t.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--calibration",
            json.to_str().unwrap(),
            "--json",
            rj.to_str().unwrap(),
            "--html",
            html.to_str().unwrap(),
        ]);
        assert_eq!(r.code, 0, "{kind}: {}", r.stderr);
        if kind == "joints" {
            crate::report::assert_page_draws(&html, "compensate", &["fig-accuracy", "fig-targets"]);
        }
        let rows = compensated_rows(&out);
        let ok: Vec<usize> = (0..rows.len()).filter(|&k| rows[k].is_some()).collect();
        let rep: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&rj).unwrap()).unwrap();
        let mut reasons = std::collections::BTreeMap::<String, usize>::new();
        for n in rep["targets"]["not_compensated"].as_array().unwrap() {
            let why = n["status"]
                .as_str()
                .unwrap()
                .split(':')
                .next()
                .unwrap()
                .to_string();
            *reasons.entry(why).or_default() += 1;
        }
        eprintln!("{kind}: not compensated: {reasons:?}");
        assert!(ok.len() >= 1900, "{kind}: {} of 2000 compensated", ok.len());
        let reached: Vec<Vector3<f64>> =
            ok.iter().map(|&k| truth_at(&rows[k].unwrap().0)).collect();
        let targets: Vec<Vector3<f64>> = ok.iter().map(|&k| poses[k].t).collect();
        let uncompensated: Vec<Vector3<f64>> = ok.iter().map(|&k| truth_at(&qs[k])).collect();
        let err = registered(&reached, &targets);
        let before = registered(&uncompensated, &targets);
        eprintln!(
            "{kind}: {} of 2000 compensated; truth robot {before:.1} um -> {err:.2} um RMS (registered), predicted {predicted:.2} um",
            ok.len()
        );
        assert!(
            err <= 1.5 * predicted,
            "{kind}: {err} um against {predicted} um predicted"
        );
        assert!(
            before > 20.0 * err,
            "{kind}: the compensation did something"
        );
        realised.push(err);

        if kind == "pose" {
            // A controller that runs its own nominal IK on the compensated Cartesian targets
            // (the closed form here, on the compensated joints' branch) makes the truth robot
            // end within 1 µm of where the compensated joints take it.
            let t = table(&c.robot);
            let tcp_inv = Frame::translation(c.model.nominal.map).inverse();
            let mut worst: f64 = 0.0;
            for &k in &ok {
                let (cq, cart) = rows[k].unwrap();
                let tcp = Frame::from_xyz_rpy(
                    [cart[0] * 1e-3, cart[1] * 1e-3, cart[2] * 1e-3],
                    [cart[3] * DEG, cart[4] * DEG, cart[5] * DEG],
                );
                let f = tcp.mul(&tcp_inv);
                let m4 = Matrix4::new(
                    f.r[(0, 0)],
                    f.r[(0, 1)],
                    f.r[(0, 2)],
                    f.t.x,
                    f.r[(1, 0)],
                    f.r[(1, 1)],
                    f.r[(1, 2)],
                    f.t.y,
                    f.r[(2, 0)],
                    f.r[(2, 1)],
                    f.r[(2, 2)],
                    f.t.z,
                    0.0,
                    0.0,
                    0.0,
                    1.0,
                );
                let Some(qc) = spherical_ik(&t, &m4).into_iter().min_by(|a, b| {
                    let d = |s: &[f64; 6]| (0..6).map(|i| adiff(s[i], cq[i])).fold(0.0, f64::max);
                    d(a).total_cmp(&d(b))
                }) else {
                    panic!("row {k}: the controller finds no solution");
                };
                // The controller's joints, continued to the compensated joints' turn.
                let qc: [f64; 6] = std::array::from_fn(|i| cq[i] + wrap(qc[i] - cq[i]));
                worst = worst.max((truth_at(&qc) - truth_at(&cq)).norm() * 1e6);
            }
            eprintln!(
                "nominal-IK controller on the compensated Cartesian targets: {worst:.4} um at most"
            );
            assert!(worst < 1.0, "{worst} um");
        }
        if kind == "joints" {
            // Offsets only: predicted against realised (the truth robot commanded q − Δθ).
            let rep: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&rj).unwrap()).unwrap();
            let pred = rep["accuracy"]["predicted_offsets_only_um"]["rms"]
                .as_f64()
                .unwrap();
            let delta: Vec<f64> = rep["mastering"]["axes"]
                .as_array()
                .unwrap()
                .iter()
                .map(|a| a["joint_delta_deg"].as_f64().unwrap() * DEG)
                .collect();
            let shifted: Vec<Vector3<f64>> = qs
                .iter()
                .map(|q| truth_at(&std::array::from_fn(|i| q[i] - delta[i])))
                .collect();
            let all_targets: Vec<Vector3<f64>> = poses.iter().map(|p| p.t).collect();
            let real = registered(&shifted, &all_targets);
            let nothing = registered(&qs.iter().map(&truth_at).collect::<Vec<_>>(), &all_targets);
            eprintln!(
                "offsets only: realised {real:.1} um RMS, predicted {pred:.1} um (nothing applied {nothing:.1} um, model {}; full compensation {err:.2} um)",
                rep["accuracy"]["uncompensated_um"]["rms"]
            );
            assert!(real < 2.0 * pred && pred < 2.0 * real, "{real} vs {pred}");
        }
    }
}

#[test]
fn a_percentage_timed_move_with_j3_following_j2_is_slowed_in_krl() {
    // KRL with the cell's J3 = q3 − q2: the controller times a PTP on its axes (J2 leads), the
    // joints' limit is joint 3's (it turns 22° while J3 turns 6°). At 80 % the move takes
    // exactly joint 3's time; a compensation that lengthens joint 3's turn or shortens J2's
    // must lower $VEL_AXIS for that move, and only for it.
    let nominal = load(&nj130_dh());
    let calibrated = load(&cal_file());
    let tcp = |r: &Robot| Frame::translation(r.tool.unwrap());
    let comp = Compensator::new(&nominal, &calibrated, &tcp(&nominal), &tcp(&calibrated));
    let c = |q: &[f64; 6]| {
        comp.compensate(&Target::Joints(q.map(|v| v * DEG)), &[0.0; 6])
            .q
            .unwrap()
            .map(|r| r / DEG)
    };
    let (a, b) = (0..54)
        .map(|k| {
            let a = [
                10.0,
                -50.0 + 2.0 * k as f64,
                -70.0 + 2.5 * k as f64,
                30.0,
                40.0,
                0.0,
            ];
            let mut b = a;
            b[1] += 16.0;
            b[2] += 22.0;
            (a, b)
        })
        .find(|(a, b)| {
            let (ca, cb) = (c(a), c(b));
            let j2 = (cb[1] - ca[1]).abs() / 100.0 / 0.8;
            let q3 = (cb[2] - ca[2]).abs() / 110.0;
            j2 < q3 * (1.0 - 1e-7)
        })
        .expect("a move the compensation makes too fast at 80 %");
    let axes = |q: &[f64; 6]| {
        format!(
            "{{A1 {}, A2 {}, A3 {}, A4 {}, A5 {}, A6 {}}}",
            q[0],
            q[1],
            q[2] - q[1],
            q[3],
            q[4],
            q[5]
        )
    };
    let vel: String = (1..=6).map(|i| format!("$VEL_AXIS[{i}] = 80\n")).collect();
    let text = format!(
        "&ACCESS RVP\nDEF speed( )\n{vel}PTP {}\nPTP {}\nPTP {}\nEND\n",
        axes(&a),
        axes(&b),
        axes(&a)
    );
    let dir = tempdir();
    let cell = dir.path().join("cell.toml");
    std::fs::write(&cell, "[controller]\nj3_coupling = -1\n").unwrap();
    let p = dir.path().join("speed.src");
    std::fs::write(&p, &text).unwrap();
    let out = dir.path().join("comp.src");
    let r = edbbgen([
        "compensate",
        cal_file().to_str().unwrap(),
        "--nominal",
        nj130_dh().to_str().unwrap(),
        "--program",
        p.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--cell",
        cell.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let new = std::fs::read_to_string(&out).unwrap();
    let lines: Vec<&str> = new.lines().collect();
    let ptp: Vec<usize> = (0..lines.len())
        .filter(|&k| lines[k].starts_with("PTP"))
        .collect();
    // Before the second PTP J2's percentage comes down; after it, 80 again.
    let before = lines[ptp[0] + 1..ptp[1]].join("\n");
    let after = lines[ptp[1] + 1..ptp[2]].join("\n");
    let lowered: i64 = before
        .lines()
        .find(|l| l.starts_with("$VEL_AXIS[2] = "))
        .unwrap_or_else(|| panic!("{new}"))
        .rsplit(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(lowered < 80, "{new}");
    assert!(after.contains("$VEL_AXIS[2] = 80"), "{new}");
    // Read back on the controller's axes: the move now takes at least joint 3's time.
    let map = edbbgen::controller::ControllerMap::resolve(
        edbbgen::cell::load(&cell).unwrap().controller.as_ref(),
        &edbbgen::dialect::by_name("krl").unwrap().defaults(),
        "krl",
        &nominal,
    )
    .unwrap();
    let parsed = edbbgen::dialect::by_name("krl")
        .unwrap()
        .read(&new, &map)
        .unwrap();
    let moves: Vec<(&[f64; 6], &edbbgen::dialect::Step)> = parsed
        .lines
        .iter()
        .filter_map(|l| match &l.step {
            s @ edbbgen::dialect::Step::Move { axes, .. } => Some((axes, s)),
            _ => None,
        })
        .collect();
    let speeds = nominal.max_speeds();
    let targets: Vec<[f64; 6]> = parsed.targets().map(|(_, t)| t.map(|d| d * DEG)).collect();
    for k in 1..moves.len() {
        let d = parsed
            .duration(moves[k - 1].0, moves[k].1, &speeds)
            .unwrap();
        let min = edbbgen::order::move_time(&targets[k - 1], &targets[k], &speeds);
        assert!(d >= min * (1.0 - 1e-9), "move {k}: {d} s against {min} s");
    }
}

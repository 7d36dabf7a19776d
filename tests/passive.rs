//! Passive links: links that hang off the chain through mimic joints are bodies like
//! any other. Checked independently of edbbgen's loader and collision model: the URDF is parsed
//! here with urdf-rs, its kinematics (mimic joints included) are computed here, and clearances
//! are measured on the original triangle meshes with parry's TriMesh (not on edbbgen's convex
//! hulls).

use crate::common::*;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d_f64::shape::TriMesh;
use rayon::prelude::*;
use std::collections::HashMap;
use std::path::Path;

/// The URDF's own kinematics: every link's pose in the root frame for joint values by name
/// (chain joints), mimic joints following their source (nested), other joints at 0.
pub struct Kin {
    pub doc: urdf_rs::Robot,
}

impl Kin {
    pub fn new(path: &Path) -> Self {
        Kin {
            doc: urdf_rs::read_file(path).expect("URDF parses"),
        }
    }

    fn value(&self, name: &str, chain: &HashMap<String, f64>) -> f64 {
        if let Some(v) = chain.get(name) {
            return *v;
        }
        let j = self
            .doc
            .joints
            .iter()
            .find(|j| j.name == name)
            .expect("joint");
        match &j.mimic {
            Some(m) => {
                m.multiplier.unwrap_or(1.0) * self.value(&m.joint, chain) + m.offset.unwrap_or(0.0)
            }
            None => 0.0,
        }
    }

    pub fn poses(&self, chain: &HashMap<String, f64>) -> HashMap<String, Isometry3<f64>> {
        let mut out = HashMap::new();
        let children: Vec<&str> = self
            .doc
            .joints
            .iter()
            .map(|j| j.child.link.as_str())
            .collect();
        let root = self
            .doc
            .links
            .iter()
            .find(|l| !children.contains(&l.name.as_str()))
            .expect("root");
        out.insert(root.name.clone(), Isometry3::identity());
        // Joints in any order: repeat until every link is placed.
        while out.len() < self.doc.links.len() {
            for j in &self.doc.joints {
                if out.contains_key(&j.child.link) {
                    continue;
                }
                let Some(parent) = out.get(&j.parent.link).copied() else {
                    continue;
                };
                let (x, r) = (j.origin.xyz.0, j.origin.rpy.0);
                let origin = Isometry3::from_parts(
                    Translation3::new(x[0], x[1], x[2]),
                    UnitQuaternion::from_euler_angles(r[0], r[1], r[2]),
                );
                let axis = Vector3::from(j.axis.xyz.0).normalize();
                let v = self.value(&j.name, chain);
                let motion = match j.joint_type {
                    urdf_rs::JointType::Revolute | urdf_rs::JointType::Continuous => {
                        Isometry3::from_parts(
                            Translation3::identity(),
                            UnitQuaternion::from_scaled_axis(axis * v),
                        )
                    }
                    urdf_rs::JointType::Prismatic => Isometry3::from_parts(
                        Translation3::from(axis * v),
                        UnitQuaternion::identity(),
                    ),
                    _ => Isometry3::identity(),
                };
                out.insert(j.child.link.clone(), parent * origin * motion);
            }
        }
        out
    }
}

/// A link's collision mesh (STL, as the URDF names it) in the link frame.
fn mesh(urdf: &Path, link: &urdf_rs::Link) -> Option<TriMesh> {
    let c = link.collision.first()?;
    let urdf_rs::Geometry::Mesh { filename, .. } = &c.geometry else {
        return None;
    };
    let mut f = std::fs::File::open(urdf.parent().unwrap().join(filename)).expect("mesh");
    let m = stl_io::read_stl(&mut f).expect("stl");
    let (x, r) = (c.origin.xyz.0, c.origin.rpy.0);
    let origin = Isometry3::from_parts(
        Translation3::new(x[0], x[1], x[2]),
        UnitQuaternion::from_euler_angles(r[0], r[1], r[2]),
    );
    let vs: Vec<Point3<f64>> = m
        .vertices
        .iter()
        .map(|v| origin * Point3::new(v[0] as f64, v[1] as f64, v[2] as f64))
        .collect();
    let ix: Vec<[u32; 3]> = m
        .faces
        .iter()
        .map(|f| f.vertices.map(|i| i as u32))
        .collect();
    Some(TriMesh::new(vs, ix).expect("trimesh"))
}

/// Joint vectors (rad) along a program's straight joint moves, no joint moving more than
/// `step` between samples (blends cut the corners by at most the 10 mm blend zone).
fn along(poses: &[[f64; 6]], step: f64) -> Vec<[f64; 6]> {
    let mut out = vec![poses[0].map(f64::to_radians)];
    for w in poses.windows(2) {
        let (a, b) = (w[0].map(f64::to_radians), w[1].map(f64::to_radians));
        let n = (0..6).map(|i| (b[i] - a[i]).abs()).fold(0.0, f64::max) / step;
        let n = n.ceil().max(1.0) as usize;
        for k in 1..=n {
            let t = k as f64 / n as f64;
            out.push(std::array::from_fn(|i| a[i] + t * (b[i] - a[i])));
        }
    }
    out
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn the_abb_program_keeps_the_margin_around_the_balancing_cylinder_on_the_meshes() {
    let urdf = shared_robot("abb_irb6700_200_260");
    let cell = crate::safety::test_cell("abb_irb6700_200_260");
    let dir = tempdir();
    let prog = dir.path().join("abb.nc");
    let r = edbbgen([
        urdf.as_os_str(),
        "--cell".as_ref(),
        cell.as_os_str(),
        "-o".as_ref(),
        prog.as_os_str(),
        "-q".as_ref(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(&prog).unwrap();
    let v = edbbgen([
        "verify".as_ref(),
        urdf.as_os_str(),
        prog.as_os_str(),
        "--cell".as_ref(),
        cell.as_os_str(),
        "--json".as_ref(),
    ]);
    assert_eq!(v.code, 0, "{}{}", v.stdout, v.stderr);
    let summary: serde_json::Value = serde_json::from_str(&v.stdout).expect("verify --json");
    let bodies = summary["bodies"]
        .as_array()
        .expect("verify lists the bodies")
        .clone();
    for passive in ["cylinder", "piston"] {
        assert!(
            bodies.iter().any(|b| b == passive),
            "verify checked {passive}: {bodies:?}"
        );
    }

    // Independent: the URDF's kinematics and meshes.
    let kin = Kin::new(&urdf);
    let meshes: Vec<(String, TriMesh)> = kin
        .doc
        .links
        .iter()
        .filter_map(|l| mesh(&urdf, l).map(|m| (l.name.clone(), m)))
        .collect();
    let joined = |a: &str, b: &str| {
        kin.doc.joints.iter().any(|j| {
            (j.parent.link == a && j.child.link == b) || (j.parent.link == b && j.child.link == a)
        })
    };
    let chain_names: Vec<String> = (1..=6).map(|i| format!("joint_{i}")).collect();
    let at = |q: &[f64; 6]| -> HashMap<String, Isometry3<f64>> {
        let m = chain_names.iter().cloned().zip(q.iter().copied()).collect();
        kin.poses(&m)
    };
    // Bounding spheres (link frame) skip pairs that are far apart: an exact mesh-mesh distance
    // is only needed when the spheres come within 5 cm (the margin is 1 cm).
    let spheres: Vec<(Point3<f64>, f64)> = meshes
        .iter()
        .map(|(_, m)| {
            let aabb = m.local_aabb();
            let c = aabb.center();
            let r = m
                .vertices()
                .iter()
                .map(|v| (v - c).norm())
                .fold(0.0, f64::max);
            (c, r)
        })
        .collect();
    let dist = |p: &HashMap<String, Isometry3<f64>>, a: usize, b: usize| {
        let (na, ma) = &meshes[a];
        let (nb, mb) = &meshes[b];
        let (ca, cb) = (p[na] * spheres[a].0, p[nb] * spheres[b].0);
        let gap = (ca - cb).norm() - spheres[a].1 - spheres[b].1;
        if gap > 0.05 {
            return gap;
        }
        parry3d_f64::query::distance(&p[na], ma, &p[nb], mb).expect("distance")
    };
    // Pairs: a passive link against every other link, except the one its joint connects it to
    // and those in contact by design (already within the margin at the home pose).
    let margin = 0.010;
    let home = at(&[0.0; 6]);
    let mut pairs = Vec::new();
    let mut by_design = Vec::new();
    for (a, (na, _)) in meshes.iter().enumerate() {
        if na != "cylinder" && na != "piston" {
            continue;
        }
        for (b, (nb, _)) in meshes.iter().enumerate() {
            if a == b || (nb == "cylinder" && na == "piston") || joined(na, nb) {
                continue;
            }
            if dist(&home, a, b) < margin {
                by_design.push(format!("{na}/{nb}"));
                continue;
            }
            pairs.push((a, b));
        }
    }
    let names = |p: &(usize, usize)| format!("{}/{}", meshes[p.0].0, meshes[p.1].0);
    eprintln!(
        "checked: {:?}; in contact by design: {by_design:?}",
        pairs.iter().map(names).collect::<Vec<_>>()
    );
    assert!(
        pairs.iter().any(|p| names(p) == "cylinder/link_2"),
        "the pair of the issue (cylinder / link_2) is checked"
    );

    let samples = along(&program_poses(&text), 1f64.to_radians());
    let worst = samples
        .par_iter()
        .map(|q| {
            let p = at(q);
            pairs
                .iter()
                .map(|pair| (dist(&p, pair.0, pair.1), *pair, *q))
                .min_by(|x, y| x.0.total_cmp(&y.0))
                .unwrap()
        })
        .min_by(|x, y| x.0.total_cmp(&y.0))
        .unwrap();
    eprintln!(
        "{} samples; smallest passive-link clearance {:.1} mm ({}; a lower bound above 50 mm) at q2 = {:.2} deg",
        samples.len(),
        worst.0 * 1e3,
        names(&worst.1),
        worst.2[1].to_degrees()
    );
    assert!(
        worst.0 >= margin,
        "{:.2} mm between {}",
        worst.0 * 1e3,
        names(&worst.1)
    );

    // The same meshes, where the issue found the overlap: q2 = −60°.
    let q = [0.0, (-60f64).to_radians(), 0.0, 0.0, 0.0, 0.0];
    let (c, l2) = (
        meshes.iter().position(|m| m.0 == "cylinder").unwrap(),
        meshes.iter().position(|m| m.0 == "link_2").unwrap(),
    );
    assert!(
        dist(&at(&q), c, l2) < margin,
        "the meshes meet near q2 = -60 deg"
    );
}

/// The NJ-130 URDF with a passive lever on link 1, moved by joint 2 through a mimic joint
/// (multiplier −1): for q2 above about 11.6° it swings into the robot's base.
fn lever_urdf(dir: &Path) -> std::path::PathBuf {
    let base = std::fs::read_to_string(nj130_urdf()).unwrap();
    let lever = r#"  <link name="balancer">
    <collision>
      <origin xyz="-0.2 0 0" rpy="0 0 0"/>
      <geometry><box size="0.4 0.12 0.12"/></geometry>
    </collision>
  </link>
  <joint name="balancer_joint" type="revolute">
    <parent link="link_1"/>
    <child link="balancer"/>
    <origin xyz="-0.45 0 0.55" rpy="0 -1.5707963267948966 -1.5707963267948966"/>
    <axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" velocity="1" effort="0"/>
    <mimic joint="axis_2" multiplier="-1.0"/>
  </joint>
"#;
    let path = dir.join("nj130_lever.urdf");
    std::fs::write(
        &path,
        base.replace(
            "  <link name=\"flange\"/>",
            &format!("{lever}  <link name=\"flange\"/>"),
        ),
    )
    .unwrap();
    path
}

#[test]
fn a_mimic_lever_that_hits_the_base_is_avoided_and_caught() {
    let dir = tempdir();
    let lever = lever_urdf(dir.path());
    let compile = |robot: &Path, out: &str| {
        let out = dir.path().join(out);
        let r = edbbgen([
            robot.as_os_str(),
            "--fixture".as_ref(),
            "258,1468,708".as_ref(),
            "-o".as_ref(),
            out.as_os_str(),
            "-q".as_ref(),
        ]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        (
            out.clone(),
            program_poses(&std::fs::read_to_string(out).unwrap()),
        )
    };
    // Without the lever the program uses q2 up to 20°; with it, it stays where the lever is
    // clear of the base (independently: the lever's end at the hinge angle q2 meets the base
    // cylinder, radius 0.3 m, once −0.45 + 0.4·sin(q2) + 0.06 > −0.3 − margin).
    let (plain, plain_poses) = compile(&nj130_urdf(), "plain.nc");
    let max_q2 = |p: &[[f64; 6]]| p.iter().map(|q| q[1]).fold(f64::MIN, f64::max);
    assert!(
        max_q2(&plain_poses) >= 15.0,
        "the plain program reaches q2 = {}",
        max_q2(&plain_poses)
    );
    let (with_lever, lever_poses) = compile(&lever, "lever.nc");
    let limit = ((-0.3 - 0.01 + 0.45 - 0.06) / 0.4f64).asin().to_degrees();
    assert!(
        max_q2(&lever_poses) < limit,
        "the lever program stays below q2 = {limit:.1} deg: {}",
        max_q2(&lever_poses)
    );
    let v = edbbgen(["verify".as_ref(), lever.as_os_str(), with_lever.as_os_str()]);
    assert_eq!(v.code, 0, "{}{}", v.stdout, v.stderr);
    // The plain program, checked on the robot with the lever, is refused naming the pair.
    let v = edbbgen(["verify".as_ref(), lever.as_os_str(), plain.as_os_str()]);
    assert_eq!(v.code, 1, "{}{}", v.stdout, v.stderr);
    assert!(
        v.stderr.contains("collision")
            && v.stderr.contains("balancer")
            && v.stderr.contains("link 0 (base)"),
        "{}",
        v.stderr
    );
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn joint_margin_keeps_every_program_off_the_limits_and_verify_checks_it() {
    // Every shipped cell's program stays ≥ 1° (the default margin) from every joint limit.
    let mut cells = vec![(nj130_dh(), crate::safety::nj130_cell())];
    for name in SHARED_ROBOTS {
        cells.push((shared_robot(name), crate::safety::test_cell(name)));
    }
    let dir = tempdir();
    for (robot, cell) in &cells {
        let out = dir.path().join("p.nc");
        let r = edbbgen([
            robot.as_os_str(),
            "--cell".as_ref(),
            cell.as_os_str(),
            "-o".as_ref(),
            out.as_os_str(),
            "--step".as_ref(),
            "20".as_ref(),
            "--max-candidates".as_ref(),
            "1500".as_ref(),
            "-q".as_ref(),
        ]);
        assert_eq!(r.code, 0, "{}: {}", robot.display(), r.stderr);
        let rob = load(robot);
        for q in program_poses(&std::fs::read_to_string(&out).unwrap()) {
            for i in 0..6 {
                let (lo, hi) = (
                    rob.joints[i].lower.to_degrees(),
                    rob.joints[i].upper.to_degrees(),
                );
                assert!(
                    q[i] >= lo + 1.0 - 1e-6 && q[i] <= hi - 1.0 + 1e-6,
                    "{}: joint {} at {} within 1 deg of {lo}..{hi}",
                    robot.display(),
                    i + 1,
                    q[i]
                );
            }
        }
    }
    // A hand-made program that goes to a limit (NJ-130 joint 2: -60 deg) fails with joint_limit,
    // and passes with the margin set to 0.
    // (Two pauses around nothing: the moves are made without the bar.)
    let text = "(hand-made)\nG21 G90 G94\nG61\nG0 X0 Y0 Z0 A0 B30 C0\nG0 X0 Y-60 Z0 A0 B30 C0\nM0\nM0\nM2\n";
    let p = dir.path().join("limit.nc");
    std::fs::write(&p, text).unwrap();
    let run = |extra: &[&str]| {
        let mut args = vec![
            "verify".to_string(),
            nj130_dh().display().to_string(),
            p.display().to_string(),
            "--fixture".into(),
            "258,1468,708".into(),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        edbbgen(&args)
    };
    let v = run(&[]);
    assert_eq!(v.code, 1, "{}{}", v.stdout, v.stderr);
    assert!(
        v.stderr.contains("joint_limit") && v.stderr.contains("joint 2"),
        "{}",
        v.stderr
    );
    assert!(
        v.stderr.contains("less the 1.00 deg joint margin"),
        "{}",
        v.stderr
    );
    let v = run(&["--joint-margin", "0"]);
    assert!(!v.stderr.contains("joint_limit"), "{}", v.stderr);
}

//! The J2/J3 coupling of a parallel-arm robot. ROS-Industrial drives the
//! ABB IRB 2400 with J23_coupled = true (its abb_driver sends ABB axis 3 = q3 + q2): on a
//! parallel-arm robot the controller's axis 3 is the forearm angle from the horizontal. The
//! `rapid` dialect writes that coupling for such a robot unless the cell states one; every
//! other dialect whose default is no coupling says, in the warnings, the report and the
//! program header, how the user states it (`[controller] j3_coupling`).

use crate::common::*;
use edbbgen::controller::parallel_arm;

fn irb2400() -> std::path::PathBuf {
    root().join("tests/robots/abb_irb2400/robot.urdf")
}

/// `--step 20 --max-candidates 600` at a fixture in front of the IRB 2400.
fn compile(
    robot: &std::path::Path,
    dialect: &str,
    out: &std::path::Path,
    cell: Option<&std::path::Path>,
) -> Run {
    let mut args = vec![
        robot.display().to_string(),
        "--fixture=800,0,600".into(),
        "--tool".into(),
        "60,30,120".into(),
        "--step".into(),
        "20".into(),
        "--max-candidates".into(),
        "600".into(),
        "--dialect".into(),
        dialect.into(),
        "-o".into(),
        out.display().to_string(),
    ];
    if let Some(c) = cell {
        args.extend(["--cell".into(), c.display().to_string()]);
    }
    let r = edbbgen(&args);
    assert_eq!(r.code, 0, "{dialect}: {}", r.stderr);
    r
}

/// The joint values of every MoveAbsJ of a RAPID module, as printed.
fn rapid_axes(text: &str) -> Vec<[f64; 6]> {
    text.lines()
        .filter_map(|l| l.split_once("MoveAbsJ [[").map(|(_, r)| r))
        .map(|r| {
            let v: Vec<f64> = r
                .split(']')
                .next()
                .unwrap()
                .split(',')
                .map(|x| x.trim().parse().unwrap())
                .collect();
            std::array::from_fn(|i| v[i])
        })
        .collect()
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn rapid_couples_j3_to_j2_on_a_parallel_arm_robot_and_says_so() {
    let dir = tempdir();
    let (ngc, rapid) = (dir.path().join("p.ngc"), dir.path().join("p.mod"));
    let report = dir.path().join("r.json");
    let r_ngc = compile(&irb2400(), "ngc", &ngc, None);
    let r_rapid = edbbgen([
        irb2400().display().to_string(),
        "--fixture=800,0,600".into(),
        "--tool".into(),
        "60,30,120".into(),
        "--step".into(),
        "20".into(),
        "--max-candidates".into(),
        "600".into(),
        "--dialect".into(),
        "rapid".into(),
        "-o".into(),
        rapid.display().to_string(),
        "--json".into(),
        report.display().to_string(),
    ]);
    assert_eq!(r_rapid.code, 0, "{}", r_rapid.stderr);
    let (ngc_text, rapid_text) = (
        std::fs::read_to_string(&ngc).unwrap(),
        std::fs::read_to_string(&rapid).unwrap(),
    );
    // The same plan; RAPID's axis 3 is ROS-Industrial's angles[2] + angles[1] (abb_driver's
    // J23_coupled), the ngc program's joints are the URDF's.
    let q = program_poses(&ngc_text);
    let c = rapid_axes(&rapid_text);
    assert_eq!(q.len(), c.len());
    assert!(
        q.iter().any(|q| q[1].abs() > 1.0),
        "the test needs poses with q2 != 0"
    );
    for (q, c) in q.iter().zip(&c) {
        for i in 0..6 {
            let want = if i == 2 { q[2] + q[1] } else { q[i] };
            assert!((c[i] - want).abs() < 1e-9, "axis {}: {c:?} vs {q:?}", i + 1);
        }
    }
    assert!(rapid_text.contains("! controller: rax_1 = q1, rax_2 = q2, rax_3 = q3 + q2,"));
    // Said in the header, the warnings and the report.
    let note = "is an ABB IRB 2400, a parallel-arm robot";
    let header_note = rapid_text
        .lines()
        .find(|l| l.trim_start().starts_with("! J3: "))
        .expect("the header note");
    assert!(
        header_note.contains(note) && header_note.contains("j3_coupling = 0"),
        "{header_note}"
    );
    assert!(r_rapid.stderr.contains(note), "{}", r_rapid.stderr);
    let rep: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert!(rep["warnings"].to_string().contains(note));
    // ngc keeps J3 = q3 and says how to state the coupling.
    assert!(ngc_text.contains("(controller: X = q1, Y = q2, Z = q3, A = q4,"));
    assert!(
        r_ngc
            .stderr
            .contains("set [controller] j3_coupling = \"auto\""),
        "{}",
        r_ngc.stderr
    );
    assert!(ngc_text.contains("(J3: the robot 'abb_irb2400' is an ABB IRB 2400"));
    // verify reads the RAPID program with the same mapping.
    let v = edbbgen([
        "verify".into(),
        irb2400().display().to_string(),
        rapid.display().to_string(),
        "--tool".into(),
        "60,30,120".into(),
    ]);
    assert_eq!(v.code, 0, "{}{}", v.stdout, v.stderr);

    // The cell states the coupling: no note, and its value is the one written.
    let cell = dir.path().join("c.toml");
    std::fs::write(&cell, "[controller]\nj3_coupling = 0\n").unwrap();
    let stated = dir.path().join("s.mod");
    let r = compile(&irb2400(), "rapid", &stated, Some(&cell));
    let text = std::fs::read_to_string(&stated).unwrap();
    assert!(
        !r.stderr.contains("J3: ") && !text.contains("! J3: "),
        "{}",
        r.stderr
    );
    for (q, c) in q.iter().zip(rapid_axes(&text)) {
        assert!((c[2] - q[2]).abs() < 1e-9);
    }
}

#[test]
fn a_parallelogram_is_found_in_the_linkage_and_nowhere_else() {
    // A URDF whose J3 motion reaches the forearm through a crank and a tie rod behind joint 3
    // (mimic joints on the upper arm, each link with its collision shape, which is how the
    // robot model keeps a passive link), under a name no list knows.
    let base = std::fs::read_to_string(irb2400()).unwrap();
    let linkage = r#"
  <link name="j3_crank">
    <collision>
      <origin xyz="-0.1 0 0" rpy="0 0 0"/>
      <geometry><box size="0.24 0.04 0.06"/></geometry>
    </collision>
  </link>
  <link name="tie_rod">
    <collision>
      <origin xyz="0 0 0.35" rpy="0 0 0"/>
      <geometry><cylinder radius="0.025" length="0.7"/></geometry>
    </collision>
  </link>
  <joint name="crank_joint" type="revolute">
    <parent link="link_2"/>
    <child link="j3_crank"/>
    <origin xyz="0 0.15 0" rpy="0 0 0"/>
    <axis xyz="0 1 0"/>
    <mimic joint="joint_3" multiplier="1"/>
    <limit effort="0" lower="-3" upper="3" velocity="10"/>
  </joint>
  <joint name="rod_joint" type="revolute">
    <parent link="j3_crank"/>
    <child link="tie_rod"/>
    <origin xyz="-0.2 0 0" rpy="0 0 0"/>
    <axis xyz="0 1 0"/>
    <mimic joint="joint_3" multiplier="-1"/>
    <limit effort="0" lower="-3" upper="3" velocity="10"/>
  </joint>
</robot>"#;
    let text = base
        .replace(
            "<robot name=\"abb_irb2400\">",
            "<robot name=\"parallel_arm_test\">",
        )
        .replace("</robot>", linkage);
    let dir = tempdir();
    let path = dir.path().join("robot.urdf");
    std::fs::write(&path, text).unwrap();
    let why = parallel_arm(&load(&path)).expect("the linkage is a parallelogram");
    assert!(why.contains("'j3_crank'"), "{why}");
    // The shared robots: the IRB 6700's balancing cylinder follows q2, not q3; the others have
    // no linkage and names no list holds; the TX2-90 and the NJ-130 are serial arms.
    for name in SHARED_ROBOTS {
        assert_eq!(parallel_arm(&load(&shared_robot(name))), None, "{name}");
    }
    assert_eq!(parallel_arm(&load(&nj130_dh())), None);
    assert_eq!(
        parallel_arm(&load(
            &root().join("tests/robots/staubli_tx2_90/robot.urdf")
        )),
        None
    );
    assert!(parallel_arm(&load(&irb2400())).is_some());
}

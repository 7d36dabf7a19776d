//! Bad input: exit 2, one line on stderr naming the problem, no output file.

use crate::common::*;

fn check_rejected(args: &[&str], needle: &str) {
    let dir = tempdir();
    let out = dir.path().join("out.nc");
    let mut all: Vec<String> = args.iter().map(|s| s.to_string()).collect();
    all.push("-o".into());
    all.push(out.display().to_string());
    let r = edbbgen(&all);
    assert_eq!(r.code, 2, "args {args:?}: stderr {}", r.stderr);
    let lines: Vec<&str> = r.stderr.lines().collect();
    assert_eq!(lines.len(), 1, "one line expected, got: {}", r.stderr);
    assert!(lines[0].starts_with("edbbgen: error: "), "{}", lines[0]);
    assert!(
        lines[0].contains(needle),
        "'{}' should name '{needle}'",
        lines[0]
    );
    assert!(!out.exists(), "no output on error");
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(leftovers.is_empty(), "no temp files left behind");
}

#[test]
fn missing_robot_file() {
    check_rejected(
        &["/nonexistent/robot.urdf", "--fixture", "258,1468,708"],
        "/nonexistent/robot.urdf",
    );
}

#[test]
fn malformed_urdf() {
    let dir = tempdir();
    let p = dir.path().join("broken.urdf");
    std::fs::write(&p, "<robot name=\"x\"><link name=\"a\"></robot").unwrap();
    check_rejected(
        &[p.to_str().unwrap(), "--fixture", "258,1468,708"],
        "broken.urdf",
    );
}

#[test]
fn urdf_with_five_revolute_joints() {
    let dir = tempdir();
    let p = dir.path().join("five.urdf");
    let mut s = String::from("<robot name=\"five\"><link name=\"l0\"/>");
    for i in 1..=5 {
        s += &format!(
            "<link name=\"l{i}\"/><joint name=\"j{i}\" type=\"revolute\"><parent link=\"l{}\"/><child link=\"l{i}\"/>\
             <origin xyz=\"0 0 0.3\"/><axis xyz=\"0 1 0\"/><limit lower=\"-1\" upper=\"1\" velocity=\"1\" effort=\"0\"/></joint>",
            i - 1
        );
    }
    s += "</robot>";
    std::fs::write(&p, s).unwrap();
    check_rejected(
        &[p.to_str().unwrap(), "--fixture", "258,1468,708"],
        "5 revolute joints",
    );
}

#[test]
fn fixture_out_of_reach() {
    check_rejected(
        &[nj130_dh().to_str().unwrap(), "--fixture", "9000,0,500"],
        "out of reach",
    );
}

#[test]
fn non_numeric_fixture() {
    check_rejected(
        &[nj130_dh().to_str().unwrap(), "--fixture", "258,abc,708"],
        "--fixture",
    );
}

#[test]
fn nan_fixture() {
    check_rejected(
        &[nj130_dh().to_str().unwrap(), "--fixture", "258,NaN,708"],
        "--fixture",
    );
}

#[test]
fn empty_shell() {
    check_rejected(
        &[
            nj130_dh().to_str().unwrap(),
            "--fixture",
            "258,1468,708",
            "--bar",
            "10..20",
        ],
        "empty shell",
    );
}

#[test]
fn malformed_bar_range() {
    check_rejected(
        &[
            nj130_dh().to_str().unwrap(),
            "--fixture",
            "258,1468,708",
            "--bar",
            "520..300",
        ],
        "--bar",
    );
}

#[test]
fn malformed_dh_toml_names_the_line() {
    let dir = tempdir();
    let p = dir.path().join("bad.dh.toml");
    let text =
        std::fs::read_to_string(nj130_dh())
            .unwrap()
            .replacen("a = 860.0", "a = \"long\"", 1);
    std::fs::write(&p, text).unwrap();
    check_rejected(&[p.to_str().unwrap(), "--fixture", "258,1468,708"], "line");
}

#[test]
fn dh_with_wrong_joint_count() {
    let dir = tempdir();
    let p = dir.path().join("five.dh.toml");
    let text = std::fs::read_to_string(nj130_dh()).unwrap();
    let cut = text.rfind("[[joints]]").unwrap();
    std::fs::write(&p, &text[..cut]).unwrap();
    check_rejected(
        &[p.to_str().unwrap(), "--fixture", "258,1468,708"],
        "5 joints",
    );
}

#[test]
fn unknown_flag_is_one_line() {
    check_rejected(
        &[
            nj130_dh().to_str().unwrap(),
            "--fixture",
            "258,1468,708",
            "--frobnicate",
        ],
        "--frobnicate",
    );
}

#[test]
fn poses_below_parameter_count() {
    check_rejected(
        &[
            nj130_dh().to_str().unwrap(),
            "--fixture",
            "258,1468,708",
            "--poses",
            "5",
            "--step",
            "20",
        ],
        "--poses",
    );
}

#[test]
fn negative_values_reach_the_value_check() {
    // A negative number is a value, not an unknown flag: its own check names it.
    let nj = nj130_dh();
    let nj = nj.to_str().unwrap();
    for (flag, value, needle) in [
        ("--margin", "-1", "--margin: -1 mm must be between"),
        ("--blend", "-5", "--blend: -5 mm is outside"),
        ("--step", "-5", "'-5' for '--step <DEG>'"),
        ("--ball", "-25", "--ball"),
    ] {
        check_rejected(&[nj, "--fixture", "258,1468,708", flag, value], needle);
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn negative_coordinates_are_accepted_in_every_form() {
    let dir = tempdir();
    let out = dir.path().join("p.nc");
    let nj = nj130_dh();
    let common = [
        "--step",
        "20",
        "--max-candidates",
        "600",
        "-o",
        out.to_str().unwrap(),
    ];
    for form in [
        vec![
            "--fixture",
            "-100,1468,708",
            "--tool",
            "-60,30,120",
            "--start",
            "-10,-5,0,0,0,0",
        ],
        vec![
            "--fixture=-100,1468,708",
            "--tool=-60,30,120",
            "--start=-10,-5,0,0,0,0",
        ],
    ] {
        let mut args = vec![nj.to_str().unwrap()];
        args.extend(form.iter());
        args.extend(common.iter());
        let r = edbbgen(&args);
        assert_eq!(r.code, 0, "{form:?}: {}", r.stderr);
        let text = std::fs::read_to_string(&out).unwrap();
        assert!(
            text.contains("(fixture: -100.000, 1468.000, 708.000 mm"),
            "{form:?}"
        );
        assert!(
            text.contains("(MAP: -60.000, 30.000, 120.000 mm"),
            "{form:?}"
        );
    }
}

/// Inputs far larger than any real one are refused by their size, before they are read
/// (sparse files: nothing is written to disk).
#[test]
fn oversized_inputs_are_refused_before_reading() {
    let dir = tempdir();
    let csv = dir.path().join("huge.csv");
    std::fs::File::create(&csv)
        .unwrap()
        .set_len(90 << 30)
        .unwrap();
    let r = edbbgen([
        "diagnose",
        nj130_dh().to_str().unwrap(),
        "--fixture",
        "258,1468,708",
        "--measured",
        csv.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert_eq!(r.stderr.lines().count(), 1, "{}", r.stderr);
    assert!(
        r.stderr.contains("huge.csv") && r.stderr.contains("90.0 GiB"),
        "{}",
        r.stderr
    );
    // A URDF whose collision mesh claims 5 GB.
    let stl = dir.path().join("link.stl");
    std::fs::File::create(&stl)
        .unwrap()
        .set_len(5 << 30)
        .unwrap();
    let urdf = std::fs::read_to_string(nj130_urdf()).unwrap();
    let first_box = urdf.find("<box").expect("a box to replace");
    let end = first_box + urdf[first_box..].find("/>").unwrap() + 2;
    let with_mesh = format!(
        "{}<mesh filename=\"link.stl\"/>{}",
        &urdf[..first_box],
        &urdf[end..]
    );
    let p = dir.path().join("robot.urdf");
    std::fs::write(&p, with_mesh).unwrap();
    check_rejected(
        &[p.to_str().unwrap(), "--fixture", "258,1468,708"],
        "link.stl",
    );
}

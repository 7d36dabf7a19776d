//! `verify PROGRAM` checks every limit the program header states (bar
//! range, safety margin, joint margin, corner blend) unless a flag or the cell states it, in
//! every dialect; an explicit flag still wins, and a header looser than it is reported.

use crate::common::*;

const DIALECTS: &[(&str, &str)] = &[
    ("ngc", "ngc"),
    ("sinumerik", "mpf"),
    ("krl", "src"),
    ("rapid", "mod"),
    ("urscript", "script"),
    ("fanuc", "ls"),
];

fn verify(program: &std::path::Path, extra: &[&str]) -> Run {
    let mut args = vec![
        "verify".to_string(),
        nj130_dh().display().to_string(),
        program.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    edbbgen(&args)
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn verify_takes_the_bar_range_margins_and_blend_from_the_header_in_every_dialect() {
    let dir = tempdir();
    for (dialect, ext) in DIALECTS {
        // A bar of 200..330 mm, half the default margin and joint margin: poses the defaults
        // (300..520 mm, 10 mm, 1 deg) refuse.
        let out = dir.path().join(format!("EDBB.{ext}"));
        let r = edbbgen([
            nj130_dh().display().to_string(),
            "--fixture".into(),
            "258,1468,708".into(),
            "--bar".into(),
            "200..330".into(),
            "--margin".into(),
            "5".into(),
            "--joint-margin".into(),
            "0.5".into(),
            "--step".into(),
            "20".into(),
            "--dialect".into(),
            dialect.to_string(),
            "-o".into(),
            out.display().to_string(),
        ]);
        assert_eq!(r.code, 0, "{dialect}: {}", r.stderr);
        let text = std::fs::read_to_string(&out).unwrap();
        // Independently of verify: the program does leave the default bar range.
        let robot = load(&nj130_dh());
        let d = edbbgen::dialect::by_name(dialect).unwrap();
        let parsed = d.read(&text, &d.default_map(&robot).unwrap()).unwrap();
        let fix = nalgebra::Vector3::new(0.258, 1.468, 0.708);
        let tool = robot.tool.unwrap();
        let shortest = parsed
            .targets()
            .map(|(_, q)| (robot.point(&q.map(f64::to_radians), &tool) - fix).norm() * 1e3)
            .fold(f64::INFINITY, f64::min);
        assert!(shortest < 300.0, "{dialect}: shortest bar {shortest} mm");

        // A plain verify checks what the header states.
        let v = verify(&out, &["--json"]);
        assert_eq!(v.code, 0, "{dialect}: {}{}", v.stdout, v.stderr);
        let j: serde_json::Value = serde_json::from_str(&v.stdout).unwrap();
        let lim = &j["limits"];
        assert_eq!(
            lim["bar_mm"],
            serde_json::json!([200.0, 330.0]),
            "{dialect}"
        );
        assert_eq!(lim["margin_mm"], 5.0, "{dialect}");
        assert_eq!(lim["joint_margin_deg"], 0.5, "{dialect}");
        assert_eq!(lim["blend_mm"], 10.0, "{dialect}");
        for k in ["bar", "safety margin", "joint margin", "corner blend"] {
            assert_eq!(lim["from"][k], "header", "{dialect} {k}");
        }
        // An explicit flag wins, and the looser header is reported.
        let v = verify(&out, &["--bar", "300..520"]);
        assert_eq!(v.code, 1, "{dialect}: {}{}", v.stdout, v.stderr);
        assert!(
            v.stderr.contains(
                "the program header states bar range 200.0..330.0 mm, wider than the 300.0..520.0 mm this check uses"
            ) && v.stderr.contains("bar_length"),
            "{dialect}: {}",
            v.stderr
        );
        let v = verify(&out, &["--margin", "8", "--joint-margin", "0.5"]);
        assert!(
            v.stderr
                .contains("states safety margin 5.0 mm, less than the 8.0 mm this check uses"),
            "{dialect}: {}",
            v.stderr
        );
        assert!(
            !v.stderr.contains("joint margin 0.5"),
            "{dialect}: {}",
            v.stderr
        );
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_header_that_states_less_than_the_program_does_fails() {
    // The header is read, not ignored: a bar range or a corner blend edited below what the
    // program's moves do fails a plain verify, naming the limit.
    let dir = tempdir();
    let out = dir.path().join("p.nc");
    let r = edbbgen([
        nj130_dh().display().to_string(),
        "--fixture".into(),
        "258,1468,708".into(),
        "--step".into(),
        "20".into(),
        "-o".into(),
        out.display().to_string(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(verify(&out, &[]).code == 0);
    let line = "(bar range: 300.0..520.0 mm; corner blend: 10.0 mm; safety margin: 10.0 mm; joint margin: 1.0 deg)";
    assert!(text.contains(line));
    for (edit, needle) in [
        (
            "(bar range: 300.0..400.0 mm; corner blend: 10.0 mm; safety margin: 10.0 mm; joint margin: 1.0 deg)",
            "bar_length",
        ),
        (
            "(bar range: 300.0..520.0 mm; corner blend: ten mm; safety margin: 10.0 mm; joint margin: 1.0 deg)",
            "corner blend 'ten' is not a number of mm",
        ),
    ] {
        let p = dir.path().join("edited.nc");
        std::fs::write(&p, text.replace(line, edit)).unwrap();
        let v = verify(&p, &[]);
        assert_ne!(v.code, 0, "{edit}");
        assert!(v.stderr.contains(needle), "{edit}: {}", v.stderr);
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_tcp_blend_above_the_header_s_corner_blend_fails() {
    // KRL's C_DIS is a TCP distance (mm at the MAP), the header's kind of corner blend: a
    // header edited below the program's C_DIS fails, naming the limit.
    let dir = tempdir();
    let out = dir.path().join("EDBB.src");
    let r = edbbgen([
        nj130_dh().display().to_string(),
        "--fixture".into(),
        "258,1468,708".into(),
        "--step".into(),
        "20".into(),
        "--dialect".into(),
        "krl".into(),
        "-o".into(),
        out.display().to_string(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(text.contains("C_DIS"), "the program blends no corner");
    assert_eq!(verify(&out, &[]).code, 0);
    let p = dir.path().join("edited.src");
    std::fs::write(
        &p,
        text.replace("corner blend: 10.0 mm", "corner blend: 4.0 mm"),
    )
    .unwrap();
    let v = verify(&p, &[]);
    assert_eq!(v.code, 1, "{}", v.stderr);
    assert!(
        v.stderr
            .contains("more than the 4.0 mm corner blend the program header states"),
        "{}",
        v.stderr
    );
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn verify_reads_the_header_s_joint_accelerations_and_names_a_difference() {
    // The header states the accelerations the program's times assume (per controller axis):
    // verify checks with the robot's, lists them, and says where the header's differ.
    let dir = tempdir();
    let out = dir.path().join("p.nc");
    let r = edbbgen([
        nj130_dh().display().to_string(),
        "--fixture".into(),
        "258,1468,708".into(),
        "--step".into(),
        "20".into(),
        "-o".into(),
        out.display().to_string(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let text = std::fs::read_to_string(&out).unwrap();
    let line = text
        .lines()
        .find(|l| l.starts_with("(joint accelerations: "))
        .expect("the header states the accelerations")
        .to_string();
    // The robot's, independently of verify: its file's, in deg/s^2.
    let robot = load(&nj130_dh());
    let want = robot.max_accelerations().map(f64::to_degrees);
    let v = verify(&out, &["--json"]);
    assert_eq!(v.code, 0, "{}", v.stderr);
    let j: serde_json::Value = serde_json::from_str(&v.stdout).unwrap();
    let got: Vec<f64> = serde_json::from_value(j["limits"]["accelerations_deg"].clone()).unwrap();
    for i in 0..6 {
        assert!((got[i] - want[i]).abs() < 1e-9, "{got:?} {want:?}");
    }
    assert_eq!(j["limits"]["from"]["joint accelerations"], "robot file");
    assert!(!v
        .stdout
        .contains("the program header states joint accelerations"));
    // The header's first acceleration doubled: still verified (the check uses the robot's),
    // with a note naming both.
    let values: Vec<&str> = line["(joint accelerations: ".len()..]
        .trim_end_matches(" deg/s^2)")
        .split(", ")
        .collect();
    assert_eq!(values.len(), 6, "{line}");
    let doubled = format!("{:.1}", values[0].parse::<f64>().unwrap() * 2.0);
    let edited = line.replacen(values[0], &doubled, 1);
    let p = dir.path().join("edited.nc");
    std::fs::write(&p, text.replace(&line, &edited)).unwrap();
    let v = verify(&p, &[]);
    assert_eq!(v.code, 0, "{}", v.stderr);
    assert!(
        v.stderr.contains(&format!(
            "the program header states joint accelerations {doubled}, "
        )) && v.stderr.contains("this check uses the robot's"),
        "{}",
        v.stderr
    );
    // Not a number: refused, naming the field.
    std::fs::write(
        &p,
        text.replace(&line, "(joint accelerations: fast deg/s^2)"),
    )
    .unwrap();
    let v = verify(&p, &[]);
    assert_eq!(v.code, 2, "{}", v.stderr);
    assert!(
        v.stderr.contains("joint accelerations 'fast'"),
        "{}",
        v.stderr
    );
}

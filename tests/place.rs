//! `edbbgen place`: where the fixture goes, by what a calibration from a program
//! compiled there would reach. Checked against what is independently known: the geometry of
//! the joint-1 axis, the reach of the arm, and — for a campaign — what `calibrate` makes of
//! simulated data of the very programs the written cell files compile.

use crate::calibrate::{dh_errors, file_points, joint_space, registered_um, true_points};
use crate::common::*;
use edbbgen::model::MeasurementModel;
use edbbgen::twin::{self, SimOptions, Truth};
use edbbgen::verify::gcode;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::Value;
use std::path::{Path, PathBuf};

fn nj130_cell() -> PathBuf {
    root().join("robots/comau_nj130/cell.toml")
}

/// Runs `place` on the NJ-130 cell with `extra` flags; returns the JSON report and stdout.
fn place(dir: &Path, tag: &str, extra: &[&str]) -> (Value, String) {
    let json = dir.join(format!("{tag}.json"));
    let mut args: Vec<String> = vec![
        "place".into(),
        nj130_dh().display().to_string(),
        "--cell".into(),
        nj130_cell().display().to_string(),
        "--json".into(),
        json.display().to_string(),
    ];
    args.extend(extra.iter().map(|s| s.to_string()));
    let r = edbbgen(&args);
    assert_eq!(r.code, 0, "{tag}: {}", r.stderr);
    let v: Value = serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    assert_eq!(v["schema"], "edbbgen.place/1");
    (v, r.stdout)
}

/// The candidate at `mm` (given with --at or the cell's fixture).
fn at(v: &Value, mm: [f64; 3]) -> &Value {
    v["candidates"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| {
            let f = c["fixture_mm"].as_array().unwrap();
            (0..3).all(|k| (f[k].as_f64().unwrap() - mm[k]).abs() < 1e-6)
        })
        .unwrap_or_else(|| panic!("no candidate at {mm:?}"))
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

const PAPER: [f64; 3] = [258.0, 1468.0, 708.0];

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn the_papers_fixture_is_ranked_and_the_joint1_axis_and_the_edge_of_reach_rank_poorly() {
    let dir = tempdir();
    let axis = [0.0, 0.0, 1400.0];
    // At the edge of reach: the NJ-130 reaches about 2.3 m from its axis at this height.
    let edge = [2500.0, 0.0, 600.0];
    let (v, stdout) = place(
        dir.path(),
        "nj130",
        &[
            "--region",
            "0..1600,-1600..1600,400..1600",
            "--grid",
            "3,3,2",
            "--top",
            "3",
            "--at",
            "0,0,1400",
            "--at",
            "2500,0,600",
        ],
    );
    let n = v["ranking"].as_array().unwrap().len();
    let paper = at(&v, PAPER);
    assert_eq!(paper["source"], "current");
    assert_eq!(
        paper["estimate"], "compile",
        "the cell's fixture is compiled"
    );
    let paper_rank = paper["rank"]
        .as_u64()
        .expect("the paper's fixture is ranked") as usize;
    let paper_um = f(&paper["score_um"]);
    assert_eq!(paper["full"]["determined"], 22, "{paper}");
    assert!(paper_um < 2.0, "{paper}");
    assert_eq!(v["current"]["rank"].as_u64(), Some(paper_rank as u64));
    assert!(
        stdout.contains(&format!("rank {paper_rank} of {n}")),
        "the text names the cell's fixture's rank:\n{stdout}"
    );

    // The edge of reach: few poses reach the shell, the ones that do are alike (cond), and the
    // parameters they cannot separate cost their prior (prediction).
    let e = at(&v, edge);
    let e_rank = e["rank"].as_u64().expect("usable, but poor") as usize;
    assert!(e_rank > n / 2, "edge of reach ranks {e_rank} of {n}");
    let why = format!("edge {e}\npaper {paper}");
    assert!(
        f(&e["proxy"]["admitted"]) < 0.5 * f(&paper["proxy"]["admitted"]),
        "pool: {why}"
    );
    assert!(
        f(&e["full"]["cond"]) > 10.0 * f(&paper["full"]["cond"]),
        "cond: {why}"
    );
    assert!(f(&e["score_um"]) > 100.0 * paper_um, "prediction: {why}");
    assert!(!e["full"]["weak"].as_array().unwrap().is_empty(), "{why}");

    // On the joint-1 axis the stand would run up through the robot's base: no pose is free.
    let a = at(&v, axis);
    assert_eq!(a["status"], "no_valid_pose", "{a}");
    assert!(a["rank"].is_null() && a["proxy"].is_null(), "{a}");
    assert!(
        a["why"].as_str().unwrap().contains("every one collides"),
        "{a}"
    );

    // Hung from above instead (no stand), it is usable, with a large pool, and still poor:
    // q1 turns the MAP about the axis through the fixture, so L does not depend on q1 ...
    let robot = load(&nj130_dh());
    let model = MeasurementModel::new(
        &robot,
        Vector3::from(axis) * 1e-3,
        Vector3::new(0.06, 0.03, 0.12),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..20 {
        let mut q: [f64; 6] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
        let l = model.length(&model.nominal, &q);
        q[0] += rng.random_range(-2.0..2.0);
        assert!((model.length(&model.nominal, &q) - l).abs() < 1e-12);
    }
    // ... and the bar sees only what the remaining joints reveal: parameters go unseen.
    let (h, _) = place(
        dir.path(),
        "hung",
        &[
            "--grid", "1,1,1", "--top", "1", "--stand", "0", "--at", "0,0,1400",
        ],
    );
    let a = at(&h, axis);
    let paper = at(&h, PAPER);
    let why = format!("axis {a}\npaper {paper}");
    assert_eq!(a["status"], "ok", "{why}");
    assert!(a["rank"].as_u64().unwrap() > paper["rank"].as_u64().unwrap());
    assert!(
        f(&a["proxy"]["admitted"]) > f(&paper["proxy"]["admitted"]),
        "not for lack of poses: {why}"
    );
    assert!(f(&a["full"]["identifiable"]) < 22.0, "{why}");
    assert!(
        f(&a["full"]["cond"]) > 5.0 * f(&paper["full"]["cond"]),
        "cond: {why}"
    );
    assert!(f(&a["score_um"]) > 100.0 * f(&paper["score_um"]), "{why}");
    assert!(!a["full"]["weak"].as_array().unwrap().is_empty(), "{why}");
}

/// Simulates `program` on the NJ-130 with geometric errors `geometric` and 1 µm noise.
fn simulate(program: &str, geometric: [f64; 30], fixture_mm: [f64; 3], seed: u64) -> String {
    let robot = load(&nj130_dh());
    let model = MeasurementModel::new(
        &robot,
        Vector3::from(fixture_mm) * 1e-3,
        Vector3::new(0.06, 0.03, 0.12),
    );
    let truth = Truth {
        geometric,
        noise: 1e-6,
        ..Truth::default()
    };
    let parsed = gcode::parse(program).expect("program parses");
    twin::simulate(
        &robot,
        &model,
        &parsed,
        &truth,
        &SimOptions { rate: 50.0, seed },
    )
    .expect("simulates")
    .to_csv()
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_three_fixture_campaign_beats_the_best_single_fixture_and_calibrate_confirms_it() {
    let dir = tempdir();
    let prefix = dir.path().join("camp");
    let (v, stdout) = place(
        dir.path(),
        "camp",
        &[
            "--region",
            "0..1600,-1600..1600,400..1600",
            "--grid",
            "3,3,2",
            "--top",
            "4",
            "--count",
            "3",
            "--write-cell",
            prefix.to_str().unwrap(),
        ],
    );
    let c = &v["campaign"];
    let predicted = f(&c["predicted_um"]);
    let single = f(&c["best_single_um"]);
    eprintln!("{stdout}");
    assert!(
        single >= 1.5 * predicted,
        "campaign {predicted} um vs best single {single} um"
    );
    // More than measuring the best position three times: the positions complement each other.
    assert!(f(&c["best_single_repeated_um"]) > 1.1 * predicted, "{c}");
    let members: Vec<usize> = c["members"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m.as_u64().unwrap() as usize)
        .collect();
    assert_eq!(members.len(), 3);

    // The next command is the compile: each written cell compiles the program that was
    // estimated (the same header prediction), and a campaign of those programs ...
    let mut programs = Vec::new();
    for (k, &m) in members.iter().enumerate() {
        let cell = PathBuf::from(format!("{}-{}.cell.toml", prefix.display(), k + 1));
        assert!(
            stdout.contains(&format!("wrote {}", cell.display())),
            "{stdout}"
        );
        let prog = dir.path().join(format!("run{k}.nc"));
        let r = edbbgen([
            nj130_dh().to_str().unwrap(),
            "--cell",
            cell.to_str().unwrap(),
            "-o",
            prog.to_str().unwrap(),
            "--step",
            "20",
            "--max-candidates",
            "600",
        ]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let text = std::fs::read_to_string(&prog).unwrap();
        let header: f64 = text
            .lines()
            .find_map(|l| l.strip_prefix("(predicted MAP position uncertainty after calibration: "))
            .and_then(|l| l.split_whitespace().next())
            .and_then(|x| x.parse().ok())
            .expect("header states its prediction");
        let estimated = f(&v["candidates"][m]["full"]["compile_predicted_um"]);
        assert!(
            (header - estimated).abs() <= 0.01 * estimated + 0.005,
            "run {k}: compiled {header} um, estimated {estimated} um"
        );
        let fx: Vec<f64> = v["candidates"][m]["fixture_mm"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        programs.push((text, [fx[0], fx[1], fx[2]]));
    }

    // ... calibrated together from simulated data reaches what was predicted (within 2×),
    // and calibrate's own statement agrees.
    let robot = load(&nj130_dh());
    let model = MeasurementModel::new(
        &robot,
        Vector3::from(programs[0].1) * 1e-3,
        Vector3::new(0.06, 0.03, 0.12),
    );
    let mut realised = Vec::new();
    let mut stated = Vec::new();
    for r in 0..3u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(500 + r);
        let geometric = dh_errors(&mut rng);
        let mut args: Vec<String> = vec!["calibrate".into(), nj130_dh().display().to_string()];
        for (k, (text, fx)) in programs.iter().enumerate() {
            let csv = dir.path().join(format!("m{r}_{k}.csv"));
            std::fs::write(&csv, simulate(text, geometric, *fx, 10 * r + k as u64)).unwrap();
            args.extend([
                "--measured".into(),
                csv.display().to_string(),
                "--fixture".into(),
                format!("{},{},{}", fx[0], fx[1], fx[2]),
            ]);
        }
        let out = dir.path().join(format!("cal{r}.dh.toml"));
        let json = dir.path().join(format!("cal{r}.json"));
        // place predicts for fixtures known in the robot's frame (they are, here): held.
        args.extend([
            "--fixture-known".into(),
            "--effects".into(),
            "none".into(),
            "-o".into(),
            out.display().to_string(),
            "--json".into(),
            json.display().to_string(),
        ]);
        let res = edbbgen(&args);
        assert_eq!(res.code, 0, "{}", res.stderr);
        let rep: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        stated.push(f(&rep["predicted_position_std_um"]["workspace_rms"]));
        let qs = joint_space(&robot, 2000, r);
        let truth = Truth {
            geometric,
            ..Truth::default()
        };
        realised.push(registered_um(
            &file_points(&out, &qs),
            &true_points(&model, &truth, &qs),
        ));
    }
    realised.sort_by(f64::total_cmp);
    let median = realised[1];
    eprintln!("campaign predicted {predicted} um; realised {realised:?} um; calibrate states {stated:?} um");
    assert!(
        median < 2.0 * predicted && predicted < 2.0 * median,
        "predicted {predicted} um, realised median {median} um"
    );
    for s in stated {
        assert!(
            s < 2.0 * predicted && predicted < 2.0 * s,
            "calibrate states {s} um, place predicted {predicted} um"
        );
    }
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn the_report_is_golden_and_the_same_on_any_thread_count_and_draws_in_a_browser() {
    let dir = tempdir();
    let run = |threads: &str| {
        let json = dir.path().join(format!("p{threads}.json"));
        let html = dir.path().join(format!("p{threads}.html"));
        let r = edbbgen_env(
            [
                "place",
                nj130_dh().to_str().unwrap(),
                "--cell",
                nj130_cell().to_str().unwrap(),
                "--region",
                "0..1200,800..1600,500..900",
                "--grid",
                "2,2,2",
                "--top",
                "2",
                "--json",
                json.to_str().unwrap(),
                "--html",
                html.to_str().unwrap(),
            ],
            &[("RAYON_NUM_THREADS", threads)],
        );
        assert_eq!(r.code, 0, "{}", r.stderr);
        (
            r.stdout,
            std::fs::read_to_string(&json).unwrap(),
            std::fs::read_to_string(&html).unwrap(),
            html,
        )
    };
    let (text1, json1, html1, page) = run("1");
    let (text2, json2, html2, _) = run("2");
    assert_eq!(json1, json2, "JSON byte-identical on 1 and 2 threads");
    assert_eq!(html1, html2, "page byte-identical on 1 and 2 threads");
    assert_eq!(text1, text2);
    assert!(!json1.contains("/work") && !json1.contains(env!("CARGO_MANIFEST_DIR")));
    crate::snapshots::assert_golden("place@nj130_small", &json1);
    assert!(
        text1.contains("best: ") && text1.contains("cell's fixture"),
        "{text1}"
    );
    crate::report::assert_page_draws(&page, "place", &["fig-candidates"]);
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn a_urdf_robot_places_and_names_its_obstacles() {
    // The KR 120's convex hulls, a table across part of the region: positions over the table
    // have no room for the stand (named), the others are scored.
    let dir = tempdir();
    let cell = dir.path().join("cell.toml");
    let base =
        std::fs::read_to_string(root().join("tests/cells/kuka_kr120_r2500pro.toml")).unwrap();
    std::fs::write(
        &cell,
        format!("{base}\n[[environment]]\nname = \"table\"\ntype = \"box\"\nsize = [800.0, 3000.0, 600.0]\norigin = [2000.0, 0.0, 300.0]\n"),
    )
    .unwrap();
    let json = dir.path().join("k.json");
    let r = edbbgen([
        "place",
        shared_robot("kuka_kr120_r2500pro").to_str().unwrap(),
        "--cell",
        cell.to_str().unwrap(),
        "--region",
        "1000..2200,-600..600,700..1300",
        "--grid",
        "3,2,2",
        "--top",
        "1",
        "--json",
        json.to_str().unwrap(),
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let v: Value = serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    let cands = v["candidates"].as_array().unwrap();
    let over_table = cands
        .iter()
        .filter(|c| f(&c["fixture_mm"][0]) > 2000.0)
        .collect::<Vec<_>>();
    assert!(!over_table.is_empty());
    for c in over_table {
        assert_eq!(c["status"], "no_room", "{c}");
        assert_eq!(c["with"], "table", "{c}");
    }
    assert!(!v["ranking"].as_array().unwrap().is_empty(), "{v}");
    let best = &v["candidates"][v["ranking"][0].as_u64().unwrap() as usize];
    assert_eq!(best["estimate"], "compile");
}

#[test]
#[ignore = "slow tier: `make test` runs it"]
fn bad_input_exits_2_with_one_line_and_writes_nothing() {
    let dir = tempdir();
    let json = dir.path().join("r.json");
    let robot = nj130_dh();
    let cell = nj130_cell();
    let base: Vec<String> = vec![
        "place".into(),
        robot.display().to_string(),
        "--json".into(),
        json.display().to_string(),
    ];
    // A cell whose obstacles leave no room: a slab over the whole front of the robot.
    let crowded = dir.path().join("crowded.toml");
    std::fs::write(
        &crowded,
        "[[environment]]\nname = \"slab\"\ntype = \"box\"\nsize = [6000.0, 12000.0, 4000.0]\norigin = [2950.0, 0.0, 2000.0]\n",
    )
    .unwrap();
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["--region", "9000..10000,0..500,0..500", "--grid", "2,2,2"],
            "--region",
        ),
        (
            vec!["--cell", crowded.to_str().unwrap(), "--grid", "3,3,2"],
            "crowded.toml: no room for the fixture",
        ),
        (vec!["--region", "0..1,2..1,0..1"], "--region"),
        (vec!["--region", "0..1000"], "--region"),
        (vec!["--grid", "0,2,2"], "--grid"),
        (vec!["--count", "0"], "--count"),
        (vec!["--stand", "-5"], "--stand"),
        (vec!["--at", "1,2"], "--at"),
        (vec!["--cell", "missing.toml"], "missing.toml"),
        (
            vec![
                "--cell",
                cell.to_str().unwrap(),
                "--region",
                "0..1600,-1600..1600,400..1600",
                "--grid",
                "2,1,1",
                "--count",
                "9",
            ],
            "--count 9",
        ),
    ];
    for (extra, says) in cases {
        let mut args = base.clone();
        args.extend(extra.iter().map(|s| s.to_string()));
        let r = edbbgen(&args);
        assert_eq!(r.code, 2, "{extra:?}: {}{}", r.stdout, r.stderr);
        let lines: Vec<&str> = r.stderr.lines().collect();
        assert_eq!(lines.len(), 1, "{extra:?}: one line: {}", r.stderr);
        assert!(lines[0].contains(says), "{extra:?}: {}", lines[0]);
        assert!(!json.exists(), "{extra:?}: no partial output");
    }
}

//! `edbbgen model`: identifiability as in the paper (Section 2.1.2).

use crate::common::*;

fn model_json(tool: &str) -> (serde_json::Value, String) {
    let r = edbbgen([
        "model",
        nj130_dh().to_str().unwrap(),
        "--fixture",
        "258,1468,708",
        "--tool",
        tool,
        "--json",
    ]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    (serde_json::from_str(&r.stdout).expect("json"), r.stderr)
}

fn fixed_names(v: &serde_json::Value) -> Vec<String> {
    v["fixture_known"]["fixed"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| p["status"] != "known")
        .map(|p| p["name"].as_str().unwrap().to_string())
        .collect()
}

#[test]
fn nj130_has_the_papers_22_identifiable_parameters() {
    let (v, stderr) = model_json("60,30,120");
    assert_eq!(v["schema"], "edbbgen.model/1");
    assert_eq!(v["fixture_known"]["identifiable_count"], 22);
    assert_eq!(fixed_names(&v), ["d3", "theta6"]);
    let d3 = v["params"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "d3")
        .unwrap();
    assert_eq!(d3["on"], serde_json::json!(["d2"]));
    assert_eq!(v["map_on_flange_axis"], false);
    assert!(
        stderr.is_empty(),
        "no warning for an off-axis tool: {stderr}"
    );
    // With the fixture free, one more: its radial position; z_fix goes with d1.
    assert_eq!(v["fixture_free"]["identifiable_count"], 23);
}

#[test]
fn a_map_on_the_flange_axis_loses_wrist_parameters_and_warns() {
    let (v, stderr) = model_json("0,0,120");
    let n = v["fixture_known"]["identifiable_count"].as_u64().unwrap();
    assert!(n < 22, "{n}");
    assert!(fixed_names(&v).contains(&"theta6".to_string()));
    assert_eq!(v["map_on_flange_axis"], true);
    assert!(stderr.contains("lies on the flange axis"), "{stderr}");
    assert_eq!(stderr.lines().count(), 1);
}

#[test]
fn text_report_names_the_fixed_parameters() {
    let r = edbbgen([
        "model",
        nj130_dh().to_str().unwrap(),
        "--fixture",
        "258,1468,708",
        "--tool",
        "60,30,120",
    ]);
    assert_eq!(r.code, 0);
    assert!(
        r.stdout
            .contains("fixture and MAP known: 22 identifiable parameters"),
        "{}",
        r.stdout
    );
    assert!(
        r.stdout
            .contains("d3 (dependent on d2); theta6 (dependent on alpha6, a6, d6)"),
        "{}",
        r.stdout
    );
}

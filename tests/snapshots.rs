//! Golden programs (insta snapshots under snapshots/, named `<kind>@<case>`), and the
//! whole-program determinism check they rely on.

use crate::common::*;

/// Every snapshot file must belong to a case here, or be a dialect program `<dialect>@<cell>`
/// of tests/dialects.rs: orphans fail (like `--unreferenced reject`).
const CASES: &[&str] = &[
    "calibrated@nj130",
    "compensated@targets",
    "compensated@user_ngc",
    "compensated@user_sinumerik",
    "compensated@user_krl",
    "compensated@user_rapid",
    "compensated@user_urscript",
    "compensated@user_fanuc",
    "drift@synthetic",
    "gcode@ldbb_circle",
    "gcode@nj130_default",
    "html@nj130_default",
    "html@nj130_diagnosis",
    "place@nj130_small",
    "json@ldbb_simulated",
    "dialects@list",
];

pub fn assert_golden(name: &str, text: &str) {
    insta::with_settings!({ snapshot_path => "../snapshots", prepend_module_to_snapshot => false, omit_expression => true }, {
        insta::assert_snapshot!(name, text);
    });
}

#[test]
fn nj130_default_program_is_deterministic_and_golden() {
    // The same file name in two places: the program's name (its header) is the file's stem.
    let (d1, d2) = (tempdir(), tempdir());
    let (one, two) = (d1.path().join("nj130.nc"), d2.path().join("nj130.nc"));
    let run = |out: &std::path::Path, threads: &str| {
        let html = out.with_extension("html");
        let r = edbbgen_env(
            [
                nj130_dh().to_str().unwrap(),
                "--fixture",
                "258,1468,708",
                "-o",
                out.to_str().unwrap(),
                "--html",
                html.to_str().unwrap(),
            ],
            &[("RAYON_NUM_THREADS", threads)],
        );
        assert_eq!(r.code, 0, "{}", r.stderr);
        (
            std::fs::read_to_string(out).unwrap(),
            std::fs::read_to_string(html).unwrap(),
        )
    };
    let (a, a_html) = run(&one, "1");
    let (b, b_html) = run(&two, "2");
    assert_eq!(a, b, "byte-identical on 1 and 2 threads");
    assert_eq!(a_html, b_html, "report byte-identical on 1 and 2 threads");
    let robot = load(&nj130_dh());
    assert_in_shell(
        &robot,
        &a,
        [258.0, 1468.0, 708.0],
        [60.0, 30.0, 120.0],
        (300.0, 520.0),
    );
    assert!(
        !a.contains("/work") && !a.contains(env!("CARGO_MANIFEST_DIR")),
        "no absolute paths in the program"
    );
    assert_golden("gcode@nj130_default", &a);
    assert_golden("html@nj130_default", &a_html);
}

#[test]
fn no_orphaned_snapshots() {
    let dir = root().join("snapshots");
    for entry in std::fs::read_dir(&dir).expect("snapshots/") {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        let Some(case) = name.strip_suffix(".snap") else {
            panic!(
                "unexpected file in snapshots/: {name} (pending .snap.new? run cargo insta review)"
            );
        };
        let dialect_case = case.split_once('@').is_some_and(|(d, c)| {
            crate::dialects::DIALECTS.contains(&d)
                && (c == "nj130_cell" || c == "nj130_dwell" || SHARED_ROBOTS.contains(&c))
        });
        assert!(
            CASES.contains(&case) || dialect_case,
            "orphaned snapshot {name}"
        );
    }
}

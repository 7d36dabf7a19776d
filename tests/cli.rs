//! The command line's own surface: completions and manual pages generated from the clap
//! definitions, `-q` on every subcommand.

use crate::common::*;

const SUBCOMMANDS: &[&str] = &[
    "model",
    "verify",
    "simulate",
    "diagnose",
    "circle",
    "ldbb",
    "ldbb-circle",
    "simulate-ldbb",
    "dialects",
    "calibrate",
    "place",
    "compensate",
    "completions",
    "man",
];

#[test]
fn completions_are_valid_scripts_naming_every_subcommand() {
    for shell in ["bash", "zsh", "fish", "elvish", "powershell"] {
        let r = edbbgen(["completions", shell]);
        assert_eq!(r.code, 0, "{shell}: {}", r.stderr);
        for sub in SUBCOMMANDS {
            assert!(r.stdout.contains(sub), "{shell} completion lacks {sub}");
        }
        assert!(r.stdout.contains("fixture"), "{shell}: flags");
    }
    // bash itself parses the bash script.
    let dir = tempdir();
    let script = dir.path().join("edbbgen.bash");
    std::fs::write(&script, edbbgen(["completions", "bash"]).stdout).unwrap();
    let out = std::process::Command::new("bash")
        .arg("-n")
        .arg(&script)
        .output()
        .expect("bash");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r = edbbgen(["completions", "tcsh"]);
    assert_eq!(r.code, 2);
    assert_eq!(r.stderr.lines().count(), 1, "{}", r.stderr);
}

#[test]
fn manual_pages_for_the_compiler_and_each_subcommand() {
    let r = edbbgen(["man"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stdout.contains(".TH edbbgen 1"));
    assert!(r.stdout.contains("fixture"));
    assert!(r.stdout.contains(".SH EXAMPLES"), "compiler: EXAMPLES");
    assert!(
        r.stdout.contains(".SH \"EXIT STATUS\""),
        "compiler: EXIT STATUS"
    );
    for sub in SUBCOMMANDS {
        let r = edbbgen(["man", sub]);
        let page = r.stdout.replace("\\-", "-");
        let examples = page.split(".SH EXAMPLES").nth(1).unwrap_or("");
        assert!(
            examples.contains(&format!("edbbgen {sub}")),
            "{sub}: the man page's EXAMPLES run the subcommand"
        );
        assert!(
            r.stdout.contains(".SH \"EXIT STATUS\"") && r.stdout.contains("bad input or usage"),
            "{sub}: EXIT STATUS"
        );
        assert_eq!(r.code, 0, "{sub}: {}", r.stderr);
        assert!(
            r.stdout.contains(&format!(".TH edbbgen-{sub} 1")),
            "{sub}: {}",
            &r.stdout[..200]
        );
        assert!(
            r.stdout.contains(env!("CARGO_PKG_VERSION")),
            "{sub}: version"
        );
    }
    let r = edbbgen(["man", "nope"]);
    assert_eq!(r.code, 2);
    assert!(
        r.stderr.contains("unknown subcommand 'nope'"),
        "{}",
        r.stderr
    );
}

#[test]
fn every_subcommand_takes_q() {
    let help = edbbgen(["--help"]).stdout;
    for sub in SUBCOMMANDS {
        let r = edbbgen([sub, "--help"]);
        assert_eq!(r.code, 0, "{sub}");
        assert!(r.stdout.contains("-q, --quiet"), "{sub} lacks -q");
        let examples = r.stdout.split("Examples:\n").nth(1).unwrap_or("");
        assert!(
            examples.contains(&format!("  edbbgen {sub}")),
            "{sub}: --help shows an example of the subcommand"
        );
        assert!(help.contains(sub), "top-level help lists {sub}");
    }
}

#[test]
fn q_leaves_warnings_and_errors_only_and_a_json_flag_takes_a_path() {
    let dir = tempdir();
    let p = |f: &str| dir.path().join(f).display().to_string();
    let nj = nj130_dh().display().to_string();
    let nj = nj.as_str();
    // The summary is stdout's only content; -q silences it, the file is still written.
    let r = edbbgen(["circle", nj, "--fixture", "258,1468,708", "-o", &p("c.nc")]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stdout.contains("circle test"), "{}", r.stdout);
    std::fs::remove_file(p("c.nc")).unwrap();
    let r = edbbgen([
        "circle",
        nj,
        "--fixture",
        "258,1468,708",
        "-o",
        &p("c.nc"),
        "-q",
    ]);
    assert_eq!((r.code, r.stdout.as_str()), (0, ""), "{}", r.stderr);
    assert!(std::fs::read_to_string(p("c.nc")).unwrap().contains("G1 "));
    assert_eq!(edbbgen(["dialects", "-q"]).stdout, "");
    // --json alone and --json - print the report on stdout in place of the list; a path
    // writes the file and the list is printed as usual (not with -q).
    let alone = edbbgen(["dialects", "--json"]).stdout;
    let dash = edbbgen(["dialects", "--json", "-"]).stdout;
    assert_eq!(alone, dash);
    let doc: serde_json::Value = serde_json::from_str(&alone).expect("JSON on stdout");
    assert_eq!(doc["schema"], "edbbgen.dialects/1");
    let r = edbbgen(["dialects", "--json", &p("d.json"), "-q"]);
    assert_eq!((r.code, r.stdout.as_str()), (0, ""), "{}", r.stderr);
    assert_eq!(std::fs::read_to_string(p("d.json")).unwrap(), alone);
    let r = edbbgen(["dialects", "--json", &p("d.json")]);
    assert!(r.stdout.contains("approximates"), "{}", r.stdout);
    // A report into a folder that does not exist: exit 2 before any work.
    let r = edbbgen(["dialects", "--json", &p("no/d.json")]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("does not exist"), "{}", r.stderr);
}

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
    for sub in [
        "model",
        "verify",
        "simulate",
        "diagnose",
        "circle",
        "ldbb",
        "ldbb-circle",
        "simulate-ldbb",
        "compensate",
    ] {
        let r = edbbgen(["man", sub]);
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
        assert!(help.contains(sub), "top-level help lists {sub}");
    }
}

//! Property-based fuzzing of every parser on stable (the CI side of `make fuzz`): valid seed
//! files mutated by random edits (deleted spans, duplicated lines, hostile tokens and numbers
//! spliced in) must give a value or an error whose message is one line — never a panic. The
//! coverage-guided targets under `fuzz/` (cargo-fuzz, nightly) run the same parsers for longer;
//! every crash either kind found is a regression case at the bottom of this file.

use crate::common::*;
use edbbgen::robot;
use nalgebra::Vector3;
use proptest::prelude::*;
use std::path::Path;

/// Tokens that break parsers: structure of every format, extreme and non-finite numbers,
/// unicode, separators.
const TOKENS: &[&str] = &[
    "",
    " ",
    "\n",
    "\r\n",
    "\t",
    "\0",
    "-",
    "+",
    ".",
    ",",
    ";",
    "=",
    "\"",
    "'",
    "[",
    "]",
    "{",
    "}",
    "(",
    ")",
    "<",
    ">",
    "/",
    "\\",
    "#",
    "0",
    "-0",
    "1",
    "-1",
    "1e308",
    "-1e308",
    "1e-320",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "18446744073709551616",
    "99999999999",
    "0.000000001",
    "1..2",
    "..",
    "[[joints]]",
    "[fixture]",
    "[tool]",
    "[[tool.shapes]]",
    "[safety]",
    "[geometric]",
    "alpha = ",
    "limits = [",
    "max_speed = 0",
    "type = \"mesh\"",
    "<joint",
    "</joint>",
    "<link name=\"x\"/>",
    "<mimic joint=\"j1\"/>",
    "<origin xyz=\"1 2\"/>",
    "<axis xyz=\"0 0 0\"/>",
    "<limit lower=\"1\" upper=\"-1\"/>",
    "G0",
    "G1",
    "G4 P",
    "G64 P",
    "G61",
    "G93",
    "G94",
    "M0",
    "M2",
    "X",
    "F",
    "N10",
    "%",
    "{{",
    "}}",
    "{%",
    "%}",
    "{% for m in moves %}",
    "{% endfor %}",
    "{{ h.cond }}",
    "{{ 1/0 }}",
    "é",
    "∞",
    "µm",
    "t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,length_mm",
    "run,load_n,angle_deg,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,deflection_um",
    "[loads]",
    "[circle]",
    "repeats = 0",
    "loads_n = []",
    "1,125,",
    ",,,,,,",
];

#[derive(Clone, Debug)]
enum Edit {
    Delete { at: usize, len: usize },
    Insert { at: usize, token: usize },
    DuplicateLine { at: usize },
    Truncate { at: usize },
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), 0usize..40).prop_map(|(at, len)| Edit::Delete { at, len }),
        (any::<usize>(), 0..TOKENS.len()).prop_map(|(at, token)| Edit::Insert { at, token }),
        any::<usize>().prop_map(|at| Edit::DuplicateLine { at }),
        any::<usize>().prop_map(|at| Edit::Truncate { at }),
    ]
}

/// Applies the edits to `seed` at char boundaries.
fn mutate(seed: &str, edits: &[Edit]) -> String {
    let mut s = seed.to_string();
    let boundary = |s: &str, at: usize| {
        let mut i = at % (s.len() + 1);
        while !s.is_char_boundary(i) {
            i -= 1;
        }
        i
    };
    for e in edits {
        match *e {
            Edit::Delete { at, len } => {
                let a = boundary(&s, at);
                let b = boundary(&s, a.saturating_add(len).min(s.len()));
                s.replace_range(a..b.max(a), "");
            }
            Edit::Insert { at, token } => {
                let a = boundary(&s, at);
                s.insert_str(a, TOKENS[token]);
            }
            Edit::DuplicateLine { at } => {
                let lines: Vec<&str> = s.lines().collect();
                if !lines.is_empty() {
                    let k = at % lines.len();
                    let mut out: Vec<&str> = lines[..=k].to_vec();
                    out.extend(&lines[k..]);
                    s = out.join("\n");
                }
            }
            Edit::Truncate { at } => {
                let a = boundary(&s, at);
                s.truncate(a);
            }
        }
    }
    s
}

fn mutated(seed: String) -> impl Strategy<Value = String> {
    proptest::collection::vec(edit(), 1..6).prop_map(move |e| mutate(&seed, &e))
}

fn read(rel: &str) -> String {
    std::fs::read_to_string(root().join(rel)).expect(rel)
}

/// The NJ-130 cell's program in a dialect, from its insta snapshot (the body after the header).
fn snapshot(d: &str) -> String {
    let snap = read(&format!("snapshots/{d}@nj130_cell.snap"));
    match snap.split_once("\n---\n") {
        Some((_, body)) => body.to_string(),
        None => snap,
    }
}

fn one_line(msg: &str) {
    assert!(
        !msg.trim().is_empty() && !msg.contains('\n'),
        "error message is not one line: {msg:?}"
    );
}

fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(config(300))]

    #[test]
    fn dh_spec(text in mutated(read("robots/comau_nj130/robot.dh.toml"))) {
        let path = Path::new("fuzz.dh.toml");
        match robot::dh::from_str(&text, path) {
            Ok(r) => { let _ = r.validate(path); }
            Err(e) => one_line(&e.to_string()),
        }
    }

    #[test]
    fn cell_file(text in mutated(read("robots/comau_nj130/cell.toml"))) {
        if let Err(e) = edbbgen::cell::from_str(&text, Path::new("fuzz.cell.toml")) {
            one_line(&e.to_string());
        }
    }

    #[test]
    fn truth_file(text in mutated(read("fuzz/corpus/truth/readme"))) {
        if let Err(e) = edbbgen::twin::Truth::from_toml(&text) {
            one_line(&e);
        }
    }

    #[test]
    fn measured_csv(text in mutated(read("fuzz/corpus/measured_csv/nj130"))) {
        if let Err(e) = edbbgen::twin::parse_csv(&text, 1) {
            one_line(&e.to_string());
        }
    }

    #[test]
    fn program_reader(text in mutated(read("fuzz/corpus/gcode/short"))) {
        if let Err(e) = edbbgen::verify::gcode::parse(&text) {
            one_line(&e.to_string());
        }
    }

    #[test]
    fn every_dialect_reader(
        k in 0usize..6,
        text in prop_oneof![
            mutated(snapshot("ngc")),
            mutated(snapshot("sinumerik")),
            mutated(snapshot("krl")),
            mutated(snapshot("rapid")),
            mutated(snapshot("urscript")),
            mutated(snapshot("fanuc")),
        ],
    ) {
        // Any text through any reader (mostly the wrong one): a program or a one-line error.
        let d = &edbbgen::dialect::all()[k];
        let map = edbbgen::controller::ControllerMap {
            sign: [1.0, -1.0, 1.0, 1.0, -1.0, 1.0],
            offset_deg: [0.0, 90.0, -90.0, 0.0, 0.0, 0.0],
            j3_coupling: -1.0,
            units: d.units,
            axis_names: d.axis_names.clone(),
        };
        match d.read(&text, &map) {
            Ok(p) => { let _ = p.targets().count(); }
            Err(e) => one_line(&e.to_string()),
        }
    }

    #[test]
    fn user_template(text in mutated(read("src/dialect/ngc/ngc.j2"))) {
        let template = edbbgen::dialect::Template {
            source: text,
            dialect: edbbgen::dialect::by_name("ngc").unwrap(),
            user: true,
        };
        if let Err(e) = edbbgen::emit::render(&template, &program()) {
            one_line(&e);
        }
    }
}

/// A user's template that asks a filter for more decimals than a number carries, or a column
/// wider than a line, fails to render with one line naming the limit: no panic, no gigabyte.
#[test]
fn absurd_decimals_and_widths_in_a_user_template_are_errors() {
    let ngc = read("src/dialect/ngc/ngc.j2");
    let fanuc = read("src/dialect/fanuc/fanuc.j2");
    for (source, name, limit) in [
        (ngc.replacen("| f(3)", "| f(4000000000)", 1), "ngc", "15"),
        (ngc.replacen("| f(3)", "| ceil(70000)", 1), "ngc", "15"),
        (
            fanuc.replacen("rjust(4)", "rjust(3000000000)", 1),
            "fanuc",
            "256",
        ),
    ] {
        assert_ne!(source, if name == "ngc" { &ngc } else { &fanuc }[..]);
        let template = edbbgen::dialect::Template {
            source,
            dialect: edbbgen::dialect::by_name(name).unwrap(),
            user: true,
        };
        let e = edbbgen::emit::render(&template, &program()).unwrap_err();
        one_line(&e);
        assert!(e.contains(limit), "{e}");
    }
    // Within the limits the filters still print.
    let template = edbbgen::dialect::Template {
        source: ngc.replacen("| f(3)", "| f(15)", 1),
        dialect: edbbgen::dialect::by_name("ngc").unwrap(),
        user: true,
    };
    assert!(edbbgen::emit::render(&template, &program()).is_ok());
}

/// A small loaded-circle recording (two loads, one run each, 90 samples) in the CSV contract,
/// and a setup that matches it.
fn ldbb_seed() -> (String, String) {
    let mut csv = String::from(edbbgen::ldbb::data::LOADED_HEADER);
    for (load, start) in [(125.0, 10.0), (250.0, 200.0)] {
        for k in 0..90 {
            let a: f64 = start + 4.0 * k as f64;
            csv += &format!(
                "\n1,{load},{a},,,,,,,{:.3}",
                300.0 * (a.to_radians() - 1.0).sin() + 0.4 * load
            );
        }
    }
    let setup = read("examples/ldbb/setup.toml")
        .replace("[125.0, 250.0, 375.0, 500.0, 625.0]", "[125.0, 250.0]")
        .replace("repeats = 3", "repeats = 1");
    (csv + "\n", setup)
}

proptest! {
    #![proptest_config(config(200))]

    #[test]
    fn ldbb_setup(text in mutated(read("examples/ldbb/setup.toml"))) {
        if let Err(e) = edbbgen::ldbb::setup::Setup::from_toml(&text, Path::new(".")) {
            one_line(&e);
        }
    }

    #[test]
    fn ldbb_truth(text in mutated(read("examples/ldbb/truth.toml"))) {
        if let Err(e) = edbbgen::ldbb::sim::Truth::from_toml(&text) {
            one_line(&e);
        }
    }

    #[test]
    fn ldbb_loaded_csv_through_the_analysis(text in mutated(ldbb_seed().0)) {
        let setup = edbbgen::ldbb::setup::Setup::from_toml(&ldbb_seed().1, Path::new(".")).unwrap();
        match edbbgen::ldbb::data::parse_loaded(&text) {
            Ok(data) => {
                let opts = edbbgen::ldbb::Options { grid_step: 10f64.to_radians(), ..Default::default() };
                if let Err(e) = edbbgen::ldbb::run(&data, &setup, None, None, &opts) {
                    one_line(&e.to_string());
                }
            }
            Err(e) => one_line(&e.to_string()),
        }
    }

    #[test]
    fn ldbb_reference_csv(text in mutated("angle_deg,error_um\n0,1.5\n90,-2\n180,0.25\n270,3\n".to_string())) {
        if let Err(e) = edbbgen::ldbb::data::parse_reference(&text) {
            one_line(&e.to_string());
        }
    }
}

#[test]
fn the_ldbb_seed_analyses() {
    // The property above means something only if the unmutated seed gets through.
    let (csv, setup) = ldbb_seed();
    let setup = edbbgen::ldbb::setup::Setup::from_toml(&setup, Path::new(".")).unwrap();
    let data = edbbgen::ldbb::data::parse_loaded(&csv).unwrap();
    let opts = edbbgen::ldbb::Options {
        grid_step: 10f64.to_radians(),
        ..Default::default()
    };
    let a = edbbgen::ldbb::run(&data, &setup, None, None, &opts).unwrap();
    assert!(
        (a.compliance[0] - 0.4e-6).abs() < 1e-9,
        "{}",
        a.compliance[0]
    );
}

proptest! {
    // The URDF loader builds a collision scene from meshes too: fewer, slower cases.
    #![proptest_config(config(120))]

    #[test]
    fn urdf_through_loader_and_scene(text in mutated(read("robots/comau_nj130/robot.urdf"))) {
        urdf_and_scene(&text, None);
    }

    #[test]
    fn obj_mesh(text in mutated(read("fuzz/corpus/mesh/obj")[1..].to_string())) {
        urdf_and_scene(&mesh_urdf("m.obj"), Some(("m.obj", text.as_bytes())));
    }

    #[test]
    fn stl_mesh(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        // Random bytes, and a valid binary STL header with a lying triangle count.
        urdf_and_scene(&mesh_urdf("m.stl"), Some(("m.stl", &bytes)));
        let mut lying = vec![0u8; 80];
        lying.extend(u32::MAX.to_le_bytes());
        lying.extend(&bytes);
        urdf_and_scene(&mesh_urdf("m.stl"), Some(("m.stl", &lying)));
    }
}

/// The NJ-130 URDF with the mesh `name` added to link 1's collision geometry.
fn mesh_urdf(name: &str) -> String {
    read("fuzz/corpus/urdf/nj130").replacen(
        "<link name=\"link_1\">",
        &format!("<link name=\"link_1\"><collision><geometry><mesh filename=\"{name}\"/></geometry></collision>"),
        1,
    )
}

fn urdf_and_scene(urdf: &str, mesh: Option<(&str, &[u8])>) {
    let dir = tempdir();
    let path = dir.path().join("robot.urdf");
    std::fs::write(&path, urdf).unwrap();
    if let Some((name, bytes)) = mesh {
        std::fs::write(dir.path().join(name), bytes).unwrap();
    }
    match robot::load(&path, &Default::default()) {
        Ok(r) => {
            let cell = edbbgen::cell::CellSpec::default();
            if let Err(e) = edbbgen::collision::build(
                &r,
                &cell,
                &Vector3::new(1.0, 0.5, 0.5),
                &Vector3::new(0.0, 0.0, 0.1),
            ) {
                one_line(&e.to_string());
            }
        }
        Err(e) => one_line(&e.to_string()),
    }
}

/// The NJ-130's program at a coarse grid, compiled once for the template cases.
fn program() -> edbbgen::ir::Program {
    static P: std::sync::OnceLock<edbbgen::ir::Program> = std::sync::OnceLock::new();
    P.get_or_init(|| {
        let robot = robot::load(&nj130_dh(), &Default::default()).unwrap();
        let mut opts = edbbgen::pipeline::CompileOptions::new(Vector3::new(0.258, 1.468, 0.708));
        opts.step = [20f64.to_radians(); 6];
        opts.max_candidates = 600;
        let ngc = edbbgen::emit::dialect("ngc").unwrap();
        edbbgen::pipeline::compile(&robot, &opts, ngc, &edbbgen::sample::NoProgress)
            .unwrap()
            .program
    })
    .clone()
}

#[test]
fn mutation_reaches_every_edit_kind() {
    // The mutator must actually change inputs, or the properties above test nothing.
    let seed = "a = 1\nb = 2\n";
    assert_eq!(
        mutate(seed, &[Edit::Delete { at: 0, len: 2 }]),
        "= 1\nb = 2\n"
    );
    assert_eq!(
        mutate(seed, &[Edit::Insert { at: 4, token: 32 }]),
        "a = nan1\nb = 2\n"
    );
    assert_eq!(
        mutate(seed, &[Edit::DuplicateLine { at: 0 }]),
        "a = 1\na = 1\nb = 2"
    );
    assert_eq!(mutate(seed, &[Edit::Truncate { at: 3 }]), "a =");
}

#[test]
fn mesh_seeds_reach_the_scene() {
    // The mesh properties only mean something if the unmutated seeds load and hull.
    for (name, bytes) in [
        (
            "m.obj",
            read("fuzz/corpus/mesh/obj").as_bytes()[1..].to_vec(),
        ),
        (
            "m.stl",
            std::fs::read(root().join("fuzz/corpus/mesh/stl")).unwrap()[1..].to_vec(),
        ),
    ] {
        let dir = tempdir();
        let path = dir.path().join("robot.urdf");
        std::fs::write(&path, mesh_urdf(name)).unwrap();
        std::fs::write(dir.path().join(name), &bytes).unwrap();
        let r = robot::load(&path, &Default::default()).expect(name);
        let cell = edbbgen::cell::CellSpec::default();
        let (_, report) = edbbgen::collision::build(
            &r,
            &cell,
            &Vector3::new(1.0, 0.5, 0.5),
            &Vector3::new(0.0, 0.0, 0.1),
        )
        .expect(name);
        let _ = report;
        // A broken copy of the same mesh is an error naming the file.
        std::fs::write(dir.path().join(name), b"\x01\x02garbage").unwrap();
        let r = robot::load(&path, &Default::default()).expect(name);
        let e = edbbgen::collision::build(
            &r,
            &cell,
            &Vector3::new(1.0, 0.5, 0.5),
            &Vector3::new(0.0, 0.0, 0.1),
        )
        .err()
        .unwrap_or_else(|| panic!("{name}: a garbage mesh was accepted"));
        assert!(e.to_string().contains(name), "{e}");
    }
}

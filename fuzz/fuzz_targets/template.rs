//! A user template (`--template FILE`) rendered with the NJ-130's default program (compiled
//! once): an error or text, never a panic or a hang.
#![no_main]
use edbbgen::ir::Program;
use libfuzzer_sys::fuzz_target;
use std::sync::OnceLock;

fn program() -> &'static Program {
    static P: OnceLock<Program> = OnceLock::new();
    P.get_or_init(|| {
        let dh = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../robots/comau_nj130/robot.dh.toml");
        let robot = edbbgen::robot::load(&dh, &Default::default()).expect("NJ-130");
        let opts =
            edbbgen::pipeline::CompileOptions::new(nalgebra::Vector3::new(0.258, 1.468, 0.708));
        let template = edbbgen::emit::dialect("ngc").expect("ngc");
        edbbgen::pipeline::compile(&robot, &opts, template, &edbbgen::sample::NoProgress)
            .expect("compile")
            .program
    })
}

// The program is compiled once, before the first input (`init`), so that its few seconds under
// the sanitizers do not count as the first input's time (libFuzzer's -timeout).
fuzz_target!(init: { program(); }, |data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let template = edbbgen::dialect::Template {
            source: text.to_string(),
            dialect: edbbgen::dialect::by_name("ngc").expect("ngc"),
            user: true,
        };
        let _ = edbbgen::emit::render(&template, program());
    }
});

//! DH spec (`*.dh.toml`) text → robot: any bytes must give a robot or an error, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(robot) = edbbgen::robot::dh::from_str(text, Path::new("fuzz.dh.toml")) {
            let _ = robot.validate(Path::new("fuzz.dh.toml"));
        }
    }
});

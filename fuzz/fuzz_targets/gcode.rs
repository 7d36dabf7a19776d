//! The program reader of `verify` and `simulate` (RS274/NGC): an error or a parsed program,
//! never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(p) = edbbgen::verify::gcode::parse(text) {
            let _ = p.targets().count();
        }
    }
});

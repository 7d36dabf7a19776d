//! The program readers of `verify` and `simulate`, every dialect: an error or a parsed
//! program, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(p) = edbbgen::verify::gcode::parse(text) {
            let _ = p.targets().count();
        }
        for d in edbbgen::dialect::all() {
            let map = edbbgen::controller::ControllerMap {
                sign: [1.0, -1.0, 1.0, 1.0, -1.0, 1.0],
                offset_deg: [0.0, 90.0, -90.0, 0.0, 0.0, 0.0],
                j3_coupling: -1.0,
                units: d.units,
                axis_names: d.axis_names.clone(),
            };
            if let Ok(p) = d.read(text, &map) {
                let _ = p.targets().count();
            }
        }
    }
});

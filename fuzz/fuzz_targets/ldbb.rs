//! The LDBB inputs: the loaded-circle CSV, the laser-tracker reference CSV, the setup TOML and
//! the simulator's truth TOML (the first byte picks the parser). An error or a value, never a
//! panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&which, rest)) = data.split_first() else {
        return;
    };
    let Ok(text) = std::str::from_utf8(rest) else {
        return;
    };
    match which % 4 {
        0 => {
            let _ = edbbgen::ldbb::data::parse_loaded(text);
        }
        1 => {
            let _ = edbbgen::ldbb::data::parse_reference(text);
        }
        2 => {
            let _ = edbbgen::ldbb::setup::Setup::from_toml(text, std::path::Path::new("."));
        }
        _ => {
            let _ = edbbgen::ldbb::sim::Truth::from_toml(text);
        }
    }
});

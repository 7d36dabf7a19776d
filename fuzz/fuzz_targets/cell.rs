//! Cell file (`cell.toml`) text → cell spec: an error or a spec, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = edbbgen::cell::from_str(text, std::path::Path::new("fuzz.cell.toml"));
    }
});

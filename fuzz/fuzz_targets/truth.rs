//! Digital-twin truth (`TRUTH.toml`) text → truth: an error or a truth, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = edbbgen::twin::Truth::from_toml(text);
    }
});

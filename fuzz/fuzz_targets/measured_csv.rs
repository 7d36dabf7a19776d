//! Measured EDBB data (CSV contract) → rows: an error or data, never a panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = edbbgen::twin::parse_csv(text, 1);
    }
});

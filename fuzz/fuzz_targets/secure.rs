//! Fuzz target: see `checks::secure` in `fuzz/checks.rs`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| pulicast_fuzz::secure(data));

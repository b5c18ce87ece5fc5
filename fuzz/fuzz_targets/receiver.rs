//! Fuzz target: see `checks::receiver` in `fuzz/checks.rs`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| pulicast_fuzz::receiver(data));

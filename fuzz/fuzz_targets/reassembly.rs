//! Fuzz target: see `checks::reassembly` in `fuzz/checks.rs`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| pulicast_fuzz::reassembly(data));

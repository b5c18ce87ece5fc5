//! Fuzz target: see `checks::datagram` in `fuzz/checks.rs`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| pulicast_fuzz::datagram(data));

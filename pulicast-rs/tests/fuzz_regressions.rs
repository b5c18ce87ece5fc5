//! Replays every input the fuzzers ever failed on (`fuzz/regressions/<target>/`)
//! through the same checks the fuzz targets run (`fuzz/checks.rs`), on stable
//! Rust, in every test run. Run the fuzzers themselves with `fuzz/run.sh`.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

#[path = "../../fuzz/checks.rs"]
mod checks;

use std::path::PathBuf;

fn replay(target: &str, check: fn(&[u8])) {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/regressions")
        .join(target);
    let mut inputs: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map(|entries| entries.map(|e| e.unwrap().path()).collect())
        .unwrap_or_default();
    inputs.sort();
    for input in inputs {
        let data = std::fs::read(&input).unwrap();
        eprintln!("replaying {}", input.display());
        check(&data);
    }
}

#[test]
fn packet() {
    replay("packet", checks::packet);
}

#[test]
fn messages() {
    replay("messages", checks::messages);
}

#[test]
fn batch() {
    replay("batch", checks::batch);
}

#[test]
fn discovery() {
    replay("discovery", checks::discovery);
}

#[test]
fn names() {
    replay("names", checks::names);
}

#[test]
fn reassembly() {
    replay("reassembly", checks::reassembly);
}

#[test]
fn secure() {
    replay("secure", checks::secure);
}

#[test]
fn receiver() {
    replay("receiver", checks::receiver);
}

/// The receiver check on inputs made here, so it runs on stable in every
/// test run, not only under the fuzzer: a few hundred operation sequences
/// from a fixed-seed generator.
#[test]
fn receiver_on_generated_inputs() {
    let mut state = 0x5eed_u64;
    let mut next = || {
        // SplitMix64.
        state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    };
    for _ in 0..300 {
        let len = (next() % 4096) as usize;
        let input: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        checks::receiver(&input);
    }
}

#[test]
fn datagram() {
    replay("datagram", checks::datagram);
}

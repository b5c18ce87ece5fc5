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

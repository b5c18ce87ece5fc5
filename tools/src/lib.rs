//! The `puli` command-line tools for pulicast fleets.
//!
//! The binaries stay thin: everything they do lives here, so it can be tested
//! and reused: the shared flags ([`flags`]), what `puli-sniffer` does
//! ([`sniff`]), what `puli pub` does ([`publish`]), recording and playback
//! ([`record`]) and the benchmarks ([`mod@bench`]).

pub mod bench;
pub mod dashboard;
pub mod flags;
pub mod publish;
pub mod record;
pub mod sniff;

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Nanoseconds since the Unix epoch: one clock that every process on this
/// host shares, so events reported by different processes can be compared.
pub fn unix_ns() -> u128 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0)
}

/// Asks `f` every 20 ms until it answers or `within` has passed: how the
/// tools wait for something discovery will tell them (a channel's type).
pub async fn poll_for<T>(within: Duration, mut f: impl FnMut() -> Option<T>) -> Option<T> {
    let deadline = Instant::now() + within;
    loop {
        if let Some(found) = f() {
            return Some(found);
        }
        if Instant::now() >= deadline {
            return None;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

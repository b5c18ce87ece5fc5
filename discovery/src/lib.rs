//! Membership and liveness of pulicast nodes, as sans-IO state machines.
//!
//! Every pulicast node needs to know which other nodes are alive and which
//! channels they publish and subscribe. This crate holds that knowledge and the
//! rules that keep it current, without touching a socket or a clock: callers feed
//! it datagrams together with the time they arrived (`now`), ask it when it next
//! needs attention (`poll_timeout`) and drain what it wants to send and the
//! events it produces. The `pulicast` crate drives it from its tokio tasks; tests
//! and simulations drive it directly with a fake clock.
//!
//! - [`gossip`]: our discovery protocol. Each member multicasts a small digest
//!   (its incarnation and state version, and a few membership updates), others
//!   pull its full state (channels, types, host) when the version changes, and
//!   silence leads to suspicion and death; see `docs/discovery.md`, whose Trust
//!   section says what a stranger on the link can and can't make it believe.
//! - [`compat`]: the Pulicast 2.x liveness scheme: every node announces its
//!   full channel list on the `__nodes` channel once per heartbeat period and
//!   is considered gone after three missed periods. Nodes speak both, so 2.x
//!   nodes and tools see us, and we see them.
//! - [`relay`]: members of other sites that a bridge speaks for here.
//! - [`wire`]: the encoding of the gossip messages.
//!
//! ```
//! use std::time::{Duration, Instant};
//! use pulicast_discovery::compat::{Heartbeat, Membership};
//!
//! let mut members = Membership::new(Duration::from_millis(100));
//! let t0 = Instant::now();
//! let hb = Heartbeat { name: "rover".into(), session_id: 7, channels: vec![] };
//! members.handle_heartbeat(t0, "127.0.0.1:40000".parse().unwrap(), hb);
//! assert_eq!(members.peers().count(), 1);
//!
//! // Three missed periods later the peer is forgotten.
//! members.handle_timeout(t0 + Duration::from_millis(301));
//! assert_eq!(members.peers().count(), 0);
//! ```

pub mod compat;
pub mod gossip;
pub mod relay;
pub mod wire;

/// What a heap block of `capacity` bytes costs in memory: the allocator
/// hands out blocks in 16-byte steps with 8 bytes of header, and never
/// fewer than 32 (glibc's malloc; others are alike). The tables bounded in
/// bytes count this, so that their bounds hold in resident memory, not only
/// in the sizes asked for: a million 9-byte names take 32 MB, not 9.
pub(crate) fn heap_bytes(capacity: usize) -> usize {
    match capacity {
        0 => 0,
        n => (n + 8).next_multiple_of(16).max(32),
    }
}

/// The first of `candidates` (bytes each holds, and who), in the order
/// given, that together free at least `needed` bytes; `None` if all of them
/// would not. The tables that are bounded in bytes make room with it.
pub(crate) fn enough_to_free<K>(
    candidates: impl IntoIterator<Item = (usize, K)>,
    needed: usize,
) -> Option<Vec<K>> {
    let mut freed = 0;
    let mut chosen = Vec::new();
    for (bytes, key) in candidates {
        if freed >= needed {
            break;
        }
        freed += bytes;
        chosen.push(key);
    }
    (freed >= needed).then_some(chosen)
}

//! Picking a port for a private fleet: a simulation run, a test, a benchmark.
//!
//! Nodes that should hear only each other share a port that nothing else on
//! the host uses. Asking the kernel for an ephemeral port (bind to port 0,
//! read it, close) is not enough: the port goes back to the ephemeral pool,
//! and the next socket anyone binds to port 0 (every node's send socket is
//! one) may get it before our nodes bind it with `SO_REUSEADDR`, which then
//! fails with [`Error::PortInUse`]. So the ports handed out here lie outside
//! the kernel's ephemeral range, where nothing lands by chance.

use std::net::{Ipv4Addr, UdpSocket};
use std::ops::RangeInclusive;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::OnceLock;

use crate::error::{Error, Result};

/// The Pulicast 2.x default port.
pub const DEFAULT_PORT: u16 = 8765;

/// Linux's default `net.ipv4.ip_local_port_range`, used where it can't be read.
const DEFAULT_EPHEMERAL: (u16, u16) = (32768, 60999);

/// Below this are well-known and registered services people actually run.
const LOWEST: u16 = 10_000;

/// A range narrower than this is not worth searching: fall back to all of it.
const MIN_SPAN: u16 = 1_000;

/// How many candidates to try before giving up.
const ATTEMPTS: u32 = 512;

/// Every call in one process moves on from the last port handed out, so
/// concurrent callers (tests running in parallel) never get the same one.
static NEXT: AtomicU32 = AtomicU32::new(0);

/// The range, read once, and where this process starts in it, drawn once,
/// so that separate processes (test binaries, benchmark children) rarely
/// meet.
static PLAN: OnceLock<(RangeInclusive<u16>, u32)> = OnceLock::new();

/// A UDP port that no socket on this host holds right now and that lies
/// outside the kernel's ephemeral range, for a fleet that should hear only
/// itself: a simulation run, a test, a benchmark.
///
/// Within one process, no two calls return the same port (until the range
/// wraps around); separate processes start at random places in the range.
///
/// ```
/// # #[tokio::main(flavor = "current_thread")]
/// # async fn main() -> pulicast::Result<()> {
/// let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("sim_rover")
///     .port(port)
///     .interface(std::net::Ipv4Addr::LOCALHOST)
///     .start()
///     .await?;
/// node.channel("pose").publish(&1.5_f64)?;
/// # Ok(())
/// # }
/// ```
///
/// # Errors
/// [`Error::Io`] when no port in the range could be bound.
pub fn unused_port() -> Result<u16> {
    let (range, start) = PLAN.get_or_init(|| (private_range(ephemeral_range()), random_offset()));
    let span = u32::from(range.end() - range.start()) + 1;
    let mut last_error = None;
    for _ in 0..ATTEMPTS {
        let step = NEXT.fetch_add(1, Ordering::Relaxed);
        let port = candidate(range, span, start.wrapping_add(step));
        if port == DEFAULT_PORT {
            continue;
        }
        match held(port) {
            Ok(()) => return Ok(port),
            Err(e) => last_error = Some(e),
        }
    }
    Err(Error::Io {
        op: "finding an unused port",
        source: last_error.unwrap_or_else(|| std::io::Error::other("no candidate port")),
    })
}

/// Binding the wildcard address without `SO_REUSEADDR` fails if any socket
/// holds the port, on any address, sharing or not.
fn held(port: u16) -> std::io::Result<()> {
    UdpSocket::bind((Ipv4Addr::UNSPECIFIED, port)).map(drop)
}

fn candidate(range: &RangeInclusive<u16>, span: u32, n: u32) -> u16 {
    // `n % span < span <= 65536 - start`, so the sum fits.
    let offset = u16::try_from(n % span).unwrap_or(0);
    range.start().saturating_add(offset)
}

/// Ports outside `ephemeral` (inclusive bounds) and above [`LOWEST`]: below
/// the ephemeral range if there is room, else above it, else (a host that
/// made almost every port ephemeral) everything from [`LOWEST`] up.
fn private_range((lo, hi): (u16, u16)) -> RangeInclusive<u16> {
    let (lo, hi) = if lo <= hi { (lo, hi) } else { (hi, lo) };
    if lo > LOWEST && lo - LOWEST >= MIN_SPAN {
        LOWEST..=lo - 1
    } else if hi < u16::MAX && u16::MAX - hi >= MIN_SPAN {
        hi.max(LOWEST - 1) + 1..=u16::MAX
    } else {
        LOWEST..=u16::MAX
    }
}

fn ephemeral_range() -> (u16, u16) {
    std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|text| parse_range(&text))
        .unwrap_or(DEFAULT_EPHEMERAL)
}

fn parse_range(text: &str) -> Option<(u16, u16)> {
    let mut parts = text.split_whitespace().map(str::parse::<u16>);
    match (parts.next(), parts.next(), parts.next()) {
        (Some(Ok(lo)), Some(Ok(hi)), None) => Some((lo, hi)),
        _ => None,
    }
}

fn random_offset() -> u32 {
    let bytes = uuid::Uuid::new_v4().into_bytes();
    u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn the_range_avoids_the_ephemeral_ports() {
        assert_eq!(private_range((32768, 60999)), 10_000..=32767);
        // Ephemeral ports from 1024: the room is above them.
        assert_eq!(private_range((1024, 40000)), 40001..=65535);
        // Reversed bounds are read as a range all the same.
        assert_eq!(private_range((60999, 32768)), 10_000..=32767);
        // Below 10 000 never, even when the ephemeral range ends low.
        assert_eq!(private_range((2000, 5000)), 10_000..=65535);
        // Nowhere to go: everything from 10 000.
        assert_eq!(private_range((10500, 65000)), 10_000..=65535);
    }

    #[test]
    fn candidates_stay_in_the_range_and_walk_all_of_it() {
        for range in [10_000..=32767, 40001..=65535, 10_000..=65535] {
            let span = u32::from(range.end() - range.start()) + 1;
            let mut seen = std::collections::HashSet::new();
            for n in (u32::MAX - span)..=u32::MAX {
                let port = candidate(&range, span, n);
                assert!(range.contains(&port), "{port} outside {range:?}");
                seen.insert(port);
            }
            assert_eq!(seen.len() as u32, span);
        }
    }

    #[test]
    fn the_kernel_range_parses_and_junk_does_not() {
        assert_eq!(parse_range("32768\t60999\n"), Some((32768, 60999)));
        assert_eq!(parse_range("32768"), None);
        assert_eq!(parse_range("1 2 3"), None);
        assert_eq!(parse_range("x 60999"), None);
        assert_eq!(parse_range("70000 80000"), None);
    }

    #[test]
    fn concurrent_callers_get_distinct_free_ports() {
        let ephemeral = ephemeral_range();
        let ports: Vec<u16> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..8)
                .map(|_| s.spawn(|| (0..16).map(|_| unused_port().unwrap()).collect::<Vec<_>>()))
                .collect();
            handles
                .into_iter()
                .flat_map(|h| h.join().unwrap())
                .collect()
        });
        let distinct: std::collections::HashSet<_> = ports.iter().collect();
        assert_eq!(distinct.len(), ports.len());
        for port in ports {
            assert!(!(ephemeral.0..=ephemeral.1).contains(&port), "{port}");
            assert_ne!(port, DEFAULT_PORT);
        }
    }

    #[test]
    fn a_port_held_on_any_address_or_shared_is_seen_as_held() {
        let port = unused_port().unwrap();
        assert!(held(port).is_ok());
        // On one address only, without sharing.
        let one = UdpSocket::bind((Ipv4Addr::LOCALHOST, port)).unwrap();
        assert!(held(port).is_err());
        drop(one);
        assert!(held(port).is_ok());
        // The way nodes hold it: the wildcard address, shared.
        let shared =
            socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::DGRAM, None).unwrap();
        shared.set_reuse_address(true).unwrap();
        shared
            .bind(&std::net::SocketAddr::from((Ipv4Addr::UNSPECIFIED, port)).into())
            .unwrap();
        assert!(held(port).is_err());
    }
}

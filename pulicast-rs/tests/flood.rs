//! A flood of garbage at the port: 100 000 datagrams/s for 10 s, aimed at
//! the very group a valid channel uses, so garbage and data share a socket.
//! Valid messages keep flowing (the delivery ratio is printed), the garbage
//! is counted, memory stays bounded, and the node answers afterwards. The
//! same again on a sealed channel, with forgeries that cost the receiver a
//! tag check each.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use common::{free_port, node, now_ms, packet, raw_sender, send_raw};
use pulicast::{DropReason, Key, NodeBuilder, Stats};
use pulicast_proto::fragment::Fragment;
use pulicast_proto::secure::Sealer;
use pulicast_proto::wire::batch::BatchBuilder;
use pulicast_proto::wire::Packet;

const RATE: u64 = 100_000;
const SECS: u64 = 10;

/// One flood at a time: each test measures its own flood, not two at once
/// on a machine that may have two cores.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            let line = s.lines().find(|l| l.starts_with("VmRSS:"))?.to_string();
            line.split_whitespace().nth(1)?.parse().ok()
        })
        .unwrap_or(0)
}

/// Garbage of every kind the node must survive, cycling: random bytes,
/// packets with bad names, truncated ZCM payloads on the valid channel,
/// fragments that announce huge messages and never finish them, and
/// malformed batches.
fn garbage(i: u64, out: &mut Vec<u8>) {
    out.clear();
    let x = i.wrapping_mul(0x9e37_79b9_7f4a_7c15);
    match i % 5 {
        0 => out.extend((0..(x % 200)).map(|k| (x >> (k % 56)) as u8)),
        1 => {
            out.extend_from_slice(b"PULI\xff");
            out.extend_from_slice(&x.to_be_bytes());
        }
        2 => Packet {
            channel: "valid/data",
            seq: x as u32,
            payload: &[0xde, 0xad],
        }
        .encode(out),
        3 => {
            // A new message of 20 MB each time that never completes: only
            // the reassembly budgets stop it.
            let (total, count) = (20_000_000u32, 10_000u16);
            Fragment::encode_header("valid/data", x as u32, total, (x % 7) as u16, count, out);
            out.resize(out.len() + Fragment::chunk_size(total, count), 0xab);
        }
        _ => {
            let mut b = BatchBuilder::new();
            b.start("valid/data", x as u32);
            b.push(b"x");
            out.extend_from_slice(b.finish());
            out.push(0); // trailing byte: malformed
        }
    }
}

/// What a sealed channel's receiver faces from someone without its key,
/// cycling: datagrams sealed under another key, genuine ones with a flipped
/// tag bit, genuine ones relayed from an address that is not their origin,
/// recorded ones too old to accept, unsealed packets, and junk behind the
/// seal's magic.
fn sealed_garbage(i: u64, out: &mut Vec<u8>) {
    let inner = packet("valid/data", i as u32, &(i as i64).to_le_bytes());
    let right = Key::from_bytes([1; 32]);
    let wrong = Key::from_bytes([2; 32]);
    let now = now_ms();
    let elsewhere = std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(127, 0, 0, 9), 9);
    out.clear();
    match i % 6 {
        0 => out.extend_from_slice(Sealer::new(&wrong, "valid/data", false).seal(&inner, now)),
        1 => {
            out.extend_from_slice(Sealer::new(&right, "valid/data", true).seal(&inner, now));
            let last = out.len() - 1;
            out[last] ^= 1;
        }
        2 => out.extend_from_slice(
            Sealer::new(&right, "valid/data", false)
                .with_origin(elsewhere)
                .seal(&inner, now),
        ),
        3 => out.extend_from_slice(
            Sealer::new(&right, "valid/data", false).seal(&inner, now - 3_600_000),
        ),
        4 => out.extend_from_slice(&inner),
        _ => {
            out.extend_from_slice(b"PSEC\x0avalid/data");
            out.extend((0..(i % 120)).map(|k| (i >> (k % 56)) as u8));
        }
    }
}

/// What one flood run saw.
struct Flood {
    /// Valid messages delivered during the flood.
    received: u64,
    stats: Stats,
}

impl Flood {
    /// Datagrams of the flood the node read: what the kernel dropped for a
    /// full buffer never reached it, so checks of what it counted are made
    /// against this. Heartbeats and gossip are in `datagrams_received` too;
    /// `slack` bounds them.
    fn read(&self, slack: u64) -> u64 {
        self.stats
            .datagrams_received
            .saturating_sub(self.received + slack)
    }
}

/// More than the test's own heartbeats and gossip in 10 s (two nodes, a
/// 20 ms heartbeat).
const SLACK: u64 = 5_000;

/// Floods `valid/data` at [`RATE`] for [`SECS`] with datagrams from `pool`
/// while a node made by `options` publishes valid messages to another at
/// 1 kHz; checks what every flood must leave true (the flood ran, valid
/// messages got through, memory stayed bounded, the node answers right
/// after) and returns the figures for the caller's own checks.
fn flood(label: &str, options: impl Fn(NodeBuilder) -> NodeBuilder, pool: Vec<Vec<u8>>) -> Flood {
    let _turn = ONE_AT_A_TIME
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let port = free_port();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let _guard = runtime.enter();
    let receiver = runtime
        .block_on(options(node("receiver", port).queue_capacity(1 << 14)).start())
        .unwrap();
    let mut valid = receiver.channel("valid/data").subscribe::<i64>().unwrap();
    let sender = runtime
        .block_on(options(node("sender", port)).start())
        .unwrap();
    let rss_before = rss_kb();

    let flood = std::thread::spawn(move || {
        let socket: UdpSocket = raw_sender();
        let start = Instant::now();
        let mut sent = 0u64;
        // Bounded in count and in time; paced in 10 ms slots.
        while sent < RATE * SECS && start.elapsed() < Duration::from_secs(SECS + 5) {
            let slot = sent / (RATE / 100);
            let due = start + Duration::from_millis(slot * 10);
            if let Some(wait) = due.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
            for _ in 0..RATE / 100 {
                let datagram = &pool[(sent % pool.len() as u64) as usize];
                send_raw(&socket, "valid/data", port, datagram);
                sent += 1;
            }
        }
        (sent, start.elapsed())
    });

    // Valid messages at 1 kHz while the flood lasts.
    let data = sender.channel("valid/data");
    let publish_start = Instant::now();
    let mut published = 0i64;
    let mut received = 0u64;
    let mut seen = std::collections::HashSet::new();
    let mut strangers = 0u64;
    let mut take = |m: pulicast::Message<i64>| {
        // Anything not published, or heard twice, came from the flood.
        if !seen.insert(m.value) {
            strangers += 1;
        }
        received += 1;
    };
    while publish_start.elapsed() < Duration::from_secs(SECS) && published < 20_000 {
        data.publish(&published).unwrap();
        published += 1;
        std::thread::sleep(Duration::from_millis(1));
        while let Some(m) = valid.try_recv() {
            take(m);
        }
    }
    let (sent, flood_time) = flood.join().unwrap();
    std::thread::sleep(Duration::from_millis(300));
    while let Some(m) = valid.try_recv() {
        take(m);
    }
    let strangers = strangers
        + seen
            .iter()
            .filter(|&&v| !(0..published).contains(&v))
            .count() as u64;
    let ratio = received as f64 / published as f64;
    let stats = receiver.stats();
    let rss_after = rss_kb();
    eprintln!(
        "{label}: {sent} garbage datagrams in {:.1} s ({:.0}/s); valid: {received} of {published} delivered ({:.1} %); \
         {} dropped and counted; RSS {rss_before} -> {rss_after} kB",
        flood_time.as_secs_f64(),
        sent as f64 / flood_time.as_secs_f64(),
        ratio * 100.0,
        stats.dropped_total(),
    );
    assert!(
        sent >= RATE * SECS * 9 / 10,
        "the flood itself fell short: {sent}"
    );
    assert!(ratio > 0.5, "valid delivery collapsed: {ratio:.3}");
    assert_eq!(strangers, 0, "garbage was delivered as messages");
    assert!(
        rss_after < rss_before + 200_000,
        "memory grew from {rss_before} to {rss_after} kB"
    );
    // The node answers afterwards: every message gets through.
    for i in 0..20i64 {
        data.publish(&(1_000_000 + i)).unwrap();
    }
    let deadline = Instant::now() + Duration::from_secs(5);
    let mut after = Vec::new();
    while after.len() < 20 && Instant::now() < deadline {
        match valid.recv_timeout(Duration::from_millis(100)) {
            Some(m) if m.value >= 1_000_000 => after.push(m.value),
            _ => {}
        }
    }
    assert_eq!(after, (1_000_000..1_000_020).collect::<Vec<i64>>());
    Flood { received, stats }
}

/// Made up front, so the flood's pace is the socket's, not ours.
fn pool(make: fn(u64, &mut Vec<u8>)) -> Vec<Vec<u8>> {
    (0..5_000)
        .map(|i| {
            let mut d = Vec::new();
            make(i, &mut d);
            d
        })
        .collect()
}

#[test]
fn a_garbage_flood_does_not_stop_valid_messages() {
    let run = flood("flood", |b| b, pool(garbage));
    // Fragments of messages that never complete are counted when given
    // up, which the last ones of the flood are not yet: so "over half".
    assert!(
        run.stats.dropped_total() > run.read(SLACK) / 2,
        "garbage is counted: {:?}",
        run.stats
    );
}

#[test]
fn a_flood_of_forgeries_does_not_stop_a_sealed_channel() {
    let sealed = |b: NodeBuilder| {
        b.keys_from_env(false)
            .key("valid", Key::from_bytes([1; 32]))
    };
    let run = flood("sealed flood", sealed, pool(sealed_garbage));
    // Everything the node read is delivered or counted, each kind under
    // its own reason.
    let s = &run.stats;
    let read = run.read(SLACK);
    let kinds = [
        DropReason::Forged,
        DropReason::Replayed,
        DropReason::Stale,
        DropReason::Unauthenticated,
        DropReason::MalformedPayload,
    ];
    let counts: Vec<String> = kinds
        .iter()
        .map(|r| format!("{} {}", r.label(), s.dropped(*r)))
        .collect();
    eprintln!("sealed flood, counted by reason: {}", counts.join(", "));
    for reason in kinds {
        assert!(
            s.dropped(reason) > read / 12,
            "{reason:?} counted {} of {read} read: {s:?}",
            s.dropped(reason),
        );
    }
    assert!(
        s.dropped_total() >= read,
        "{read} forgeries read, {} counted: {s:?}",
        s.dropped_total()
    );
}

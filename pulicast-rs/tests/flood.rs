//! A flood of garbage at the port: 100 000 datagrams/s for 10 s, aimed at
//! the very group a valid channel uses, so garbage and data share a socket.
//! Valid messages keep flowing (the delivery ratio is printed), the garbage
//! is counted, memory stays bounded, and the node answers afterwards.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use common::{free_port, node, raw_sender, send_raw};
use pulicast::proto::batch::BatchBuilder;
use pulicast::proto::fragment::Fragment;
use pulicast::wire::Packet;

const RATE: u64 = 100_000;
const SECS: u64 = 10;

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

#[test]
fn a_garbage_flood_does_not_stop_valid_messages() {
    let port = free_port();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let _guard = runtime.enter();
    let receiver = runtime
        .block_on(node("receiver", port).queue_capacity(1 << 14).start())
        .unwrap();
    let mut valid = receiver.channel("valid/data").subscribe::<i64>().unwrap();
    let sender = runtime.block_on(node("sender", port).start()).unwrap();
    let rss_before = rss_kb();

    let flood = std::thread::spawn(move || {
        let socket: UdpSocket = raw_sender();
        // Made up front, so the flood's pace is the socket's, not ours.
        let pool: Vec<Vec<u8>> = (0..5_000)
            .map(|i| {
                let mut d = Vec::new();
                garbage(i, &mut d);
                d
            })
            .collect();
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
                send_raw(&socket, "valid/data", port, &pool[(sent % 5_000) as usize]);
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
    while publish_start.elapsed() < Duration::from_secs(SECS) && published < 20_000 {
        data.publish(&published).unwrap();
        published += 1;
        std::thread::sleep(Duration::from_millis(1));
        while valid.try_recv().is_some() {
            received += 1;
        }
    }
    let (sent, flood_time) = flood.join().unwrap();
    std::thread::sleep(Duration::from_millis(300));
    while valid.try_recv().is_some() {
        received += 1;
    }
    let ratio = received as f64 / published as f64;
    let stats = receiver.stats();
    let rss_after = rss_kb();
    eprintln!(
        "flood: {sent} garbage datagrams in {:.1} s ({:.0}/s); valid: {received} of {published} delivered ({:.1} %); \
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
    assert!(
        stats.dropped_total() > sent / 2,
        "garbage is counted: {stats:?}"
    );
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
}

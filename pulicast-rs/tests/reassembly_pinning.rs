//! A stranger without keys pins reassembly memory on an open channel. A test
//! binary of its own: it measures the resident memory of its process, which
//! other tests beside it would add to.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use common::*;
use pulicast::Key;
use pulicast_proto::fragment::{Fragment, ReassemblyLimits};

/// From ten sockets, 90 % of the fragments of ten messages on an open
/// channel the victim subscribes, sized to fill the 512 MiB of reassembly
/// memory all channels share, then one more fragment of each every second
/// (under the old rule, the timeout ran from the latest fragment, so this
/// held the memory forever). Meanwhile twenty 4 MiB messages on a channel
/// sealed under the victim's key all arrive (none did before: the open
/// channel's fragments took the whole budget). Once the attack stops, the
/// messages reach their deadline and the victim's memory goes back near
/// where it was.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fragments_on_an_open_channel_never_keep_a_sealed_channel_out() {
    let port = free_port();
    let key = Key::from_bytes([7; 32]);
    let victim = node("victim", port)
        .keys_from_env(false)
        .key("secure", key.clone())
        .start()
        .await
        .unwrap();
    let publisher = node("publisher", port)
        .keys_from_env(false)
        .key("secure", key)
        .start()
        .await
        .unwrap();
    let _open = victim.channel("open/big").subscribe_raw().unwrap();
    let mut sealed = victim.channel("secure/big").subscribe_raw().unwrap();
    tokio::time::sleep(Duration::from_millis(300)).await;
    let baseline = resident_bytes();

    // The attack's fragments: only their headers and sizes matter. Ten
    // messages that leave less than 4 MiB of the total budget free.
    let sockets = 10;
    let size = (ReassemblyLimits::default().total / sockets - (128 << 10)) as u32;
    let count = Fragment::count_for("open/big", size as usize) as u16;
    let chunk = vec![0x5a; Fragment::chunk_size(size, count)];
    let fragment = |seq: u32, index: u16| {
        let mut d = Vec::new();
        Fragment::encode_header("open/big", seq, size, index, count, &mut d);
        let len = Fragment::chunk_of_len(size, index, count);
        d.extend_from_slice(&chunk[..len]);
        d
    };
    let attackers: Vec<UdpSocket> = (0..sockets).map(|_| raw_sender()).collect();
    let sent_until = count as usize * 9 / 10;
    let flood = Instant::now();
    for index in 0..sent_until as u16 {
        for (seq, socket) in attackers.iter().enumerate() {
            send_raw(socket, "open/big", port, &fragment(seq as u32, index));
        }
        if index % 2 == 0 {
            // Paced a little: what the victim can't take is lost anyway.
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    }
    let peak_after_flood = resident_bytes();
    eprintln!(
        "flood: {} fragments from each of {sockets} sockets in {:?}",
        sent_until,
        flood.elapsed()
    );

    // The trickle, and the sealed channel's messages.
    let big: Vec<u8> = (0..4 << 20).map(|i: u32| (i % 251) as u8).collect();
    let channel = publisher.channel("secure/big");
    let mut delivered = 0;
    let mut trickled = sent_until as u16;
    let mut last_trickle = Instant::now();
    for _ in 0..20 {
        if last_trickle.elapsed() >= Duration::from_secs(1) && trickled < count {
            for (seq, socket) in attackers.iter().enumerate() {
                send_raw(socket, "open/big", port, &fragment(seq as u32, trickled));
            }
            trickled += 1;
            last_trickle = Instant::now();
        }
        channel.publish_bytes(&big).unwrap();
        let deadline = Instant::now() + Duration::from_millis(250);
        while Instant::now() < deadline {
            if let Some(m) = sealed.try_recv() {
                assert_eq!(m.value.len(), big.len());
                delivered += 1;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
    while let Some(m) = sealed.recv_timeout(Duration::from_millis(500)) {
        assert_eq!(m.value.len(), big.len());
        delivered += 1;
    }
    let during = resident_bytes();

    // The attack stops: every message it started reaches its deadline.
    let deadline = ReassemblyLimits::default().deadline_for(size as usize);
    tokio::time::sleep(deadline + Duration::from_secs(1)).await;
    let after = resident_bytes();
    let stats = victim.stats();
    eprintln!(
        "resident: {} MB before, {} MB after the flood, {} MB during the trickle, {} MB after; \
         {delivered} of 20 sealed messages delivered; {:?}",
        baseline >> 20,
        peak_after_flood >> 20,
        during >> 20,
        after >> 20,
        stats.dropped,
    );
    assert_eq!(delivered, 20, "sealed messages kept out");
    assert!(
        after.saturating_sub(baseline) < 100 << 20,
        "memory stayed {} MB above where it was",
        (after - baseline) >> 20
    );
}

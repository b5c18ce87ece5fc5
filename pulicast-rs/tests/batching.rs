//! Batching between real nodes on loopback: order, leads, delays, flushes,
//! large messages, several publishing threads, malformed batches and stop.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::net::UdpSocket;
use std::time::Duration;

use common::{
    eventually, free_port, node, packet, raw_sender, recv, send_raw, wire_listener, WAIT,
};
use pulicast::{DropReason, Error};
use pulicast_proto::wire::batch::{Batch, BatchBuilder};

/// The datagrams the listener has heard, until it has been quiet a while.
fn heard(listener: &UdpSocket) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut buf = vec![0; 65536];
    while let Ok(n) = listener.recv(&mut buf) {
        out.push(buf[..n].to_vec());
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flushed_batch_is_one_datagram_and_arrives_as_single_messages() {
    let port = free_port();
    let sub_node = node("sub", port)
        .queue_capacity(4096)
        .start()
        .await
        .unwrap();
    let mut sub = sub_node.channel("imu").subscribe_ordered::<i64>().unwrap();
    let listener = wire_listener("imu", port, Duration::from_millis(300));
    let pub_node = node("pub", port).start().await.unwrap();
    let imu = pub_node.channel("imu");
    // Until gossip vouches for the subscriber, its 2.x heartbeat alone makes
    // it look like a 2.x node, which would (rightly) stop batching.
    eventually("gossip knows the subscriber", || {
        imu.subscribers().iter().any(|m| !m.compat)
    })
    .await;
    tokio::time::sleep(Duration::from_millis(100)).await;
    imu.enable_batching(Duration::from_secs(1)).unwrap();
    for i in 0..1000i64 {
        imu.publish(&i).unwrap();
    }
    imu.flush().unwrap();
    for i in 0..1000i64 {
        let m = recv(&mut sub).await;
        assert_eq!((m.value, m.seq, m.lead), (i, i as u32, 1));
    }
    let batches: Vec<Vec<u8>> = heard(&listener)
        .into_iter()
        .filter(|d| Batch::is_batch(d))
        .collect();
    // 1000 i64 messages (8 + 8 bytes each) fit one datagram.
    assert_eq!(batches.len(), 1, "{} batches on the wire", batches.len());
    let batch = Batch::decode(&batches[0]).unwrap();
    assert_eq!(
        (batch.channel, batch.first_seq, batch.count),
        ("imu", 0, 1000)
    );
}

/// `publish_bytes_now` on a batching channel: what the batch holds goes
/// first, as one batch, then the message in a datagram of its own, with
/// the next sequence number; nothing waits for the batch's delay.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_message_published_now_follows_the_batch_in_a_datagram_of_its_own() {
    let port = free_port();
    let sub_node = node("sub", port).start().await.unwrap();
    let mut sub = sub_node.channel("log").subscribe_raw().unwrap();
    let listener = wire_listener("log", port, Duration::from_millis(300));
    let pub_node = node("pub", port).start().await.unwrap();
    let log = pub_node.channel("log");
    eventually("gossip knows the subscriber", || {
        log.subscribers().iter().any(|m| !m.compat)
    })
    .await;
    log.enable_batching(Duration::from_secs(1)).unwrap();
    for line in [&b"one"[..], b"two", b"three"] {
        log.publish_bytes(line).unwrap();
    }
    log.publish_bytes_now(b"now").unwrap();
    for (seq, line) in [&b"one"[..], b"two", b"three", b"now"].iter().enumerate() {
        let m = recv(&mut sub).await;
        assert_eq!((&m.value[..], m.seq), (*line, seq as u32));
    }
    let datagrams = heard(&listener);
    let batches: Vec<_> = datagrams.iter().filter(|d| Batch::is_batch(d)).collect();
    assert_eq!(batches.len(), 1, "one batch: {datagrams:?}");
    assert_eq!(Batch::decode(batches[0]).unwrap().count, 3);
    let single = pulicast_proto::wire::Packet::decode(datagrams.last().unwrap()).unwrap();
    assert_eq!((single.seq, single.payload), (3, &b"now"[..]));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_batch_leaves_by_its_delay_without_a_flush() {
    let port = free_port();
    let n = node("n", port).start().await.unwrap();
    let mut sub = n.channel("odom").subscribe::<f64>().unwrap();
    let odom = n.channel("odom");
    odom.enable_batching(Duration::from_millis(20)).unwrap();
    odom.publish(&1.0).unwrap();
    odom.publish(&2.0).unwrap();
    // Nobody flushes: the flusher thread sends the batch.
    assert_eq!(recv(&mut sub).await.value, 1.0);
    assert_eq!(recv(&mut sub).await.value, 2.0);
    // And again after an idle spell: the thread waits for the next batch.
    tokio::time::sleep(Duration::from_millis(50)).await;
    odom.publish(&3.0).unwrap();
    let m = recv(&mut sub).await;
    assert_eq!((m.value, m.seq, m.lead), (3.0, 2, 1));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn large_messages_on_a_batching_channel_keep_their_order() {
    let port = free_port();
    let n = node("n", port).queue_capacity(64).start().await.unwrap();
    let mut sub = n.channel("mixed").subscribe_ordered::<Vec<u8>>().unwrap();
    let mixed = n.channel("mixed");
    mixed.enable_batching(Duration::from_secs(1)).unwrap();
    let sizes = [10usize, 20, 40_000, 30, 70_000, 300_000, 5, 64_000, 6];
    for (i, &size) in sizes.iter().enumerate() {
        mixed.publish(&vec![i as u8; size]).unwrap();
    }
    mixed.flush().unwrap();
    for (i, &size) in sizes.iter().enumerate() {
        let m = tokio::time::timeout(Duration::from_secs(10), sub.recv())
            .await
            .unwrap()
            .unwrap();
        assert_eq!((m.value.len(), m.seq, m.lead), (size, i as u32, 1));
        assert!(m.value.iter().all(|&b| b == i as u8));
    }
}

#[test]
fn several_publishing_threads_share_one_batching_channel() {
    let port = free_port();
    let n = node("n", port)
        .queue_capacity(1 << 16)
        .start_blocking()
        .unwrap();
    let mut sub = n.channel("events").subscribe_raw().unwrap();
    let events = n.channel("events");
    events.enable_batching(Duration::from_millis(5)).unwrap();
    let threads: Vec<_> = (0..4u8)
        .map(|t| {
            let events = events.clone();
            std::thread::spawn(move || {
                for i in 0..2500u16 {
                    let mut m = [t; 3];
                    m[1..].copy_from_slice(&i.to_be_bytes());
                    events.publish_bytes(&m).unwrap();
                }
            })
        })
        .collect();
    for t in threads {
        t.join().unwrap();
    }
    events.flush().unwrap();
    let mut seen = vec![false; 10_000];
    let mut next_per_thread = [0u16; 4];
    for _ in 0..10_000 {
        let m = sub.recv_timeout(WAIT).expect("every message arrives");
        // Batches hold consecutive sequence numbers and leave in order.
        assert_eq!(m.lead, 1, "seq {}", m.seq);
        assert!(!std::mem::replace(&mut seen[m.seq as usize], true));
        let (t, i) = (
            usize::from(m.value[0]),
            u16::from_be_bytes([m.value[1], m.value[2]]),
        );
        assert_eq!(i, next_per_thread[t], "thread {t} out of order");
        next_per_thread[t] += 1;
    }
    assert!(seen.iter().all(|&s| s));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stopping_node_sends_its_pending_batches() {
    let port = free_port();
    let sub_node = node("sub", port).start().await.unwrap();
    let mut sub = sub_node.channel("log").subscribe::<String>().unwrap();
    let pub_node = node("pub", port).start().await.unwrap();
    let log = pub_node.channel("log");
    log.enable_batching(Duration::from_secs(1)).unwrap();
    log.publish("last words").unwrap();
    pub_node.stop();
    let m = tokio::time::timeout(Duration::from_millis(900), sub.recv())
        .await
        .expect("sent at stop, not after the delay")
        .unwrap();
    assert_eq!(m.value, "last words");
    assert!(matches!(log.flush(), Err(Error::NodeStopped)));
    assert!(matches!(
        log.enable_batching(Duration::from_millis(1)),
        Err(Error::NodeStopped)
    ));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_delays_and_names_are_refused() {
    let port = free_port();
    let n = node("n", port).start().await.unwrap();
    let c = n.channel("c");
    for delay in [Duration::ZERO, Duration::from_secs(2)] {
        assert!(matches!(
            c.enable_batching(delay),
            Err(Error::InvalidConfig { .. })
        ));
    }
    assert!(matches!(
        n.channel("__nodes")
            .enable_batching(Duration::from_millis(1)),
        Err(Error::InvalidName { .. })
    ));
    assert!(matches!(
        n.channel("bad\u{7}name")
            .enable_batching(Duration::from_millis(1)),
        Err(Error::InvalidName { .. })
    ));
    // Flushing a channel that does not batch is harmless.
    c.flush().unwrap();
    c.enable_batching(Duration::from_millis(1)).unwrap();
    c.disable_batching().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn disabling_sends_what_is_pending_and_goes_back_to_single_datagrams() {
    let port = free_port();
    let n = node("n", port).start().await.unwrap();
    let mut sub = n.channel("c").subscribe::<i64>().unwrap();
    let listener = wire_listener("c", port, Duration::from_millis(300));
    let c = n.channel("c");
    c.enable_batching(Duration::from_secs(1)).unwrap();
    c.publish(&1i64).unwrap();
    c.disable_batching().unwrap();
    c.publish(&2i64).unwrap();
    assert_eq!(recv(&mut sub).await.value, 1);
    assert_eq!(recv(&mut sub).await.value, 2);
    let kinds: Vec<&[u8]> = heard(&listener)
        .iter()
        .map(|d| {
            if Batch::is_batch(d) {
                &b"PBAT"[..]
            } else {
                &b"PULI"[..]
            }
        })
        .collect();
    assert_eq!(kinds, [&b"PBAT"[..], &b"PULI"[..]]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_batches_are_dropped_whole_and_counted() {
    let port = free_port();
    let n = node("n", port).start().await.unwrap();
    let mut sub = n.channel("c").subscribe_raw().unwrap();
    let raw = raw_sender();
    let mut builder = BatchBuilder::new();
    builder.start("c", 0);
    builder.push(b"first");
    builder.push(b"second");
    let good = builder.finish().to_vec();
    // Truncated: the second entry runs past the end.
    send_raw(&raw, "c", port, &good[..good.len() - 1]);
    // Trailing garbage after the announced entries.
    let mut trailing = good.clone();
    trailing.extend_from_slice(b"xx");
    send_raw(&raw, "c", port, &trailing);
    send_raw(&raw, "c", port, b"PBAT\x01c");
    // A valid packet and a valid batch still get through.
    send_raw(&raw, "c", port, &packet("c", 100, b"plain"));
    let m = recv(&mut sub).await;
    assert_eq!((&m.value[..], m.seq), (&b"plain"[..], 100));
    builder.start("c", 101);
    builder.push(b"batched");
    send_raw(&raw, "c", port, builder.finish());
    let m = recv(&mut sub).await;
    assert_eq!((&m.value[..], m.seq, m.lead), (&b"batched"[..], 101, 1));
    eventually("drops counted", || n.stats().dropped_total() >= 3).await;
    let stats = n.stats();
    assert_eq!(
        stats.dropped(DropReason::MalformedPayload) + stats.dropped(DropReason::TooShort),
        3
    );
    assert!(sub.try_recv().is_none(), "nothing of the bad batches");
}

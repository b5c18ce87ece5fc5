//! Zero heap allocations per message on the publish path and on the receive
//! path up to the subscriber, counted by a counting allocator
//! (`allocation-counter`, which counts this thread's allocations).
//!
//! Everything runs on one thread (a current-thread runtime driven inside the
//! measurement), so the count sees the publish, the receive loop and the
//! delivery. Gossip and the 2.x heartbeat are off here: they allocate on
//! their own timers, not per message.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;

/// A node without timers of its own, on a current-thread runtime.
fn quiet_node(queue_capacity: usize) -> (tokio::runtime::Runtime, pulicast::Node) {
    quiet_node_with(queue_capacity, |b| b)
}

/// The same, with more options.
fn quiet_node_with(
    queue_capacity: usize,
    options: impl FnOnce(pulicast::NodeBuilder) -> pulicast::NodeBuilder,
) -> (tokio::runtime::Runtime, pulicast::Node) {
    let port = pulicast::unused_port().unwrap();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let builder = pulicast::Node::new("counted")
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .discovery(false)
        .compat_heartbeat(false)
        .keys_from_env(false)
        .queue_capacity(queue_capacity);
    let builder = options(builder);
    let node = runtime.block_on(async { builder.start().await.unwrap() });
    (runtime, node)
}

/// The next message, or a failure (not a hang) if it never comes.
async fn received(
    sub: &mut pulicast::Subscription<pulicast::Bytes>,
) -> pulicast::Message<pulicast::Bytes> {
    tokio::time::timeout(std::time::Duration::from_secs(5), sub.recv())
        .await
        .expect("a published message is received")
        .expect("subscription open")
}

#[test]
fn publishing_and_receiving_allocate_nothing_per_message() {
    exchanges_allocate_nothing(quiet_node(256));
}

/// Sealing and opening (encrypted, the longer path) work in buffers they
/// keep, and open received datagrams where they lie.
#[test]
fn sealed_channels_allocate_nothing_per_message_either() {
    exchanges_allocate_nothing(quiet_node_with(256, |b| {
        b.key("/", pulicast::Key::from_bytes([9; 32])).encrypt(true)
    }));
}

fn exchanges_allocate_nothing((runtime, node): (tokio::runtime::Runtime, pulicast::Node)) {
    let channel = node.channel("alloc/test");
    let mut sub = channel.subscribe_raw().unwrap();
    let payload = [7u8; 64];
    let exchange = |sub: &mut pulicast::Subscription<pulicast::Bytes>, n: usize| {
        runtime.block_on(async {
            for _ in 0..n {
                channel.publish_bytes(&payload).unwrap();
                let m = received(sub).await;
                assert_eq!(m.value.len(), 64);
            }
        })
    };
    // Warm up: buffers, queues and maps reach their working size.
    exchange(&mut sub, 5_000);

    // In rounds of 200, drained after each: the runtime is idle while we
    // publish, so a round must fit the subscription's queue and the
    // kernel's receive buffer (at its default size, about 400 datagrams).
    let mut publishing = 0;
    for _ in 0..10 {
        publishing += allocation_counter::measure(|| {
            for _ in 0..200 {
                channel.publish_bytes(&payload).unwrap();
            }
        })
        .count_total;
        runtime.block_on(async {
            for _ in 0..200 {
                received(&mut sub).await;
            }
        });
    }
    let round_trips = allocation_counter::measure(|| exchange(&mut sub, 100_000));
    eprintln!(
        "allocations: {} for 2000 publishes, {} for 100000 publish+receive",
        publishing, round_trips.count_total
    );
    assert_eq!(publishing, 0, "publishing allocates");
    // Per message nothing: the few allocations left come from rotating the
    // 2 MiB receive buffers (about one per 27 000 datagrams of this size),
    // not from messages.
    assert!(
        round_trips.count_total <= 10,
        "{} allocations for 100 000 messages",
        round_trips.count_total
    );
}

#[test]
fn batching_allocates_nothing_per_message_either() {
    let (runtime, node) = quiet_node(4096);
    let channel = node.channel("alloc/batched");
    channel
        .enable_batching(std::time::Duration::from_secs(1))
        .unwrap();
    let mut sub = channel.subscribe_raw().unwrap();
    let payload = [3u8; 64];
    // 500 messages a batch: the flush sends one datagram, which the receive
    // loop delivers as 500 messages.
    let rounds = |sub: &mut pulicast::Subscription<pulicast::Bytes>, n: usize| {
        runtime.block_on(async {
            for _ in 0..n {
                for _ in 0..500 {
                    channel.publish_bytes(&payload).unwrap();
                }
                channel.flush().unwrap();
                for _ in 0..500 {
                    let m = received(sub).await;
                    assert_eq!((m.value.len(), m.lead), (64, 1));
                }
            }
        })
    };
    rounds(&mut sub, 20);
    let counted = allocation_counter::measure(|| rounds(&mut sub, 200));
    eprintln!(
        "allocations: {} for 100000 batched publish+receive",
        counted.count_total
    );
    assert!(
        counted.count_total <= 10,
        "{} allocations for 100 000 batched messages",
        counted.count_total
    );
}

/// A handler on the receive path: no queue, and nothing allocated per
/// message either (the outbox keeps its capacity).
#[test]
fn handlers_allocate_nothing_per_message() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;
    let (runtime, node) = quiet_node(256);
    let channel = node.channel("alloc/handled");
    let seen = Arc::new(AtomicUsize::new(0));
    let counted = Arc::clone(&seen);
    let _handler = channel
        .subscribe_raw_with(move |m| {
            assert_eq!(m.value.len(), 64);
            counted.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
    let payload = [5u8; 64];
    let exchange = |n: usize| {
        runtime.block_on(async {
            for _ in 0..n {
                let before = seen.load(Ordering::Relaxed);
                channel.publish_bytes(&payload).unwrap();
                let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(5);
                while seen.load(Ordering::Relaxed) == before {
                    assert!(tokio::time::Instant::now() < deadline, "never handled");
                    tokio::task::yield_now().await;
                }
            }
        })
    };
    exchange(5_000);
    let counted = allocation_counter::measure(|| exchange(100_000));
    eprintln!(
        "allocations: {} for 100000 publish+handle",
        counted.count_total
    );
    assert!(
        counted.count_total <= 10,
        "{} allocations for 100 000 handled messages",
        counted.count_total
    );
}

/// Draining a batch at a time reuses the caller's vector and the
/// subscription's own.
#[test]
fn draining_allocates_nothing_per_message() {
    let (runtime, node) = quiet_node(1024);
    let channel = node.channel("alloc/drained");
    channel
        .enable_batching(std::time::Duration::from_secs(1))
        .unwrap();
    let mut sub = channel.subscribe_raw().unwrap();
    let payload = [3u8; 64];
    let mut out = Vec::with_capacity(512);
    let mut rounds = |n: usize| {
        runtime.block_on(async {
            for _ in 0..n {
                for _ in 0..500 {
                    channel.publish_bytes(&payload).unwrap();
                }
                channel.flush().unwrap();
                let mut got = 0;
                while got < 500 {
                    out.clear();
                    let n = tokio::time::timeout(
                        std::time::Duration::from_secs(5),
                        sub.recv_many(&mut out, 512),
                    )
                    .await
                    .expect("a batch is received");
                    assert!(n > 0 && out.iter().all(|m| m.value.len() == 64));
                    got += n;
                }
            }
        })
    };
    rounds(20);
    let counted = allocation_counter::measure(|| rounds(200));
    eprintln!(
        "allocations: {} for 100000 batched publish+recv_many",
        counted.count_total
    );
    assert!(
        counted.count_total <= 10,
        "{} allocations for 100 000 drained messages",
        counted.count_total
    );
}

/// A receive socket takes its first buffer (128 KiB) with its first
/// datagram: of a bridge's or a recorder's thousands of channels (20
/// groups a socket), the sockets that never hear one (a stranger's names
/// nobody sends on) hold none. Once one comes, it is received as ever.
#[test]
fn sockets_that_hear_nothing_hold_no_buffer() {
    let (runtime, node) = quiet_node(16);
    let mut subs: Vec<_> = (0..400)
        .map(|i| {
            node.channel(&format!("quiet/c{i:03}"))
                .subscribe_raw()
                .unwrap()
        })
        .collect();
    let sockets = node.stats().receive_sockets;
    assert!(sockets >= 10, "{sockets} receive sockets");
    // The receive loops start here and wait for their first datagram.
    let idle = allocation_counter::measure(|| {
        runtime.block_on(async {
            tokio::time::sleep(std::time::Duration::from_millis(300)).await;
        });
    });
    eprintln!(
        "{sockets} receive sockets, idle: {} bytes held",
        idle.bytes_current
    );
    assert!(
        idle.bytes_current < (sockets as i64) * (16 << 10),
        "{} bytes held by {sockets} idle sockets",
        idle.bytes_current
    );
    let last = subs.last_mut().unwrap();
    node.channel("quiet/c399")
        .publish_bytes(&[1, 2, 3])
        .unwrap();
    let message = runtime.block_on(received(last));
    assert_eq!(&message.value[..], &[1, 2, 3]);
}

//! Real sockets on loopback: nodes in one process talking over multicast pinned
//! to 127.0.0.1 with TTL 0. Every wait has a timeout.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::net::Ipv4Addr;
use std::time::{Duration, Instant};

use common::{eventually, free_port, node, packet, raw_sender, recv, send_raw, WAIT};
use pulicast::{DropReason, Error, Node, Schema};
use pulicast_proto::wire::zcm::Primitive;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Schema, Debug, Clone, PartialEq)]
struct Pose {
    x: f64,
    y: f64,
    heading: f32,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn typed_primitive_and_raw_messages_between_nodes() {
    let port = free_port();
    let a = node("a", port).namespace("rover1").start().await.unwrap();
    let b = node("b", port).start().await.unwrap();

    let mut poses = b.channel("rover1/pose").subscribe::<Pose>().unwrap();
    let mut texts = b
        .make_namespace("/rover1")
        .channel("ctrl")
        .subscribe::<String>()
        .unwrap();
    let mut raw = b.channel("rover1/left_arm/blob").subscribe_raw().unwrap();
    let mut floats = b.channel("rover1/f").subscribe::<f32>().unwrap();

    let pose = Pose {
        x: 1.0,
        y: 2.0,
        heading: 0.5,
    };
    a.channel("pose").publish(&pose).unwrap();
    a.channel("ctrl").publish(&"Go LEFT!").unwrap();
    a.ns("left_arm")
        .channel("blob")
        .publish_bytes(&[1, 2, 3])
        .unwrap();
    a.channel("f").publish(&1.5f32).unwrap();

    let m = recv(&mut poses).await;
    assert_eq!((m.value, m.lead, m.seq), (pose, 1, 0));
    assert_eq!(recv(&mut texts).await.value, "Go LEFT!");
    assert_eq!(&recv(&mut raw).await.value[..], &[1, 2, 3]);
    assert_eq!(recv(&mut floats).await.value, 1.5);

    a.channel("ctrl").publish(&String::from("again")).unwrap();
    let m = recv(&mut texts).await;
    assert_eq!((m.value.as_str(), m.lead, m.seq), ("again", 1, 1));
    assert_eq!(m.source.ip(), Ipv4Addr::LOCALHOST);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hundred_channels_in_one_node() {
    let port = free_port();
    let sub = node("sub", port).start().await.unwrap();
    let publisher = node("pub", port).start().await.unwrap();
    let mut subs: Vec<_> = (0..100)
        .map(|i| {
            sub.channel(&format!("many/ch{i}"))
                .subscribe::<i64>()
                .unwrap()
        })
        .collect();
    for i in 0..100 {
        publisher
            .channel(&format!("many/ch{i}"))
            .publish(&(i as i64))
            .unwrap();
    }
    for (i, s) in subs.iter_mut().enumerate() {
        let m = recv(s).await;
        assert_eq!(m.value, i as i64, "channel {i}");
    }
    // 101 groups (with __nodes) do not fit the kernel's per-socket limit.
    let limit: usize = std::fs::read_to_string("/proc/sys/net/ipv4/igmp_max_memberships")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(20);
    if limit < 101 {
        assert!(sub.stats().receive_sockets >= 101usize.div_ceil(limit));
    }
    // Unsubscribing everything leaves the groups; subscribing again works.
    subs.clear();
    let mut again = sub.channel("many/ch7").subscribe::<i64>().unwrap();
    publisher.channel("many/ch7").publish(&7i64).unwrap();
    assert_eq!(recv(&mut again).await.value, 7);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_datagrams_are_counted_and_do_not_disturb_valid_ones() {
    let port = free_port();
    let n = node("victim", port).start().await.unwrap();
    let mut values = n.channel("x").subscribe::<i64>().unwrap();
    let s = raw_sender();

    let good = |seq: u32| {
        let mut payload = Vec::new();
        Primitive::I64(i64::from(seq)).encode(&mut payload);
        packet("x", seq, &payload)
    };
    let mut truncated = good(100);
    truncated.truncate(truncated.len() - 3);
    let mut string_payload = Vec::new();
    Primitive::String("not an int".into()).encode(&mut string_payload);
    let garbage: Vec<(Vec<u8>, DropReason)> = vec![
        (b"PU".to_vec(), DropReason::TooShort),
        (b"LCM2xxxxxxxxxxx".to_vec(), DropReason::BadMagic),
        (b"PULI\xf0x\0\0\0\0".to_vec(), DropReason::NamePastEnd),
        (b"PULI\x01\xfe\0\0\0\0".to_vec(), DropReason::NonAsciiName),
        (truncated, DropReason::TruncatedPayload),
        (packet("x", 101, &string_payload), DropReason::WrongType),
        (
            packet("x", 102, &[0xde, 0xad]),
            DropReason::TruncatedPayload,
        ),
        (packet("x", 103, &[0xff; 300]), DropReason::WrongType),
    ];
    for seq in 0..5 {
        send_raw(&s, "x", port, &good(seq));
        for (g, _) in &garbage {
            send_raw(&s, "x", port, g);
        }
    }
    for seq in 0..5 {
        let m = recv(&mut values).await;
        assert_eq!(m.value, i64::from(seq));
    }
    // The node still works afterwards; receiving past the last garbage also
    // makes the subscription decode (and count) everything queued before it.
    n.channel("x").publish(&42i64).unwrap();
    assert_eq!(recv(&mut values).await.value, 42);

    let want = |r: DropReason| 5 * garbage.iter().filter(|(_, reason)| *reason == r).count() as u64;
    let stats = n.stats();
    for reason in DropReason::ALL {
        assert_eq!(stats.dropped(reason), want(reason), "{reason:?}");
    }
    assert_eq!(stats.dropped_total(), 5 * garbage.len() as u64);
    assert_eq!(stats.messages_delivered, 6);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leads_and_ordered_subscriptions() {
    let port = free_port();
    let n = node("orderly", port).start().await.unwrap();
    let mut all = n.channel("seq").subscribe_raw().unwrap();
    let mut ordered = n.channel("seq").subscribe_ordered::<bool>().unwrap();
    let s = raw_sender();
    let mut t = Vec::new();
    Primitive::Bool(true).encode(&mut t);
    for seq in [5u32, 6, 9, 7, 9, 10] {
        send_raw(&s, "seq", port, &packet("seq", seq, &t));
    }
    let mut leads = Vec::new();
    for _ in 0..6 {
        leads.push(recv(&mut all).await.lead);
    }
    assert_eq!(leads, [1, 1, 3, -2, 0, 1]);
    let mut seqs = Vec::new();
    for _ in 0..4 {
        seqs.push(recv(&mut ordered).await.seq);
    }
    assert_eq!(seqs, [5, 6, 9, 10]);
    assert_eq!(n.stats().out_of_order_skipped, 2);
}

/// A node that sends no 2.x heartbeats, so that what it and its peers
/// count as received is the test's traffic only.
fn quiet(name: &str, port: u16) -> pulicast::NodeBuilder {
    node(name, port).compat_heartbeat(false)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_subscriber_loses_oldest_and_others_are_unaffected() {
    let port = free_port();
    // Without 2.x heartbeats, only the burst counts as received: a
    // heartbeat counted first would end the wait below before the burst's
    // last message was queued.
    let n = quiet("slow", port).queue_capacity(4).start().await.unwrap();
    let mut slow = n.channel("burst").subscribe::<i64>().unwrap();
    let p = quiet("fast", port).start().await.unwrap();
    for i in 0..10i64 {
        p.channel("burst").publish(&i).unwrap();
    }
    eventually("all ten received", || n.stats().messages_received >= 10).await;
    let got: Vec<i64> = std::iter::from_fn(|| slow.try_recv().map(|m| m.value)).collect();
    assert_eq!(got, [6, 7, 8, 9]);
    assert_eq!(n.stats().dropped(DropReason::QueueOverflow), 6);
    assert_eq!(n.stats().messages_received, 10);

    // The other policy keeps the first ones.
    let port = free_port();
    let n = quiet("prefix", port)
        .queue_capacity(4)
        .queue_policy(pulicast::QueuePolicy::DropNewest)
        .start()
        .await
        .unwrap();
    let mut log = n.channel("log").subscribe::<i64>().unwrap();
    let p = quiet("logger", port).start().await.unwrap();
    for i in 0..10i64 {
        p.channel("log").publish(&i).unwrap();
    }
    eventually("all ten received", || n.stats().messages_received >= 10).await;
    let got: Vec<i64> = std::iter::from_fn(|| log.try_recv().map(|m| m.value)).collect();
    assert_eq!(got, [0, 1, 2, 3]);
    assert_eq!(n.stats().dropped(DropReason::QueueOverflow), 6);
    assert_eq!(n.stats().messages_received, 10);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_misuse_gets_clear_errors() {
    let port = free_port();
    let n = node("misuse", port).start().await.unwrap();
    assert!(matches!(
        n.channel("").publish(&1i64),
        Err(Error::InvalidName { .. })
    ));
    assert!(matches!(
        n.channel("r\u{f6}ver").subscribe::<i64>(),
        Err(Error::InvalidName { .. })
    ));
    assert!(matches!(
        n.try_channel(&"x".repeat(256)),
        Err(Error::InvalidName { .. })
    ));
    assert!(matches!(
        n.ns("bad\u{1}").channel("x").publish(&1i64),
        Err(Error::InvalidName { .. })
    ));
    let too_big = vec![0u8; (64 << 20) + 1];
    assert!(matches!(
        n.channel("big").publish_bytes(&too_big),
        Err(Error::PayloadTooLarge { max, .. }) if max == 64 << 20
    ));

    assert!(matches!(
        n.channel("__nodes").publish_bytes(b"x"),
        Err(Error::InvalidName {
            reason: pulicast::NameError::Reserved,
            ..
        })
    ));
    assert!(
        n.channel("/__nodes").subscribe_raw().is_ok(),
        "listening to heartbeats is fine"
    );

    let mut sub = n.channel("s").subscribe::<i64>().unwrap();
    n.stop();
    assert!(matches!(
        n.channel("s").publish(&1i64),
        Err(Error::NodeStopped)
    ));
    assert!(matches!(
        n.channel("s").subscribe::<i64>(),
        Err(Error::NodeStopped)
    ));
    assert!(tokio::time::timeout(WAIT, sub.recv())
        .await
        .expect("returns at once")
        .is_none());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn peers_come_and_go_with_heartbeats() {
    let port = free_port();
    let a = node("alpha", port).start().await.unwrap();
    let _sub = a.channel("rover1/pose").subscribe::<Pose>().unwrap();
    let b = node("beta", port)
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    b.channel("pose")
        .publish(&Pose {
            x: 0.0,
            y: 0.0,
            heading: 0.0,
        })
        .unwrap();

    eventually("b sees a", || {
        b.peers()
            .iter()
            .any(|p| p.session_id == a.compat_session_id())
    })
    .await;
    eventually("a sees b's publication", || {
        a.peers()
            .iter()
            .any(|p| p.name == "beta" && p.publishes().any(|c| c == "rover1/pose"))
    })
    .await;
    eventually("b sees alpha's subscription and heartbeat", || {
        b.peers().iter().any(|p| {
            p.name == "alpha"
                && p.subscribes().any(|c| c == "rover1/pose")
                && p.publishes().any(|c| c == "__nodes")
        })
    })
    .await;
    assert!(
        !a.peers()
            .iter()
            .any(|p| p.session_id == a.compat_session_id()),
        "self not listed"
    );

    drop(b);
    eventually("a forgets b", || a.peers().iter().all(|p| p.name != "beta")).await;
}

#[test]
fn blocking_facade_without_async_code() {
    let port = free_port();
    let n = node("blocking", port).start_blocking().unwrap();
    let mut sub = n.channel("loop").subscribe::<i32>().unwrap();
    assert!(sub.try_recv().is_none());
    assert!(sub.recv_timeout(Duration::from_millis(20)).is_none());
    n.channel("loop").publish(&3i32).unwrap();
    assert_eq!(sub.recv_timeout(WAIT).map(|m| m.value), Some(3));
    n.channel("loop").publish(&4i32).unwrap();
    assert_eq!(sub.recv_blocking().map(|m| m.value), Some(4));
    drop(n);
    assert!(
        sub.recv_blocking().is_none(),
        "dropping the last node handle stops it"
    );
}

/// More channels than one receive socket may join (20 groups by default),
/// subscribed from a plain thread: the node opens another socket on its
/// own runtime (this panicked with "no reactor running" before).
#[test]
fn a_blocking_node_subscribes_more_groups_than_one_socket_holds() {
    let port = free_port();
    let n = node("many_blocking", port).start_blocking().unwrap();
    let mut subs: Vec<_> = (0..40)
        .map(|i| {
            n.channel(&format!("blocking/ch{i}"))
                .subscribe::<i64>()
                .unwrap()
        })
        .collect();
    assert!(n.stats().receive_sockets >= 2);
    for (i, sub) in subs.iter_mut().enumerate() {
        n.channel(&format!("blocking/ch{i}"))
            .publish(&(i as i64))
            .unwrap();
        assert_eq!(sub.recv_timeout(WAIT).map(|m| m.value), Some(i as i64));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_wrong_types_does_not_evict_valid_messages() {
    let port = free_port();
    let n = quiet("picky", port)
        .queue_capacity(4)
        .start()
        .await
        .unwrap();
    let mut ints = n.channel("mixed").subscribe::<i64>().unwrap();
    let p = quiet("noisy", port).start().await.unwrap();
    let mixed = p.channel("mixed");
    for i in 0..3i64 {
        for _ in 0..20 {
            mixed.publish("not an int").unwrap();
        }
        mixed.publish(&i).unwrap();
    }
    eventually("all received", || n.stats().messages_received >= 63).await;
    let got: Vec<i64> = std::iter::from_fn(|| ints.try_recv().map(|m| m.value)).collect();
    assert_eq!(got, [0, 1, 2]);
    let stats = n.stats();
    assert_eq!(stats.dropped(DropReason::WrongType), 60);
    assert_eq!(stats.dropped(DropReason::QueueOverflow), 0);
    assert_eq!(stats.messages_received, 63);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heartbeats_always_lead_with_nodes_even_when_channels_overflow_them() {
    let port = free_port();
    let busy = node("busy", port).start().await.unwrap();
    let watcher = node("watcher", port).start().await.unwrap();
    let mut heartbeats = watcher.channel("__nodes").subscribe_raw().unwrap();
    // 320 channels of 200-byte names (215 bytes each) do not fit one datagram.
    for i in 0..320 {
        busy.channel(&format!("{i:03}{}", "x".repeat(197)))
            .publish(&1i64)
            .unwrap();
    }
    let deadline = Instant::now() + WAIT;
    loop {
        assert!(
            Instant::now() < deadline,
            "no full heartbeat from the busy node"
        );
        let m = recv(&mut heartbeats).await;
        let hb = pulicast_proto::wire::zcm::decode_heartbeat(&m.value).unwrap();
        if hb.session_id != busy.compat_session_id() || hb.channels.len() < 100 {
            continue;
        }
        assert_eq!(hb.channels[0].name, "__nodes");
        assert!(hb.channels[0].is_published);
        assert!(hb.channels.len() < 321, "some channels were left out");
        assert!(m.value.len() <= 65507);
        // Creation order, as 2.x lists them.
        let names: Vec<&str> = hb.channels[1..].iter().map(|c| &c.name[..3]).collect();
        let mut sorted = names.clone();
        sorted.sort();
        assert_eq!(names, sorted);
        break;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn large_messages_travel_in_fragments() {
    let port = free_port();
    let n = node("camera", port)
        .queue_capacity(8)
        .start()
        .await
        .unwrap();
    let mut images = n.channel("cam/image").subscribe_raw().unwrap();
    let mut typed = n.channel("cam/typed").subscribe::<Vec<u8>>().unwrap();
    let p = node("source", port).start().await.unwrap();
    for (i, size) in [65_000usize, 1 << 20, 4 << 20].into_iter().enumerate() {
        let image: Vec<u8> = (0..size).map(|k| (k % 251) as u8 ^ i as u8).collect();
        p.channel("cam/image").publish_bytes(&image).unwrap();
        let m = tokio::time::timeout(Duration::from_secs(10), images.recv())
            .await
            .unwrap()
            .unwrap();
        assert_eq!(m.value.len(), size);
        assert!(m.value[..] == image[..], "{size} bytes differ");
        assert_eq!((m.lead, m.seq), (1, i as u32));
    }
    let big: Vec<u8> = vec![7; 3 << 20];
    p.channel("cam/typed").publish(&big).unwrap();
    let m = tokio::time::timeout(Duration::from_secs(10), typed.recv())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(m.value, big);
    assert_eq!(n.stats().dropped(DropReason::IncompleteMessage), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fragments_of_several_senders_interleaved_with_packets_arrive_intact() {
    let port = free_port();
    let n = node("sink", port)
        .queue_capacity(4096)
        .start()
        .await
        .unwrap();
    let mut sub = n.channel("mix/big").subscribe_raw().unwrap();
    let senders: Vec<Node> = futures_start(port, 2).await;
    // Two senders' fragments interleave datagram by datagram, with small
    // packets of the same channel between them.
    let threads: Vec<_> = senders
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let channel = s.channel("mix/big");
            std::thread::spawn(move || {
                for i in 0..20u32 {
                    let size = if i % 3 == 0 {
                        100
                    } else {
                        200_000 + 1000 * i as usize
                    };
                    let fill = (k as u8) << 7 | i as u8;
                    channel.publish_bytes(&vec![fill; size]).unwrap();
                }
            })
        })
        .collect();
    for t in threads {
        t.join().unwrap();
    }
    let mut seen = std::collections::HashSet::new();
    while seen.len() < 40 {
        let m = tokio::time::timeout(Duration::from_secs(10), sub.recv())
            .await
            .expect("every message arrives on loopback")
            .unwrap();
        let fill = m.value[0];
        let i = u32::from(fill & 0x7f);
        let expected = if i % 3 == 0 {
            100
        } else {
            200_000 + 1000 * i as usize
        };
        assert_eq!(m.value.len(), expected);
        assert!(
            m.value.iter().all(|&b| b == fill),
            "message {fill:#x} corrupted"
        );
        assert!(seen.insert(fill), "message {fill:#x} twice");
    }
    assert_eq!(n.stats().dropped(DropReason::IncompleteMessage), 0);
}

async fn futures_start(port: u16, count: usize) -> Vec<Node> {
    let mut out = Vec::new();
    for k in 0..count {
        out.push(node(&format!("src{k}"), port).start().await.unwrap());
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reassembly_limits_are_the_nodes_to_set() {
    use pulicast_proto::fragment::ReassemblyLimits;
    let port = free_port();
    let limits = ReassemblyLimits {
        per_source: 300_000,
        per_channel: 300_000,
        total: 300_000,
        timeout: Duration::from_secs(1),
    };
    let n = node("small", port)
        .reassembly_limits(limits)
        .start()
        .await
        .unwrap();
    let mut sub = n.channel("big").subscribe_raw().unwrap();
    let p = node("sender", port).start().await.unwrap();
    // Over the budget: dropped and counted, not delivered.
    p.channel("big").publish_bytes(&vec![1u8; 1 << 20]).unwrap();
    eventually("the refusal counted", || {
        n.stats().dropped(DropReason::IncompleteMessage) >= 1
    })
    .await;
    // Within it: delivered.
    p.channel("big").publish_bytes(&vec![2u8; 150_000]).unwrap();
    let m = recv(&mut sub).await;
    assert_eq!((m.value.len(), m.value[0]), (150_000, 2));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn runs_of_bytes_published_typed_go_raw_like_publish_bytes() {
    let port = free_port();
    let a = node("bytes_a", port).start().await.unwrap();
    let b = node("bytes_b", port).start().await.unwrap();
    let mut raw = b.channel("blob").subscribe_raw().unwrap();
    let mut vecs = b.channel("blob").subscribe::<Vec<u8>>().unwrap();
    let blob = a.channel("blob");
    blob.publish(&vec![1u8, 2, 3]).unwrap();
    blob.publish(&[4u8, 5][..]).unwrap();
    blob.publish(&Vec::<u8>::new()).unwrap();
    blob.publish(&vec![7u8; 300]).unwrap(); // a two-byte length in postcard
    blob.publish_bytes(&[9, 9]).unwrap();
    let expected: [&[u8]; 5] = [&[1, 2, 3], &[4, 5], &[], &[7; 300], &[9, 9]];
    for want in expected {
        assert_eq!(&recv(&mut raw).await.value[..], want);
        // A Vec<u8> subscription takes any payload raw, as it came.
        assert_eq!(recv(&mut vecs).await.value, want);
    }
    // Raw bytes announce no type.
    let me = a.discovery().local();
    let blob_info = me.channels.iter().find(|c| c.name == "blob").unwrap();
    assert_eq!(blob_info.message_type, None);
}

#[test]
fn a_node_name_with_a_nul_starts_a_blocking_node() {
    // The node's thread is named after the node: a NUL there would panic.
    let port = free_port();
    let n = node("a\0b", port).start_blocking().unwrap();
    assert_eq!(n.name(), "a\0b");
    n.stop();
}

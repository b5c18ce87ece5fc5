//! Interop with the Pulicast 2.x reference implementation (`pulicast==2.0.1`
//! from PyPI, run by `tests/python/peer.py` in a venv that the first test sets
//! up). Everything stays on loopback.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::time::Duration;

use pulicast::Schema;
use pulicast_tests::{free_port, loopback_node, python_peer, python_talker};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

const WAIT: Duration = Duration::from_secs(20);

async fn recv_n<T>(sub: &mut pulicast::Subscription<T>, n: usize) -> Vec<pulicast::Message<T>> {
    let mut out = Vec::new();
    for _ in 0..n {
        let m = tokio::time::timeout(WAIT, sub.recv())
            .await
            .expect("message from the Python peer in time")
            .expect("subscription open");
        out.push(m);
    }
    out
}

/// A Python 2.x node that prints `count` messages of `channel` decoded `as_`.
fn py_subscribe(port: &str, channel: &str, as_: &str, count: &str) -> pulicast_tests::Peer {
    python_peer(&[
        "subscribe",
        "--port",
        port,
        "--name",
        "py_listener",
        "--channel",
        channel,
        "--as",
        as_,
        "--count",
        count,
        "--timeout",
        "20",
    ])
}

fn py_publish(port: u16, channel: &str, kind: &str, value: &str) -> pulicast_tests::Peer {
    let port = port.to_string();
    // `--value=...` so that negative numbers are not taken for options.
    let value = format!("--value={value}");
    python_peer(&[
        "publish",
        "--port",
        &port,
        "--name",
        "py_talker",
        "--channel",
        channel,
        "--kind",
        kind,
        &value,
        "--count",
        "3",
        "--period",
        "0.02",
    ])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_publishes_rust_receives() {
    let port = free_port();
    let node = loopback_node("rust_listener", port).await;
    let mut strs = node.channel("py/str").subscribe::<String>().unwrap();
    let mut ints = node.channel("py/int").subscribe::<i64>().unwrap();
    let mut floats = node.channel("py/float").subscribe::<f64>().unwrap();
    let mut bools = node.channel("py/bool").subscribe::<bool>().unwrap();
    let mut bytes = node.channel("py/bytes").subscribe_raw().unwrap();
    let mut i32s = node.channel("py/i32").subscribe::<i32>().unwrap();

    let peers = [
        py_publish(port, "py/str", "str", "Go LEFT! {i}"),
        py_publish(port, "py/int", "int", "-4{i}"),
        py_publish(port, "py/float", "float", "3.{i}"),
        py_publish(port, "py/bool", "bool", "true"),
        py_publish(port, "py/bytes", "bytes", "00ff0{i}"),
        py_publish(port, "py/i32", "int32_msg", "7{i}"),
    ];

    let check_leads = |leads: Vec<(i64, u32)>| assert_eq!(leads, [(1, 0), (1, 1), (1, 2)]);
    let got = recv_n(&mut strs, 3).await;
    assert_eq!(
        got.iter().map(|m| m.value.as_str()).collect::<Vec<_>>(),
        ["Go LEFT! 0", "Go LEFT! 1", "Go LEFT! 2"]
    );
    check_leads(got.iter().map(|m| (m.lead, m.seq)).collect());
    let got = recv_n(&mut ints, 3).await;
    assert_eq!(
        got.iter().map(|m| m.value).collect::<Vec<_>>(),
        [-40, -41, -42]
    );
    check_leads(got.iter().map(|m| (m.lead, m.seq)).collect());
    let got = recv_n(&mut floats, 3).await;
    assert_eq!(
        got.iter().map(|m| m.value).collect::<Vec<_>>(),
        [3.0, 3.1, 3.2]
    );
    let got = recv_n(&mut bools, 3).await;
    assert!(got.iter().all(|m| m.value));
    let got = recv_n(&mut bytes, 3).await;
    assert_eq!(
        got.iter().map(|m| m.value.to_vec()).collect::<Vec<_>>(),
        [vec![0, 0xff, 0], vec![0, 0xff, 1], vec![0, 0xff, 2]]
    );
    check_leads(got.iter().map(|m| (m.lead, m.seq)).collect());
    let got = recv_n(&mut i32s, 3).await;
    assert_eq!(
        got.iter().map(|m| m.value).collect::<Vec<_>>(),
        [70, 71, 72]
    );

    for peer in peers {
        peer.wait_success(WAIT);
    }
    assert_eq!(node.stats().dropped_total(), 0, "{:?}", node.stats());
}

#[derive(Serialize, Deserialize, Schema)]
struct Native {
    x: f64,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rust_publishes_python_receives() {
    let port = free_port();
    let p = port.to_string();
    let subscriber = |channel: &str, as_: &str, count: &str| py_subscribe(&p, channel, as_, count);
    let subs = [
        ("rs/str", subscriber("rs/str", "str", "3")),
        ("rs/int", subscriber("rs/int", "int", "3")),
        ("rs/float", subscriber("rs/float", "float", "3")),
        ("rs/bool", subscriber("rs/bool", "bool", "3")),
        ("rs/bytes", subscriber("rs/bytes", "bytes", "3")),
        ("rs/small", subscriber("rs/small", "auto", "5")),
        // A 2.x node subscribed to a channel with native messages must survive
        // them: it sees bytes it can't decode, then the string after them.
        ("rs/mixed", subscriber("rs/mixed", "auto", "2")),
    ];
    for (_, s) in &subs {
        s.wait_ready(WAIT);
    }
    let node = loopback_node("rust_talker", port).await;
    for i in 0..3i64 {
        node.channel("rs/str")
            .publish(&format!("hello {i}"))
            .unwrap();
        node.channel("rs/int").publish(&(i - 1)).unwrap();
        node.channel("rs/float").publish(&(0.5 + i as f64)).unwrap();
        node.channel("rs/bool").publish(&(i % 2 == 0)).unwrap();
        node.channel("rs/bytes")
            .publish_bytes(&[0xca, 0xfe, i as u8])
            .unwrap();
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let small = node.channel("rs/small");
    small.publish(&-5i8).unwrap();
    small.publish(&300i16).unwrap();
    small.publish(&70000i32).unwrap();
    small.publish(&255u8).unwrap();
    small.publish(&1.25f32).unwrap();
    node.channel("rs/mixed")
        .publish(&Native { x: 1.0 })
        .unwrap();
    node.channel("rs/mixed").publish("after native").unwrap();

    let mut results = std::collections::HashMap::new();
    for (channel, s) in subs {
        let n = match channel {
            "rs/small" => 5,
            "rs/mixed" => 2,
            _ => 3,
        };
        results.insert(channel, s.take_json(n, WAIT));
        s.wait_success(WAIT);
    }
    let values = |ch: &str| {
        results[ch]
            .iter()
            .map(|m| m["value"].clone())
            .collect::<Vec<Value>>()
    };
    let types = |ch: &str| {
        results[ch]
            .iter()
            .map(|m| m["type"].clone())
            .collect::<Vec<Value>>()
    };
    assert_eq!(
        values("rs/str"),
        [json!("hello 0"), json!("hello 1"), json!("hello 2")]
    );
    assert_eq!(values("rs/int"), [json!(-1), json!(0), json!(1)]);
    assert_eq!(values("rs/float"), [json!(0.5), json!(1.5), json!(2.5)]);
    assert_eq!(values("rs/bool"), [json!(true), json!(false), json!(true)]);
    assert_eq!(
        values("rs/bytes"),
        [json!("cafe00"), json!("cafe01"), json!("cafe02")]
    );
    assert_eq!(types("rs/str"), [json!("str"), json!("str"), json!("str")]);
    assert_eq!(
        values("rs/small"),
        [json!(-5), json!(300), json!(70000), json!(255), json!(1.25)]
    );
    assert_eq!(
        types("rs/small"),
        [
            json!("int"),
            json!("int"),
            json!("int"),
            json!("int"),
            json!("float")
        ]
    );
    assert_eq!(types("rs/mixed")[0], json!("bytes"));
    assert_eq!(values("rs/mixed")[1], json!("after native"));
    for ch in ["rs/str", "rs/int", "rs/bytes"] {
        let leads: Vec<Value> = results[ch].iter().map(|m| m["lead"].clone()).collect();
        assert_eq!(leads, [json!(1), json!(1), json!(1)], "{ch}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_channel_that_a_2x_node_subscribes_is_not_batched() {
    let port = free_port();
    let listener = py_subscribe(&port.to_string(), "rs/batched", "int", "20");
    listener.wait_ready(WAIT);
    let node = loopback_node("rust_batcher", port).await;
    let channel = node.channel("rs/batched");
    // Batching is asked for before and after the 2.x node is known: neither
    // may produce a batch it can't read.
    channel.enable_batching(Duration::from_millis(5)).unwrap();
    let deadline = tokio::time::Instant::now() + WAIT;
    while !channel.subscribers().iter().any(|m| m.compat) {
        assert!(
            tokio::time::Instant::now() < deadline,
            "2.x subscriber not seen"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    for i in 0..20i64 {
        channel.publish(&i).unwrap();
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let got = listener.take_json(20, WAIT);
    listener.wait_success(WAIT);
    let values: Vec<Value> = got.iter().map(|m| m["value"].clone()).collect();
    assert_eq!(values, (0..20).map(|i| json!(i)).collect::<Vec<_>>());
    assert!(got.iter().all(|m| m["lead"] == json!(1)), "{got:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_side_lists_the_other() {
    let port = free_port();
    let node = loopback_node("rust_member", port).await;
    let _sub = node.channel("fleet/pose").subscribe::<String>().unwrap();
    node.channel("fleet/ctrl").publish("hi").unwrap();

    let p = port.to_string();
    let lister = python_peer(&["nodes", "--port", &p, "--name", "py_lister", "--for", "1.5"]);
    let py_session = lister.wait_ready(WAIT)["session_id"]
        .as_i64()
        .expect("session id");

    // Rust sees the Python node while it runs.
    let deadline = std::time::Instant::now() + WAIT;
    loop {
        let peers = node.peers();
        if let Some(py) = peers.iter().find(|p| p.session_id == py_session) {
            assert_eq!(py.name, "py_lister");
            // A 2.x node's first heartbeat lists __nodes as not yet published.
            if py.publishes().any(|c| c == "__nodes") {
                break;
            }
        }
        assert!(
            std::time::Instant::now() < deadline,
            "Python node never listed: {peers:?}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    // The fleet view lists it too, as a 2.x (compat) member with its channels.
    let deadline = std::time::Instant::now() + WAIT;
    let compat = loop {
        if let Some(m) = node
            .discovery()
            .members()
            .into_iter()
            .find(|m| m.key == py_session)
        {
            break m;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "Python node not in the fleet view"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert!(compat.compat && compat.session.is_none());
    assert_eq!(compat.name, "py_lister");

    // Python sees the Rust node, with its channels.
    let listed = lister.take_json(1, WAIT).remove(0);
    let nodes = listed.as_array().expect("array");
    let ours = nodes
        .iter()
        .find(|n| n["session_id"] == json!(node.compat_session_id()))
        .unwrap_or_else(|| panic!("Rust node missing from {nodes:?}"));
    assert_eq!(ours["name"], "rust_member");
    let channel = |name: &str| {
        ours["channels"]
            .as_array()
            .and_then(|cs| cs.iter().find(|c| c["name"] == name).cloned())
            .unwrap_or_else(|| panic!("{name} missing in {ours}"))
    };
    assert_eq!(channel("fleet/ctrl")["published"], true);
    assert_eq!(channel("fleet/pose")["subscribed"], true);
    assert_eq!(ours["heartbeat_period_s"], 0.1);
    lister.wait_success(WAIT);

    // And forgets it after it stops (3 missed heartbeats).
    let deadline = std::time::Instant::now() + WAIT;
    while node.peers().iter().any(|p| p.session_id == py_session) {
        assert!(
            std::time::Instant::now() < deadline,
            "Python node never expired"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Receives until 3 messages of `node` came, each of the publisher heard.
async fn hears(laser: &mut pulicast::NearestSubscription<String>, node: &str) {
    let deadline = std::time::Instant::now() + WAIT;
    let mut got = 0;
    while got < 3 {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        let event = tokio::time::timeout(left, laser.recv_event())
            .await
            .unwrap_or_else(|_| panic!("never heard {node}: {:?}", laser.hearing()))
            .unwrap();
        if let pulicast::NearestEvent::Message(m) = event {
            let heard = laser.hearing().unwrap();
            assert_eq!(m.source, heard.source);
            let from_python = m.value.starts_with("hi ");
            assert_eq!(
                from_python,
                heard.node == "py_laser",
                "{} from {heard:?}",
                m.value
            );
            if heard.node == node {
                got += 1;
            }
        }
    }
}

/// A nearest subscription hears a 2.x publisher (whose data address its
/// heartbeats do not give: the source is learnt from the channel), moves
/// to a nearer pulicast-rs publisher when one starts, and back when that
/// one stops.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nearest_subscription_hears_a_2x_publisher_and_a_nearer_rust_one() {
    let port = free_port();
    let p = port.to_string();
    // 400 messages, 50 ms apart: 20 s at most.
    let talker = python_talker(&p, "py_laser", "laser", 400);
    talker.wait_ready(WAIT);
    let listener = pulicast::Node::new("listener")
        .port(port)
        .interface(std::net::Ipv4Addr::LOCALHOST)
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    let mut laser = listener.subscribe_nearest::<String>("laser").unwrap();
    hears(&mut laser, "py_laser").await;
    assert_eq!(laser.hearing().unwrap().channel, "laser");

    let rust = loopback_node("rust_laser", port).await;
    let channel = rust.channel("rover1/laser");
    let publishing = tokio::spawn(async move {
        for _ in 0..400 {
            channel.publish("rust").unwrap();
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    hears(&mut laser, "rust_laser").await;
    publishing.abort();
    rust.stop();
    hears(&mut laser, "py_laser").await;
    drop(talker);
}

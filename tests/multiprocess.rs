//! Nodes in separate processes on loopback.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::time::Duration;

use pulicast_tests::{free_port, Peer};
use serde_json::Value;

const WAIT: Duration = Duration::from_secs(10);

/// Starts `pulicast-test-peer` with whitespace-separated `args`.
fn rust_peer(args: &str) -> Peer {
    let args: Vec<&str> = args.split_whitespace().collect();
    Peer::spawn(env!("CARGO_BIN_EXE_pulicast-test-peer"), &args)
}

#[test]
fn publisher_and_subscriber_processes() {
    let port = free_port();
    let sub = rust_peer(&format!(
        "subscribe --port {port} --name sub --channel fleet/ctrl --kind str --count 5"
    ));
    sub.wait_ready(WAIT);
    let publisher = rust_peer(&format!(
        "publish --port {port} --name pub --channel fleet/ctrl --kind str --value go_{{i}} --count 5 --period 0.01"
    ));
    let got = sub.take_json(5, WAIT);
    for (i, m) in got.iter().enumerate() {
        assert_eq!(m["value"], format!("go_{i}"));
        assert_eq!(m["seq"], i as u64);
        assert_eq!(m["lead"], 1);
    }
    publisher.wait_success(WAIT);
    sub.wait_success(WAIT);
}

#[test]
fn processes_list_each_other() {
    let port = free_port();
    let talker = rust_peer(&format!(
        "publish --port {port} --name talker --channel t --kind int --value 1 --count 1 --linger 5"
    ));
    talker.wait_ready(WAIT);
    let lister = rust_peer(&format!("nodes --port {port} --name lister --for 0.6"));
    let nodes = lister.take_json(1, WAIT).remove(0);
    let nodes = nodes.as_array().expect("array");
    let talker_entry = nodes
        .iter()
        .find(|n| n["name"] == "talker")
        .unwrap_or_else(|| panic!("talker missing in {nodes:?}"));
    let publishes: Vec<&str> = talker_entry["publishes"]
        .as_array()
        .expect("publishes")
        .iter()
        .filter_map(Value::as_str)
        .collect();
    assert!(
        publishes.contains(&"t") && publishes.contains(&"__nodes"),
        "{publishes:?}"
    );
}

#[test]
fn a_restarted_publisher_is_a_new_source_and_nothing_is_dropped() {
    let port = free_port();
    let sub = rust_peer(&format!(
        "subscribe --port {port} --name sub --channel restart --kind int --count 6 --ordered"
    ));
    sub.wait_ready(WAIT);
    let publish = || {
        rust_peer(&format!(
            "publish --port {port} --name pub --channel restart --kind int --value {{i}} --count 3 --period 0.01"
        ))
        .wait_success(WAIT)
    };
    publish();
    publish(); // the same program again: sequence numbers restart at 0
    let got = sub.take_json(6, WAIT);
    let seqs: Vec<u64> = got
        .iter()
        .map(|m| m["seq"].as_u64().expect("seq"))
        .collect();
    let leads: Vec<i64> = got
        .iter()
        .map(|m| m["lead"].as_i64().expect("lead"))
        .collect();
    assert_eq!(seqs, [0, 1, 2, 0, 1, 2]);
    assert_eq!(
        leads, [1; 6],
        "the restart starts a new source, not a late one"
    );
    assert_ne!(got[0]["source"], got[3]["source"]);
    sub.wait_success(WAIT);
}

/// Reads `watch` events until one matches, failing after `WAIT`.
fn wait_event(watcher: &Peer, pred: impl Fn(&Value) -> bool) -> Value {
    let deadline = std::time::Instant::now() + WAIT;
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        let line = watcher
            .next_json(left)
            .unwrap_or_else(|| panic!("no matching event; stderr:\n{}", watcher.stderr()));
        if pred(&line) {
            return line;
        }
    }
}

#[test]
fn a_killed_process_fails_and_a_finished_one_leaves() {
    let port = free_port();
    let watcher = rust_peer(&format!("watch --port {port} --name watcher --for 20"));
    watcher.wait_ready(WAIT);
    let victim = rust_peer(&format!(
        "publish --port {port} --name victim --channel v --kind int --value 1 --count 1 --linger 30"
    ));
    wait_event(&watcher, |e| {
        e["event"] == "joined" && e["name"] == "victim"
    });
    let killed = std::time::Instant::now();
    drop(victim); // SIGKILL: no leave message
    let failed = wait_event(&watcher, |e| {
        e["name"] == "victim" && (e["event"] == "failed" || e["event"] == "left")
    });
    let took = killed.elapsed();
    assert_eq!(failed["event"], "failed");
    // Three 100 ms heartbeat periods plus a digest interval, with ample
    // slack for a busy machine; the benchmark measures it precisely.
    assert!(took < Duration::from_millis(3000), "{took:?} {failed}");

    let polite = rust_peer(&format!(
        "publish --port {port} --name polite --channel p --kind int --value 1 --count 1 --linger 2"
    ));
    wait_event(&watcher, |e| {
        e["event"] == "joined" && e["name"] == "polite"
    });
    let left = wait_event(&watcher, |e| {
        e["name"] == "polite" && (e["event"] == "failed" || e["event"] == "left")
    });
    assert_eq!(
        left["event"], "left",
        "a clean exit is a leave, not a failure"
    );
    polite.wait_success(WAIT);
}

#[test]
fn crashed_publishers_and_subscribers_come_back_without_help() {
    let port = free_port();
    let long_publisher = || {
        let p = rust_peer(&format!(
            "publish --port {port} --name pub --channel crash --kind int --value {{i}} --count 100000 --period 0.005"
        ));
        p.wait_ready(WAIT);
        p
    };
    let subscriber = || {
        let s = rust_peer(&format!(
            "subscribe --port {port} --name sub --channel crash --kind int --count 100000 --timeout 60"
        ));
        s.wait_ready(WAIT);
        s
    };
    // A subscriber that crashes and one that is restarted in its place.
    let first_sub = subscriber();
    let first_pub = long_publisher();
    let before = first_sub.take_json(20, WAIT);
    drop(first_sub); // SIGKILL
    let second_sub = subscriber();
    let after = second_sub.take_json(20, WAIT);
    // The publisher never noticed; the new subscriber starts mid-stream,
    // and its first message leads by 1 (nothing known lost before it).
    assert_eq!(after[0]["lead"], 1);
    assert!(after[0]["seq"].as_u64().unwrap() > before[19]["seq"].as_u64().unwrap());
    for pair in after.windows(2) {
        assert_eq!(pair[1]["lead"], 1, "{pair:?}");
    }
    // The publisher crashes mid-stream and comes back: the running
    // subscriber hears the new process as a new source from seq 0.
    let old_source = after[0]["source"].clone();
    drop(first_pub); // SIGKILL
    let _second_pub = long_publisher();
    let mut restarted = None;
    for _ in 0..2000 {
        let m = second_sub
            .next_json(WAIT)
            .unwrap_or_else(|| panic!("no message after the restart: {}", second_sub.stderr()));
        if m["source"] != old_source {
            restarted = Some(m);
            break;
        }
    }
    let m = restarted.expect("the restarted publisher reaches the old subscriber");
    assert_eq!(
        (m["seq"].as_u64(), m["lead"].as_i64()),
        (Some(0), Some(1)),
        "{m}"
    );
    let more = second_sub.take_json(10, WAIT);
    assert!(
        more.iter()
            .all(|m| m["lead"] == 1 && m["source"] != old_source),
        "{more:?}"
    );
}

//! Two sites as two hosts in network namespaces (`tests/netns/netns.sh`,
//! made and removed here): no multicast between them and nothing but one
//! TCP path (the Zenoh link). Each site's nodes are pinned to its loopback;
//! a bridge per site joins them. Needs root and iptables as CI has; skipped
//! (saying why) elsewhere unless `PULICAST_REQUIRE_NETNS=1`.
//!
//! The nodes of a site run in this test binary itself, started again
//! inside the site's namespace as the ignored test [`site_node`], which
//! reads its role from the environment.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::collections::BTreeSet;
use std::net::Ipv4Addr;
use std::time::{Duration, Instant};

use pulicast_tests::netns::{run, say, Net};
use pulicast_tests::Peer;
use serde_json::{json, Value};

const BRIDGE: &str = env!("CARGO_BIN_EXE_puli-bridge");
/// The sites' pulicast port (each site is its own namespace).
const PORT: &str = "21000";
/// The Zenoh link's port.
const ZENOH: &str = "7447";

/// A node of a site, started inside its namespace (see the module docs):
/// `PULI_SITE_ROLE=talker` publishes a counter on `site_a/count` every
/// 20 ms; `listener` subscribes it and prints each value, and both print
/// the live members they see every 200 ms. Both run `PULI_SITE_SECS`.
#[test]
#[ignore = "a site's node for two_sites_over_one_tcp_path_survive_a_cut, run by it"]
fn site_node() {
    let Ok(role) = std::env::var("PULI_SITE_ROLE") else {
        return;
    };
    let secs: u64 = std::env::var("PULI_SITE_SECS").unwrap().parse().unwrap();
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async move {
        let node = pulicast::Node::new(role.clone())
            .port(PORT.parse().unwrap())
            .interface(Ipv4Addr::LOCALHOST)
            .start()
            .await
            .unwrap();
        let channel = node.channel("site_a/count");
        let mut sub = (role == "listener").then(|| channel.subscribe::<u64>().unwrap());
        let end = Instant::now() + Duration::from_secs(secs);
        let mut n = 0u64;
        let mut tick = tokio::time::interval(Duration::from_millis(20));
        let mut last_members = Instant::now();
        while Instant::now() < end {
            if let Some(sub) = &mut sub {
                tokio::select! {
                    m = sub.recv() => {
                        let m = m.unwrap();
                        println!("{}", json!({"n": m.value}));
                    }
                    _ = tick.tick() => {}
                }
            } else {
                tick.tick().await;
                channel.publish(&n).unwrap();
                n += 1;
            }
            if last_members.elapsed() >= Duration::from_millis(200) {
                last_members = Instant::now();
                let remote: Vec<String> = node
                    .discovery()
                    .live_members()
                    .into_iter()
                    .filter(|m| m.remote.is_some())
                    .map(|m| m.name)
                    .collect();
                println!("{}", json!({"members": remote}));
            }
        }
        node.stop();
    });
}

fn site_node_in(net: &Net, host: usize, role: &str, secs: u64) -> Peer {
    let exe = std::env::current_exe().unwrap();
    let exe = exe.to_str().unwrap();
    let role = format!("PULI_SITE_ROLE={role}");
    let secs = format!("PULI_SITE_SECS={secs}");
    net.spawn(
        host,
        "env",
        &[
            &role,
            &secs,
            exe,
            "--exact",
            "site_node",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ],
    )
}

fn bridge_in(net: &Net, host: usize, site: &str, link: &[&str]) -> Peer {
    let mut args = vec![
        "--site",
        site,
        "--port",
        PORT,
        "--interface",
        "127.0.0.1",
        "--lease",
        "1s",
        "--report",
        "0s",
    ];
    args.extend_from_slice(link);
    net.spawn(host, BRIDGE, &args)
}

/// What a listener printed so far: values in arrival order, and when it
/// last saw the talker as a member (and when it did not).
#[derive(Default)]
struct Heard {
    values: Vec<u64>,
    /// (time, whether the talker was listed), one per member report.
    talker_listed: Vec<(Instant, bool)>,
}

impl Heard {
    fn take(&mut self, listener: &Peer, wait: Duration) {
        if let Some(line) = listener.next_json_object(wait) {
            self.note(&line);
        }
    }

    fn note(&mut self, line: &Value) {
        if let Some(n) = line.get("n").and_then(Value::as_u64) {
            self.values.push(n);
        }
        if let Some(members) = line.get("members").and_then(Value::as_array) {
            let listed = members.iter().any(|m| m == "talker");
            self.talker_listed.push((Instant::now(), listed));
        }
    }

    fn drain(&mut self, listener: &Peer) {
        while let Some(line) = listener.next_json_object(Duration::ZERO) {
            self.note(&line);
        }
    }

    /// Reads the listener until `cond` holds, at most `within`.
    fn until(
        &mut self,
        listener: &Peer,
        within: Duration,
        what: &str,
        cond: impl Fn(&Heard) -> bool,
    ) {
        let deadline = Instant::now() + within;
        while !cond(self) {
            assert!(
                Instant::now() < deadline,
                "timed out waiting for {what}; listener's stderr:\n{}",
                listener.stderr()
            );
            self.take(listener, Duration::from_millis(100));
        }
    }

    fn listed_now(&self) -> bool {
        self.talker_listed.last().is_some_and(|(_, l)| *l)
    }
}

/// A publisher on site A reaches a subscriber on site B through two
/// bridges and one TCP path, values and order intact; each site lists the
/// other's node; the path cut for 5 s and restored: the remote members
/// fail, come back, and traffic resumes with the losses counted, without
/// restarting anything.
#[test]
fn two_sites_over_one_tcp_path_survive_a_cut() {
    let Some(net) = Net::up("brs", 2) else { return };
    for host in ["1", "2"] {
        run(&["block-mcast", &net.tag, host]);
        run(&["only-tcp", &net.tag, host, ZENOH]);
    }
    let listen = format!("tcp/{}:{ZENOH}", net.ip(1));
    let bridge_a = bridge_in(&net, 1, "site-a", &["--listen", &listen]);
    let bridge_b = bridge_in(&net, 2, "site-b", &["--connect", &listen]);
    let secs = 60;
    let talker = site_node_in(&net, 1, "talker", secs);
    let listener = site_node_in(&net, 2, "listener", secs);
    let mut heard = Heard::default();

    // Values in order, and each site lists the other's node.
    heard.until(
        &listener,
        Duration::from_secs(20),
        "the first values",
        |h| h.values.len() >= 50 && h.listed_now(),
    );
    let talker_sees_listener = || {
        let deadline = Instant::now() + Duration::from_secs(10);
        while let Some(line) =
            talker.next_json_object(deadline.saturating_duration_since(Instant::now()))
        {
            if line["members"]
                .as_array()
                .is_some_and(|m| m.iter().any(|n| n == "listener"))
            {
                return true;
            }
        }
        false
    };
    assert!(talker_sees_listener(), "site A lists the listener");
    let first = heard.values.clone();
    assert!(
        first.windows(2).all(|w| w[1] == w[0] + 1),
        "in order and none lost on a healthy link: {first:?}"
    );

    // The path is cut on both sides for 5 s.
    say("cutting the TCP path for 5 s");
    let cut_at = Instant::now();
    run(&["cut", &net.tag, "1"]);
    run(&["cut", &net.tag, "2"]);
    heard.until(
        &listener,
        Duration::from_secs(10),
        "the talker to fail on site B",
        |h| !h.listed_now(),
    );
    let failed_after = cut_at.elapsed();
    // The lease (1 s), then the bridge's next step and the relayed
    // member's end reaching the listener.
    assert!(
        failed_after < Duration::from_secs(4),
        "the talker failed on site B {failed_after:?} after the cut"
    );
    let before_cut = heard.values.last().copied().unwrap();
    std::thread::sleep(Duration::from_secs(5).saturating_sub(cut_at.elapsed()));
    heard.drain(&listener);
    run(&["uncut", &net.tag, "1"]);
    run(&["uncut", &net.tag, "2"]);
    say(&format!(
        "restored; the talker failed on site B after {failed_after:?}"
    ));
    let restored = Instant::now();

    // The talker comes back, and values flow again.
    heard.until(
        &listener,
        Duration::from_secs(30),
        "the talker to come back",
        |h| h.listed_now() && h.values.last().is_some_and(|v| *v > before_cut + 300),
    );
    let back_after = restored.elapsed();
    say(&format!(
        "the talker is back on site B after {back_after:?}"
    ));
    let values: BTreeSet<u64> = heard.values.iter().copied().collect();
    assert_eq!(values.len(), heard.values.len(), "no value twice");
    assert!(
        heard.values.windows(2).all(|w| w[1] > w[0]),
        "in order across the cut"
    );

    // The bridges' counters: site B's counted what the cut lost.
    bridge_b.terminate();
    bridge_a.terminate();
    let stats_b = final_stats(bridge_b);
    let stats_a = final_stats(bridge_a);
    say(&format!("site A: {stats_a}"));
    say(&format!("site B: {stats_b}"));
    let lost = stats_b["in_lost"].as_u64().unwrap();
    let missing = heard
        .values
        .windows(2)
        .map(|w| w[1] - w[0] - 1)
        .sum::<u64>();
    assert!(lost > 0, "the cut lost messages: {stats_b}");
    assert_eq!(lost, missing, "the bridge counted what the listener missed");
    assert_eq!(stats_b["out_messages"], 0, "nothing went back: {stats_b}");
    assert_eq!(stats_a["in_messages"], 0, "nothing came back: {stats_a}");
    drop((talker, listener));
}

/// The one JSON line a bridge prints when it stops.
fn final_stats(mut bridge: Peer) -> Value {
    let status = bridge.wait_exit(Duration::from_secs(20));
    assert!(
        status.is_some_and(|s| s.success()),
        "bridge ended with {status:?}; stderr:\n{}",
        bridge.stderr()
    );
    bridge
        .next_json_object(Duration::from_secs(5))
        .unwrap_or_else(|| panic!("no counters; stderr:\n{}", bridge.stderr()))
}

//! Several hosts on one machine: network namespaces on a bridge, made and
//! removed by these tests (`tests/netns/netns.sh`). They need root and
//! `iptables`, as CI has (`.ci/run` installs it); elsewhere they say why and
//! pass without running, unless `PULICAST_REQUIRE_NETNS=1` (set by `.ci/run`)
//! makes a missing prerequisite a failure.
//!
//! The tests run one at a time (each holds [`ONE_AT_A_TIME`] while its network
//! exists), so they never compete for the machine or for `netns.sh`; each
//! says on stderr what it runs, which `cargo test` shows as it goes.
//!
//! Traffic stays inside the namespaces: they have no link to the real network.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::time::{Duration, Instant};

use pulicast_tests::netns::{run, Net};
use pulicast_tests::{repo_root, Peer};
use serde_json::Value;

const PEER: &str = env!("CARGO_BIN_EXE_pulicast-test-peer");

/// Starts `pulicast-test-peer` inside `host` (1-based), on the host's
/// address at TTL 1.
fn peer(net: &Net, host: usize, args: &str) -> Peer {
    let mut all: Vec<String> = args.split_whitespace().map(String::from).collect();
    all.extend([
        "--interface".into(),
        net.ip(host).to_string(),
        "--ttl".into(),
        "1".into(),
    ]);
    let refs: Vec<&str> = all.iter().map(String::as_str).collect();
    net.spawn(host, PEER, &refs)
}

/// Collects a `watch` peer's events until its final member list.
fn finish(watcher: Peer, within: Duration) -> (Vec<Value>, Vec<String>) {
    let deadline = Instant::now() + within;
    let mut events = Vec::new();
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let Some(line) = watcher.next_json(left) else {
            panic!(
                "watcher ended without a member list; stderr:\n{}",
                watcher.stderr()
            );
        };
        if let Some(members) = line.get("members") {
            let names = members
                .as_array()
                .expect("array")
                .iter()
                .filter_map(|v| v.as_str().map(String::from))
                .collect();
            return (events, names);
        }
        events.push(line);
    }
}

/// Whether `name` is among `members` at the end, or left in the last three
/// seconds (watchers stop at about the same time, and a stopping node
/// leaves; each counts time from its own start, and on a busy machine the
/// watchers start up to a second or two apart).
fn present_until_the_end(events: &[Value], members: &[String], name: &str, secs: u64) -> bool {
    members.iter().any(|m| m == name)
        || events.iter().any(|e| {
            e["event"] == "left"
                && e["name"] == name
                && e["t_ms"].as_f64().unwrap_or(0.0) > secs.saturating_sub(3) as f64 * 1000.0
        })
}

fn joined_at(events: &[Value], name: &str) -> Option<f64> {
    events
        .iter()
        .find(|e| e["event"] == "joined" && e["name"] == name)
        .and_then(|e| e["t_ms"].as_f64())
}

#[test]
fn three_hosts_converge_and_twenty_percent_loss_kills_nobody() {
    let Some(net) = Net::up("plo", 3) else { return };
    for host in 1..=3 {
        run(&["loss", &net.tag, &host.to_string(), "0.2"]);
    }
    let secs = 32;
    let watchers: Vec<Peer> = (1..=3)
        .map(|h| {
            peer(
                &net,
                h,
                &format!("watch --port 8765 --name h{h} --for {secs} --publish h{h}/pose"),
            )
        })
        .collect();
    for w in &watchers {
        w.wait_ready(Duration::from_secs(10));
    }
    for (i, w) in watchers.into_iter().enumerate() {
        let me = format!("h{}", i + 1);
        let (events, members) = finish(w, Duration::from_secs(secs + 15));
        let others: Vec<String> = (1..=3)
            .map(|h| format!("h{h}"))
            .filter(|n| *n != me)
            .collect();
        for other in &others {
            assert!(
                present_until_the_end(&events, &members, other, secs),
                "{me} lost {other}: {events:?}"
            );
            let t =
                joined_at(&events, other).unwrap_or_else(|| panic!("{me} never saw {other} join"));
            // From this watcher's start, so it includes the others' start-up.
            assert!(t < 5000.0, "{me} saw {other} after {t} ms");
        }
        let deaths: Vec<&Value> = events
            .iter()
            .filter(|e| {
                e["event"] == "failed"
                    || (e["event"] == "left"
                        && e["t_ms"].as_f64().unwrap_or(0.0) < (secs - 1) as f64 * 1000.0)
            })
            .collect();
        assert!(
            deaths.is_empty(),
            "{me}: false deaths under 20 % loss: {deaths:?}"
        );
        let suspicions = events.iter().filter(|e| e["event"] == "suspected").count();
        eprintln!("{me}: {suspicions} suspicions in {secs} s at 20 % loss, none fatal");
    }
}

#[test]
fn a_host_without_multicast_learns_the_fleet_through_a_seed_peer() {
    let Some(net) = Net::up("pse", 3) else { return };
    run(&["block-mcast", &net.tag, "3"]);
    let secs = 8;
    let seed = format!("{}:7777", net.ip(1));
    let watchers = [
        peer(
            &net,
            1,
            &format!("watch --port 8765 --name seed --for {secs} --discovery-port 7777"),
        ),
        peer(
            &net,
            2,
            &format!("watch --port 8765 --name member --for {secs} --publish member/pose"),
        ),
        peer(
            &net,
            3,
            &format!(
                "watch --port 8765 --name blind --for {secs} --peer {seed} --publish blind/pose"
            ),
        ),
    ];
    let names = ["seed", "member", "blind"];
    for w in &watchers {
        w.wait_ready(Duration::from_secs(10));
    }
    for (i, w) in watchers.into_iter().enumerate() {
        let (events, members) = finish(w, Duration::from_secs(secs + 15));
        let others: Vec<String> = names
            .iter()
            .filter(|n| **n != names[i])
            .map(|n| n.to_string())
            .collect();
        for other in &others {
            assert!(
                present_until_the_end(&events, &members, other, secs),
                "{} lost {other}: {events:?}",
                names[i]
            );
            let t = joined_at(&events, other)
                .unwrap_or_else(|| panic!("{} never saw {other}", names[i]));
            assert!(t < 6000.0, "{} saw {other} after {t} ms", names[i]);
        }
        assert!(
            !events.iter().any(|e| e["event"] == "failed"),
            "{}: {events:?}",
            names[i]
        );
    }
}

/// Starts a `tally` of `channel` on host 2, a little longer than the
/// publishers of these tests run (slow machines included).
fn start_tally(net: &Net, channel: &str, extra: &str) -> Peer {
    let tally = peer(
        net,
        2,
        &format!("tally --port 8765 --name counter --channel {channel} --for 12{extra}"),
    );
    tally.wait_ready(Duration::from_secs(10));
    tally
}

/// A tally's `[seq, lead, value]` triples under `key`.
fn triples(report: &Value, key: &str) -> Vec<(i64, i64, i64)> {
    report[key]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            (
                t[0].as_i64().unwrap(),
                t[1].as_i64().unwrap(),
                t[2].as_i64().unwrap(),
            )
        })
        .collect()
}

/// Host 1 publishes `count` numbered messages; host 2, whose multicast
/// input loses `loss` of the data channel's datagrams (iptables), counts
/// them. Leads must account for every lost message exactly, ordered and
/// plain subscriptions must agree (a real link does not reorder), and the
/// loss must be near what iptables was told.
fn leads_count_losses_exactly(tag: &str, loss: f64, sealed: bool) {
    // Sealed: the fleet has a key, and a stranger on a third host, without
    // it, publishes on the same channel; none of that may be counted.
    let hosts = if sealed { 3 } else { 2 };
    let Some(net) = Net::up(tag, hosts) else {
        return;
    };
    let keys = match sealed {
        true => format!(" --key /={} --encrypt", "9d".repeat(32)),
        false => String::new(),
    };
    let channel = "loss/data";
    let group = pulicast::group_for(channel);
    run(&[
        "loss",
        &net.tag,
        "2",
        &loss.to_string(),
        &format!("{group}/32"),
    ]);
    let count = 1500;
    let tally = start_tally(&net, channel, &keys);
    let publisher = peer(
&net,
        1,
        &format!(
            "publish --port 8765 --name source --channel {channel} --kind int --value {{i}} --count {count} --period 0.004 --delay 0.5{keys}"
        ),
    );
    publisher.wait_ready(Duration::from_secs(10));
    let _stranger = sealed.then(|| {
        peer(
&net,
            3,
            &format!(
                "publish --port 8765 --name stranger --channel {channel} --kind int --value 999999 --count 300 --period 0.01 --delay 0.5"
            ),
        )
    });
    let report = tally
        .next_json(Duration::from_secs(30))
        .unwrap_or_else(|| panic!("no tally; stderr:\n{}", tally.stderr()));
    let (plain, ordered) = (triples(&report, "plain"), triples(&report, "ordered"));
    assert!(plain.len() > 100, "only {} received", plain.len());
    assert_eq!(
        plain, ordered,
        "no reordering on this link, so the two agree"
    );
    let mut missing = 0;
    for (i, &(seq, lead, value)) in plain.iter().enumerate() {
        assert_eq!(value, seq, "the publisher sends its index as the value");
        if i == 0 {
            assert_eq!(lead, 1, "a source's first message leads by 1");
        } else {
            assert_eq!(lead, seq - plain[i - 1].0, "lead of seq {seq}");
            missing += lead - 1;
        }
    }
    let (first, last) = (plain[0].0, plain[plain.len() - 1].0);
    assert_eq!(
        plain.len() as i64 + missing,
        last - first + 1,
        "received and leads account for every message"
    );
    let lost = 1.0 - plain.len() as f64 / count as f64;
    eprintln!(
        "{:.0} % loss asked: {} of {count} received ({:.1} % lost), {missing} counted by leads, rss {} kB",
        loss * 100.0,
        plain.len(),
        lost * 100.0,
        report["rss_kb"]
    );
    assert!((lost - loss).abs() < 0.06, "lost {lost:.3}, asked {loss}");
    if sealed {
        assert!(
            report["dropped"].as_u64().unwrap() > 0,
            "the stranger's messages are counted"
        );
    } else {
        assert_eq!(report["dropped"], 0, "nothing malformed");
    }
    assert!(
        report["rss_kb"].as_u64().unwrap() < 100_000,
        "memory stays small"
    );
}

#[test]
fn ten_percent_loss_is_counted_exactly_by_leads() {
    leads_count_losses_exactly("l10", 0.1, false);
}

#[test]
fn a_sealed_fleet_counts_losses_exactly_and_ignores_a_stranger() {
    leads_count_losses_exactly("s10", 0.1, true);
}

#[test]
fn thirty_percent_loss_is_counted_exactly_by_leads() {
    leads_count_losses_exactly("l30", 0.3, false);
}

/// Takes a host's interface down for a second and up again.
fn flap(net: &Net, host: usize) {
    let host = host.to_string();
    run(&["exec", &net.tag, &host, "ip", "link", "set", "eth0", "down"]);
    std::thread::sleep(Duration::from_secs(1));
    run(&["exec", &net.tag, &host, "ip", "link", "set", "eth0", "up"]);
}

#[test]
fn interfaces_going_down_and_up_interrupt_delivery_only_meanwhile() {
    let Some(net) = Net::up("ifl", 2) else { return };
    let channel = "flap/data";
    let tally = start_tally(&net, channel, "");
    // 100 messages/s for 7 s; publishing goes on through failures.
    let publisher = peer(
&net,
        1,
        &format!(
            "publish --port 8765 --name source --channel {channel} --kind int --value {{i}} --count 700 --period 0.01 --keep-going"
        ),
    );
    publisher.wait_ready(Duration::from_secs(10));
    std::thread::sleep(Duration::from_millis(1500));
    flap(&net, 2); // the subscriber's link
    std::thread::sleep(Duration::from_millis(1500));
    flap(&net, 1); // the publisher's link
    let published = publisher
        .next_json(Duration::from_secs(20))
        .unwrap_or_else(|| panic!("publisher ended early: {}", publisher.stderr()));
    let report = tally
        .next_json(Duration::from_secs(20))
        .unwrap_or_else(|| panic!("no tally: {}", tally.stderr()));
    let seqs: Vec<(i64, i64)> = triples(&report, "plain")
        .into_iter()
        .map(|(seq, lead, _)| (seq, lead))
        .collect();
    // Delivery resumed after each outage without anyone doing anything:
    // the last messages arrived, and the gaps show as leads.
    let last = seqs.last().expect("messages arrived").0;
    assert!(
        last >= 650,
        "delivery did not resume to the end: last seq {last}"
    );
    let gaps: Vec<i64> = seqs
        .iter()
        .map(|&(_, lead)| lead)
        .filter(|&l| l > 1)
        .collect();
    assert!(
        !gaps.is_empty(),
        "the outages lost messages, and leads show it"
    );
    let missing: i64 = gaps.iter().map(|l| l - 1).sum();
    assert_eq!(seqs.len() as i64 + missing, last - seqs[0].0 + 1);
    // The publisher's own outage shows as failed sends, not as a crash.
    let failed = published["failed"].as_u64().unwrap();
    eprintln!(
        "flaps: {} of 700 received, {missing} lost in {} gaps; {failed} publishes failed while the publisher's link was down",
        seqs.len(),
        gaps.len()
    );
    let warnings = publisher.stderr().matches("sending fails").count();
    assert_eq!(
        warnings,
        1,
        "logged {warnings} times:\n{}",
        publisher.stderr()
    );
}

/// One host with a network (a default route's interface) and loopback:
/// nodes of ours pinned to loopback, nodes of ours with the default
/// interface and a Pulicast 2.x node with its defaults, all at TTL 0. The
/// namespace stands in for a robot's computer, so that the 2.x node's and
/// our default node's joins on its network stay inside the test.
#[test]
fn on_one_host_nodes_hear_each_other_whatever_interface_each_chose() {
    let Some(net) = Net::up("ifd", 1) else { return };
    let python = pulicast_tests::reference_python().display().to_string();
    let script = repo_root()
        .join("tests/python/peer.py")
        .display()
        .to_string();
    let port = pulicast_tests::free_port().to_string();
    // Our nodes: "pinned" to loopback, "default" without an interface.
    let ours = |interface: &str, args: &[&str]| {
        let mut all = args.to_vec();
        all.extend(["--port", &port, "--interface", interface, "--ttl", "0"]);
        net.spawn(1, PEER, &all)
    };
    let theirs = |args: &[&str]| {
        let mut all = vec!["-u", script.as_str()];
        all.extend_from_slice(args);
        all.extend(["--port", &port, "--defaults"]);
        net.spawn(1, &python, &all)
    };
    let publish = |name: &'static str, channel: &'static str| {
        [
            "publish",
            "--name",
            name,
            "--channel",
            channel,
            "--kind",
            "int",
            "--value",
            "7",
            "--count",
            "400",
            "--period",
            "0.05",
        ]
    };
    let _pinned_pub = ours("127.0.0.1", &publish("pinned_pub", "from_pinned"));
    let _default_pub = ours("0.0.0.0", &publish("default_pub", "from_default"));
    let _python_pub = theirs(&publish("py_pub", "from_2x"));

    let sub = |who: &str, channel: &str| {
        let name = format!("{who}_{channel}");
        let args = [
            "subscribe",
            "--name",
            &name,
            "--channel",
            channel,
            "--count",
            "3",
        ];
        match who {
            "pinned" => ours(
                "127.0.0.1",
                &[&args[..], &["--kind", "int", "--timeout", "30"]].concat(),
            ),
            "default" => ours(
                "0.0.0.0",
                &[&args[..], &["--kind", "int", "--timeout", "30"]].concat(),
            ),
            _ => theirs(&[&args[..], &["--timeout", "30"]].concat()),
        }
    };
    let pairs = [
        ("pinned", "from_default"),
        ("pinned", "from_pinned"),
        ("default", "from_pinned"),
        ("default", "from_default"),
        ("default", "from_2x"),
        ("2x", "from_pinned"),
        ("2x", "from_default"),
    ];
    let subscribers: Vec<(String, Peer)> = pairs
        .iter()
        .map(|(who, channel)| (format!("{who} <- {channel}"), sub(who, channel)))
        .collect();
    // The one pair no default of ours can serve: a 2.x node with its
    // defaults sends on the network's interface, where a node pinned to
    // loopback has not joined (docs/guide.md, "Interfaces and TTL").
    let unheard = sub("pinned", "from_2x");
    for (pair, subscriber) in &subscribers {
        assert!(
            subscriber.next_json(Duration::from_secs(30)).is_some(),
            "{pair}: nothing heard; stderr:\n{}",
            subscriber.stderr()
        );
    }
    assert!(
        unheard.next_json(Duration::from_secs(2)).is_none(),
        "a node pinned to loopback now hears a 2.x node with its defaults: update the guide"
    );
}

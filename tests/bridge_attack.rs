//! Two sites joined by two `puli-bridge` processes over Zenoh TCP on
//! loopback, and a stranger on site A with 200 fake Pulicast 2.x nodes,
//! each from a socket of its own, announcing 2400 names each (480 000 in
//! all, half published, half subscribed) every 2 s; then the same with fakes
//! that expire between two heartbeats and come back with the next (churn);
//! then fakes that announce new names every time (fresh names).
//! A test binary of its own: it loads the machine, which other tests beside
//! it would feel; the two attacks take turns.
//!
//! What must hold: the real stream between the sites keeps flowing, each
//! bridge's memory stays under 100 MB, and each ends within 2 s of SIGTERM
//! while the attack goes on. Memory is what the bridge allocated (resident
//! and not a mapped file: the debug build's code alone maps 33 MB, the
//! release build's 16 MB); the gap asserted is the one a debug build keeps
//! on two busy cores (under 3 s: 0.2-0.4 s as a rule, up to 1.5 s). What
//! was measured, and what a release build does (67-92 MB allocated, gaps
//! under 0.15 s), is in docs/bridge.md.
//! Before the bounds, the same attack took a bridge past 1.5 GB.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use pulicast_tests::{free_port, free_tcp_port, workspace_bin, Peer};

const WAIT: Duration = Duration::from_secs(30);

fn bridge(port: u16, site: &str, link: &[&str]) -> Peer {
    let p = port.to_string();
    let mut args = vec![
        "--prefix",
        "attack",
        "--site",
        site,
        "--lease",
        "1s",
        "--port",
        &p,
        "--interface",
        "127.0.0.1",
    ];
    args.extend_from_slice(link);
    Peer::spawn(workspace_bin("puli-bridge"), &args)
}

/// One attack at a time: each loads the machine.
static ALONE: Mutex<()> = Mutex::new(());

#[test]
fn a_strangers_names_neither_blow_up_the_bridges_nor_stop_the_stream() {
    let _alone = ALONE.lock().unwrap_or_else(|e| e.into_inner());
    // Past two trials (10 s each): idle places give way and are taken
    // again, twice.
    attack(Names::Steady, attack_for(25), &[]);
}

/// The fakes announce a period of 250 ms and speak every 2 s: each expires
/// between two heartbeats and joins again with the next, so the bridges see
/// 200 members and their 480,000 names leave and come back every 2 s.
#[test]
fn a_strangers_names_that_leave_and_come_back_neither_blow_up_the_bridges_nor_stop_the_stream() {
    let _alone = ALONE.lock().unwrap_or_else(|e| e.into_inner());
    attack(Names::Churn, attack_for(10), &[]);
}

/// The fakes announce new names with every heartbeat (every 2 s, 1200
/// each, so 120,000 new subscribed names every 2 s): each
/// name a bridge imports would cost it Zenoh state for good, so names
/// that change would grow it for as long as the attack lasts. Bridge A
/// imports at most `--max-import-names` distinct names, and an eighth of
/// that for names no other site lists a publisher of (all of these):
/// 1024 by default, as many as it imports of them at once. Its places fill
/// with the first names; those leave 10 s after the fakes stopped
/// announcing them, and no new name takes their place, however long the
/// attack. The real stream keeps crossing.
#[test]
fn a_strangers_names_that_change_cost_the_bridges_no_more_than_their_bound() {
    let _alone = ALONE.lock().unwrap_or_else(|e| e.into_inner());
    let counters = attack(Names::Fresh, attack_for(25), &[]);
    let a = &counters[0];
    let names = &a["import_names"];
    eprintln!(
        "bridge A: import_names {names}, imports_refused {}",
        a["imports_refused"]
    );
    assert_eq!(names[1], 1024, "{a}");
    assert!(a["imports_refused"].as_u64() > Some(0), "{a}");
}

/// What the fakes announce.
#[derive(Clone, Copy)]
enum Names {
    /// The same names every 2 s.
    Steady,
    /// The same names, each fake expiring between two heartbeats.
    Churn,
    /// New names every 2 s.
    Fresh,
}

/// How long an attack lasts: `seconds`, or `PULI_ATTACK_SECS` (at most
/// 600) to watch a longer one, as docs/bridge.md's figures did.
fn attack_for(seconds: u64) -> Duration {
    let asked = std::env::var("PULI_ATTACK_SECS")
        .ok()
        .and_then(|s| s.parse::<u64>().ok());
    Duration::from_secs(asked.unwrap_or(seconds).min(600))
}

/// The attack of fakes announcing `names`, for `length`, bridge A run
/// with `extra` options. Returns the bridges' last counters.
fn attack(names: Names, length: Duration, extra: &[&str]) -> Vec<serde_json::Value> {
    let (a, b) = (free_port(), free_port());
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let mut link_a = vec!["--listen", endpoint.as_str()];
    link_a.extend_from_slice(extra);
    let bridge_a = bridge(a, "site-a", &link_a);
    let bridge_b = bridge(b, "site-b", &["--connect", &endpoint]);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let _entered = runtime.enter();
    let node = |name: &str, port: u16| {
        pulicast::Node::new(name)
            .port(port)
            .interface(std::net::Ipv4Addr::LOCALHOST)
            .start_blocking()
            .unwrap()
    };
    let talker = node("rover", a);
    let listener = node("ground", b);
    let arrivals: Arc<Mutex<Vec<Instant>>> = Arc::default();
    let heard = Arc::clone(&arrivals);
    let _sub = listener
        .channel("rover1/pose")
        .subscribe_with(move |_: pulicast::Message<u64>| {
            heard.lock().unwrap().push(Instant::now());
        })
        .unwrap();
    // The rover has 300 channels: a share of what a bridge reads is 80
    // with the strangers' 200 members beside it, and `rover1/status`, the
    // last, must still cross. Announced first, then the stream.
    let many: Vec<pulicast::Channel> = (0..298)
        .map(|i| talker.channel(&format!("rover1/a{i:03}")))
        .collect();
    for channel in &many {
        channel.publish(&0u64).unwrap();
    }
    let status = talker.channel("rover1/status");
    let statuses: Arc<Mutex<Vec<Instant>>> = Arc::default();
    let heard_status = Arc::clone(&statuses);
    let _status_sub = listener
        .channel("rover1/status")
        .subscribe_with(move |_: pulicast::Message<u64>| {
            heard_status.lock().unwrap().push(Instant::now());
        })
        .unwrap();
    let pose = talker.channel("rover1/pose");
    let talking = Arc::new(AtomicBool::new(true));
    let talks = Arc::clone(&talking);
    let publisher = std::thread::spawn(move || {
        let end = Instant::now() + length + Duration::from_secs(60);
        let mut n = 0u64;
        while talks.load(Ordering::SeqCst) && Instant::now() < end {
            let _ = pose.publish(&n);
            if n % 10 == 0 {
                let _ = status.publish(&n);
            }
            n += 1;
            std::thread::sleep(Duration::from_millis(20));
        }
    });
    let started = Instant::now();
    while arrivals.lock().unwrap().len() < 20 || statuses.lock().unwrap().len() < 2 {
        assert!(started.elapsed() < WAIT, "the stream never crossed");
        std::thread::sleep(Duration::from_millis(50));
    }
    let before = (bridge_a.resident_bytes(), bridge_b.resident_bytes());
    let allocated_before = (bridge_a.allocated_bytes(), bridge_b.allocated_bytes());

    // The attack: each fake node from its own socket, a heartbeat every
    // 2 s, on while the bridges are stopped.
    let every = Duration::from_secs(2);
    let attack = match names {
        Names::Steady => pulicast_tests::fake_2x_flood_announcing(a, 200, 2400, every, every * 2),
        Names::Churn => pulicast_tests::fake_2x_flood_announcing(
            a,
            200,
            2400,
            every,
            Duration::from_millis(250),
        ),
        // 1200 names each: 2000 (with the round in each name, 2000 fill
        // a datagram) took a debug bridge A to 89-96 MB, too near the
        // bound asserted for a test on a busy machine; the release
        // figures at 2000 are in docs/bridge.md.
        Names::Fresh => pulicast_tests::fake_2x_flood_of_fresh_names(a, 200, 1200, every),
    };
    let attack_start = Instant::now();
    let mut peak = (0u64, 0u64);
    let mut allocated = (0u64, 0u64);
    let mut said = Duration::ZERO;
    while attack_start.elapsed() < length {
        if attack_start.elapsed() >= said + Duration::from_secs(5) {
            said = attack_start.elapsed();
            eprintln!(
                "{said:.1?}: allocated {:?} MB",
                (
                    bridge_a.allocated_bytes().unwrap_or(0) / 1_000_000,
                    bridge_b.allocated_bytes().unwrap_or(0) / 1_000_000
                )
            );
        }
        peak.0 = peak.0.max(bridge_a.resident_bytes().unwrap_or(0));
        peak.1 = peak.1.max(bridge_b.resident_bytes().unwrap_or(0));
        allocated.0 = allocated.0.max(bridge_a.allocated_bytes().unwrap_or(0));
        allocated.1 = allocated.1.max(bridge_b.allocated_bytes().unwrap_or(0));
        std::thread::sleep(Duration::from_millis(200));
    }
    let gaps: Vec<Duration> = {
        let arrivals = arrivals.lock().unwrap();
        let during: Vec<Instant> = arrivals
            .iter()
            .copied()
            .filter(|t| *t >= attack_start)
            .collect();
        let mut edges = vec![attack_start];
        edges.extend(during);
        edges.push(Instant::now());
        edges.windows(2).map(|w| w[1] - w[0]).collect()
    };
    let longest = gaps.iter().max().copied().unwrap_or_default();
    // The status, every 200 ms, in the attack's last 5 s.
    let late = Instant::now() - Duration::from_secs(5);
    let statuses_late = statuses
        .lock()
        .unwrap()
        .iter()
        .filter(|t| **t >= late)
        .count();
    eprintln!(
        "resident before {before:?}, peak during the attack {peak:?}; allocated before {allocated_before:?}, peak {allocated:?}; longest gap in the stream {longest:?} over {} messages; {statuses_late} statuses in the last 5 s",
        gaps.len().saturating_sub(1)
    );

    if longest >= Duration::from_secs(1) {
        let tail = |p: &Peer| {
            p.stderr()
                .lines()
                .rev()
                .take(15)
                .collect::<Vec<_>>()
                .join("\n")
        };
        eprintln!(
            "bridge A said:\n{}\nbridge B said:\n{}",
            tail(&bridge_a),
            tail(&bridge_b)
        );
    }
    // Stopped while the attack goes on.
    let mut ends = Vec::new();
    let mut counters = Vec::new();
    for mut bridge in [bridge_a, bridge_b] {
        let asked = Instant::now();
        bridge.terminate();
        let status = bridge.wait_exit(Duration::from_secs(10));
        ends.push((asked.elapsed(), status));
        // The counters, the last line on stdout.
        let last = bridge.lines_so_far().pop().unwrap_or_default();
        counters.push(serde_json::from_str(&last).unwrap_or_default());
    }
    drop(attack);
    talking.store(false, Ordering::SeqCst);
    publisher.join().unwrap();
    eprintln!("ended after {ends:?}");

    assert!(
        longest < Duration::from_secs(3),
        "the stream stopped for {longest:?}"
    );
    assert!(
        statuses_late >= 10,
        "the rover's 300th channel stopped crossing: {statuses_late} statuses in 5 s"
    );
    assert!(
        allocated.0 < 100_000_000,
        "bridge A allocated {} MB",
        allocated.0 / 1_000_000
    );
    assert!(
        allocated.1 < 100_000_000,
        "bridge B allocated {} MB",
        allocated.1 / 1_000_000
    );
    for (took, status) in ends {
        assert!(
            status.is_some(),
            "a bridge did not end within 10 s of SIGTERM"
        );
        assert!(
            took < Duration::from_secs(2),
            "a bridge took {took:?} to end"
        );
    }
    counters
}

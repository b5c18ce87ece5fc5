//! A flood of fake Pulicast 2.x heartbeats beside the 2.x reference peer.
//! A test binary of its own: it measures the CPU time of its process, which
//! other tests running beside it in one process would add to.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::time::Duration;

use pulicast::Node;
use pulicast_tests::{free_port, loopback_node, python_peer};

const WAIT: Duration = Duration::from_secs(20);

/// The tests measure their process's CPU time and memory: one at a time.
static ALONE: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// A stranger floods `__nodes` with heartbeats of 200 made-up 2.x sessions,
/// each listing 3000 channels (a 60 KB datagram), 100 a second for 8 s: the
/// heartbeats cost time linear in their size (about a fifth of a core here,
/// in a debug build; a full core when every heartbeat copied every peer's
/// channels), and the real 2.x peer beside them is never taken for failed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_of_fake_2x_nodes_never_fails_a_real_one() {
    let _alone = ALONE.lock().await;
    use pulicast::{ChannelAnnouncement, DiscoveryEvent};
    use pulicast_discovery::compat::Heartbeat;
    let port = free_port();
    let observer = loopback_node("observer", port).await;
    let p = port.to_string();
    let real = python_peer(&[
        "publish",
        "--port",
        &p,
        "--name",
        "py_real",
        "--channel",
        "py/alive",
        "--kind",
        "int",
        "--value",
        "1",
        "--count",
        "600",
        "--period",
        "0.05",
    ]);
    real.wait_ready(WAIT);
    let listed = |observer: &Node| {
        observer
            .discovery()
            .live_members()
            .iter()
            .any(|m| m.name == "py_real")
    };
    let deadline = std::time::Instant::now() + WAIT;
    while !listed(&observer) {
        assert!(
            std::time::Instant::now() < deadline,
            "the 2.x peer never joined"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let mut events = observer.discovery().events();

    let flood = std::net::UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).unwrap();
    flood.set_multicast_ttl_v4(0).unwrap();
    flood.set_multicast_loop_v4(true).unwrap();
    socket2::SockRef::from(&flood)
        .set_multicast_if_v4(&Ipv4Addr::LOCALHOST)
        .unwrap();
    let channels: Vec<ChannelAnnouncement> = (0..3000)
        .map(|i| ChannelAnnouncement {
            name: format!("c{i:04}"),
            period_ns: 0,
            is_published: true,
            is_subscribed: false,
        })
        .collect();
    // Encoded once, so the flood itself costs this process little.
    let payloads: Vec<Vec<u8>> = (0..200)
        .map(|i| {
            let heartbeat = Heartbeat {
                name: format!("fake{i}"),
                session_id: 0x0fa_0000 + i,
                channels: channels.clone(),
            };
            let mut payload = Vec::new();
            pulicast_proto::wire::zcm::encode_heartbeat(&heartbeat, &mut payload);
            payload
        })
        .collect();
    let group = std::net::SocketAddr::from((pulicast::group_for("__nodes"), port));
    let cpu_before = cpu_time();
    let resident_before = resident_bytes();
    let mut resident_peak = resident_before;
    let started = std::time::Instant::now();
    let mut seq = 0u32;
    while started.elapsed() < Duration::from_secs(8) {
        resident_peak = resident_peak.max(resident_bytes());
        for _ in 0..10 {
            let mut datagram = Vec::new();
            pulicast_proto::wire::Packet {
                channel: "__nodes",
                seq,
                payload: &payloads[seq as usize % payloads.len()],
            }
            .encode(&mut datagram);
            flood.send_to(&datagram, group).unwrap();
            seq += 1;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let busy = (cpu_time() - cpu_before).as_secs_f64() / started.elapsed().as_secs_f64();
    assert!(seq >= 200, "sent {seq} heartbeats");
    eprintln!(
        "{seq} fake heartbeats of 60 KB: this process was busy {:.0} % of a core",
        busy * 100.0
    );
    // The work the node does for them, not how fast: linear in their size,
    // it is a few percent of a core; copying every peer's channels for
    // every heartbeat (quadratic) took more than a core.
    assert!(
        busy < 0.5,
        "{:.0} % of a core for the heartbeats",
        busy * 100.0
    );
    // Memory: the 2.x table's 16 MiB (counted in allocator bytes), at most
    // 256 heartbeats waiting as copies (16 MiB), the events' views (256
    // channels each). Queued as views of their receive buffers, the same
    // flood held one 2 MiB buffer per few heartbeats: hundreds of MB.
    let grew = resident_peak.saturating_sub(resident_before);
    eprintln!("resident memory grew by {} MiB at most", grew >> 20);
    assert!(
        grew < 64 << 20,
        "the flood grew this process by {} MiB",
        grew >> 20
    );
    while let Some(e) = events.try_recv() {
        assert!(
            !matches!(&e, DiscoveryEvent::Failed { name, .. } if name == "py_real"),
            "the real 2.x peer was taken for failed during the flood"
        );
    }
    assert!(listed(&observer), "the real 2.x peer is gone");
}

/// 200 fake 2.x nodes, each from a socket of its own, announce 2400 names
/// each (as in `tests/bridge_attack.rs`), while a node subscribes a real
/// channel and asks for its publishers ten times a second. What the node
/// reads of the fleet for itself (the type check of its subscriptions
/// every second, a channel's publishers, a service's servers, a setting's
/// owners) copies only the channels it looks at: copying the whole fleet
/// for each, as it did, made every such read cost the stranger's hundreds
/// of thousands of names.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reading_the_fleet_costs_what_is_looked_at_not_what_a_stranger_announces() {
    let _alone = ALONE.lock().await;
    let port = free_port();
    let observer = loopback_node("observer", port).await;
    let real = loopback_node("real", port).await;
    let pose = real.channel("real/pose");
    pose.publish(&1u64).unwrap();
    let watched = observer.channel("real/pose");
    let _subscribed = watched.subscribe::<u64>().unwrap();
    let attack = pulicast_tests::fake_2x_flood(port, 200, 2400, Duration::from_secs(2));
    let deadline = std::time::Instant::now() + WAIT;
    while observer.discovery().members_within(0).len() < 50 {
        assert!(
            std::time::Instant::now() < deadline,
            "the fake nodes never joined"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let announced: usize = observer
        .discovery()
        .members_within(usize::MAX)
        .iter()
        .map(|m| m.channels.len())
        .sum();
    let cpu_before = cpu_time();
    let resident_before = resident_bytes();
    let mut resident_peak = resident_before;
    let started = std::time::Instant::now();
    let mut reads = 0;
    while started.elapsed() < Duration::from_secs(5) {
        resident_peak = resident_peak.max(resident_bytes());
        let publishers = watched.publishers();
        assert!(
            publishers.iter().any(|m| m.name == "real"),
            "the real publisher is not listed"
        );
        reads += 1;
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let busy = (cpu_time() - cpu_before).as_secs_f64() / started.elapsed().as_secs_f64();
    let grew = resident_peak.saturating_sub(resident_before);
    drop(attack);
    eprintln!(
        "{announced} names announced; {reads} reads of the publishers: busy {:.0} % of a core, \
         memory grew by {} MiB",
        busy * 100.0,
        grew >> 20
    );
    assert!(announced > 100_000, "only {announced} names announced");
    assert!(busy < 0.5, "{:.0} % of a core", busy * 100.0);
    assert!(grew < 32 << 20, "grew by {} MiB", grew >> 20);
}

/// This process's resident memory, from `/proc`.
fn resident_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let kb: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .unwrap()
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .unwrap();
    kb * 1024
}

/// CPU time this process has used (user and system), from `/proc`.
fn cpu_time() -> Duration {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap();
    // Fields after the command name, which is in parentheses.
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .unwrap()
        .1
        .split_whitespace()
        .collect();
    let ticks: u64 = fields[11].parse::<u64>().unwrap() + fields[12].parse::<u64>().unwrap();
    // Linux reports clock ticks of 1/100 s (USER_HZ).
    Duration::from_millis(ticks * 10)
}

/// A batching node under a churning flood: 200 fake 2.x nodes, each
/// subscribing 2400 names, each expiring and joining again every 250 ms.
/// A real 2.x subscriber that comes later still pauses batching on its
/// channel, and batching resumes once it has gone. Which channels a 2.x
/// node subscribes is kept from what changed in the table, not worked out
/// again from the whole of it (the unit tests of `runtime::eligibility`
/// count the peers walked); this shows the answers stay right while the
/// table churns.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn batching_follows_a_real_2x_subscriber_through_a_churning_flood() {
    let _alone = ALONE.lock().await;
    let port = free_port();
    let node = loopback_node("batcher", port).await;
    let imu = node.channel("rig/imu");
    imu.enable_batching(Duration::from_millis(5)).unwrap();
    let listener = group_listener("rig/imu", port);
    let _attack = pulicast_tests::fake_2x_flood_announcing(
        port,
        200,
        2400,
        Duration::from_millis(250),
        Duration::from_millis(50),
    );
    // The fakes never settle into fleet members (they expire first): the
    // 2.x table is where they are.
    let deadline = std::time::Instant::now() + WAIT;
    while node.peers().len() < 50 {
        assert!(
            std::time::Instant::now() < deadline,
            "the fake nodes never joined"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let batches = |expected: bool, what: &str| {
        let deadline = std::time::Instant::now() + WAIT;
        let mut value = 0u64;
        loop {
            let mut heard = Vec::new();
            for _ in 0..20 {
                imu.publish(&value).unwrap();
                value += 1;
            }
            imu.flush().unwrap();
            let until = std::time::Instant::now() + Duration::from_millis(200);
            let mut buf = vec![0; 65536];
            while std::time::Instant::now() < until {
                let Ok(n) = listener.recv(&mut buf) else {
                    continue;
                };
                // Another channel may share the group (`__nodes`, where
                // the fakes announce).
                let datagram = &buf[..n];
                if let Ok(batch) = pulicast_proto::wire::batch::Batch::decode(datagram) {
                    heard.push(batch.channel == "rig/imu");
                } else if pulicast_proto::wire::Packet::decode(datagram)
                    .is_ok_and(|p| p.channel == "rig/imu")
                {
                    heard.push(false);
                }
            }
            if !heard.is_empty() && heard.iter().all(|b| *b == expected) {
                return;
            }
            assert!(std::time::Instant::now() < deadline, "{what}: {heard:?}");
        }
    };
    batches(true, "batching under the flood alone");
    // For the record (not asserted: the flood's own sending and the
    // heartbeats' decoding dominate it).
    let cpu_before = cpu_time();
    let started = std::time::Instant::now();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let busy = (cpu_time() - cpu_before).as_secs_f64() / started.elapsed().as_secs_f64();
    eprintln!(
        "under the churning flood: busy {:.0} % of a core",
        busy * 100.0
    );
    let real = pulicast_tests::Stranger::new(port);
    let subscriber = real.address();
    let announcing = real.keep_announcing(WAIT * 3, |s| {
        s.heartbeat("real_2x", 0x5eed, &[("rig/imu", false, true)]);
    });
    batches(false, "a real 2.x subscriber pauses batching");
    drop(announcing);
    batches(true, "batching resumes once it has gone");
    eprintln!("2.x subscriber {subscriber} came and went under the churning flood");
}

/// A socket that hears the datagrams of `channel`'s group on `port`.
fn group_listener(channel: &str, port: u16) -> std::net::UdpSocket {
    let socket = socket2::Socket::new(
        socket2::Domain::IPV4,
        socket2::Type::DGRAM,
        Some(socket2::Protocol::UDP),
    )
    .unwrap();
    socket.set_reuse_address(true).unwrap();
    socket.set_multicast_all_v4(false).unwrap();
    socket
        .bind(&std::net::SocketAddr::from((Ipv4Addr::UNSPECIFIED, port)).into())
        .unwrap();
    socket
        .join_multicast_v4(&pulicast::group_for(channel), &Ipv4Addr::LOCALHOST)
        .unwrap();
    let socket: std::net::UdpSocket = socket.into();
    socket
        .set_read_timeout(Some(Duration::from_millis(20)))
        .unwrap();
    socket
}

//! Gossip discovery between real nodes on loopback.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::{Ipv4Addr, SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use pulicast::{DiscoveryEvent, MemberState, Node, NodeBuilder, Schema, TypeEncoding};
use pulicast_discovery::wire::{Digest, Message};
use serde::{Deserialize, Serialize};

mod common;
use common::free_port;

const WAIT: Duration = Duration::from_secs(5);

#[derive(Serialize, Deserialize, Schema, Debug, Clone, PartialEq)]
struct Pose {
    x: f64,
    y: f64,
}

fn node(name: &str, port: u16) -> NodeBuilder {
    Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST)
}

async fn eventually<T>(what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + WAIT;
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

async fn next_event(
    events: &mut pulicast::DiscoveryEvents,
    pred: impl Fn(&DiscoveryEvent) -> bool,
) -> DiscoveryEvent {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let event = tokio::time::timeout_at(deadline, events.recv())
            .await
            .expect("event in time")
            .expect("node running");
        if pred(&event) {
            return event;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn members_see_each_other_with_channels_and_types() {
    let port = free_port();
    let a = node("alpha", port)
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    let mut events = a.discovery().events();
    let b = node("beta", port)
        .namespace("rover2")
        .start()
        .await
        .unwrap();
    b.channel("pose").publish(&Pose { x: 1.0, y: 2.0 }).unwrap();
    let _text = b.channel("/fleet/status").subscribe::<String>().unwrap();

    next_event(
        &mut events,
        |e| matches!(e, DiscoveryEvent::Joined(m) if m.name == "beta"),
    )
    .await;
    // Joined as soon as heard; if a busy machine delays its gossip past the
    // 2.x grace, first as a 2.x member. The gossip view follows.
    let view = eventually("beta by gossip", || {
        a.discovery()
            .members()
            .into_iter()
            .find(|m| m.name == "beta" && !m.compat)
    })
    .await;
    assert_eq!(view.session, Some(b.session_id()));
    assert_eq!(view.key, b.compat_session_id());
    assert_eq!(view.namespace, "rover2");
    assert!(!view.compat);

    let beta = eventually("beta's channels", || {
        a.discovery()
            .members()
            .into_iter()
            .find(|m| m.name == "beta" && m.channels.len() == 2)
    })
    .await;
    assert_eq!(beta.state, MemberState::Alive);
    assert!(!beta.host.is_empty());
    assert!(beta.start_time.is_some());
    let pose = beta
        .channels
        .iter()
        .find(|c| c.name == "rover2/pose")
        .unwrap();
    assert!(pose.publishes && !pose.subscribes);
    let ty = pose.message_type.as_ref().unwrap();
    assert_eq!(
        (ty.encoding, ty.name.as_str()),
        (TypeEncoding::Native, "Pose")
    );
    assert_eq!(
        ty.fingerprint,
        pulicast_proto::wire::fingerprint_of::<Pose>().0
    );
    let schema: postcard_schema::schema::owned::OwnedNamedType =
        postcard::from_bytes(&ty.schema).unwrap();
    assert_eq!(schema.name, "Pose");
    let status = beta
        .channels
        .iter()
        .find(|c| c.name == "fleet/status")
        .unwrap();
    assert!(status.subscribes);
    assert_eq!(status.message_type.as_ref().unwrap().name, "string_msg");

    // Channel lookups, this node's own use included.
    assert_eq!(a.channel("/rover2/pose").publishers().len(), 1);
    assert_eq!(a.channel("/fleet/status").subscribers()[0].name, "beta");
    let _mine = a.channel("/fleet/status").subscribe::<String>().unwrap();
    assert_eq!(a.channel("/fleet/status").subscribers().len(), 2);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channel_changes_and_graceful_leave_are_events() {
    let port = free_port();
    let a = node("watcher", port).start().await.unwrap();
    let mut events = a.discovery().events();
    let b = node("changer", port).start().await.unwrap();
    next_event(
        &mut events,
        |e| matches!(e, DiscoveryEvent::Joined(m) if m.name == "changer"),
    )
    .await;

    let sub = b.channel("grow").subscribe::<i64>().unwrap();
    let e = next_event(&mut events, |e| {
        matches!(e, DiscoveryEvent::ChannelAppeared { .. })
    })
    .await;
    assert!(
        matches!(e, DiscoveryEvent::ChannelAppeared { ref channel, .. } if channel.name == "grow" && channel.subscribes)
    );
    drop(sub);
    let e = next_event(&mut events, |e| {
        matches!(e, DiscoveryEvent::ChannelDisappeared { .. })
    })
    .await;
    assert!(
        matches!(e, DiscoveryEvent::ChannelDisappeared { ref channel, .. } if channel.name == "grow")
    );

    let key = b.compat_session_id();
    let stopped = Instant::now();
    b.stop();
    let e = next_event(&mut events, |e| {
        matches!(
            e,
            DiscoveryEvent::Left { .. } | DiscoveryEvent::Failed { .. }
        )
    })
    .await;
    assert_eq!(
        e,
        DiscoveryEvent::Left {
            key,
            name: "changer".into()
        }
    );
    // `Left`, not `Failed`: the leave message was heard, where a timeout
    // (three heartbeat periods) would have declared it failed.
    eprintln!("leave heard after {:?}", stopped.elapsed());
    let gone = a
        .discovery()
        .members()
        .into_iter()
        .find(|m| m.key == key)
        .unwrap();
    assert_eq!(gone.state, MemberState::Left);
    assert!(a.discovery().live_members().iter().all(|m| m.key != key));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wait_for_publisher_and_nearest_channel() {
    let port = free_port();
    let a = node("seeker", port)
        .namespace("rover1/arm")
        .start()
        .await
        .unwrap();
    let b = node("lasers", port).start().await.unwrap();

    let waiting = tokio::spawn({
        let ch = a.channel("/laser");
        async move { ch.wait_for_publisher(WAIT).await }
    });
    tokio::time::sleep(Duration::from_millis(50)).await;
    b.channel("laser").publish(&1.0f64).unwrap();
    let found = waiting.await.unwrap().unwrap();
    assert_eq!(found.name, "lasers");

    let err = a
        .channel("/nobody")
        .wait_for_publisher(Duration::from_millis(100))
        .await;
    assert!(matches!(err, Err(pulicast::Error::Timeout(_))));

    // Only the root one exists: it is the nearest.
    assert_eq!(a.resolve_nearest("laser").unwrap().name(), "laser");
    // A closer one wins once it has a publisher.
    b.channel("rover1/laser").publish(&2.0f64).unwrap();
    eventually("rover1/laser is the nearest", || {
        (a.resolve_nearest("laser")?.name() == "rover1/laser").then_some(())
    })
    .await;
    // Our own publication is closer still.
    a.channel("laser").publish(&3.0f64).unwrap();
    assert_eq!(
        a.resolve_nearest("laser").unwrap().name(),
        "rover1/arm/laser"
    );
    assert_eq!(a.resolve_nearest("/laser").unwrap().name(), "laser");
    assert!(a.resolve_nearest("sonar").is_none());
    assert!(a
        .channel("/x")
        .wait_for_publisher_blocking(Duration::from_millis(20))
        .is_err());
}

/// DROS's order: the configuration is the outer axis. A user's own
/// publisher at the root wins over everyone's on the same robot; once it
/// stops, everyone's is found; another user's is never found, and a node
/// without a configuration sees only those of none.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_nearest_channel_is_searched_in_the_own_configuration_first() {
    let port = free_port();
    let alice = node("seeker", port)
        .namespace("rover1")
        .config("alice")
        .start()
        .await
        .unwrap();
    let anyone = node("anyone", port)
        .namespace("rover1")
        .config("")
        .start()
        .await
        .unwrap();
    assert_eq!(alice.config(), "alice");
    let everyones = node("everyones", port).config("").start().await.unwrap();
    everyones.channel("rover1/laser").publish(&1.0f64).unwrap();
    let alices = node("alices", port).config("alice").start().await.unwrap();
    alices.channel("laser").publish(&2.0f64).unwrap();
    let bobs = node("bobs", port).config("bob").start().await.unwrap();
    bobs.channel("rover1/laser").publish(&3.0f64).unwrap();

    eventually("alice's own root laser is the nearest", || {
        (alice.resolve_nearest("laser")?.name() == "laser").then_some(())
    })
    .await;
    // Discovery shows each member's configuration.
    let seen = alice.discovery().live_members();
    let config_of = |name: &str| {
        seen.iter()
            .find(|m| m.name == name)
            .map(|m| m.config.clone())
    };
    assert_eq!(config_of("alices").as_deref(), Some("alice"));
    assert_eq!(config_of("bobs").as_deref(), Some("bob"));
    assert_eq!(config_of("everyones").as_deref(), Some(""));
    // Without a configuration, alice's and bob's are not candidates.
    eventually("everyone's rover1 laser for a node of none", || {
        (anyone.resolve_nearest("laser")?.name() == "rover1/laser").then_some(())
    })
    .await;
    alices.stop();
    eventually("everyone's rover1 laser once alice's stops", || {
        (alice.resolve_nearest("laser")?.name() == "rover1/laser").then_some(())
    })
    .await;
    everyones.stop();
    // Bob's publishes the same name, but in bob's configuration.
    eventually("nothing once everyone's stops too", || {
        alice.resolve_nearest("laser").is_none().then_some(())
    })
    .await;
    assert!(anyone.resolve_nearest("laser").is_none());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_that_cannot_hear_the_multicast_learns_the_fleet_from_a_seed() {
    // Nodes on another port don't hear our discovery multicast: the same
    // situation as a link without multicast, on loopback.
    let port = free_port();
    let a = node("seed", port)
        .discovery_port(free_port())
        .start()
        .await
        .unwrap();
    let b = node("member", port).start().await.unwrap();
    b.channel("b/data").publish(&1i64).unwrap();
    let seed = a.discovery().local_address().unwrap();
    let seed = SocketAddr::from((Ipv4Addr::LOCALHOST, seed.port()));
    let c = node("remote", free_port())
        .peer(seed)
        .start()
        .await
        .unwrap();
    c.channel("c/data").publish(&2i64).unwrap();

    let names = |n: &Node| {
        let mut v: Vec<String> = n
            .discovery()
            .live_members()
            .into_iter()
            .map(|m| m.name)
            .collect();
        v.sort();
        v
    };
    eventually("c knows a and b", || {
        (names(&c) == ["member", "seed"]).then_some(())
    })
    .await;
    eventually("b knows c, through a", || {
        (names(&b) == ["remote", "seed"]).then_some(())
    })
    .await;
    let remote = b
        .discovery()
        .members()
        .into_iter()
        .find(|m| m.name == "remote")
        .unwrap();
    assert!(remote.publishes("c/data"));
    let member = c
        .discovery()
        .members()
        .into_iter()
        .find(|m| m.name == "member")
        .unwrap();
    assert!(member.publishes("b/data"));
    // It stays that way (members learned indirectly are vouched for).
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(names(&c), ["member", "seed"]);
    assert_eq!(names(&b), ["remote", "seed"]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_forged_digest_is_suspicious() {
    let port = free_port();
    let a = node("victim", port).start().await.unwrap();
    let mut events = a.discovery().events();
    let b = node("honest", port).start().await.unwrap();
    next_event(
        &mut events,
        |e| matches!(e, DiscoveryEvent::Joined(m) if m.name == "honest"),
    )
    .await;

    let forger = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).unwrap();
    socket2::SockRef::from(&forger)
        .set_multicast_if_v4(&Ipv4Addr::LOCALHOST)
        .unwrap();
    let digest = Message::Digest(Digest {
        sender: b.compat_session_id(),
        incarnation: 7,
        version: 1,
        updates: vec![],
    });
    let group = SocketAddr::from((pulicast::group_for(pulicast::DISCOVERY_CHANNEL), port));
    forger.send_to(&digest.encode(), group).unwrap();
    let e = next_event(&mut events, |e| {
        matches!(e, DiscoveryEvent::Suspicious { .. })
    })
    .await;
    assert!(matches!(e, DiscoveryEvent::Suspicious { key, .. } if key == b.compat_session_id()));
    let honest = a
        .discovery()
        .members()
        .into_iter()
        .find(|m| m.name == "honest")
        .unwrap();
    // Its own incarnation (0, or 1 if a busy machine made it refute a
    // suspicion), never the forger's 7.
    assert!(
        honest.incarnation < 7,
        "the forged incarnation was taken: {}",
        honest.incarnation
    );
    // Garbage with the discovery magic is counted, not fatal.
    forger.send_to(b"PDSC\x01\xff\xff\xff", group).unwrap();
    eventually("counted", || {
        (a.stats().dropped(pulicast::DropReason::MalformedDiscovery) > 0).then_some(())
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_without_gossip_still_appears_through_its_heartbeat() {
    let port = free_port();
    let a = node("gossiper", port).start().await.unwrap();
    let plain = node("plain", port).discovery(false).start().await.unwrap();
    plain.channel("plain/out").publish(&1i64).unwrap();
    assert!(!plain.discovery().is_gossiping());
    let seen = eventually("plain listed", || {
        a.discovery()
            .members()
            .into_iter()
            .find(|m| m.name == "plain")
    })
    .await;
    assert!(seen.compat && seen.session.is_none());
    eventually("its channel", || {
        a.discovery()
            .members()
            .into_iter()
            .find(|m| m.name == "plain" && m.publishes("plain/out"))
    })
    .await;
    // And it sees the gossiping node through that node's heartbeat.
    eventually("gossiper listed", || {
        plain
            .discovery()
            .members()
            .into_iter()
            .find(|m| m.name == "gossiper")
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn event_streams_end_when_the_node_stops() {
    let port = free_port();
    let a = node("ending", port).start().await.unwrap();
    let mut events = a.discovery().events();
    a.stop();
    let end = tokio::time::timeout(WAIT, events.recv())
        .await
        .expect("returns");
    assert!(end.is_none());
    assert!(a.discovery().events().try_recv().is_none());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_measured_publishing_period_is_announced() {
    let port = free_port();
    let a = node("observer", port).start().await.unwrap();
    let b = node("metronome", port).start().await.unwrap();
    for i in 0..30i64 {
        b.channel("tick").publish(&i).unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let period = eventually("a period near 20 ms", || {
        let m = a
            .discovery()
            .members()
            .into_iter()
            .find(|m| m.name == "metronome")?;
        let c = m.channels.into_iter().find(|c| c.name == "tick")?;
        (c.period_ns > 0).then_some(c.period_ns)
    })
    .await;
    assert!((10_000_000..60_000_000).contains(&period), "{period} ns");
}

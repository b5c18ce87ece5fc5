//! Members of other sites relayed by a bridge (`Discovery::relay`), on
//! loopback: how they appear, how they end, and who may relay them.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::time::{Duration, Instant};

use common::*;
use pulicast::{
    ChannelInfo, DiscoveryEvent, DropReason, MemberInfo, MemberState, RelayedMember, TypeEncoding,
    TypeInfo, DISCOVERY_CHANNEL,
};
use pulicast_discovery::wire::{Message, Relayed};

/// A member of a far site with one published channel, its data coming
/// from `data_port`.
fn far_member(session: u8, data_port: u16) -> RelayedMember {
    RelayedMember {
        info: MemberInfo {
            session: [session; 16],
            name: format!("far{session}"),
            namespace: "far".into(),
            host: "elsewhere".into(),
            pid: 7,
            start_time_ms: 1,
            data_port,
            channels: vec![ChannelInfo {
                name: "far/pose".into(),
                publishes: true,
                subscribes: false,
                period_ns: 0,
                message_type: Some(TypeInfo {
                    encoding: TypeEncoding::Native,
                    name: "Pose".into(),
                    fingerprint: [3; 8],
                    schema: Vec::new(),
                }),
            }],
            config: String::new(),
            extensions: Vec::new(),
        },
        incarnation: 0,
        state: MemberState::Alive,
        site: "site-a".into(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn relayed_members_appear_marked_remote_and_fail_with_their_bridge() {
    let port = free_port();
    let observer = node("observer", port).start().await.unwrap();
    let bridge = node("bridge", port).start().await.unwrap();
    let mut events = observer.discovery().events();
    let data_port = bridge.discovery().local().data_address.unwrap().port();
    let far = far_member(0x41, data_port);
    let far_key = far.info.key();
    bridge.discovery().relay(vec![far.clone()]).unwrap();

    let find = || {
        observer
            .discovery()
            .live_members()
            .into_iter()
            .find(|m| m.key == far_key)
    };
    eventually("the observer lists the far member", || find().is_some()).await;
    let view = find().unwrap();
    let remote = view.remote.clone().expect("marked remote");
    assert_eq!(remote.bridge, bridge.compat_session_id());
    assert_eq!(remote.site, "site-a");
    let bridge_port = bridge.discovery().local_address().unwrap().port();
    assert_eq!(view.address.port(), bridge_port);
    assert_eq!(view.data_address.unwrap().port(), data_port);
    // Lookups see its channel, as they see a local one.
    let channel = observer.channel("far/pose");
    assert!(channel.publishers().iter().any(|m| m.key == far_key));
    assert!(observer.ns("far").resolve_nearest("pose").is_some());
    let joined = tokio::time::timeout(WAIT, async {
        loop {
            if let Some(DiscoveryEvent::Joined(m)) = events.recv().await {
                if m.key == far_key {
                    return m;
                }
            }
        }
    })
    .await
    .unwrap();
    assert!(joined.remote.is_some());

    // Dropped from the bridge's list: it fails once its last refresh ages
    // out (three seconds), not at once and not never.
    let dropped_at = Instant::now();
    bridge.discovery().relay(Vec::new()).unwrap();
    eventually("the unrefreshed member fails", || find().is_none()).await;
    assert!(dropped_at.elapsed() >= Duration::from_secs(1));

    // Relayed again, then the bridge stops: its members fail with it.
    bridge.discovery().relay(vec![far]).unwrap();
    eventually("the member is back", || find().is_some()).await;
    let stopped_at = Instant::now();
    bridge.stop();
    eventually("the member fails with its bridge", || find().is_none()).await;
    // A clean stop is a Leave, seen at once; well within the entry's
    // three-second lifetime.
    assert!(stopped_at.elapsed() < Duration::from_secs(2));
}

/// A list of relayed members is taken only from a live member's own
/// discovery address: neither a made-up bridge nor one naming a real member
/// from another socket gets a member into the fleet view.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stranger_cannot_relay_members() {
    let port = free_port();
    let observer = node("observer", port).start().await.unwrap();
    let honest = node("honest", port).start().await.unwrap();
    let honest_key = honest.compat_session_id();
    eventually("the observer lists the honest member", || {
        observer
            .discovery()
            .live_members()
            .iter()
            .any(|m| m.key == honest_key)
    })
    .await;
    let attacker = raw_sender();
    let fake = far_member(0x66, 9);
    let fake_key = fake.info.key();
    for sender in [0x0bad_5eed, honest_key] {
        let datagram = Message::Relayed(Relayed {
            sender,
            members: vec![fake.clone()],
        })
        .encode();
        for _ in 0..20 {
            send_raw(&attacker, DISCOVERY_CHANNEL, port, &datagram);
        }
    }
    eventually("the forged lists are counted", || {
        observer.stats().dropped(DropReason::UntrustedRelay) >= 40
    })
    .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(!observer
        .discovery()
        .members()
        .iter()
        .any(|m| m.key == fake_key));
    assert_eq!(observer.discovery().relay_stats().unwrap().accepted, 0);
}

//! Attacks by a stranger on the link, without keys, against real nodes on
//! loopback: one ordinary UDP socket that speaks the discovery wire format
//! (docs/wire.md, `pulicast_discovery::wire`). Each test is the attack
//! first, then what must still hold.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::time::{Duration, Instant};

use common::*;
use pulicast::{DiscoveryEvent, MemberState, DISCOVERY_CHANNEL};
use pulicast_discovery::wire::{Digest, Message, Update};

/// A digest from a made-up sender saying, ten times a second for 3 s, that
/// a live member left (then died, then is suspected) at its next
/// incarnation: no node drops it, and a node started meanwhile lists it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stranger_cannot_make_a_live_member_leave() {
    let port = free_port();
    let observer = node("observer", port).start().await.unwrap();
    let victim = node("victim", port).start().await.unwrap();
    let key = victim.compat_session_id();
    let mut events = observer.discovery().events();
    eventually("the observer lists the victim", || {
        observer
            .discovery()
            .live_members()
            .iter()
            .any(|m| m.key == key)
    })
    .await;
    let attacker = raw_sender();
    let started = Instant::now();
    let mut late = None;
    let mut round = 0i64;
    while started.elapsed() < Duration::from_secs(3) {
        let view = observer
            .discovery()
            .members()
            .into_iter()
            .find(|m| m.key == key)
            .unwrap();
        assert_eq!(
            view.state,
            MemberState::Alive,
            "after {:?}",
            started.elapsed()
        );
        for state in [MemberState::Left, MemberState::Dead, MemberState::Suspect] {
            let forged = Message::Digest(Digest {
                sender: 0x5eed_0000 + round,
                incarnation: 0,
                version: 0,
                updates: vec![Update {
                    member: key,
                    incarnation: view.incarnation + 1,
                    version: 1,
                    state,
                    address: view.address,
                }],
            });
            send_raw(&attacker, DISCOVERY_CHANNEL, port, &forged.encode());
        }
        round += 1;
        if late.is_none() && started.elapsed() > Duration::from_secs(1) {
            late = Some(node("latecomer", port).start().await.unwrap());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let late = late.unwrap();
    eventually("the latecomer lists the victim", || {
        late.discovery().live_members().iter().any(|m| m.key == key)
    })
    .await;
    while let Some(e) = events.try_recv() {
        assert!(
            !matches!(
                e,
                DiscoveryEvent::Left { key: k, .. } | DiscoveryEvent::Failed { key: k, .. } if k == key
            ),
            "{e:?}"
        );
    }
}

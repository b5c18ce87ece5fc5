//! Authenticated channels between real nodes on loopback: sealed traffic is
//! delivered, and what strangers send (unsealed, under another key,
//! tampered with, replayed, stale, or spoofed from a member's address) is
//! dropped and counted, for data and for discovery alike.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket};
use std::time::{Duration, Instant};

use common::{
    eventually, free_port, node, now_ms, packet, raw_sender, recv, send_raw, wire_listener, WAIT,
};
use pulicast::{
    group_for, DiscoveryEvent, DropReason, Key, MemberState, Node, NodeBuilder, DISCOVERY_CHANNEL,
};
use pulicast_discovery::wire::{Leave, Message as Gossip};
use pulicast_proto::secure::Sealer;
use socket2::{Domain, Protocol, Socket, Type};

fn key(byte: u8) -> Key {
    Key::from_bytes([byte; 32])
}

/// A node that ignores the environment, so the tests see only their keys.
fn keyed(name: &str, port: u16) -> NodeBuilder {
    node(name, port).keys_from_env(false)
}

/// The next datagram on `socket` that starts with `magic` and mentions
/// `channel`.
fn capture(socket: &UdpSocket, magic: &[u8], channel: &str) -> Vec<u8> {
    let mut buf = vec![0; 65536];
    let deadline = Instant::now() + WAIT;
    while Instant::now() < deadline {
        let n = socket.recv(&mut buf).expect("a datagram in time");
        let d = &buf[..n];
        if d.starts_with(magic) && d.windows(channel.len()).any(|w| w == channel.as_bytes()) {
            return d.to_vec();
        }
    }
    panic!("no {channel} datagram captured");
}

/// The next sealed discovery datagram whose sender seals from `port`.
fn capture_sealed_by(socket: &UdpSocket, port: u16) -> Vec<u8> {
    let deadline = Instant::now() + WAIT;
    while Instant::now() < deadline {
        let d = capture(socket, b"PSEC", DISCOVERY_CHANNEL);
        let sealed = pulicast_proto::wire::sealed::Sealed::decode(&d).map(|s| s.origin.port());
        if sealed == Ok(port) {
            return d;
        }
    }
    panic!("no sealed gossip from port {port} captured");
}

fn dropped(node: &Node, reason: DropReason) -> u64 {
    node.stats().dropped(reason)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sealed_channels_deliver_and_everyone_else_is_dropped() {
    for encrypt in [false, true] {
        let port = free_port();
        let ns_key = key(1);
        let alice = keyed("alice", port)
            .key("rover1", ns_key.clone())
            .encrypt(encrypt)
            .start()
            .await
            .unwrap();
        // Bob opens both modes whatever his own setting.
        let bob = keyed("bob", port)
            .key("/rover1/", ns_key.clone())
            .start()
            .await
            .unwrap();
        let mallory = keyed("mallory", port).start().await.unwrap();
        let eve = keyed("eve", port)
            .key("rover1", key(2))
            .start()
            .await
            .unwrap();

        let mut cmds = bob.channel("rover1/cmd").subscribe::<String>().unwrap();
        let mut blobs = bob.channel("rover1/blob").subscribe_raw().unwrap();
        let mut open = bob.channel("rover2/open").subscribe::<u32>().unwrap();
        let mut stolen = mallory.channel("rover1/cmd").subscribe::<String>().unwrap();
        let wire = wire_listener("rover1/cmd", port, WAIT);

        for i in 0..20 {
            alice
                .channel("rover1/cmd")
                .publish(&format!("secret order {i}"))
                .unwrap();
        }
        for i in 0..20 {
            let m = recv(&mut cmds).await;
            assert_eq!((m.value, m.lead), (format!("secret order {i}"), 1));
        }
        // What the link sees.
        let sealed = capture(&wire, b"PSEC", "rover1/cmd");
        let visible = sealed.windows(12).any(|w| w == b"secret order");
        assert_eq!(visible, !encrypt, "encrypt {encrypt}");

        // A message of many fragments, each sealed; and batches.
        let blob: Vec<u8> = (0..300_000u32).map(|i| (i % 251) as u8).collect();
        alice.channel("rover1/blob").publish_bytes(&blob).unwrap();
        assert_eq!(recv(&mut blobs).await.value, blob[..]);
        let batched = alice.channel("rover1/cmd");
        batched.enable_batching(Duration::from_millis(1)).unwrap();
        for i in 0..500 {
            batched.publish(&format!("batched {i}")).unwrap();
        }
        batched.flush().unwrap();
        for i in 0..500 {
            assert_eq!(recv(&mut cmds).await.value, format!("batched {i}"));
        }
        batched.disable_batching().unwrap();

        // Strangers: no key, and the wrong key.
        for i in 0..5 {
            mallory
                .channel("rover1/cmd")
                .publish(&"forward".to_string())
                .unwrap();
            eve.channel("rover1/cmd")
                .publish(&format!("eve {i}"))
                .unwrap();
        }
        eventually("strangers counted", || {
            dropped(&bob, DropReason::Unauthenticated) >= 5
                && dropped(&bob, DropReason::Forged) >= 5
        })
        .await;
        // A channel without a key stays open to everyone, 2.x style.
        mallory.channel("rover2/open").publish(&7u32).unwrap();
        assert_eq!(recv(&mut open).await.value, 7);
        // Mallory, without the key, hears nothing of rover1 and says why.
        eventually("no_key counted", || {
            dropped(&mallory, DropReason::NoKey) >= 20
        })
        .await;
        // She hears her own messages only.
        while let Some(m) = stolen.try_recv() {
            assert_eq!(m.value, "forward");
        }
        assert!(
            cmds.try_recv().is_none(),
            "a stranger's message was delivered"
        );
        for n in [&alice, &bob, &mallory, &eve] {
            n.stop();
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tampered_replayed_and_stale_datagrams_are_dropped_and_counted() {
    let port = free_port();
    let alice = keyed("alice", port)
        .key("rover1", key(1))
        .start()
        .await
        .unwrap();
    let bob = keyed("bob", port)
        .key("rover1", key(1))
        .start()
        .await
        .unwrap();
    let mut cmds = bob.channel("rover1/cmd").subscribe::<u32>().unwrap();
    let wire = wire_listener("rover1/cmd", port, WAIT);
    alice.channel("rover1/cmd").publish(&1u32).unwrap();
    assert_eq!(recv(&mut cmds).await.value, 1);
    let sealed = capture(&wire, b"PSEC", "rover1/cmd");

    let attacker = raw_sender();
    // The very datagram again: a replay.
    send_raw(&attacker, "rover1/cmd", port, &sealed);
    eventually("replay counted", || {
        dropped(&bob, DropReason::Replayed) == 1
    })
    .await;
    // A changed copy of it is still a replay: its counter is used up, and
    // that is checked before the tag.
    let mut changed = sealed.clone();
    let last = changed.len() - 1;
    changed[last] ^= 0x40;
    send_raw(&attacker, "rover1/cmd", port, &changed);
    eventually("changed replay counted", || {
        dropped(&bob, DropReason::Replayed) == 2
    })
    .await;
    // Changed in flight before bob saw it: any bit flipped, in the header,
    // the payload or the tag. (Not the name: that would only make it
    // another channel's.) Sealed here as if by a member at the attacker's
    // address, so only the flipped bit can make bob refuse it.
    let origin = match attacker.local_addr().unwrap() {
        SocketAddr::V4(a) => a,
        other => panic!("{other}"),
    };
    let mut member = Sealer::new(&key(1), "rover1/cmd", false).with_origin(origin);
    for seq in 0..3 {
        let inner = packet("rover1/cmd", 100 + seq, &7u32.to_be_bytes());
        let mut tampered = member.seal(&inner, now_ms()).to_vec();
        let at = [20, tampered.len() / 2, tampered.len() - 1][seq as usize];
        tampered[at] ^= 0x40;
        send_raw(&attacker, "rover1/cmd", port, &tampered);
    }
    eventually("tampering counted", || {
        dropped(&bob, DropReason::Forged) == 3
    })
    .await;
    // The control: the same, unchanged, is taken.
    let mut eight = Vec::new();
    pulicast_proto::wire::encode_native(&8u32, &mut eight).unwrap();
    let inner = packet("rover1/cmd", 200, &eight);
    send_raw(&attacker, "rover1/cmd", port, member.seal(&inner, now_ms()));
    assert_eq!(recv(&mut cmds).await.value, 8);
    // Cut short.
    let inner = packet("rover1/cmd", 300, &eight);
    let whole = member.seal(&inner, now_ms());
    send_raw(&attacker, "rover1/cmd", port, &whole[..whole.len() - 20]);
    // Sealed with the right key, but a minute old or a minute ahead: only
    // someone holding the key makes these, so they stand for recorded
    // traffic replayed to a node that never saw it.
    let now_ms = now_ms();
    for sent in [now_ms - 60_000, now_ms + 60_000] {
        let mut sealer = Sealer::new(&key(1), "rover1/cmd", false);
        let stale = sealer.seal(&packet("rover1/cmd", 9, &9u32.to_be_bytes()), sent);
        send_raw(&attacker, "rover1/cmd", port, stale);
    }
    eventually("stale counted", || dropped(&bob, DropReason::Stale) == 2).await;
    eventually("truncation counted", || {
        dropped(&bob, DropReason::Forged) + dropped(&bob, DropReason::MalformedPayload) == 4
    })
    .await;
    // Nothing of it reached the subscriber, and the channel still works.
    assert!(cmds.try_recv().is_none());
    alice.channel("rover1/cmd").publish(&2u32).unwrap();
    let m = recv(&mut cmds).await;
    assert_eq!((m.value, m.lead), (2, 1));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_key_change_has_no_gap() {
    let port = free_port();
    let (old, new) = (key(1), key(2));
    // Mid-change: one node still seals with the old key, one with the new;
    // both accept both.
    let behind = keyed("behind", port)
        .key("/", old.clone())
        .key("/", new.clone())
        .start()
        .await
        .unwrap();
    let ahead = keyed("ahead", port)
        .key("/", new.clone())
        .key("/", old.clone())
        .start()
        .await
        .unwrap();
    // Done: only the new key.
    let done = keyed("done", port).key("/", new).start().await.unwrap();
    let mut at_behind = behind.channel("x").subscribe::<u32>().unwrap();
    let mut at_ahead = ahead.channel("x").subscribe::<u32>().unwrap();
    let mut at_done = done.channel("x").subscribe::<u32>().unwrap();
    behind.channel("x").publish(&1u32).unwrap();
    ahead.channel("x").publish(&2u32).unwrap();
    for sub in [&mut at_behind, &mut at_ahead] {
        let mut got = [recv(sub).await.value, recv(sub).await.value];
        got.sort();
        assert_eq!(got, [1, 2]);
    }
    // The finished node hears the new key only.
    assert_eq!(recv(&mut at_done).await.value, 2);
    eventually("old key refused", || {
        dropped(&done, DropReason::Forged) >= 1
    })
    .await;
}

/// Sends a UDP datagram with a forged source address, as anyone on a link
/// can: a raw socket writes the UDP header itself. `None` without the
/// privilege (raw sockets need root, as CI has).
fn spoof(from: SocketAddrV4, to: SocketAddrV4, payload: &[u8]) -> Option<()> {
    let s = match Socket::new(Domain::IPV4, Type::RAW, Some(Protocol::UDP)) {
        Ok(s) => s,
        Err(e) if e.kind() == std::io::ErrorKind::PermissionDenied => return None,
        Err(e) => panic!("raw socket: {e}"),
    };
    s.bind(&SocketAddr::from((*from.ip(), 0)).into()).unwrap();
    let mut d = Vec::new();
    d.extend_from_slice(&from.port().to_be_bytes());
    d.extend_from_slice(&to.port().to_be_bytes());
    d.extend_from_slice(&u16::try_from(8 + payload.len()).unwrap().to_be_bytes());
    d.extend_from_slice(&[0, 0]); // no checksum, which IPv4 allows
    d.extend_from_slice(payload);
    s.send_to(&d, &SocketAddr::V4(to).into()).unwrap();
    Some(())
}

/// Forges `victim` leaving, from the victim's own discovery address, to
/// `target`'s discovery socket. False if spoofing is not possible here.
fn forge_leave(target: &Node, victim: &Node) -> bool {
    let view = target
        .discovery()
        .live_members()
        .into_iter()
        .find(|m| m.key == victim.compat_session_id())
        .expect("victim known");
    let SocketAddr::V4(from) = view.address else {
        panic!("IPv4")
    };
    let to = SocketAddrV4::new(
        Ipv4Addr::LOCALHOST,
        target.discovery().local_address().unwrap().port(),
    );
    let leave = Gossip::Leave(Leave {
        sender: victim.compat_session_id(),
        incarnation: view.incarnation + 1,
    })
    .encode();
    spoof(from, to, &leave).is_some()
}

async fn knows(node: &Node, other: &Node) {
    let key = other.compat_session_id();
    let discovery = node.discovery();
    eventually("members see each other", || {
        discovery
            .live_members()
            .iter()
            .any(|m| m.key == key && !m.compat)
    })
    .await;
}

fn state_of(node: &Node, other: &Node) -> Option<MemberState> {
    let key = other.compat_session_id();
    let members = node.discovery().members();
    members.into_iter().find(|m| m.key == key).map(|m| m.state)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn strangers_cant_join_leave_or_impersonate_a_keyed_fleet() {
    // Without keys, anyone who can send to the link makes a member leave
    // with one forged datagram: the attack the key must stop.
    let port = free_port();
    let a = keyed("a", port).start().await.unwrap();
    let b = keyed("b", port).start().await.unwrap();
    knows(&a, &b).await;
    let mut events = a.discovery().events();
    if !forge_leave(&a, &b) {
        eprintln!("skipping: spoofing source addresses needs a raw socket (root)");
        return;
    }
    // The victim refutes it once the claim reaches it (it may be back
    // within a digest interval), so the event shows it, not the state.
    let victim = b.compat_session_id();
    let left = tokio::time::timeout(WAIT, async {
        while let Some(e) = events.recv().await {
            if matches!(e, DiscoveryEvent::Left { key, .. } if key == victim) {
                return true;
            }
        }
        false
    })
    .await;
    assert_eq!(left, Ok(true), "the forged leave worked on an open fleet");
    a.stop();
    b.stop();

    let port = free_port();
    let fleet = key(7);
    let a = keyed("a", port)
        .key("/", fleet.clone())
        .start()
        .await
        .unwrap();
    let b = keyed("b", port)
        .key("/", fleet.clone())
        .start()
        .await
        .unwrap();
    knows(&a, &b).await;
    knows(&b, &a).await;
    let wire = wire_listener(DISCOVERY_CHANNEL, port, WAIT);

    // The same forged leave, now refused.
    assert!(forge_leave(&a, &b));
    eventually("the forged leave counted", || {
        dropped(&a, DropReason::Unauthenticated) == 1
    })
    .await;
    // A sealed gossip datagram of b's, replayed.
    let genuine = capture(&wire, b"PSEC", DISCOVERY_CHANNEL);
    let group = SocketAddr::from((group_for(DISCOVERY_CHANNEL), port));
    raw_sender().send_to(&genuine, group).unwrap();
    eventually("the replay counted", || {
        dropped(&a, DropReason::Replayed) >= 1
    })
    .await;

    // Strangers try to join: one without a key, one with another.
    let stranger = keyed("stranger", port).start().await.unwrap();
    let impostor = keyed("impostor", port)
        .key("/", key(8))
        .start()
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_secs(1)).await;
    // Alive, or suspect for a moment if a busy machine held b's gossip
    // back, but not gone: it never left.
    let state = state_of(&a, &b);
    assert!(
        matches!(state, Some(MemberState::Alive | MemberState::Suspect)),
        "the forged leave worked: {state:?}"
    );
    // Neither stranger joined: not by gossip, not by 2.x heartbeats.
    for outsider in [&stranger, &impostor] {
        let key = outsider.compat_session_id();
        assert!(a.discovery().members().iter().all(|m| m.key != key));
        assert!(a.peers().iter().all(|p| p.session_id != key));
        // And they see nothing of the fleet.
        assert!(outsider.discovery().members().is_empty());
        assert!(outsider.peers().is_empty());
    }
    assert!(dropped(&a, DropReason::Forged) > 0);
    assert!(dropped(&stranger, DropReason::NoKey) > 0);
    // A node that just started has heard nobody yet: b's recorded gossip,
    // relayed to it from elsewhere, must not pin b to the relay's address.
    // Recorded before it starts, relayed the moment it does: first.
    // Only b's: the socket also holds the impostor's gossip, sealed under
    // another key, which the newcomer would count as such.
    let b_port = b.discovery().local_address().unwrap().port();
    let recorded: Vec<Vec<u8>> = (0..3).map(|_| capture_sealed_by(&wire, b_port)).collect();
    let newcomer = keyed("newcomer", port)
        .key("/", fleet.clone())
        .start()
        .await
        .unwrap();
    let to = SocketAddr::from((
        Ipv4Addr::LOCALHOST,
        newcomer.discovery().local_address().unwrap().port(),
    ));
    let relay = raw_sender();
    for genuine in &recorded {
        relay.send_to(genuine, to).unwrap();
    }
    for genuine in &recorded {
        relay.send_to(genuine, group).unwrap();
    }
    eventually("relayed gossip refused", || {
        dropped(&newcomer, DropReason::Replayed) >= 3
    })
    .await;
    knows(&newcomer, &b).await;
    let seen = newcomer.discovery().live_members();
    let b_there = seen
        .iter()
        .find(|m| m.key == b.compat_session_id())
        .unwrap();
    assert_eq!(
        b_there.address.port(),
        b.discovery().local_address().unwrap().port(),
        "b pinned to a relay"
    );
    // A real leave, sealed, is heard.
    b.stop();
    eventually("b's sealed leave heard", || {
        state_of(&a, &b) == Some(MemberState::Left)
    })
    .await;
}

//! Member state that is small on the wire and large in memory, from a
//! stranger without keys. A test binary of its own: it measures the
//! resident memory of its process, which other tests beside it would add to.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::net::UdpSocket;
use std::time::{Duration, Instant};

use common::*;
use pulicast::DISCOVERY_CHANNEL;
use pulicast_discovery::wire::{ChannelInfo, Digest, MemberKey, Message};

fn digest(key: MemberKey) -> Vec<u8> {
    Message::Digest(Digest {
        sender: key,
        incarnation: 0,
        version: 1,
        updates: vec![],
    })
    .encode()
}

/// Forty made-up members, each from a socket of its own, with full states
/// that are small on the wire and large in memory: twenty at the largest
/// size the wire allows (16 parts of 60 000 bytes, about 190 000 channels,
/// about 20 MB each once decoded) and twenty of about 3.5 MB each (70 MB
/// together, more than the 64 MiB all members may hold), kept alive by
/// digests, while the member list is read as a tool does. The node's memory
/// grows by less than 200 MB (it grew by over 800 MB before the byte
/// bound), the states that don't fit are refused or make room (counted
/// either way), and a real
/// node that starts meanwhile is listed with its channel.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn member_state_that_is_large_in_memory_is_bounded_in_bytes() {
    let port = free_port();
    let heartbeat = Duration::from_millis(100);
    let victim = node("victim", port)
        .heartbeat_period(heartbeat)
        .start()
        .await
        .unwrap();
    let _ = victim.discovery().members();
    let baseline = resident_bytes();

    let fakes: Vec<(MemberKey, UdpSocket, Vec<Vec<u8>>)> = (0..40)
        .map(|i| {
            let key = 0x0bad_0000 + i as MemberKey;
            // The largest state the wire allows, or one that holds about
            // 3.5 MB in memory (under the 4 MiB a member may hold).
            let small = 3_500_000 / std::mem::size_of::<ChannelInfo>();
            let channels = if i < 20 { 191_000 } else { small };
            (
                key,
                raw_sender(),
                full_state_datagrams(&bulky_info(key, channels)),
            )
        })
        .collect();
    let keep_alive = |fakes: &[(MemberKey, UdpSocket, Vec<Vec<u8>>)]| {
        for (key, socket, _) in fakes {
            send_raw(socket, DISCOVERY_CHANNEL, port, &digest(*key));
        }
    };
    let mut peak = 0;
    let mut last_digests = Instant::now();
    for (key, socket, parts) in &fakes {
        send_raw(socket, DISCOVERY_CHANNEL, port, &digest(*key));
        for part in parts {
            send_raw(socket, DISCOVERY_CHANNEL, port, part);
            // Paced: a burst would only overflow the socket's buffer.
            tokio::time::sleep(Duration::from_millis(2)).await;
            if last_digests.elapsed() > heartbeat / 2 {
                keep_alive(&fakes);
                last_digests = Instant::now();
                peak = peak.max(resident_bytes());
                let _ = victim.discovery().members();
            }
        }
    }
    let real = node("real", port)
        .heartbeat_period(heartbeat)
        .start()
        .await
        .unwrap();
    real.channel("real/pose").publish(&1.0f64).unwrap();
    let started = Instant::now();
    let mut listed = false;
    while started.elapsed() < Duration::from_secs(3) {
        keep_alive(&fakes);
        let members = victim.discovery().members();
        listed |= members
            .iter()
            .any(|m| m.name == "real" && m.publishes("real/pose"));
        peak = peak.max(resident_bytes());
        tokio::time::sleep(heartbeat / 2).await;
    }
    let stats = victim.discovery().stats().unwrap();
    let grown = peak.saturating_sub(baseline);
    eprintln!(
        "resident: {} MB before, peak {} MB; {} states refused, {} evicted",
        baseline >> 20,
        peak >> 20,
        stats.states_refused,
        stats.states_evicted
    );
    assert!(listed, "the real node is not listed with its channel");
    // The twenty largest are refused from their channel count alone. Of
    // the smaller ones, some don't fit: each is refused, or makes room by
    // dropping the state of a fake that a busy machine let go silent
    // (members that are gone give way first).
    assert!(stats.states_refused >= 20, "{stats:?}");
    assert!(
        stats.states_refused + stats.states_evicted > 20,
        "{stats:?}"
    );
    assert!(grown < 200 << 20, "memory grew by {} MB", grown >> 20);
}

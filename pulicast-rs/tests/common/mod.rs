//! Helpers shared by the loopback test files: every socket pinned to
//! 127.0.0.1, TTL 0, and every wait bounded.

#![allow(dead_code)] // each test file uses its own subset

use std::net::{Ipv4Addr, SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use pulicast::wire::Packet;
use pulicast::{group_for, Node, NodeBuilder};

/// How long any single wait in a test may take.
pub const WAIT: Duration = Duration::from_secs(5);

/// A port no other test (or test process) is using right now.
pub fn free_port() -> u16 {
    pulicast::unused_port().expect("an unused port")
}

pub fn node(name: &str, port: u16) -> NodeBuilder {
    Node::new(name)
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .heartbeat_period(Duration::from_millis(20))
}

/// A plain socket that sends hand-made datagrams to a channel's group.
pub fn raw_sender() -> UdpSocket {
    let s = UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).expect("bind");
    s.set_multicast_loop_v4(true).expect("loop");
    s.set_multicast_ttl_v4(0).expect("ttl");
    let sock = socket2::SockRef::from(&s);
    sock.set_multicast_if_v4(&Ipv4Addr::LOCALHOST)
        .expect("iface");
    s
}

pub fn send_raw(s: &UdpSocket, channel: &str, port: u16, datagram: &[u8]) {
    s.send_to(datagram, SocketAddr::from((group_for(channel), port)))
        .expect("send");
}

pub fn packet(channel: &str, seq: u32, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    Packet {
        channel,
        seq,
        payload,
    }
    .encode(&mut out);
    out
}

pub async fn eventually(what: &str, mut cond: impl FnMut() -> bool) {
    let deadline = Instant::now() + WAIT;
    while !cond() {
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

pub async fn recv<T>(sub: &mut pulicast::Subscription<T>) -> pulicast::Message<T> {
    tokio::time::timeout(WAIT, sub.recv())
        .await
        .expect("message within the timeout")
        .expect("subscription open")
}

//! Helpers shared by the loopback test files: every socket pinned to
//! 127.0.0.1, TTL 0, and every wait bounded.

#![allow(dead_code)] // each test file uses its own subset

use std::net::{Ipv4Addr, SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use pulicast::{group_for, Node, NodeBuilder};
use pulicast_proto::wire::Packet;

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

/// Milliseconds since the Unix epoch: the clock seals carry.
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// A plain socket that hears a channel's group, as any host on the link
/// could, to see what goes on the wire; reads give up after `timeout`.
pub fn wire_listener(channel: &str, port: u16, timeout: Duration) -> UdpSocket {
    let s = socket2::Socket::new(
        socket2::Domain::IPV4,
        socket2::Type::DGRAM,
        Some(socket2::Protocol::UDP),
    )
    .expect("socket");
    s.set_reuse_address(true).expect("reuse");
    // Only this group, not every group some socket on the host joined.
    s.set_multicast_all_v4(false).expect("multicast_all");
    s.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, port)).into())
        .expect("bind");
    s.join_multicast_v4(&group_for(channel), &Ipv4Addr::LOCALHOST)
        .expect("join");
    let s: UdpSocket = s.into();
    s.set_read_timeout(Some(timeout)).expect("timeout");
    s
}

/// This process's resident memory, in bytes (Linux).
pub fn resident_bytes() -> usize {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let kb: usize = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS");
    kb * 1024
}

/// A made-up member's full state: `channels` channels with empty names,
/// 5 bytes each on the wire and a whole `ChannelInfo` in memory.
pub fn bulky_info(
    key: pulicast_discovery::wire::MemberKey,
    channels: usize,
) -> pulicast_discovery::wire::MemberInfo {
    use pulicast_discovery::wire::{ChannelInfo, MemberInfo};
    let mut session = [0u8; 16];
    session[..8].copy_from_slice(&key.to_be_bytes());
    MemberInfo {
        session,
        name: format!("fake{key}"),
        namespace: String::new(),
        host: String::new(),
        pid: 0,
        start_time_ms: 0,
        data_port: 0,
        channels: vec![
            ChannelInfo {
                name: String::new(),
                publishes: false,
                subscribes: false,
                period_ns: 0,
                message_type: None,
            };
            channels
        ],
        config: String::new(),
        extensions: Vec::new(),
    }
}

/// The datagrams that multicast `info` as its owner would, at version 1.
pub fn full_state_datagrams(info: &pulicast_discovery::wire::MemberInfo) -> Vec<Vec<u8>> {
    use pulicast_discovery::wire::{self, Message};
    let encoded = wire::encode_info(info);
    wire::full_parts(info.key(), 0, 1, &encoded)
        .expect("within the parts a state may have")
        .into_iter()
        .map(|part| Message::Full(part).encode())
        .collect()
}

/// A raw socket that sends UDP datagrams with any source address (root
/// only, as CI has); `None` where there is none.
pub fn raw_spoofer() -> Option<socket2::Socket> {
    let raw = socket2::Socket::new(
        socket2::Domain::IPV4,
        socket2::Type::RAW,
        Some(socket2::Protocol::UDP),
    )
    .ok()?;
    raw.set_header_included_v4(true).ok()?;
    raw.set_multicast_if_v4(&Ipv4Addr::LOCALHOST).ok()?;
    raw.set_multicast_loop_v4(true).ok()?;
    Some(raw)
}

/// Sends `datagram` from `from` (forged) to `to` over the raw socket
/// `raw`, at TTL 0.
pub fn send_spoofed(raw: &socket2::Socket, from: SocketAddr, to: SocketAddr, datagram: &[u8]) {
    let (SocketAddr::V4(from), SocketAddr::V4(to)) = (from, to) else {
        panic!("IPv4 only");
    };
    let udp_len = 8 + datagram.len();
    let mut ip = vec![0x45, 0, 0, 0, 0, 0, 0, 0, 0 /* TTL 0 */, 17, 0, 0];
    ip.extend_from_slice(&from.ip().octets());
    ip.extend_from_slice(&to.ip().octets());
    let total = (ip.len() + udp_len) as u16;
    ip[2..4].copy_from_slice(&total.to_be_bytes());
    ip.extend_from_slice(&from.port().to_be_bytes());
    ip.extend_from_slice(&to.port().to_be_bytes());
    ip.extend_from_slice(&(udp_len as u16).to_be_bytes());
    ip.extend_from_slice(&[0, 0]); // no UDP checksum
    ip.extend_from_slice(datagram);
    raw.send_to(&ip, &SocketAddr::V4(to).into())
        .expect("raw send");
}

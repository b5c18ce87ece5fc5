//! The raw-socket baseline every row is compared with: plain socket2 UDP
//! multicast sockets, set up like pulicast's (loopback, the same receive
//! buffer), blocking or busy-polled. `bench call` borrows the sockets.

use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket};

use anyhow::Result;
use socket2::{Domain, Protocol, Socket, Type};

/// The raw baseline sends larger messages as datagrams of this size.
pub(super) const RAW_CHUNK: usize = 60_000;

pub(crate) fn group(name: &str, port: u16) -> SocketAddrV4 {
    SocketAddrV4::new(pulicast::group_for(name), port)
}

pub(crate) fn raw_sender() -> Result<UdpSocket> {
    let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    s.set_multicast_if_v4(&Ipv4Addr::LOCALHOST)?;
    s.set_multicast_ttl_v4(0)?;
    s.set_multicast_loop_v4(true)?;
    s.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0)).into())?;
    Ok(s.into())
}

pub(crate) fn raw_receiver(group: SocketAddrV4, rcvbuf: usize) -> Result<UdpSocket> {
    let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    s.set_reuse_address(true)?;
    s.set_multicast_all_v4(false)?;
    let _ = s.set_recv_buffer_size(rcvbuf);
    s.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, group.port())).into())?;
    s.join_multicast_v4(group.ip(), &Ipv4Addr::LOCALHOST)?;
    Ok(s.into())
}

/// A non-blocking raw receiver, for busy-polling.
pub(super) fn raw_spinning_receiver(group: SocketAddrV4, rcvbuf: usize) -> Result<UdpSocket> {
    let socket = raw_receiver(group, rcvbuf)?;
    socket.set_nonblocking(true)?;
    Ok(socket)
}

/// Polls a non-blocking socket until a datagram comes or `give_up` says so
/// (asked every 4096 polls).
pub(super) fn spin_recv(
    socket: &UdpSocket,
    buf: &mut [u8],
    mut give_up: impl FnMut() -> bool,
) -> Option<usize> {
    let mut polls = 0u32;
    loop {
        match socket.recv_from(buf) {
            Ok((n, _)) => return Some(n),
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                polls = polls.wrapping_add(1);
                if polls % 4096 == 0 && give_up() {
                    return None;
                }
                std::hint::spin_loop();
            }
            Err(_) => return None,
        }
    }
}

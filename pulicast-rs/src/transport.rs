//! Sockets: the only module that knows socket2 and tokio networking.
//!
//! One send socket per node, so all its channels share one source address (which
//! is what receivers track leads by). Receive sockets all bind `0.0.0.0:port` with
//! `SO_REUSEADDR`, so any number of nodes on one host share the port, and set
//! `IP_MULTICAST_ALL` off, so each socket sees only the groups it joined. Linux
//! limits group memberships per socket (`net.ipv4.igmp_max_memberships`, 20 by
//! default); [`ReceivePool`] opens another socket whenever the current ones are
//! full.

use std::collections::HashMap;
use std::io;
use std::net::{Ipv4Addr, SocketAddr, UdpSocket as StdUdpSocket};
use std::sync::Arc;

use socket2::{Domain, Protocol, Socket, Type};
use tokio::net::UdpSocket;

/// Receive buffer we ask for: bursts of large messages overflow the default.
const RECV_BUFFER: usize = 4 << 20;

/// Socket options shared by sending and receiving.
#[derive(Debug, Clone)]
pub(crate) struct NetConfig {
    pub port: u16,
    pub ttl: u32,
    pub interface: Option<Ipv4Addr>,
}

impl NetConfig {
    fn interface_or_any(&self) -> Ipv4Addr {
        self.interface.unwrap_or(Ipv4Addr::UNSPECIFIED)
    }
}

/// Opens the node's send socket: blocking, so publishing needs no runtime.
pub(crate) fn send_socket(cfg: &NetConfig) -> io::Result<StdUdpSocket> {
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_multicast_ttl_v4(cfg.ttl)?;
    socket.set_multicast_loop_v4(true)?;
    if let Some(iface) = cfg.interface {
        socket.set_multicast_if_v4(&iface)?;
    }
    socket.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0)).into())?;
    Ok(socket.into())
}

fn receive_socket(cfg: &NetConfig) -> io::Result<UdpSocket> {
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_reuse_address(true)?;
    #[cfg(target_os = "linux")]
    socket.set_multicast_all_v4(false)?;
    if let Err(e) = socket.set_recv_buffer_size(RECV_BUFFER) {
        tracing::debug!("could not set receive buffer size: {e}");
    }
    let granted = socket.recv_buffer_size().unwrap_or(0);
    if granted < RECV_BUFFER {
        warn_small_buffer(granted);
    }
    socket.set_nonblocking(true)?;
    socket.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, cfg.port)).into())?;
    UdpSocket::from_std(socket.into())
}

fn warn_small_buffer(granted: usize) {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        tracing::warn!(
            granted,
            wanted = RECV_BUFFER,
            "the kernel grants a smaller receive buffer than asked for; bursts may be lost \
             (raise net.core.rmem_max)"
        );
    });
}

/// Whether a join failed because the socket holds the most memberships allowed.
fn is_membership_limit(e: &io::Error) -> bool {
    e.raw_os_error() == Some(libc_enobufs())
}

const fn libc_enobufs() -> i32 {
    // ENOBUFS on Linux and the BSDs alike.
    if cfg!(target_os = "linux") {
        105
    } else {
        55
    }
}

/// A receive socket and how many groups it has joined.
struct Member {
    socket: Arc<UdpSocket>,
    groups: usize,
    full: bool,
}

/// The receive sockets of one node and which groups each has joined.
pub(crate) struct ReceivePool {
    cfg: NetConfig,
    members: Vec<Member>,
    /// Group -> (index into `members`, number of channels using it).
    groups: HashMap<Ipv4Addr, (usize, usize)>,
}

impl ReceivePool {
    pub fn new(cfg: NetConfig) -> Self {
        Self {
            cfg,
            members: Vec::new(),
            groups: HashMap::new(),
        }
    }

    /// Joins `group` for one more channel. Returns a socket that was opened for
    /// it, which the caller must start receiving on.
    pub fn join(&mut self, group: Ipv4Addr) -> io::Result<Option<Arc<UdpSocket>>> {
        if let Some((_, users)) = self.groups.get_mut(&group) {
            *users += 1;
            return Ok(None);
        }
        let iface = self.cfg.interface_or_any();
        for (i, m) in self.members.iter_mut().enumerate() {
            if m.full {
                continue;
            }
            match m.socket.join_multicast_v4(group, iface) {
                Ok(()) => {
                    m.groups += 1;
                    self.groups.insert(group, (i, 1));
                    return Ok(None);
                }
                Err(e) if is_membership_limit(&e) => m.full = true,
                Err(e) => return Err(e),
            }
        }
        let socket = Arc::new(receive_socket(&self.cfg)?);
        socket.join_multicast_v4(group, iface)?;
        self.members.push(Member {
            socket: Arc::clone(&socket),
            groups: 1,
            full: false,
        });
        self.groups.insert(group, (self.members.len() - 1, 1));
        tracing::debug!(sockets = self.members.len(), "opened a receive socket");
        Ok(Some(socket))
    }

    /// Releases one channel's use of `group`; leaves it when no channel needs it.
    pub fn leave(&mut self, group: Ipv4Addr) {
        let Some((idx, users)) = self.groups.get_mut(&group) else {
            return;
        };
        *users -= 1;
        if *users > 0 {
            return;
        }
        let idx = *idx;
        self.groups.remove(&group);
        if let Some(m) = self.members.get_mut(idx) {
            if let Err(e) = m
                .socket
                .leave_multicast_v4(group, self.cfg.interface_or_any())
            {
                tracing::debug!(%group, "leaving multicast group failed: {e}");
            }
            m.groups -= 1;
            m.full = false;
        }
    }

    /// Number of receive sockets open.
    pub fn socket_count(&self) -> usize {
        self.members.len()
    }
}

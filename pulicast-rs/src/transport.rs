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

/// Socket options shared by sending and receiving.
#[derive(Debug, Clone)]
pub(crate) struct NetConfig {
    pub port: u16,
    pub ttl: u32,
    pub interface: Option<Ipv4Addr>,
    /// Receive buffer to ask for, per receive socket.
    pub receive_buffer: usize,
}

impl NetConfig {
    /// The receive buffer the kernel grants a receive socket asked for
    /// [`NetConfig::receive_buffer`] (as `SO_RCVBUF` reads: twice the
    /// payload it holds), found on a socket opened for it and closed;
    /// `None` if it can't be read.
    pub(crate) fn granted_receive_buffer(&self) -> Option<usize> {
        let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP)).ok()?;
        // A refusal leaves the default, which is then what it grants.
        let _ = socket.set_recv_buffer_size(self.receive_buffer);
        socket.recv_buffer_size().ok()
    }

    /// The interface multicast leaves from: the one given, or at TTL 0
    /// loopback. TTL 0 keeps datagrams on this host whatever the interface,
    /// so loopback reaches the same nodes, and more: nodes pinned to
    /// loopback only hear datagrams sent on it, and a datagram sent out of a
    /// real interface at TTL 0 is put on the wire when no socket of the host
    /// has joined its group there. `None` leaves the choice to the routes.
    pub(crate) fn send_interface(&self) -> Option<Ipv4Addr> {
        self.interface
            .or((self.ttl == 0).then_some(Ipv4Addr::LOCALHOST))
    }

    /// The address other nodes see this node's datagrams come from: the
    /// send interface's, or where the routes send multicast from (asked of
    /// the kernel without sending anything); unspecified when unknown.
    pub(crate) fn source_ip(&self) -> Ipv4Addr {
        self.send_interface().unwrap_or_else(|| {
            let routed = || -> io::Result<Ipv4Addr> {
                let probe = StdUdpSocket::bind((Ipv4Addr::UNSPECIFIED, 0))?;
                probe.connect((crate::name::GROUP_BASE, self.port))?;
                match probe.local_addr()? {
                    SocketAddr::V4(a) => Ok(*a.ip()),
                    SocketAddr::V6(_) => Ok(Ipv4Addr::UNSPECIFIED),
                }
            };
            routed().unwrap_or(Ipv4Addr::UNSPECIFIED)
        })
    }
}

/// Says once per process, for a node pinned to loopback at TTL 0 on a host
/// with a network, what pinning costs: Pulicast 2.x nodes started with their
/// defaults send on the network's interface, where a pinned node has not
/// joined, so it never hears them (every node of ours it does hear: they send
/// on loopback at TTL 0). No default of ours can change what 2.x sends on.
pub(crate) fn warn_pinned_to_loopback(cfg: &NetConfig) {
    if cfg.ttl != 0 || cfg.interface != Some(Ipv4Addr::LOCALHOST) {
        return;
    }
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let routed = NetConfig {
            interface: None,
            ttl: 1,
            ..cfg.clone()
        }
        .source_ip();
        if routed.is_unspecified() || routed.is_loopback() {
            return; // no network: 2.x nodes send on loopback too
        }
        tracing::warn!(
            "pinned to 127.0.0.1: this node hears the nodes of this host that send on loopback \
             (all pulicast-rs nodes at TTL 0, 2.x nodes given interface_address=\"127.0.0.1\"), \
             but not Pulicast 2.x nodes started with their defaults, which send on {routed}; \
             leave the interface unset to hear those too"
        );
    });
}

/// Opens the node's send socket: blocking, so publishing needs no runtime.
pub(crate) fn send_socket(cfg: &NetConfig) -> io::Result<StdUdpSocket> {
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_multicast_ttl_v4(cfg.ttl)?;
    socket.set_multicast_loop_v4(true)?;
    if let Some(iface) = cfg.send_interface() {
        socket.set_multicast_if_v4(&iface)?;
    }
    socket.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0)).into())?;
    Ok(socket.into())
}

/// Opens the socket a node's service calls leave from and their answers
/// come back to: multicast as the send socket (`send`) is, non-blocking
/// (it is read by a task), on a port of its own.
pub(crate) fn service_socket(send: &StdUdpSocket) -> io::Result<UdpSocket> {
    let like = socket2::SockRef::from(send);
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_multicast_ttl_v4(like.multicast_ttl_v4()?)?;
    socket.set_multicast_loop_v4(true)?;
    socket.set_multicast_if_v4(&like.multicast_if_v4()?)?;
    socket.set_nonblocking(true)?;
    socket.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0)).into())?;
    UdpSocket::from_std(socket.into())
}

/// Opens the node's discovery socket: it multicasts the node's digests and
/// receives unicast from peers (seeds, pulls). A fixed `port` lets other nodes
/// name this one as their seed; 0 picks a free one.
pub(crate) fn discovery_socket(cfg: &NetConfig, port: u16) -> io::Result<UdpSocket> {
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_multicast_ttl_v4(cfg.ttl)?;
    socket.set_multicast_loop_v4(true)?;
    if let Some(iface) = cfg.send_interface() {
        socket.set_multicast_if_v4(&iface)?;
    }
    socket.set_nonblocking(true)?;
    socket.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, port)).into())?;
    UdpSocket::from_std(socket.into())
}

fn receive_socket(cfg: &NetConfig) -> io::Result<UdpSocket> {
    let socket = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    socket.set_reuse_address(true)?;
    #[cfg(target_os = "linux")]
    socket.set_multicast_all_v4(false)?;
    if let Err(e) = socket.set_recv_buffer_size(cfg.receive_buffer) {
        tracing::debug!("could not set receive buffer size: {e}");
    }
    let granted = socket.recv_buffer_size().unwrap_or(0);
    // Linux reports twice what it grants as payload (the other half is
    // bookkeeping), and grants at most net.core.rmem_max.
    if granted < cfg.receive_buffer {
        warn_small_buffer(granted, cfg.receive_buffer);
    }
    socket.set_nonblocking(true)?;
    socket.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, cfg.port)).into())?;
    UdpSocket::from_std(socket.into())
}

/// The receive buffer a socket gets when its program asks for none
/// (`net.core.rmem_default`, as `SO_RCVBUF` reads it), what a Pulicast
/// 2.x node runs with unless configured; Linux's usual 212 992 bytes if
/// it can't be read.
pub(crate) fn default_receive_buffer() -> usize {
    std::fs::read_to_string("/proc/sys/net/core/rmem_default")
        .ok()
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(212_992)
}

fn warn_small_buffer(granted: usize, wanted: usize) {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        tracing::warn!(
            granted,
            wanted,
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

/// A receive socket and how many memberships it holds.
struct Member {
    socket: Arc<UdpSocket>,
    memberships: usize,
    full: bool,
}

/// Which socket carries a group, on which interfaces, for how many channels.
struct GroupUse {
    member: usize,
    interfaces: Vec<Ipv4Addr>,
    users: usize,
}

/// What [`ReceivePool::join`] gives: the index of the socket that carries
/// the group, and the socket if it was opened for it.
pub(crate) type Joined = (usize, Option<Arc<UdpSocket>>);

/// The receive sockets of one node and which groups each has joined.
pub(crate) struct ReceivePool {
    cfg: NetConfig,
    members: Vec<Member>,
    groups: HashMap<Ipv4Addr, GroupUse>,
}

enum JoinError {
    /// The socket holds the most memberships the kernel allows.
    Full,
    Io(io::Error),
}

impl ReceivePool {
    pub(crate) fn new(cfg: NetConfig) -> Self {
        Self {
            cfg,
            members: Vec::new(),
            groups: HashMap::new(),
        }
    }

    /// The interfaces a group is joined on. Like Pulicast 2.x, a node that is
    /// not pinned to loopback joins on loopback as well, so it hears local
    /// nodes that are (and, at TTL 0, every node of ours, which send on
    /// loopback); on the routes' interface it hears 2.x nodes, which send
    /// there.
    fn interfaces(&self) -> Vec<Ipv4Addr> {
        match self.cfg.interface {
            Some(iface) if iface.is_loopback() => vec![iface],
            Some(iface) => vec![iface, Ipv4Addr::LOCALHOST],
            None => vec![Ipv4Addr::UNSPECIFIED, Ipv4Addr::LOCALHOST],
        }
    }

    /// Joins `group` for one more channel. Returns the index of the socket
    /// that carries it (see [`ReceivePool::socket_of`]) and, if it was
    /// opened for it, the socket, which the caller must start receiving on.
    pub(crate) fn join(&mut self, group: Ipv4Addr) -> io::Result<Joined> {
        if let Some(used) = self.groups.get_mut(&group) {
            used.users += 1;
            return Ok((used.member, None));
        }
        let interfaces = self.interfaces();
        for i in 0..self.members.len() {
            if self.members[i].full {
                continue;
            }
            match join_all(&self.members[i].socket, group, &interfaces) {
                Ok(joined) => {
                    self.record(group, i, joined);
                    return Ok((i, None));
                }
                Err(JoinError::Full) => self.members[i].full = true,
                Err(JoinError::Io(e)) => return Err(e),
            }
        }
        let socket = Arc::new(receive_socket(&self.cfg)?);
        let joined = match join_all(&socket, group, &interfaces) {
            Ok(joined) => joined,
            Err(JoinError::Full) => {
                return Err(io::Error::other("a new socket cannot join even one group"))
            }
            Err(JoinError::Io(e)) => return Err(e),
        };
        self.members.push(Member {
            socket: Arc::clone(&socket),
            memberships: 0,
            full: false,
        });
        let index = self.members.len() - 1;
        self.record(group, index, joined);
        tracing::debug!(sockets = self.members.len(), "opened a receive socket");
        Ok((index, Some(socket)))
    }

    /// The index of the socket that carries `group`, if it is joined.
    /// Sockets are numbered in the order they were opened, from 0, and
    /// keep their number until [`ReceivePool::close`].
    pub(crate) fn socket_of(&self, group: Ipv4Addr) -> Option<usize> {
        self.groups.get(&group).map(|used| used.member)
    }

    fn record(&mut self, group: Ipv4Addr, member: usize, interfaces: Vec<Ipv4Addr>) {
        self.members[member].memberships += interfaces.len();
        self.groups.insert(
            group,
            GroupUse {
                member,
                interfaces,
                users: 1,
            },
        );
    }

    /// Releases one channel's use of `group`; leaves it when no channel needs it.
    pub(crate) fn leave(&mut self, group: Ipv4Addr) {
        let Some(used) = self.groups.get_mut(&group) else {
            return;
        };
        used.users -= 1;
        if used.users > 0 {
            return;
        }
        let Some(used) = self.groups.remove(&group) else {
            return;
        };
        if let Some(m) = self.members.get_mut(used.member) {
            for iface in &used.interfaces {
                if let Err(e) = m.socket.leave_multicast_v4(group, *iface) {
                    tracing::debug!(%group, %iface, "leaving multicast group failed: {e}");
                }
            }
            m.memberships -= used.interfaces.len();
            m.full = false;
        }
    }

    /// Leaves every group and closes every socket (the receive tasks that
    /// hold them are aborted separately).
    pub(crate) fn close(&mut self) {
        self.members.clear();
        self.groups.clear();
    }
}

/// Joins `group` on every interface that accepts it; all or nothing with
/// respect to the membership limit. An interface other than loopback that
/// refuses (no default route, say) is skipped with a warning, as long as some
/// interface joined.
fn join_all(
    socket: &UdpSocket,
    group: Ipv4Addr,
    interfaces: &[Ipv4Addr],
) -> Result<Vec<Ipv4Addr>, JoinError> {
    let mut joined = Vec::with_capacity(interfaces.len());
    let mut last_error = None;
    for iface in interfaces {
        match socket.join_multicast_v4(group, *iface) {
            Ok(()) => joined.push(*iface),
            Err(e) if is_membership_limit(&e) => {
                for done in &joined {
                    let _ = socket.leave_multicast_v4(group, *done);
                }
                return Err(JoinError::Full);
            }
            Err(e) if !iface.is_loopback() => {
                warn_interface_once(*iface, &e);
                last_error = Some(e);
            }
            Err(e) => return Err(JoinError::Io(e)),
        }
    }
    match (joined.is_empty(), last_error) {
        (true, Some(e)) => Err(JoinError::Io(e)),
        _ => Ok(joined),
    }
}

fn warn_interface_once(iface: Ipv4Addr, e: &io::Error) {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        tracing::warn!(%iface, "cannot join multicast groups on this interface ({e}); receiving on loopback only");
    });
}

//! The node: configuration, lifecycle, and the shared state behind every handle.

use std::collections::HashSet;
use std::io::IoSlice;
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket as StdUdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use bytes::BytesMut;
use indexmap::IndexMap;
use pulicast_discovery::compat::{self, ChannelAnnouncement, Membership, Peer};
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;
use uuid::Uuid;

use crate::batching::Flusher;
use crate::channel::Namespace;
use crate::discovery::{self, DiscoveryOptions, DiscoveryState, Fleet, MemberView};
use crate::error::{Error, Result};
use crate::name::{group_for, resolve_path};
use crate::proto::fragment::{Landed, Limits, Loan};
use crate::proto::heartbeat::{self, Heard};
use crate::proto::receiver::{self, Expected, KeyUse, RawMessage, Subscriber};
use crate::proto::secure::Key;
use crate::proto::ChannelTx;
use crate::proto::Receiver;
use crate::queue::{Queue, QueuePolicy};
use crate::security::{Security, SecurityOptions};
use crate::stats::{Counters, Stats};
use crate::subscription::QueueSink;
use crate::transport::{self, NetConfig, ReceivePool};
use crate::wire::{zcm, DropReason, MAX_DATAGRAM};
use pulicast_discovery::wire::{ChannelInfo, MemberInfo, TypeInfo};

/// The Pulicast 2.x default port.
pub const DEFAULT_PORT: u16 = 8765;
/// The Pulicast 2.x default multicast TTL: 0 keeps traffic on this host.
pub const DEFAULT_TTL: u32 = 0;
/// The Pulicast 2.x default heartbeat period.
pub const DEFAULT_HEARTBEAT_PERIOD: Duration = Duration::from_millis(100);
/// Messages a subscription buffers before its queue policy drops one.
pub const DEFAULT_QUEUE_CAPACITY: usize = 1024;
/// The receive buffer a socket asks for by default: see
/// [`NodeBuilder::receive_buffer`].
pub const DEFAULT_RECEIVE_BUFFER: usize = 4 << 20;
/// How long a receive loop polls before parking by default: see
/// [`NodeBuilder::receive_spin`].
pub const DEFAULT_RECEIVE_SPIN: Duration = Duration::from_micros(50);
/// The longest receive spin allowed.
pub const MAX_RECEIVE_SPIN: Duration = Duration::from_millis(1);

/// Configures and starts a [`Node`]. Made by [`Node::new`].
///
/// ```no_run
/// # async fn run() -> pulicast::Result<()> {
/// use std::net::Ipv4Addr;
/// let node = pulicast::Node::new("rover_controller")
///     .namespace("rover1")
///     .interface(Ipv4Addr::LOCALHOST)
///     .start()
///     .await?;
/// # Ok(()) }
/// ```
#[derive(Debug, Clone)]
#[must_use = "a builder does nothing until started"]
pub struct NodeBuilder {
    name: String,
    namespace: String,
    port: u16,
    ttl: u32,
    interface: Option<Ipv4Addr>,
    heartbeat_period: Duration,
    queue_capacity: usize,
    queue_policy: QueuePolicy,
    discovery: DiscoveryOptions,
    compat_heartbeat: bool,
    receive_spin: Duration,
    receive_buffer: usize,
    reassembly: Limits,
    security: SecurityOptions,
}

impl NodeBuilder {
    /// The default namespace: relative channel names resolve against it
    /// (default: the root).
    pub fn namespace(mut self, namespace: impl Into<String>) -> Self {
        self.namespace = namespace.into();
        self
    }

    /// The UDP port all channels use (default 8765). Nodes only hear each other
    /// on the same port.
    pub fn port(mut self, port: u16) -> Self {
        self.port = port;
        self
    }

    /// Multicast TTL (default 0: traffic stays on this host; 1: the local link).
    pub fn ttl(mut self, ttl: u32) -> Self {
        self.ttl = ttl;
        self
    }

    /// Send and join groups on this interface (and join on loopback too).
    ///
    /// Without it, a node at TTL 0 sends on loopback and joins on loopback
    /// and on the routes' interface, so it hears and is heard by every node
    /// of this host: ours pinned to loopback or not, and Pulicast 2.x nodes
    /// with their defaults. At a TTL above 0 the routes choose where it sends.
    /// Pinned to loopback, a node hears every node of ours on the host but
    /// not 2.x nodes started with their defaults (they send on the network's
    /// interface); it says so once at start. See `docs/guide.md`,
    /// "Interfaces and TTL".
    pub fn interface(mut self, interface: Ipv4Addr) -> Self {
        self.interface = Some(interface);
        self
    }

    /// How often the node announces itself on `__nodes` (default 100 ms,
    /// allowed 10 ms ..= 10 s). Peers consider the node gone after three
    /// missed periods.
    pub fn heartbeat_period(mut self, period: Duration) -> Self {
        self.heartbeat_period = period;
        self
    }

    /// How many received messages each subscription buffers (default 1024)
    /// before its queue policy drops one.
    pub fn queue_capacity(mut self, capacity: usize) -> Self {
        self.queue_capacity = capacity;
        self
    }

    /// What a full subscription queue drops: the oldest message (the
    /// default: slow subscribers see the latest data) or the new one (they
    /// see a contiguous prefix). Either way the receive loop never waits and
    /// the drop is counted as [`crate::DropReason::QueueOverflow`].
    pub fn queue_policy(mut self, policy: QueuePolicy) -> Self {
        self.queue_policy = policy;
        self
    }

    /// Turns gossip discovery off (default: on). The node still sends and
    /// consumes Pulicast 2.x heartbeats, so it and 2.x tools still see the
    /// fleet, with less detail.
    pub fn discovery(mut self, enabled: bool) -> Self {
        self.discovery.enabled = enabled;
        self
    }

    /// The UDP port of the node's discovery socket (default: any free one).
    /// Give a node a fixed one to make it a seed other nodes can name.
    pub fn discovery_port(mut self, port: u16) -> Self {
        self.discovery.port = port;
        self
    }

    /// A seed peer: the discovery address (`host:port`) of a node reached by
    /// unicast, for links where multicast does not pass. The fleet's
    /// membership is learned through it. May be given several times.
    pub fn peer(mut self, address: SocketAddr) -> Self {
        if !self.discovery.seeds.contains(&address) {
            self.discovery.seeds.push(address);
        }
        self
    }

    /// Whether to send the Pulicast 2.x `__nodes` heartbeat (default: on, so
    /// 2.x tools see the node). Fleets without 2.x nodes can save its
    /// traffic; gossip discovery carries the same facts.
    pub fn compat_heartbeat(mut self, enabled: bool) -> Self {
        self.compat_heartbeat = enabled;
        self
    }

    /// How long a receive loop polls for the next datagram before it
    /// parks, while datagrams arrive closer together than this (default
    /// [`DEFAULT_RECEIVE_SPIN`], at most [`MAX_RECEIVE_SPIN`]; zero: never).
    ///
    /// Parking between datagrams costs every sender a wake-up of this node
    /// and costs the node an idle CPU's wake-up time (tens of µs). Polling
    /// briefly instead keeps a busy receiver ahead of a fast sender and cuts
    /// latency; a node whose traffic is further apart than this parks at
    /// once and spends nothing. Set zero where CPU time matters more than
    /// throughput and latency.
    pub fn receive_spin(mut self, spin: Duration) -> Self {
        self.receive_spin = spin;
        self
    }

    /// The kernel receive buffer each receive socket asks for, in bytes
    /// (default [`DEFAULT_RECEIVE_BUFFER`], at least 64 KiB, at most 1 GiB).
    ///
    /// It absorbs bursts while the node is busy elsewhere: a 16 MiB message
    /// is a burst of 280 datagrams. Linux grants at most
    /// `net.core.rmem_max` (often 208 KiB or 4 MiB: raise it with
    /// `sysctl -w net.core.rmem_max=...`); the node logs a warning once when
    /// it gets less than it asked for.
    pub fn receive_buffer(mut self, bytes: usize) -> Self {
        self.receive_buffer = bytes;
        self
    }

    /// Bounds the memory that messages still being reassembled from
    /// fragments may hold: per sender, per channel and in all, and how long
    /// after its first fragment a message is given up (defaults: 128 MiB,
    /// 128 MiB, 512 MiB, 2 s plus its size at 8 MiB/s). Each message is
    /// charged its size plus one datagram. When the total is full, the
    /// channel holding the most gives up messages for one holding less, so
    /// one channel's fragments never keep another's messages out. Messages
    /// that don't fit are dropped and counted as
    /// [`crate::DropReason::IncompleteMessage`]; a sender can't take more.
    ///
    /// ```
    /// use std::time::Duration;
    /// use pulicast::proto::fragment::Limits;
    /// let camera_node = pulicast::Node::new("viewer").reassembly_limits(Limits {
    ///     per_source: 64 << 20,
    ///     per_channel: 64 << 20,
    ///     total: 256 << 20,
    ///     timeout: Duration::from_millis(500),
    /// });
    /// # drop(camera_node);
    /// ```
    pub fn reassembly_limits(mut self, limits: Limits) -> Self {
        self.reassembly = limits;
        self
    }

    /// A pre-shared key for the channels in `namespace` (`/` for the root:
    /// every channel without a more specific key, discovery and `__nodes`
    /// included). Off by default.
    ///
    /// Datagrams on those channels are then sealed: they carry an
    /// authentication tag, and receivers drop what is unsealed, forged,
    /// replayed or stale (counted as [`crate::DropReason::Unauthenticated`],
    /// [`Forged`](crate::DropReason::Forged) and so on). Nodes without the key,
    /// Pulicast 2.x nodes among them, can't read or write those channels;
    /// other channels stay as they were. The channel with the most specific
    /// key uses it.
    ///
    /// A second key for the same namespace is accepted from others but
    /// not used to seal: that is how a fleet changes keys without a gap.
    /// Keys also come from the environment variable [`crate::KEYS_ENV`]
    /// (after the builder's ones). Keys are never logged. See
    /// `docs/security.md`.
    ///
    /// ```
    /// use std::net::Ipv4Addr;
    /// use pulicast::{Key, Node};
    /// # let port = pulicast::unused_port()?;
    /// let fleet_key = Key::from_hex(&"5e".repeat(32)).expect("64 hex digits");
    /// let node = Node::new("rover_controller")
    ///     .key("/", fleet_key)
    ///     .interface(Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// let mut cmds = node.channel("rover1/cmd").subscribe::<String>()?;
    /// node.channel("rover1/cmd").publish(&"stop".to_string())?; // sealed
    /// let m = cmds.recv_timeout(std::time::Duration::from_secs(5)).expect("our own message");
    /// assert_eq!(m.value, "stop");
    /// # Ok::<(), pulicast::Error>(())
    /// ```
    pub fn key(mut self, namespace: impl Into<String>, key: Key) -> Self {
        self.security.keys.push((namespace.into(), key));
        self
    }

    /// Whether sealed datagrams also hide their payload (default: off, they
    /// are authenticated but readable by anyone on the link). Also turned on
    /// by the environment variable [`crate::ENCRYPT_ENV`]. Receivers
    /// open both kinds either way.
    pub fn encrypt(mut self, encrypt: bool) -> Self {
        self.security.encrypt = encrypt;
        self
    }

    /// How far a sealed datagram's send time (by its sender's clock) may be
    /// from this node's clock (default [`crate::DEFAULT_SEALED_MAX_AGE`]).
    ///
    /// Replays are caught by sequence for senders the node remembers; this
    /// bound catches replays of old traffic to a node that forgot, or never
    /// knew, the sender (after a restart, say). It needs the fleet's clocks
    /// to agree to within it (NTP or PTP does). `None` turns the check off,
    /// for fleets without synchronized clocks, at the price of those
    /// replays.
    pub fn sealed_max_age(mut self, max_age: Option<Duration>) -> Self {
        self.security.max_age = max_age;
        self
    }

    /// Whether the node reads [`crate::KEYS_ENV`] and
    /// [`crate::ENCRYPT_ENV`] (default: yes), so keys can be deployed
    /// without code changes.
    pub fn keys_from_env(mut self, read: bool) -> Self {
        self.security.from_env = read;
        self
    }

    fn validate(&self) -> Result<String> {
        let invalid = |setting, reason: String| Err(Error::config(setting, reason));
        if self.port == 0 {
            return invalid("port", "0: all nodes must agree on one fixed port".into());
        }
        if self.ttl > 255 {
            return invalid("ttl", format!("{} is above 255", self.ttl));
        }
        if !(compat::PERIOD_RANGE.0..=compat::PERIOD_RANGE.1).contains(&self.heartbeat_period) {
            return invalid(
                "heartbeat period",
                format!(
                    "heartbeat period {:?} is outside {:?} ..= {:?}, the range peers accept",
                    self.heartbeat_period,
                    compat::PERIOD_RANGE.0,
                    compat::PERIOD_RANGE.1
                ),
            );
        }
        if self.queue_capacity == 0 {
            return invalid("queue capacity", "0".into());
        }
        if !(64 << 10..=1 << 30).contains(&self.receive_buffer) {
            return invalid(
                "receive buffer",
                format!("{} bytes is outside 64 KiB ..= 1 GiB", self.receive_buffer),
            );
        }
        let limits = self.reassembly;
        if limits.timeout.is_zero()
            || limits.per_source == 0
            || limits.per_channel == 0
            || limits.per_source > limits.total
            || limits.per_channel > limits.total
        {
            return invalid(
                "reassembly limits",
                format!("{limits:?}: need a timeout, and 0 < per source, per channel <= total"),
            );
        }
        if self.receive_spin > MAX_RECEIVE_SPIN {
            return invalid(
                "receive spin",
                format!("{:?} is above {MAX_RECEIVE_SPIN:?}", self.receive_spin),
            );
        }
        if self.name.len() > 1024 {
            return invalid("node name", "longer than 1024 bytes".into());
        }
        resolve_path(&self.namespace, "")
    }

    /// Opens the sockets and starts the node's tasks on the current tokio runtime.
    ///
    /// Fails if called outside a tokio runtime, on invalid options, or if the
    /// sockets can't be opened.
    pub async fn start(self) -> Result<Node> {
        let runtime = tokio::runtime::Handle::try_current().map_err(|_| {
            Error::config(
                "runtime",
                "Node::start needs a tokio runtime; use start_blocking() outside one",
            )
        })?;
        let namespace = self.validate()?;
        let security = Security::new(&self.security)?;
        let net = NetConfig {
            port: self.port,
            ttl: self.ttl,
            interface: self.interface,
            receive_buffer: self.receive_buffer,
        };
        let send = transport::send_socket(&net).map_err(Error::io("opening the send socket"))?;
        transport::warn_pinned_to_loopback(&net);
        let data_port = send
            .local_addr()
            .map_err(Error::io("reading the send socket's address"))?
            .port();
        let session = Uuid::new_v4();
        let start_time_ms = discovery::unix_ms();
        let host = discovery::host_name();
        let discovery_state = if self.discovery.enabled {
            let socket = transport::discovery_socket(&net, self.discovery.port)
                .map_err(Error::io("opening the discovery socket"))?;
            let info = MemberInfo {
                session: *session.as_bytes(),
                name: self.name.clone(),
                namespace: namespace.clone(),
                host: host.clone(),
                pid: std::process::id(),
                start_time_ms,
                data_port,
                channels: Vec::new(),
            };
            let port = socket
                .local_addr()
                .map_err(Error::io("reading the discovery socket's address"))?
                .port();
            // Multicast leaves from the interface's address; unicast may
            // take another route, or a NAT, so only multicast is bound to
            // an address.
            let multicast =
                SocketAddrV4::new(net.send_interface().unwrap_or(Ipv4Addr::UNSPECIFIED), port);
            let unbound = SocketAddrV4::new(Ipv4Addr::UNSPECIFIED, 0);
            let channel = discovery::DISCOVERY_CHANNEL;
            let sealers = security
                .as_ref()
                .and_then(|s| Some((s.sealer(channel, multicast)?, s.sealer(channel, unbound)?)));
            let state = DiscoveryState::new(
                socket,
                discovery::group(self.port),
                info,
                self.heartbeat_period,
                &self.discovery.seeds,
                sealers,
            )
            .map_err(Error::io("setting up discovery"))?;
            Some(state)
        } else {
            None
        };
        // Known for sure only when the node chose the interface; where the
        // routes choose, it is left open (and so unchecked by receivers).
        let origin = SocketAddrV4::new(
            net.send_interface().unwrap_or(Ipv4Addr::UNSPECIFIED),
            data_port,
        );
        let source_ip = net.source_ip();
        let discovery_sealed = security
            .as_ref()
            .is_some_and(|s| s.covers(discovery::DISCOVERY_CHANNEL));
        let mut own_ports = vec![data_port];
        own_ports.extend(discovery_state.as_ref().and_then(|d| d.local_port()));
        let receiver_config = receiver::Config {
            limits: self.reassembly,
            opener: security.as_ref().map(Security::opener),
            gossip: discovery_state.is_some(),
            gossip_sealed: discovery_sealed,
            own_ip: source_ip,
            own_ports,
        };
        let inner = Arc::new(Inner {
            name: self.name,
            session,
            compat_session_id: compat_session_id(&session),
            namespace: namespace.clone(),
            host,
            start_time_ms,
            data_port,
            heartbeat_period: self.heartbeat_period,
            queue_capacity: self.queue_capacity,
            queue_policy: self.queue_policy,
            receive_spin: self.receive_spin,
            compat_heartbeat: self.compat_heartbeat,
            port: self.port,
            fleet: Fleet::new(discovery_state),
            send,
            counters: Counters::new(),
            channels: Mutex::new(IndexMap::new()),
            receiver: Mutex::new(Receiver::new(receiver_config)),
            pool: Mutex::new(ReceivePool::new(net)),
            membership: Mutex::new(Membership::new(self.heartbeat_period)),
            stopped: AtomicBool::new(false),
            heartbeat_truncated: AtomicBool::new(false),
            send_failing: AtomicBool::new(false),
            stop_signal: tokio::sync::Notify::new(),
            runtime,
            tasks: Mutex::new(Vec::new()),
            next_subscriber: AtomicU64::new(0),
            flusher: Arc::default(),
            security,
            origin,
            source_ip,
            type_warnings: Mutex::new(HashSet::new()),
        });
        // From here on the node runs: a failure must stop what started.
        if let Err(e) = start_tasks(&inner) {
            inner.stop();
            return Err(e);
        }
        tracing::debug!(node = %inner.name, session = %inner.session, "node started");
        Ok(Node {
            namespace: Namespace::new(Arc::clone(&inner), namespace.into()),
            _lifetime: Arc::new(StopOnDrop(inner)),
        })
    }

    /// Starts the node on a runtime thread of its own, for programs without
    /// async code. Receive with [`crate::Subscription::recv_blocking`],
    /// [`crate::Subscription::recv_timeout`] or [`crate::Subscription::try_recv`].
    ///
    /// The thread ends when the node stops.
    ///
    /// ```
    /// use std::{net::Ipv4Addr, time::Duration};
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("robot_loop")
    ///     .interface(Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// let mut speeds = node.channel("speed").subscribe::<f64>()?;
    /// node.channel("speed").publish(&1.5)?;
    /// let m = speeds.recv_timeout(Duration::from_secs(5)).expect("our own message");
    /// assert_eq!((m.value, m.lead), (1.5, 1));
    /// # Ok::<(), pulicast::Error>(())
    /// ```
    pub fn start_blocking(self) -> Result<Node> {
        let (tx, rx) = std::sync::mpsc::channel();
        let thread_name = format!(
            "pulicast-{}",
            self.name.chars().take(16).collect::<String>()
        );
        std::thread::Builder::new()
            .name(thread_name)
            .spawn(move || {
                let runtime = match tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                {
                    Ok(rt) => rt,
                    Err(e) => {
                        let _ = tx.send(Err(Error::Io {
                            op: "creating the node's runtime",
                            source: e,
                        }));
                        return;
                    }
                };
                runtime.block_on(async move {
                    let started = self.start().await;
                    let inner = started.as_ref().ok().map(|n| Arc::clone(n.inner()));
                    if tx.send(started).is_err() {
                        return;
                    }
                    if let Some(inner) = inner {
                        inner.wait_stopped().await;
                    }
                });
            })
            .map_err(Error::io("spawning the node's runtime thread"))?;
        rx.recv().unwrap_or(Err(Error::NodeStopped))
    }
}

/// A pulicast node: one participant of the fleet, with its own session.
///
/// A node is also a [`Namespace`] (its default namespace), so channels are
/// reached directly from it: `node.channel("ctrl")`. Clones share the node; it
/// stops when [`Node::stop`] is called or the last clone is dropped.
///
/// ```no_run
/// # #[derive(serde::Serialize, serde::Deserialize, pulicast::Schema)] struct Twist { linear: f64, angular: f64 }
/// # #[derive(serde::Serialize, serde::Deserialize, pulicast::Schema)] struct Pose { x: f64 }
/// # async fn run() -> pulicast::Result<()> {
/// use pulicast::Node;
/// let node = Node::new("rover_controller").namespace("rover1").start().await?;
/// node.channel("ctrl").publish(&"Go LEFT!")?;                 // -> rover1/ctrl
/// let arm = node.ns("left_arm");                              // rover1/left_arm
/// arm.channel("ctrl").publish(&Twist { linear: 0.3, angular: 0.0 })?;
/// let peer = node.make_namespace("/rover2");                  // from the root
/// let mut poses = peer.channel("pose").subscribe::<Pose>()?;  // rover2/pose
/// while let Some(m) = poses.recv().await { /* m.value, m.source, m.lead */ }
/// # Ok(()) }
/// ```
#[derive(Clone)]
pub struct Node {
    namespace: Namespace,
    _lifetime: Arc<StopOnDrop>,
}

impl std::fmt::Debug for Node {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Node")
            .field("name", &self.inner().name)
            .field("session", &self.inner().session)
            .field("namespace", &self.namespace.path())
            .finish()
    }
}

impl Node {
    fn inner(&self) -> &Arc<Inner> {
        &self._lifetime.0
    }

    /// Starts configuring a node called `name`. Names are for people: they need
    /// not be unique, the session id tells nodes apart.
    #[allow(clippy::new_ret_no_self)]
    pub fn new(name: impl Into<String>) -> NodeBuilder {
        NodeBuilder {
            name: name.into(),
            namespace: String::new(),
            port: DEFAULT_PORT,
            ttl: DEFAULT_TTL,
            interface: None,
            heartbeat_period: DEFAULT_HEARTBEAT_PERIOD,
            queue_capacity: DEFAULT_QUEUE_CAPACITY,
            queue_policy: QueuePolicy::default(),
            discovery: DiscoveryOptions::default(),
            compat_heartbeat: true,
            receive_spin: DEFAULT_RECEIVE_SPIN,
            receive_buffer: DEFAULT_RECEIVE_BUFFER,
            reassembly: Limits::default(),
            security: SecurityOptions::default(),
        }
    }

    /// The node's name.
    pub fn name(&self) -> &str {
        &self.inner().name
    }

    /// The node's session: a random UUID, new every time a node starts.
    pub fn session_id(&self) -> Uuid {
        self.inner().session
    }

    /// The 64-bit session id that Pulicast 2.x heartbeats carry: the first eight
    /// bytes of [`Node::session_id`], big-endian.
    pub fn compat_session_id(&self) -> i64 {
        self.inner().compat_session_id
    }

    /// The live peers heard on `__nodes`, Pulicast 2.x nodes included, without
    /// this node itself. A peer is forgotten after three missed heartbeats.
    pub fn peers(&self) -> Vec<Peer> {
        self.inner().compat_peers()
    }

    /// The node's view of the fleet: members, their channels, and changes as
    /// they happen.
    pub fn discovery(&self) -> crate::Discovery {
        crate::Discovery {
            inner: Arc::clone(self.inner()),
        }
    }

    /// The node's counters: received, delivered, and dropped per reason.
    pub fn stats(&self) -> Stats {
        let inner = self.inner();
        let mut stats = inner.counters.snapshot();
        stats.receive_sockets = lock(&inner.pool).socket_count();
        let receiver = lock(&inner.receiver);
        let counts = receiver.counts();
        stats.datagrams_received = counts.datagrams;
        stats.messages_received = counts.messages;
        stats.out_of_order_skipped += counts.out_of_order_skipped;
        for (total, more) in stats.dropped.iter_mut().zip(counts.dropped) {
            *total += more;
        }
        stats
    }

    /// What the keys of each namespace this node has keys for met so far:
    /// datagrams that opened, sealed ones that did not (another key), and
    /// unsealed ones refused. Empty for a node without keys. A key whose
    /// `opened` stays 0 while the others grow is not the fleet's key.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")] async fn main() -> Result<(), Box<dyn std::error::Error>> {
    /// let key = pulicast::Key::from_hex(&"7a".repeat(32))?;
    /// let node = pulicast::Node::new("doc_keys")
    ///     .port(pulicast::unused_port()?)
    ///     .interface(std::net::Ipv4Addr::LOCALHOST)
    ///     .keys_from_env(false)
    ///     .key("rover1", key)
    ///     .start()
    ///     .await?;
    /// let uses = node.key_uses();
    /// assert_eq!((uses[0].namespace.as_str(), uses[0].opened), ("rover1", 0));
    /// # Ok(()) }
    /// ```
    pub fn key_uses(&self) -> Vec<KeyUse> {
        lock(&self.inner().receiver).key_uses()
    }

    /// Stops the node: its tasks end, its subscriptions close (their `recv`
    /// returns `None`) and publishing returns [`Error::NodeStopped`].
    pub fn stop(&self) {
        self.inner().stop();
    }

    /// Whether the node has stopped.
    pub fn is_stopped(&self) -> bool {
        self.inner().is_stopped()
    }
}

impl std::ops::Deref for Node {
    type Target = Namespace;

    fn deref(&self) -> &Namespace {
        &self.namespace
    }
}

/// Stops the node when the last [`Node`] clone goes away.
struct StopOnDrop(Arc<Inner>);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.stop();
    }
}

fn compat_session_id(session: &Uuid) -> i64 {
    let bytes = session.as_bytes();
    let mut first = [0; 8];
    first.copy_from_slice(&bytes[..8]);
    i64::from_be_bytes(first)
}

/// What the node knows about one channel it has touched.
pub(crate) struct ChannelState {
    pub name: Arc<str>,
    pub group: Ipv4Addr,
    pub destination: SocketAddrV4,
    /// `destination` as the socket layer takes it.
    address: socket2::SockAddr,
    /// Whether a key covers the channel.
    sealed: bool,
    /// The send side: prefixes, sequence numbers, pending batch, sealer.
    tx: Mutex<ChannelTx>,
    published: AtomicBool,
    pub subscribers: AtomicUsize,
    period: Mutex<PeriodMeter>,
    /// Fingerprint of the last typed use (0: none), checked without a lock
    /// on every publish; the description itself is behind the mutex.
    type_fingerprint: AtomicU64,
    message_type: Mutex<Option<TypeInfo>>,
    /// Whether the log already said why this channel does not batch.
    legacy_logged: AtomicBool,
}

impl ChannelState {
    /// The channel as announced in discovery, if this node uses it.
    fn info(&self) -> Option<ChannelInfo> {
        let publishes = self.published.load(Ordering::Relaxed);
        let subscribes = self.subscribers.load(Ordering::Relaxed) > 0;
        if !publishes && !subscribes {
            return None;
        }
        Some(ChannelInfo {
            name: self.name.to_string(),
            publishes,
            subscribes,
            period_ns: lock(&self.period).period_ns as u64,
            message_type: lock(&self.message_type).clone(),
        })
    }

    /// Records the type used on this channel; true if it changed.
    pub(crate) fn note_type(
        &self,
        fingerprint: [u8; 8],
        describe: impl FnOnce() -> TypeInfo,
    ) -> bool {
        let fp = u64::from_be_bytes(fingerprint);
        // A plain load on the hot path; the lock only when the type changes,
        // and fingerprint and description change together under it.
        if self.type_fingerprint.load(Ordering::Relaxed) == fp {
            return false;
        }
        let mut described = lock(&self.message_type);
        if self.type_fingerprint.load(Ordering::Relaxed) == fp {
            return false;
        }
        *described = Some(describe());
        self.type_fingerprint.store(fp, Ordering::Relaxed);
        true
    }
}

/// Smoothed interval between publications, announced in heartbeats.
#[derive(Default)]
struct PeriodMeter {
    last: Option<Instant>,
    period_ns: f64,
    announced_ns: f64,
}

impl PeriodMeter {
    /// Records a publication; true when the period moved enough (25 %) from
    /// the one last announced to be worth announcing again.
    fn record(&mut self, now: Instant) -> bool {
        if let Some(last) = self.last {
            let sample = now.duration_since(last).as_nanos() as f64;
            // An exponential average follows rate changes within ~10 messages.
            self.period_ns = if self.period_ns == 0.0 {
                sample
            } else {
                0.9 * self.period_ns + 0.1 * sample
            };
        }
        self.last = Some(now);
        let moved = (self.period_ns - self.announced_ns).abs() > 0.25 * self.announced_ns.max(1.0);
        if moved && self.period_ns > 0.0 {
            self.announced_ns = self.period_ns;
            return true;
        }
        false
    }
}

/// State shared by a node's handles and tasks.
pub(crate) struct Inner {
    pub name: String,
    pub session: Uuid,
    /// The 2.x session id: the first 8 bytes of `session` (see
    /// [`Node::compat_session_id`]).
    pub compat_session_id: i64,
    namespace: String,
    host: String,
    start_time_ms: u64,
    data_port: u16,
    pub heartbeat_period: Duration,
    pub queue_capacity: usize,
    queue_policy: QueuePolicy,
    receive_spin: Duration,
    compat_heartbeat: bool,
    port: u16,
    pub fleet: Fleet,
    send: StdUdpSocket,
    pub counters: Counters,
    /// In creation order, which is the order heartbeats list them in.
    channels: Mutex<IndexMap<Arc<str>, Arc<ChannelState>>>,
    /// The receive path: dispatch, leads, reassembly and opening.
    receiver: Mutex<Receiver<QueueSink>>,
    pool: Mutex<ReceivePool>,
    membership: Mutex<Membership>,
    stopped: AtomicBool,
    heartbeat_truncated: AtomicBool,
    /// Whether the last send failed (see `note_send`).
    send_failing: AtomicBool,
    stop_signal: tokio::sync::Notify,
    runtime: tokio::runtime::Handle,
    tasks: Mutex<Vec<JoinHandle<()>>>,
    next_subscriber: AtomicU64,
    flusher: Arc<Flusher>,
    /// The node's keys, if it has any.
    security: Option<Security>,
    /// Where data leaves from, as far as the node knows: sealed datagrams
    /// carry it, so receivers refuse them relayed from elsewhere.
    origin: SocketAddrV4,
    /// The address other nodes see this node's datagrams come from, as
    /// well as it is known: what its own view of itself shows.
    source_ip: Ipv4Addr,
    /// (channel, announced type) disagreements already warned about.
    type_warnings: Mutex<HashSet<(String, [u8; 8])>>,
}

/// Most type disagreements a node remembers having warned about; past it
/// the memory starts over (and may say one again). Anyone can announce
/// types: the bound keeps the set small, [`TYPE_WARNINGS_PER_CHECK`] the log.
const MAX_TYPE_WARNINGS: usize = 1024;
/// Most type warnings one check (one a second) logs.
const TYPE_WARNINGS_PER_CHECK: usize = 4;

/// The wall clock in ms for a channel's sealer; 0, unread, without one.
fn wall_clock_for(tx: &ChannelTx) -> u64 {
    match tx.is_sealed() {
        true => discovery::unix_ms(),
        false => 0,
    }
}

/// Locks a mutex, recovering the data if a panicking thread poisoned it: every
/// critical section leaves the maps consistent, so the data stays usable.
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Inner {
    pub(crate) fn is_stopped(&self) -> bool {
        self.stopped.load(Ordering::Acquire)
    }

    fn membership(&self) -> MutexGuard<'_, Membership> {
        lock(&self.membership)
    }

    fn add_task(&self, task: JoinHandle<()>) {
        let mut tasks = lock(&self.tasks);
        if self.is_stopped() {
            task.abort();
        } else {
            tasks.push(task);
        }
    }

    async fn wait_stopped(&self) {
        if !self.is_stopped() {
            self.stop_signal.notified().await;
        }
    }

    pub(crate) fn stop(&self) {
        if self.stopped.swap(true, Ordering::AcqRel) {
            return;
        }
        self.fleet.leave();
        // What was published before the stop still goes out.
        self.flusher.stop();
        for channel in self.flusher.channels() {
            let _ = self.flush_batch(&channel, None);
        }
        for task in lock(&self.tasks).drain(..) {
            task.abort();
        }
        // Dropping the senders closes every subscription.
        lock(&self.receiver).clear();
        lock(&self.pool).close();
        self.stop_signal.notify_one();
        tracing::debug!(node = %self.name, "node stopped");
    }

    /// The state of a resolved channel, created on first use.
    pub(crate) fn channel_state(&self, name: &str) -> Arc<ChannelState> {
        let mut channels = lock(&self.channels);
        if let Some(state) = channels.get(name) {
            return Arc::clone(state);
        }
        let name: Arc<str> = name.into();
        let group = group_for(&name);
        let sealer = self
            .security
            .as_ref()
            .and_then(|s| s.sealer(&name, self.origin));
        let state = Arc::new(ChannelState {
            name: Arc::clone(&name),
            group,
            destination: SocketAddrV4::new(group, self.port),
            address: SocketAddrV4::new(group, self.port).into(),
            sealed: sealer.is_some(),
            tx: Mutex::new(ChannelTx::new(Arc::clone(&name), sealer)),
            published: AtomicBool::new(false),
            subscribers: AtomicUsize::new(0),
            period: Mutex::new(PeriodMeter::default()),
            type_fingerprint: AtomicU64::new(0),
            message_type: Mutex::new(None),
            legacy_logged: AtomicBool::new(false),
        });
        channels.insert(name, Arc::clone(&state));
        state
    }

    /// Sends one message whose payload `encode` appends to the buffer it gets.
    pub(crate) fn publish_with(
        &self,
        channel: &ChannelState,
        encode: impl FnOnce(&mut Vec<u8>) -> Result<()>,
    ) -> Result<()> {
        thread_local! {
            static BUFFER: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        BUFFER.with(|buffer| {
            // A fresh Vec if the buffer is somehow in use (a publish from inside
            // a Serialize impl); the common path reuses one allocation.
            let mut fallback = Vec::new();
            let mut guard = buffer.try_borrow_mut();
            let buf = match guard.as_deref_mut() {
                Ok(buf) => buf,
                Err(_) => &mut fallback,
            };
            buf.clear();
            encode(buf)?;
            let sent = self.publish_payload(channel, buf);
            // Keep the buffer, but not a giant one.
            if buf.capacity() > 1 << 20 {
                buf.clear();
                buf.shrink_to(1 << 20);
            }
            sent
        })
    }

    /// Publishes an encoded payload: batched, as one datagram, or as
    /// fragments (see [`ChannelTx::publish`]). The payload is never copied
    /// on its way to the kernel unless it joins a batch or is sealed.
    pub(crate) fn publish_payload(&self, channel: &ChannelState, payload: &[u8]) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let now = Instant::now();
        let mut tx = lock(&channel.tx);
        let unix_ms = wall_clock_for(&tx);
        let sent = tx.publish(now, unix_ms, payload, &mut |parts| {
            self.transmit(channel, parts)
        });
        drop(tx);
        self.note_send(&sent);
        if let Some(deadline) = sent? {
            self.flusher.schedule(deadline);
        }
        if !channel.published.swap(true, Ordering::Relaxed) {
            self.announce_change();
        }
        if lock(&channel.period).record(now) {
            self.announce_change();
        }
        self.counters.messages_sent.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }

    /// Sends one datagram of `channel`, given in parts: gathered by the
    /// kernel, without joining them first.
    fn transmit(&self, channel: &ChannelState, parts: &[&[u8]]) -> std::io::Result<()> {
        match parts {
            [one] => self.send.send_to(one, channel.destination).map(drop),
            [a, b, c] => {
                let parts = [IoSlice::new(a), IoSlice::new(b), IoSlice::new(c)];
                let socket = socket2::SockRef::from(&self.send);
                socket.send_to_vectored(&parts, &channel.address).map(drop)
            }
            more => self
                .send
                .send_to(&more.concat(), channel.destination)
                .map(drop),
        }
    }

    /// Logs once when sending starts failing (an interface went down, the
    /// route is gone) and once when it works again, however many sends fail
    /// in between: the errors themselves go to the callers.
    fn note_send<T>(&self, sent: &Result<T>) {
        match sent {
            Ok(_) => {
                if self.send_failing.load(Ordering::Relaxed)
                    && self.send_failing.swap(false, Ordering::Relaxed)
                {
                    tracing::info!(node = %self.name, "sending works again");
                }
            }
            Err(e @ Error::Io { .. }) => {
                if !self.send_failing.swap(true, Ordering::Relaxed) {
                    tracing::warn!(node = %self.name, "sending fails, will keep trying: {e}");
                }
            }
            // Not a send that failed (a payload too large, say).
            Err(_) => {}
        }
    }

    /// Sends the channel's pending batch if it is due at `now` (`None`:
    /// whatever its deadline); returns the deadline of one still pending.
    pub(crate) fn flush_batch(
        &self,
        channel: &ChannelState,
        now: Option<Instant>,
    ) -> Result<Option<Instant>> {
        let mut tx = lock(&channel.tx);
        let unix_ms = wall_clock_for(&tx);
        let mut send = |parts: &[&[u8]]| self.transmit(channel, parts);
        // Not noted in `note_send`: the flusher logs its own failures, and
        // a flush with nothing pending says nothing about sending.
        let sent = match now {
            Some(now) => tx.handle_timeout(now, unix_ms, &mut send),
            None => tx.flush(unix_ms, &mut send),
        };
        sent.map(|()| tx.poll_timeout())
    }

    /// Turns batching on for `channel` (`Some(delay)`) or off (`None`,
    /// sending what is pending).
    pub(crate) fn set_batching(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
        max_delay: Option<Duration>,
    ) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        if let Some(delay) = max_delay {
            ChannelTx::check_batching_delay(delay)?;
            // Which 2.x nodes subscribe is known before the first message
            // may join a batch.
            self.flusher.register(Arc::downgrade(self), channel);
            self.update_batching_eligibility();
        }
        let mut tx = lock(&channel.tx);
        let unix_ms = wall_clock_for(&tx);
        let deadline = tx.set_batching(max_delay, unix_ms, &mut |parts| {
            self.transmit(channel, parts)
        })?;
        drop(tx);
        // A shorter delay may make a pending batch due sooner.
        if let Some(deadline) = deadline {
            self.flusher.schedule(deadline);
        }
        Ok(())
    }

    /// Sends the channel's pending batch now.
    pub(crate) fn flush(&self, channel: &ChannelState) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        self.flush_batch(channel, None).map(drop)
    }

    /// Marks the batching channels that a Pulicast 2.x node subscribes, which
    /// can't read batches, so they are published one message per datagram.
    ///
    /// A heartbeat peer that is not a gossip member counts as 2.x. A node of
    /// ours whose heartbeat arrives before its gossip does looks like one for
    /// a moment too; batching pauses then, but the log only speaks of peers
    /// that stayed 2.x-only past the grace period.
    fn update_batching_eligibility(&self) {
        if !self.flusher.is_used() {
            return;
        }
        let gossip = self.fleet.gossip_keys();
        let legacy: Vec<Peer> = self
            .compat_peers()
            .into_iter()
            .filter(|peer| !gossip.contains(&peer.session_id))
            .collect();
        let now = Instant::now();
        for channel in self.flusher.channels() {
            let subscriber = |settled: bool| {
                legacy.iter().find(|peer| {
                    (!settled || self.fleet.is_settled(now, peer))
                        && peer
                            .channels
                            .iter()
                            .any(|c| c.is_subscribed && c.name == *channel.name)
                })
            };
            let blocked = subscriber(false).is_some();
            let batching = {
                let mut tx = lock(&channel.tx);
                tx.set_legacy_subscriber(blocked);
                tx.is_batching()
            };
            if let Some(peer) = subscriber(true) {
                if batching && !channel.legacy_logged.swap(true, Ordering::Relaxed) {
                    tracing::warn!(
                        channel = %channel.name,
                        peer = %peer.name,
                        "not batching: a Pulicast 2.x node subscribes this channel and can't read batches"
                    );
                }
            }
        }
    }

    /// Registers a subscriber on `channel`, joining its group if needed.
    pub(crate) fn subscribe(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
    ) -> Result<(u64, Arc<Queue<RawMessage>>)> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let id = self.next_subscriber.fetch_add(1, Ordering::Relaxed);
        let queue = Arc::new(Queue::new(self.queue_capacity, self.queue_policy));
        let subscriber = Subscriber {
            id,
            ordered,
            expected,
            sink: QueueSink(Arc::clone(&queue)),
        };
        let mut receiver = lock(&self.receiver);
        // stop() sets the flag before it clears the table under this lock, so
        // checking again here means no subscription outlives a stop.
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        if !receiver.subscribes(&channel.name) {
            let opened = lock(&self.pool)
                .join(channel.group)
                .map_err(Error::bind("joining a multicast group", self.port))?;
            if let Some(socket) = opened {
                let task = self.runtime.spawn(receive_loop(Arc::clone(self), socket));
                self.add_task(task);
            }
        }
        let _first = receiver.subscribe(&channel.name, channel.sealed, subscriber);
        if channel.subscribers.fetch_add(1, Ordering::Relaxed) == 0 {
            self.announce_change();
        }
        Ok((id, queue))
    }

    /// Removes a subscriber; leaves the group when its channel has none left.
    pub(crate) fn unsubscribe(&self, channel: &ChannelState, id: u64) {
        let mut receiver = lock(&self.receiver);
        let Some(removed) = receiver.unsubscribe(&channel.name, id) else {
            return;
        };
        if channel.subscribers.fetch_sub(1, Ordering::Relaxed) == 1 {
            self.announce_change();
        }
        if removed.last {
            lock(&self.pool).leave(channel.group);
        }
    }

    /// Runs `f` on the receiver, then hands on what it gave out, after
    /// unlocking it: gossip to discovery, drops to the log (so a log layer
    /// may call `Node::stats`).
    fn with_receiver<R>(&self, f: impl FnOnce(&mut Receiver<QueueSink>) -> R) -> R {
        let mut receiver = lock(&self.receiver);
        let result = f(&mut receiver);
        // One datagram gives at most one gossip datagram; drops are rare
        // but come in bursts (a batch of the wrong type): no allocation
        // unless there are any.
        let gossip = receiver.poll_gossip();
        let drops: Vec<_> = std::iter::from_fn(|| receiver.poll_drop()).collect();
        let more_gossip: Vec<_> = std::iter::from_fn(|| receiver.poll_gossip()).collect();
        drop(receiver);
        for (source, datagram) in gossip.into_iter().chain(more_gossip) {
            self.fleet.inbound(source, &datagram);
        }
        for dropped in &drops {
            self.counters.log.log(dropped);
        }
        result
    }

    /// Handles a datagram read from a receive socket (see
    /// [`Receiver::handle_datagram`]); also returns the messages received
    /// so far, which the receive loop paces itself by.
    fn handle_datagram(&self, buf: &mut BytesMut, source: SocketAddr) -> (Option<Loan>, u64) {
        let (now, unix_ms) = (Instant::now(), discovery::unix_ms());
        self.with_receiver(|rx| {
            let loan = rx.handle_datagram(now, unix_ms, source, buf);
            (loan, rx.counts().messages)
        })
    }

    /// Takes back a loan (see [`Receiver::repay`]).
    fn repay(&self, loan: Loan, received: bool) -> Option<Loan> {
        self.with_receiver(|rx| rx.repay(loan, received))
    }

    /// Opens a discovery datagram received by unicast, where it lies, and
    /// returns where the gossip in it is (see [`Receiver::open_gossip`]).
    pub(crate) fn unseal_discovery(
        &self,
        datagram: &mut [u8],
        source: SocketAddr,
    ) -> Option<std::ops::Range<usize>> {
        let unix_ms = discovery::unix_ms();
        self.with_receiver(|rx| rx.open_gossip(unix_ms, source, datagram))
    }

    /// Gives up on fragmented messages that stopped arriving, when due.
    fn expire_fragments(&self) {
        let now = Instant::now();
        self.with_receiver(|rx| {
            if rx.poll_timeout().is_some_and(|due| now > due) {
                rx.handle_timeout(now);
            }
        });
    }

    /// Sends the 2.x heartbeat: every channel this node uses that fits one
    /// datagram (see [`heartbeat::announce`]).
    fn send_heartbeat(&self, nodes: &ChannelState) {
        let announcement = {
            let mut table = lock(&self.channels);
            // Forget channels nobody holds, publishes or subscribes, so names
            // made on the fly cost nothing lasting. Published ones stay: their
            // sequence numbers must continue if the channel is made again.
            table.retain(|_, state| {
                Arc::strong_count(state) > 1
                    || state.published.load(Ordering::Relaxed)
                    || state.subscribers.load(Ordering::Relaxed) > 0
            });
            let channels = table.values().map(|state| ChannelAnnouncement {
                name: state.name.to_string(),
                period_ns: lock(&state.period).period_ns as i64,
                is_published: state.published.load(Ordering::Relaxed),
                is_subscribed: state.subscribers.load(Ordering::Relaxed) > 0,
            });
            heartbeat::announce(
                &self.name,
                self.compat_session_id,
                self.heartbeat_period,
                nodes.subscribers.load(Ordering::Relaxed) > 0,
                channels,
            )
        };
        let left_out = announcement.left_out;
        if left_out > 0 && !self.heartbeat_truncated.swap(true, Ordering::Relaxed) {
            tracing::warn!(
                left_out,
                "more channels than one heartbeat datagram holds; announcing those that fit"
            );
        }
        let sent = self.publish_with(nodes, |buf| {
            zcm::encode_heartbeat(&announcement.heartbeat, buf);
            Ok(())
        });
        if let Err(e) = sent {
            if !self.is_stopped() {
                tracing::debug!("heartbeat not sent: {e}");
            }
        }
    }

    /// Feeds a message heard on `__nodes` to the 2.x table.
    fn handle_heartbeat(&self, message: RawMessage) {
        match heartbeat::hear(self.compat_session_id, &message) {
            Ok(Heard::Peer(heartbeat)) => {
                self.membership()
                    .handle_heartbeat(Instant::now(), message.source, heartbeat);
                self.log_membership_events();
            }
            Ok(Heard::Late) => {
                self.counters
                    .out_of_order_skipped
                    .fetch_add(1, Ordering::Relaxed);
            }
            Ok(Heard::Own) => {}
            Err(e) => {
                let channel = Some(compat::NODES_CHANNEL);
                self.counters.drop_decode(&e, channel, message.source);
            }
        }
    }

    fn log_membership_events(&self) {
        let mut expired = Vec::new();
        let mut suspicious = Vec::new();
        let mut membership = self.membership();
        while let Some(event) = membership.poll_event() {
            match event {
                compat::Event::Joined {
                    name,
                    session_id,
                    address,
                } => {
                    tracing::debug!(peer = %name, session_id, %address, "peer joined");
                }
                compat::Event::Expired { name, session_id } => {
                    tracing::debug!(peer = %name, session_id, "peer missed its heartbeats");
                    expired.push((session_id, name));
                }
                compat::Event::Suspicious { session_id, what } => {
                    tracing::warn!(session_id, "peer session changed: {what}");
                    suspicious.push((session_id, what));
                }
                compat::Event::Evicted {
                    session_id,
                    name,
                    bytes,
                } => {
                    tracing::warn!(
                        peer = %name,
                        session_id,
                        bytes,
                        "2.x peer table full in bytes; dropped a larger peer to make room"
                    );
                    expired.push((session_id, name));
                }
                compat::Event::Rejected { session_id }
                    if self
                        .counters
                        .count_drop(DropReason::MalformedPayload)
                        .is_some() =>
                {
                    tracing::warn!(session_id, "peer table full; ignoring a new session");
                }
                _ => {}
            }
        }
        drop(membership);
        for (key, what) in suspicious {
            self.fleet
                .compat_suspicious(key, format!("2.x heartbeat: {what}"));
        }
        self.announce_settled_compat(&expired);
    }

    /// Tells discovery about 2.x peers that settled or expired. Called for
    /// every heartbeat received, so it costs time in the number of peers,
    /// never in their channels: only peers announced for the first time are
    /// copied. (Copying every peer's channel list for every heartbeat made a
    /// flood of large fake heartbeats cost time quadratic in their size.)
    fn announce_settled_compat(&self, expired: &[(i64, String)]) {
        let now = Instant::now();
        let settled: Vec<i64> = self
            .membership()
            .peers()
            .filter(|p| p.session_id != self.compat_session_id && self.fleet.is_settled(now, p))
            .map(|p| p.session_id)
            .collect();
        let new = self.fleet.unannounced_compat(&settled);
        if new.is_empty() && expired.is_empty() {
            return;
        }
        let peers: Vec<Peer> = {
            let membership = self.membership();
            new.iter()
                .filter_map(|id| membership.peer(*id).cloned())
                .collect()
        };
        self.fleet.update_compat(now, &peers, expired);
    }

    /// The 2.x heartbeat table's peers, without this node.
    pub(crate) fn compat_peers(&self) -> Vec<Peer> {
        self.membership()
            .peers()
            .filter(|p| p.session_id != self.compat_session_id)
            .cloned()
            .collect()
    }

    /// The fleet without this node: gossip members and 2.x-only peers.
    pub(crate) fn fleet_members(&self) -> Vec<MemberView> {
        self.fleet.members(&self.compat_peers())
    }

    /// Warns, once per channel and type, about members that publish another
    /// type on a channel than this node subscribes to it as: every message they send
    /// there is dropped (as [`DropReason::WrongType`]), and without this the
    /// subscriber would only see nothing arrive. Both types are named, from
    /// what discovery announces.
    fn warn_type_mismatches(&self) {
        let ours: Vec<(Arc<str>, TypeInfo)> = lock(&self.channels)
            .values()
            .filter(|c| c.subscribers.load(Ordering::Relaxed) > 0)
            .filter_map(|c| Some((Arc::clone(&c.name), lock(&c.message_type).clone()?)))
            .collect();
        if ours.is_empty() {
            return;
        }
        let mut said = 0;
        for member in self.fleet_members() {
            if member.session == Some(self.session) || !member.is_live() {
                continue;
            }
            for channel in member.channels.iter().filter(|c| c.publishes) {
                let Some(theirs) = &channel.message_type else {
                    continue;
                };
                let Some((name, mine)) = ours.iter().find(|(n, _)| **n == *channel.name) else {
                    continue;
                };
                if theirs.fingerprint == mine.fingerprint {
                    continue;
                }
                if said >= TYPE_WARNINGS_PER_CHECK {
                    return;
                }
                let mut warned = lock(&self.type_warnings);
                if warned.len() >= MAX_TYPE_WARNINGS {
                    warned.clear();
                }
                if !warned.insert((name.to_string(), theirs.fingerprint)) {
                    continue;
                }
                said += 1;
                tracing::warn!(
                    channel = %name,
                    member = %member.name,
                    "this node subscribes to {name} as {}, but {} publishes {} there: \
                     its messages are dropped (counted as wrong_type)",
                    mine.name,
                    member.name,
                    theirs.name
                );
            }
        }
    }

    /// This node's announcement: its identity and its channels.
    pub(crate) fn local_info(&self) -> MemberInfo {
        let channels = lock(&self.channels)
            .values()
            .filter(|c| c.name.as_ref() != compat::NODES_CHANNEL)
            .filter_map(|c| c.info())
            .collect();
        MemberInfo {
            session: *self.session.as_bytes(),
            name: self.name.clone(),
            namespace: self.namespace.clone(),
            host: self.host.clone(),
            pid: std::process::id(),
            start_time_ms: self.start_time_ms,
            data_port: self.data_port,
            channels,
        }
    }

    /// This node as others see it.
    pub(crate) fn local_view(&self) -> MemberView {
        let info = self.local_info();
        // The discovery socket is bound to every address; others see it
        // at the one its datagrams leave from.
        let port = self.fleet.local_address().map_or(0, |a| a.port());
        let address = SocketAddr::from((self.source_ip, port));
        MemberView {
            key: self.compat_session_id,
            session: Some(self.session),
            name: info.name,
            namespace: info.namespace,
            host: info.host,
            address,
            data_address: Some(SocketAddr::new(address.ip(), self.data_port)),
            start_time: Some(std::time::UNIX_EPOCH + Duration::from_millis(self.start_time_ms)),
            incarnation: 0,
            state: pulicast_discovery::wire::MemberState::Alive,
            channels: info.channels,
            compat: false,
            contested_by: None,
        }
    }

    /// Tells discovery that our announcement changed.
    pub(crate) fn announce_change(&self) {
        if let Some(d) = &self.fleet.discovery {
            d.changed.notify_one();
        }
    }
}

/// Subscribes the heartbeat channel, joins the discovery group and spawns the
/// node's tasks.
fn start_tasks(inner: &Arc<Inner>) -> Result<()> {
    // The node's own subscriber of `__nodes`, not a user's `Subscription`:
    // it lives as long as the node.
    let nodes = inner.channel_state(compat::NODES_CHANNEL);
    let (id, heartbeats) = inner.subscribe(&nodes, false, None)?;
    let heartbeats = OwnSubscriber {
        inner: Arc::clone(inner),
        channel: Arc::clone(&nodes),
        id,
        queue: heartbeats,
    };
    let task = inner
        .runtime
        .spawn(heartbeat_loop(Arc::clone(inner), nodes, heartbeats));
    inner.add_task(task);
    if inner.fleet.discovery.is_some() {
        let group = discovery::group(inner.port);
        let opened = lock(&inner.pool)
            .join(*group.ip())
            .map_err(Error::bind("joining the discovery group", inner.port))?;
        if let Some(socket) = opened {
            let task = inner.runtime.spawn(receive_loop(Arc::clone(inner), socket));
            inner.add_task(task);
        }
        let task = inner
            .runtime
            .spawn(discovery::discovery_loop(Arc::clone(inner)));
        inner.add_task(task);
    }
    Ok(())
}

/// A subscriber of the node's own (`__nodes`), removed when its task ends
/// however it ends, so its queue never fills unread.
struct OwnSubscriber {
    inner: Arc<Inner>,
    channel: Arc<ChannelState>,
    id: u64,
    queue: Arc<Queue<RawMessage>>,
}

impl Drop for OwnSubscriber {
    fn drop(&mut self) {
        self.inner.unsubscribe(&self.channel, self.id);
    }
}

/// Messages a receive loop delivers before it lets other tasks run.
const YIELD_EVERY: u64 = 256;
/// Bytes a receive loop takes in before it lets other tasks run: a fraction
/// of the receive buffers kept for reuse.
const YIELD_BYTES: usize = ReceiveBuffers::SIZE / 2;

/// Reads datagrams from one receive socket until the node stops.
async fn receive_loop(inner: Arc<Inner>, socket: Arc<UdpSocket>) {
    let mut buffers = ReceiveBuffers::default();
    let mut delivered = 0;
    let mut bytes = 0;
    let mut spin = Spin::new(inner.receive_spin);
    let mut loan: Option<Loan> = None;
    loop {
        let (received, len, messages) = match loan.take() {
            Some(l) => {
                let (next, len) = receive_into(&inner, &socket, l, &mut spin, &mut buffers).await;
                let messages = match next {
                    AfterLoan::Loan(l) => {
                        loan = Some(l);
                        None
                    }
                    AfterLoan::Other(source) => {
                        let (next, messages) = inner.handle_datagram(&mut buffers.current, source);
                        loan = next;
                        Some(messages)
                    }
                    AfterLoan::Nothing => None,
                };
                (len.is_some(), len.unwrap_or(0), messages)
            }
            None => {
                let buf = buffers.next();
                match receive(&socket, buf, &mut spin).await {
                    Ok((len, source)) => {
                        let (next, messages) = inner.handle_datagram(buf, source);
                        loan = next;
                        (true, len, Some(messages))
                    }
                    Err(e) => {
                        // Errors here are transient (e.g. an interface going
                        // away); back off a little so a persistent one can't
                        // spin the CPU.
                        tracing::debug!("receive failed: {e}");
                        tokio::time::sleep(Duration::from_millis(10)).await;
                        (false, 0, None)
                    }
                }
            }
        };
        if !received {
            continue;
        }
        // On a single-threaded runtime the subscribers only run when this
        // loop yields. tokio's budget makes it yield every 128 datagrams,
        // which is too rare twice over: a batch delivers hundreds of
        // messages per datagram, more than a queue may hold, and 128 large
        // datagrams pin more receive buffers than are kept for reuse (so
        // fresh ones, with their page faults, would be needed). So yield by
        // messages and by bytes as well.
        bytes += len;
        let messages = messages.unwrap_or(delivered);
        if messages.wrapping_sub(delivered) >= YIELD_EVERY || bytes >= YIELD_BYTES {
            delivered = messages;
            bytes = 0;
            tokio::task::yield_now().await;
        } else {
            tokio::task::consume_budget().await;
        }
    }
}

/// Receives one datagram into `buf`, polling briefly before parking.
async fn receive(
    socket: &UdpSocket,
    buf: &mut BytesMut,
    spin: &mut Spin,
) -> std::io::Result<(usize, SocketAddr)> {
    let received = loop {
        match socket.try_recv_buf_from(buf) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if !spin.wait(socket).await {
                    break socket.recv_buf_from(buf).await;
                }
            }
            other => break other,
        }
    };
    spin.arrived();
    received
}

/// What [`receive_into`] leaves to do.
enum AfterLoan {
    /// The fragment came; here is the loan for the one after.
    Loan(Loan),
    /// Another datagram came, now in the current receive buffer: handle it
    /// the ordinary way.
    Other(SocketAddr),
    /// Nothing (the message completed, or receiving failed).
    Nothing,
}

/// Receives the next datagram straight into a lent message buffer. If it is
/// the fragment the loan waits for, its chunk lands in place and no copy is
/// made; anything else is copied out (see [`Loan::land`]). Returns what to
/// do next and the datagram's length.
async fn receive_into(
    inner: &Inner,
    socket: &UdpSocket,
    mut loan: Loan,
    spin: &mut Spin,
    buffers: &mut ReceiveBuffers,
) -> (AfterLoan, Option<usize>) {
    let Some(landing) = loan.prepare() else {
        // Too little before the chunk to hold the header: receive normally.
        let _none = inner.repay(loan, false);
        return (AfterLoan::Nothing, None);
    };
    let received = receive(socket, &mut loan.data, spin).await;
    if let Err(e) = &received {
        tracing::debug!("receive failed: {e}");
    }
    let received = received.ok();
    match loan.land(landing, received, buffers.next()) {
        Landed::Awaited => {
            let todo = match inner.repay(loan, true) {
                Some(next) => AfterLoan::Loan(next),
                None => AfterLoan::Nothing,
            };
            (todo, received.map(|(n, _)| n))
        }
        Landed::Other { source, len } => {
            let _none = inner.repay(loan, false);
            (AfterLoan::Other(source), Some(len))
        }
        Landed::Nothing => {
            let _none = inner.repay(loan, false);
            (AfterLoan::Nothing, None)
        }
    }
}

/// Adaptive busy-polling of a receive socket.
///
/// A receiver that parks between datagrams makes every sender pay for
/// waking it (on loopback, inside its `sendto`), and pays an idle CPU's
/// wake-up time itself (15-30 µs on these machines). When datagrams come
/// closer together than the spin time, the loop polls a little before it
/// parks: the next datagram is then picked up without a wake-up. When they
/// come further apart, it parks at once, so a quiet node burns no CPU.
struct Spin {
    limit: Duration,
    /// When the last datagram arrived.
    last: Instant,
    /// The gap before it.
    gap: Duration,
}

impl Spin {
    fn new(limit: Duration) -> Self {
        Self {
            limit,
            last: Instant::now(),
            gap: Duration::MAX,
        }
    }

    /// Notes an arrival.
    fn arrived(&mut self) {
        if self.limit.is_zero() {
            return;
        }
        let now = Instant::now();
        self.gap = now - self.last;
        self.last = now;
    }

    /// Polls until the socket is readable or the spin time is up, letting
    /// other tasks run between polls; true if it became readable. Only when
    /// the last gap was short: otherwise false at once.
    async fn wait(&mut self, socket: &UdpSocket) -> bool {
        if self.gap >= self.limit {
            return false;
        }
        let deadline = self.last + self.limit;
        while Instant::now() < deadline {
            // Yielding lets the runtime poll its I/O driver (without
            // blocking), which marks the socket readable when data came.
            tokio::task::yield_now().await;
            if socket
                .try_io(tokio::io::Interest::READABLE, || Ok(()))
                .is_ok()
            {
                return true;
            }
        }
        false
    }
}

/// Where datagrams are received: large buffers handed out as views, so
/// delivering a message costs no copy.
///
/// When the current buffer has no room for a full datagram, a buffer whose
/// messages have all been dropped is taken back (its memory already mapped,
/// so no allocation and no page faults); only while messages still hold all
/// of them is a new one allocated. Buffers that messages still hold beyond
/// the last few are let go: their memory is freed with the last message.
#[derive(Default)]
struct ReceiveBuffers {
    current: BytesMut,
    spare: std::collections::VecDeque<BytesMut>,
}

impl ReceiveBuffers {
    const SIZE: usize = 2 << 20;
    const SPARES: usize = 4;

    /// An empty buffer with room for one full datagram.
    fn next(&mut self) -> &mut BytesMut {
        self.current.clear();
        if self.current.capacity() <= MAX_DATAGRAM {
            let reclaimable = self.spare.iter_mut().position(|b| {
                b.clear();
                b.try_reclaim(Self::SIZE)
            });
            let reclaimed = reclaimable.and_then(|i| self.spare.remove(i));
            let fresh = reclaimed.unwrap_or_else(|| BytesMut::with_capacity(Self::SIZE));
            let old = std::mem::replace(&mut self.current, fresh);
            self.spare.push_back(old);
            if self.spare.len() > Self::SPARES {
                self.spare.pop_front();
            }
        }
        &mut self.current
    }
}

/// Announces the node and tracks its peers until the node stops.
async fn heartbeat_loop(inner: Arc<Inner>, nodes: Arc<ChannelState>, heartbeats: OwnSubscriber) {
    let mut tick = tokio::time::interval(inner.heartbeat_period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Types are compared about once a second, not every heartbeat.
    let mut last_type_check = Instant::now();
    loop {
        let expiry = inner.membership().poll_timeout();
        let expire = async {
            match expiry {
                // Deadlines are inclusive, so wake just after.
                Some(at) => tokio::time::sleep_until((at + Duration::from_millis(1)).into()).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = tick.tick() => {
                if inner.compat_heartbeat {
                    inner.send_heartbeat(&nodes);
                }
                inner.log_membership_events();
                // Which channels 2.x peers subscribe, once a tick rather
                // than for every heartbeat.
                inner.update_batching_eligibility();
                inner.expire_fragments();
                if last_type_check.elapsed() >= Duration::from_secs(1) {
                    last_type_check = Instant::now();
                    inner.warn_type_mismatches();
                }
            }
            _ = expire => {
                inner.membership().handle_timeout(Instant::now());
                inner.log_membership_events();
            }
            received = heartbeats.queue.recv() => match received {
                Some(message) => inner.handle_heartbeat(message),
                None => return,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compat_session_id_is_the_uuid_prefix() {
        let uuid = Uuid::from_bytes([
            0xbb, 0x10, 0xf3, 0xc6, 0xe3, 0x71, 0xdd, 0x0e, 1, 2, 3, 4, 5, 6, 7, 8,
        ]);
        assert_eq!(compat_session_id(&uuid), -4967202353444692722);
    }

    #[test]
    fn receive_buffers_are_taken_back_once_their_messages_are_dropped() {
        let mut buffers = ReceiveBuffers::default();
        let mut bases = std::collections::HashSet::new();
        for round in 0..400 {
            let buf = buffers.next();
            if buf.capacity() == ReceiveBuffers::SIZE {
                bases.insert(buf.as_ptr() as usize);
            }
            buf.extend_from_slice(&[round as u8; 60_000]);
            let message = buf.split().freeze();
            assert_eq!(message.len(), 60_000);
            drop(message);
        }
        // 400 x 60 kB went through a handful of buffers, not 12 new ones.
        assert!(bases.len() <= 2, "{} buffers", bases.len());

        // While messages are held, new buffers are taken, and let go of later.
        let held: Vec<bytes::Bytes> = (0..100)
            .map(|_| {
                let buf = buffers.next();
                buf.extend_from_slice(&[7; 60_000]);
                buf.split().freeze()
            })
            .collect();
        assert!(held.iter().all(|m| m.len() == 60_000));
        assert!(buffers.spare.len() <= ReceiveBuffers::SPARES);
    }

    #[test]
    fn invalid_options_are_refused() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let err = |b: NodeBuilder| rt.block_on(b.start()).err();
        assert!(matches!(
            err(Node::new("n").port(0)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").ttl(256)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").heartbeat_period(Duration::ZERO)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").queue_capacity(0)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").receive_spin(MAX_RECEIVE_SPIN * 2)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").receive_buffer(1000)),
            Some(Error::InvalidConfig { .. })
        ));
        let limits = Limits {
            per_source: 10,
            per_channel: 5,
            total: 5,
            timeout: Duration::from_secs(1),
        };
        assert!(matches!(
            err(Node::new("n").reassembly_limits(limits)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").namespace("r\u{f6}ver")),
            Some(Error::InvalidName { .. })
        ));
    }

    #[test]
    fn start_outside_a_runtime_is_an_error() {
        let fut = Node::new("n").start();
        let result = futures_lite_block_on(fut);
        assert!(matches!(result, Err(Error::InvalidConfig { .. })));
    }

    /// Polls a future to completion without a tokio runtime.
    fn futures_lite_block_on<F: std::future::Future>(fut: F) -> F::Output {
        use std::task::{Context, Poll, Waker};
        let mut fut = std::pin::pin!(fut);
        let mut cx = Context::from_waker(Waker::noop());
        loop {
            if let Poll::Ready(out) = fut.as_mut().poll(&mut cx) {
                return out;
            }
        }
    }
}

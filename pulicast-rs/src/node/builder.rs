//! [`NodeBuilder`]: a node's settings, checked, and starting it.

use super::*;

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
    /// A builder with every setting at its default (see [`Node::new`]).
    pub(super) fn named(name: String) -> Self {
        Self {
            name,
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
            receivers: Receivers::new(Receiver::new(receiver_config)),
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

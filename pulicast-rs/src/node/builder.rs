//! [`NodeBuilder`]: a node's settings, checked, and starting it.

use std::net::{Ipv4Addr, SocketAddr};

use super::*;
use crate::runtime::fleet::DiscoveryOptions;

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
    s: Settings,
}

impl NodeBuilder {
    /// A builder with every setting at its default (see [`Node::new`]).
    pub(super) fn named(name: String) -> Self {
        let s = Settings {
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
            fragment_rate: Some(crate::node::DEFAULT_FRAGMENT_RATE),
            reassembly: ReassemblyLimits::default(),
            security: SecurityOptions::default(),
            settings_file: None,
            config: None,
        };
        Self { s }
    }

    /// The default namespace: relative channel names resolve against it
    /// (default: the root).
    pub fn namespace(mut self, namespace: impl Into<String>) -> Self {
        self.s.namespace = namespace.into();
        self
    }

    /// The configuration this node runs in (`alice`, `sim-42`): several
    /// instances of one system share a machine or a fleet, each in its own
    /// configuration, as DROS runs one per user. It is announced in
    /// discovery (`puli-sniffer nodes` shows it), and a search for the
    /// nearest provider tries the caller's configuration first, then
    /// providers of none, so a user's own server overrides everyone's.
    ///
    /// Without it the node takes [`crate::CONFIG_ENV`] (`PULICAST_CONFIG`)
    /// if set, else runs in none; `config("")` is none whatever the
    /// environment says. A name is ASCII letters, digits, `_`, `-` and `.`,
    /// at most [`crate::MAX_CONFIG_LEN`] bytes; any other is
    /// [`Error::InvalidConfig`] at start.
    ///
    /// ```
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("laser_driver")
    ///     .namespace("rover1")
    ///     .config("alice")
    ///     .interface(std::net::Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// assert_eq!(node.config(), "alice");
    /// assert_eq!(node.discovery().local().config, "alice");
    /// # Ok::<(), pulicast::Error>(())
    /// ```
    pub fn config(mut self, config: impl Into<String>) -> Self {
        self.s.config = Some(config.into());
        self
    }

    /// The UDP port all channels use (default 8765). Nodes only hear each other
    /// on the same port.
    pub fn port(mut self, port: u16) -> Self {
        self.s.port = port;
        self
    }

    /// Multicast TTL (default 0: traffic stays on this host; 1: the local link).
    pub fn ttl(mut self, ttl: u32) -> Self {
        self.s.ttl = ttl;
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
        self.s.interface = Some(interface);
        self
    }

    /// Start-up values of this node's distributed settings, from a file
    /// in the puliconf format (TOML, as `puli config pull` and 2.x
    /// `puliconf pull` write it: one key per fleet-wide setting name,
    /// `nan` for no value). A setting made under a name in the file starts
    /// from the file's value instead of its coded default, and a reset
    /// goes back to it.
    ///
    /// The file is read when the node starts: one that can't be read or
    /// is not TOML is [`Error::InvalidConfig`]. Its values are checked as
    /// any request is, read-only included: a value its setting refuses (or
    /// of another type) makes that setting's creation fail with
    /// [`Error::SettingRefused`], saying why, rather than start from a
    /// value nobody checked. Names no setting of this node takes are
    /// ignored, so one file can hold a whole fleet.
    ///
    /// ```
    /// # let port = pulicast::unused_port()?;
    /// # let dir = std::env::temp_dir().join(format!("pulicast-doc-{port}"));
    /// # std::fs::create_dir_all(&dir)?;
    /// let file = dir.join("rover1.toml");
    /// std::fs::write(&file, "\"rover1/max_speed\" = 0.8\n\"rover2/max_speed\" = 1.2\n")?;
    /// let node = pulicast::Node::new("controller")
    ///     .namespace("rover1")
    ///     .settings_file(&file)
    ///     .interface(std::net::Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// let speed = node.setting("max_speed", 1.5f64)?;
    /// assert_eq!(speed.get(), Some(0.8));
    /// # std::fs::remove_dir_all(&dir).ok();
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn settings_file(mut self, path: impl Into<std::path::PathBuf>) -> Self {
        self.s.settings_file = Some(path.into());
        self
    }

    /// How often the node announces itself on `__nodes` (default 100 ms,
    /// allowed 10 ms ..= 10 s). Peers consider the node gone after three
    /// missed periods.
    pub fn heartbeat_period(mut self, period: Duration) -> Self {
        self.s.heartbeat_period = period;
        self
    }

    /// How many received datagrams' worth each subscription buffers
    /// (default 1024) before its queue policy drops one: a message, or a
    /// whole batch of small messages sent together
    /// ([`crate::Channel::enable_batching`]). Either is at most one
    /// datagram's bytes, so a queue's memory is bounded the same way
    /// whether its publisher batches or not, and a batched stream of
    /// millions of messages a second fits it.
    pub fn queue_capacity(mut self, capacity: usize) -> Self {
        self.s.queue_capacity = capacity;
        self
    }

    /// What a full subscription queue drops: the oldest message (the
    /// default: slow subscribers see the latest data) or the new one (they
    /// see a contiguous prefix). Either way the receive loop never waits and
    /// the drop is counted as [`crate::DropReason::QueueOverflow`].
    pub fn queue_policy(mut self, policy: QueuePolicy) -> Self {
        self.s.queue_policy = policy;
        self
    }

    /// Turns gossip discovery off (default: on). The node still sends and
    /// consumes Pulicast 2.x heartbeats, so it and 2.x tools still see the
    /// fleet, with less detail.
    pub fn discovery(mut self, enabled: bool) -> Self {
        self.s.discovery.enabled = enabled;
        self
    }

    /// The UDP port of the node's discovery socket (default: any free one).
    /// Give a node a fixed one to make it a seed other nodes can name.
    pub fn discovery_port(mut self, port: u16) -> Self {
        self.s.discovery.port = port;
        self
    }

    /// A seed peer: the discovery address (`host:port`) of a node reached by
    /// unicast, for links where multicast does not pass. The fleet's
    /// membership is learned through it. May be given several times.
    pub fn peer(mut self, address: SocketAddr) -> Self {
        if !self.s.discovery.seeds.contains(&address) {
            self.s.discovery.seeds.push(address);
        }
        self
    }

    /// Whether to send the Pulicast 2.x `__nodes` heartbeat (default: on, so
    /// 2.x tools see the node). Fleets without 2.x nodes can save its
    /// traffic; gossip discovery carries the same facts.
    pub fn compat_heartbeat(mut self, enabled: bool) -> Self {
        self.s.compat_heartbeat = enabled;
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
        self.s.receive_spin = spin;
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
        self.s.receive_buffer = bytes;
        self
    }

    /// How fast the fragments of a large message leave, in bytes a second
    /// (default [`DEFAULT_FRAGMENT_RATE`], 1 GiB/s; at least
    /// [`MIN_FRAGMENT_RATE`]), or `None` for as fast as the kernel takes
    /// them.
    ///
    /// A message too large for one datagram leaves as fragments, and a
    /// subscriber loses the whole message if one fragment finds its
    /// socket's receive buffer full. So fragments leave at this rate, in
    /// bursts of at most half the smallest receive buffer the channel's
    /// subscribers announce (a Pulicast 2.x subscriber, which announces
    /// none, counts as this host's `net.core.rmem_default`). Messages of
    /// one datagram never wait. A `publish` of a large message takes as
    /// long as its pacing: 16 MiB to subscribers of 8 MiB buffers takes
    /// about 12 ms at the default rate. What waited is counted in
    /// [`crate::Stats::paced_datagrams`] and [`crate::Stats::paced_wait`].
    ///
    /// ```no_run
    /// # async fn demo() -> pulicast::Result<()> {
    /// // A camera on a 1 Gbit/s link: no faster than the link.
    /// let node = pulicast::Node::new("camera")
    ///     .fragment_rate(Some(100 << 20))
    ///     .start()
    ///     .await?;
    /// # Ok(()) }
    /// ```
    pub fn fragment_rate(mut self, bytes_per_second: Option<u64>) -> Self {
        self.s.fragment_rate = bytes_per_second;
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
    /// use pulicast::ReassemblyLimits;
    /// let camera_node = pulicast::Node::new("viewer").reassembly_limits(ReassemblyLimits {
    ///     per_source: 64 << 20,
    ///     per_channel: 64 << 20,
    ///     total: 256 << 20,
    ///     timeout: Duration::from_millis(500),
    /// });
    /// # drop(camera_node);
    /// ```
    pub fn reassembly_limits(mut self, limits: ReassemblyLimits) -> Self {
        self.s.reassembly = limits;
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
        self.s.security.keys.push((namespace.into(), key));
        self
    }

    /// Whether sealed datagrams also hide their payload (default: off, they
    /// are authenticated but readable by anyone on the link). Also turned on
    /// by the environment variable [`crate::ENCRYPT_ENV`]. Receivers
    /// open both kinds either way.
    pub fn encrypt(mut self, encrypt: bool) -> Self {
        self.s.security.encrypt = encrypt;
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
        self.s.security.max_age = max_age;
        self
    }

    /// Whether the node reads [`crate::KEYS_ENV`] and
    /// [`crate::ENCRYPT_ENV`] (default: yes), so keys can be deployed
    /// without code changes.
    pub fn keys_from_env(mut self, read: bool) -> Self {
        self.s.security.from_env = read;
        self
    }

    fn validate(&self) -> Result<String> {
        let invalid = |setting, reason: String| Err(Error::config(setting, reason));
        configuration(self.s.config.as_deref(), |name| std::env::var(name).ok())?;
        if self.s.port == 0 {
            return invalid("port", "0: all nodes must agree on one fixed port".into());
        }
        if self.s.ttl > 255 {
            return invalid("ttl", format!("{} is above 255", self.s.ttl));
        }
        if !(compat::PERIOD_RANGE.0..=compat::PERIOD_RANGE.1).contains(&self.s.heartbeat_period) {
            return invalid(
                "heartbeat period",
                format!(
                    "heartbeat period {:?} is outside {:?} ..= {:?}, the range peers accept",
                    self.s.heartbeat_period,
                    compat::PERIOD_RANGE.0,
                    compat::PERIOD_RANGE.1
                ),
            );
        }
        if self.s.queue_capacity == 0 {
            return invalid("queue capacity", "0".into());
        }
        if self
            .s
            .fragment_rate
            .is_some_and(|rate| rate < crate::node::MIN_FRAGMENT_RATE)
        {
            return invalid(
                "fragment rate",
                format!(
                    "{:?} bytes a second is below {} (None turns pacing off)",
                    self.s.fragment_rate,
                    crate::node::MIN_FRAGMENT_RATE
                ),
            );
        }
        if !(64 << 10..=1 << 30).contains(&self.s.receive_buffer) {
            return invalid(
                "receive buffer",
                format!(
                    "{} bytes is outside 64 KiB ..= 1 GiB",
                    self.s.receive_buffer
                ),
            );
        }
        let limits = self.s.reassembly;
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
        if self.s.receive_spin > MAX_RECEIVE_SPIN {
            return invalid(
                "receive spin",
                format!("{:?} is above {MAX_RECEIVE_SPIN:?}", self.s.receive_spin),
            );
        }
        if self.s.name.len() > 1024 {
            return invalid("node name", "longer than 1024 bytes".into());
        }
        resolve_path(&self.s.namespace, "")
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
        let inner = self.s.start(namespace.clone(), runtime, None)?;
        Ok(Node::running(inner, namespace))
    }

    /// Starts the node on a runtime thread of its own, for programs without
    /// async code. Receive with [`crate::Subscription::recv_blocking`],
    /// [`crate::Subscription::recv_timeout`], [`crate::Subscription::recv_many_timeout`]
    /// or [`crate::Subscription::try_recv`], or with a handler
    /// ([`crate::Channel::subscribe_with`]).
    ///
    /// While one of your threads waits in a blocking receive, that thread
    /// drives the node (so the message reaches it without a hand-off
    /// between threads); otherwise the node's thread does. The thread ends
    /// when the node stops.
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
        let namespace = self.validate()?;
        let inner = self.s.start_on_own_thread(namespace.clone())?;
        Ok(Node::running(inner, namespace))
    }
}

/// The configuration a node runs in: `given` by the builder, else
/// [`crate::CONFIG_ENV`]'s value from `env`, else none (empty); checked.
pub(crate) fn configuration(
    given: Option<&str>,
    env: impl Fn(&str) -> Option<String>,
) -> Result<String> {
    let (config, from) = match given {
        Some(given) => (given.to_string(), "config"),
        None => (
            env(crate::CONFIG_ENV).unwrap_or_default(),
            crate::CONFIG_ENV,
        ),
    };
    let bad = |reason: String| Err(Error::config(from, format!("{config:?} {reason}")));
    if config.len() > crate::MAX_CONFIG_LEN {
        return bad(format!("is longer than {} bytes", crate::MAX_CONFIG_LEN));
    }
    if let Some(c) = config
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '-' | '.')))
    {
        return bad(format!(
            "holds {c:?}: a configuration is ASCII letters, digits, '_', '-' and '.'"
        ));
    }
    Ok(config)
}

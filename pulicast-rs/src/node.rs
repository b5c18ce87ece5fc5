//! The node: configuration, lifecycle, and the shared state behind every handle.

use std::collections::HashSet;
use std::io::IoSlice;
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket as StdUdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use bytes::BytesMut;
use indexmap::IndexMap;
use pulicast_discovery::compat::{self, ChannelAnnouncement, Membership, Peer};
use tokio::net::UdpSocket;
use tokio::task::JoinHandle;
use uuid::Uuid;

use crate::batching::{Flush, Flushed, Flusher};
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
pub(crate) use crate::sync::lock;
use crate::transport::{self, NetConfig, ReceivePool};
use crate::wire::{zcm, DropReason, MAX_DATAGRAM};
use pulicast_discovery::wire::{ChannelInfo, MemberInfo, TypeInfo};

mod builder;
mod legacy;
mod receive;
mod send;

pub use builder::NodeBuilder;
use legacy::{heartbeat_loop, OwnSubscriber};
use receive::{receive_loop, Receivers};

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
        NodeBuilder::named(name.into())
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
        let counts = inner.receivers.counts();
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
        self.inner().receivers.key_uses()
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

/// A channel that batches, as the flusher thread sees it.
pub(crate) struct BatchingChannel {
    inner: Weak<Inner>,
    channel: Arc<ChannelState>,
}

impl Flush for BatchingChannel {
    fn flush_due(&self, now: Instant) -> Flushed {
        let Some(inner) = self.inner.upgrade() else {
            return Flushed::Gone;
        };
        match inner.flush_batch(&self.channel, Some(now)) {
            Ok(next) => Flushed::Pending(next),
            Err(e) => Flushed::Failed(e),
        }
    }

    fn is(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.channel, &other.channel)
    }

    fn channel(&self) -> &str {
        &self.channel.name
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
    /// The receive path (dispatch, leads, reassembly and opening), one
    /// receiver per socket of the pool.
    receivers: Receivers,
    /// The receive sockets. Lock order: pool, then a receiver, then the
    /// reassembly the receivers share.
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
    flusher: Arc<Flusher<BatchingChannel>>,
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
        for BatchingChannel { channel, .. } in self.flusher.channels().iter().map(|c| &**c) {
            let _ = self.flush_batch(channel, None);
        }
        for task in lock(&self.tasks).drain(..) {
            task.abort();
        }
        // Dropping the senders closes every subscription. Under the pool's
        // lock, which subscribe() checks the flag under.
        let mut pool = lock(&self.pool);
        for shard in self.receivers.all() {
            lock(&shard).clear();
        }
        pool.close();
        drop(pool);
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
        let (index, opened) = lock(&inner.pool)
            .join(*group.ip())
            .map_err(Error::bind("joining the discovery group", inner.port))?;
        if let Some(socket) = opened {
            let shard = inner.receivers.get(index);
            let task = inner
                .runtime
                .spawn(receive_loop(Arc::clone(inner), socket, shard));
            inner.add_task(task);
        }
        let task = inner
            .runtime
            .spawn(discovery::discovery_loop(Arc::clone(inner)));
        inner.add_task(task);
    }
    Ok(())
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

//! The runtime: the node's shared state ([`Inner`]) and the code that
//! drives the sans-IO core ([`crate::proto`], `pulicast_discovery`) with
//! sockets, tasks, threads and clocks. The API (`node`, `channel`,
//! `subscription`, `discovery`) reaches it through `Inner`'s `pub(crate)`
//! methods; nothing here imports the API.

use std::collections::HashSet;
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket as StdUdpSocket};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use indexmap::IndexMap;
use pulicast_discovery::compat::{self, Membership};
use tokio::task::JoinHandle;
use uuid::Uuid;

use crate::batching::{Flush, Flushed, Flusher};
use crate::error::{Error, Result};
use crate::name::group_for;
use crate::proto::receiver::{KeyUse, RawMessage};
use crate::proto::view::{MemberView, Select};
use crate::proto::ChannelTx;
use crate::queue::{Queue, QueuePolicy};
use crate::security::Security;
use crate::stats::{Counters, Stats};
pub(crate) use crate::sync::lock;
use crate::transport::ReceivePool;
use fleet::{DiscoveryState, Fleet};
use pulicast_discovery::wire::{ChannelInfo, MemberInfo, TypeInfo};

pub(crate) mod asking;
pub(crate) mod calling;
mod delivery;
mod drive;
mod eligibility;
pub(crate) mod fleet;
mod legacy;
mod receive;
mod send;
pub(crate) mod services;
pub(crate) mod serving;
mod start;

pub(crate) use delivery::{Handler, Queued};
use legacy::{heartbeat_loop, OwnSubscriber};
use receive::Receivers;
pub(crate) use start::Settings;

fn compat_session_id(session: &Uuid) -> i64 {
    let bytes = session.as_bytes();
    let mut first = [0; 8];
    first.copy_from_slice(&bytes[..8]);
    i64::from_be_bytes(first)
}

/// What the node knows about one channel it has touched.
pub(crate) struct ChannelState {
    name: Arc<str>,
    group: Ipv4Addr,
    /// `destination` as the socket layer takes it.
    address: socket2::SockAddr,
    /// Whether a key covers the channel.
    sealed: bool,
    /// The send side: prefixes, sequence numbers, pending batch, sealer.
    tx: Mutex<ChannelTx>,
    published: AtomicBool,
    /// Subscriptions discovery announces; quiet ones (a bridge's relay
    /// servers) are not counted, so they never show.
    subscribers: AtomicUsize,
    period: Mutex<PeriodMeter>,
    /// Fingerprint of the last typed use (0: none), checked without a lock
    /// on every publish; the description itself is behind the mutex.
    type_fingerprint: AtomicU64,
    message_type: Mutex<Option<TypeInfo>>,
    /// Announcements held without publishing or subscribing (services'
    /// clients and servers, and what is announced beside their request
    /// channels): publish, subscribe.
    held: [AtomicUsize; 2],
}

impl ChannelState {
    /// The channel's full name.
    pub(crate) fn name(&self) -> &Arc<str> {
        &self.name
    }

    /// The channel as announced in discovery, if this node uses it.
    fn info(&self) -> Option<ChannelInfo> {
        let [held_pub, held_sub] = &self.held;
        let publishes =
            self.published.load(Ordering::Relaxed) || held_pub.load(Ordering::Relaxed) > 0;
        let subscribes = self.announced_subscribers() > 0 || held_sub.load(Ordering::Relaxed) > 0;
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

    /// The subscriptions discovery announces: all but the quiet ones.
    pub(crate) fn announced_subscribers(&self) -> usize {
        self.subscribers.load(Ordering::Relaxed)
    }

    /// Holds an announcement that this node publishes (`publishes`) or
    /// subscribes the channel, without doing it; true if the channel's
    /// announcement changed.
    pub(crate) fn hold(&self, publishes: bool) -> bool {
        self.held[usize::from(!publishes)].fetch_add(1, Ordering::Relaxed) == 0
    }

    /// Lets go of an announcement [`ChannelState::hold`] took; true if the
    /// channel's announcement changed.
    pub(crate) fn release(&self, publishes: bool) -> bool {
        let held = &self.held[usize::from(!publishes)];
        held.fetch_update(Ordering::Relaxed, Ordering::Relaxed, |n| n.checked_sub(1)) == Ok(1)
    }

    /// Whether a key seals the channel.
    pub(crate) fn is_sealed(&self) -> bool {
        self.sealed
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
    name: String,
    session: Uuid,
    /// The 2.x session id: the first 8 bytes of `session` (see
    /// [`crate::Node::compat_session_id`]).
    compat_session_id: i64,
    namespace: String,
    host: String,
    start_time_ms: u64,
    /// When the node started, for how long discovery has listened.
    started: Instant,
    /// Held while this node relays members (see `Inner::relay`).
    relay_marker: Mutex<Option<Arc<ChannelState>>>,
    data_port: u16,
    heartbeat_period: Duration,
    queue_capacity: usize,
    queue_policy: QueuePolicy,
    receive_spin: Duration,
    compat_heartbeat: bool,
    port: u16,
    fleet: Fleet,
    send: StdUdpSocket,
    counters: Counters,
    /// In creation order, which is the order heartbeats list them in.
    channels: Mutex<IndexMap<Arc<str>, Arc<ChannelState>>>,
    /// The receive path (dispatch, leads, reassembly and opening), one
    /// receiver per socket of the pool.
    receivers: Receivers,
    /// Receive sockets open: read by `stats` without the pool's lock, so a
    /// log layer may call `Node::stats` from a line written under it.
    receive_sockets: AtomicUsize,
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
    /// A `start_blocking` node's runtime, which threads waiting in a
    /// blocking receive drive (see `runtime/drive.rs`).
    own_runtime: Option<Arc<drive::OwnRuntime>>,
    tasks: Mutex<Vec<JoinHandle<()>>>,
    next_subscriber: AtomicU64,
    flusher: Arc<Flusher<BatchingChannel>>,
    /// Which batching channels 2.x-only peers subscribe, as last worked out
    /// (see `update_batching_eligibility`).
    batching_view: Mutex<eligibility::Eligibility>,
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
    /// Start-up values of settings (`NodeBuilder::settings_file`).
    start_values: start::StartValues,
    /// Calls in flight and this node's servers.
    services: services::Services,
}

/// What the API reads of a node (`Node`, `Discovery`, `Channel`,
/// `Subscription`): the narrow surface the API layer reaches the runtime
/// through.
impl Inner {
    /// The start-up value of setting `name` from the node's settings
    /// file, if it names it, and the file's name.
    pub(crate) fn start_value(
        &self,
        name: &str,
    ) -> Option<(&Result<crate::proto::setting::FileValue, String>, &str)> {
        let values = &self.start_values;
        values.values.get(name).map(|v| (v, values.file.as_str()))
    }

    /// The runtime the node's tasks run on.
    pub(crate) fn runtime_handle(&self) -> &tokio::runtime::Handle {
        &self.runtime
    }

    /// The node's name.
    pub(crate) fn name(&self) -> &str {
        &self.name
    }

    /// The node's session.
    pub(crate) fn session(&self) -> Uuid {
        self.session
    }

    /// How long after its start a node has given discovery a fair chance
    /// to show the fleet: a 2.x peer is listed [`fleet::COMPAT_GRACE`]
    /// after its first heartbeat, which comes within its period (ours,
    /// three times over as 2.x counts a node dead after three); a gossip
    /// member within a digest interval and a pull, well inside that.
    pub(crate) fn fair_chance(&self) -> Duration {
        fleet::COMPAT_GRACE + 3 * self.heartbeat_period
    }

    /// The period of this node's 2.x heartbeats.
    pub(crate) fn heartbeat_period(&self) -> Duration {
        self.heartbeat_period
    }

    /// Whether this node holds members that the member `bridge` relays.
    pub(crate) fn relayed_from(&self, bridge: i64) -> bool {
        self.fleet
            .discovery
            .as_ref()
            .is_some_and(|d| d.relayed_from(bridge))
    }

    /// How long the node has run.
    pub(crate) fn age(&self) -> Duration {
        self.started.elapsed()
    }

    /// The 2.x session id (the first 8 bytes of the session).
    pub(crate) fn compat_session_id(&self) -> i64 {
        self.compat_session_id
    }

    /// The node's counters, the receivers' summed in.
    pub(crate) fn stats(&self) -> Stats {
        let mut stats = self.counters.snapshot();
        stats.receive_sockets = self.receive_sockets.load(Ordering::Relaxed);
        stats.late_answers = self.late_answers();
        let counts = self.receivers.counts();
        stats.datagrams_received = counts.datagrams;
        stats.messages_received = counts.messages;
        stats.out_of_order_skipped += counts.out_of_order_skipped;
        for (total, more) in stats.dropped.iter_mut().zip(counts.dropped) {
            *total += more;
        }
        stats
    }

    /// What each namespace's keys met, over all receivers.
    pub(crate) fn key_uses(&self) -> Vec<KeyUse> {
        self.receivers.key_uses()
    }

    /// The counters a subscription adds its decode drops to.
    pub(crate) fn counters(&self) -> &Counters {
        &self.counters
    }

    /// Fleet changes from now on.
    pub(crate) fn fleet_events(
        &self,
    ) -> tokio::sync::broadcast::Receiver<crate::proto::view::DiscoveryEvent> {
        self.fleet.subscribe()
    }

    /// Whether gossip discovery runs.
    pub(crate) fn is_gossiping(&self) -> bool {
        self.fleet.discovery.is_some()
    }

    /// The gossip protocol's counters, if it runs.
    pub(crate) fn gossip_stats(&self) -> Option<pulicast_discovery::gossip::GossipStats> {
        self.fleet.discovery.as_ref().map(DiscoveryState::stats)
    }

    /// Replaces the members this node relays from other sites.
    pub(crate) fn relay(
        &self,
        members: Vec<pulicast_discovery::wire::RelayedMember>,
    ) -> Result<()> {
        match &self.fleet.discovery {
            Some(d) => {
                // Announced while it relays anything, so that a node
                // joining knows to wait for the list (Discovery::settle).
                let relays = !members.is_empty();
                d.relay(members);
                let mut marker = lock(&self.relay_marker);
                if relays != marker.is_some() {
                    let changed = match marker.take() {
                        Some(held) => held.release(true),
                        None => {
                            let held = self.channel_state(crate::wire::RELAYS_CHANNEL);
                            let changed = held.hold(true);
                            *marker = Some(held);
                            changed
                        }
                    };
                    drop(marker);
                    if changed {
                        self.announce_change();
                    }
                }
                Ok(())
            }
            None => Err(Error::InvalidConfig {
                setting: "relay",
                reason: "gossip discovery is disabled on this node; relayed members travel on it"
                    .into(),
            }),
        }
    }

    /// The relay table's counters, if discovery runs.
    pub(crate) fn relay_stats(&self) -> Option<pulicast_discovery::relay::RelayStats> {
        self.fleet
            .discovery
            .as_ref()
            .map(DiscoveryState::relay_stats)
    }

    /// The discovery socket's address, if discovery runs.
    pub(crate) fn discovery_address(&self) -> Option<SocketAddr> {
        self.fleet.local_address()
    }

    /// Waits until `found` returns something, re-checking on every fleet
    /// event and every 50 ms (2.x peers change without events); fails
    /// with [`Error::Timeout`] after `timeout`, [`Error::NodeStopped`] if
    /// the node stops.
    pub(crate) async fn wait_for<T>(
        &self,
        timeout: Duration,
        mut found: impl FnMut() -> Option<T>,
    ) -> Result<T> {
        let mut events = self.fleet_events();
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            if let Some(value) = found() {
                return Ok(value);
            }
            if self.is_stopped() {
                return Err(Error::NodeStopped);
            }
            let tick = tokio::time::Instant::now() + Duration::from_millis(50);
            match tokio::time::timeout_at(deadline.min(tick), events.recv()).await {
                Err(_) if tokio::time::Instant::now() >= deadline => {
                    return found().ok_or(Error::Timeout(timeout));
                }
                _ => {}
            }
        }
    }

    /// Like [`Inner::wait_for`], blocking the thread (checks every 10 ms).
    pub(crate) fn wait_for_blocking<T>(
        &self,
        timeout: Duration,
        mut found: impl FnMut() -> Option<T>,
    ) -> Result<T> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(value) = found() {
                return Ok(value);
            }
            if self.is_stopped() {
                return Err(Error::NodeStopped);
            }
            if Instant::now() >= deadline {
                return Err(Error::Timeout(timeout));
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
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

    pub(crate) async fn wait_stopped(&self) {
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
            shard.lock().clear();
        }
        pool.close();
        self.receive_sockets.store(0, Ordering::Relaxed);
        drop(pool);
        self.stop_signal.notify_one();
        if let Some(own) = &self.own_runtime {
            own.stopped();
        }
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
            address: SocketAddrV4::new(group, self.port).into(),
            sealed: sealer.is_some(),
            tx: Mutex::new(ChannelTx::new(Arc::clone(&name), sealer)),
            published: AtomicBool::new(false),
            subscribers: AtomicUsize::new(0),
            period: Mutex::new(PeriodMeter::default()),
            type_fingerprint: AtomicU64::new(0),
            message_type: Mutex::new(None),
            held: Default::default(),
        });
        channels.insert(name, Arc::clone(&state));
        state
    }

    /// The sessions of this node and of the gossip members it knows: the
    /// callers whose calls a server remembers for as long as they live.
    pub(crate) fn live_sessions(&self) -> std::collections::HashSet<i64> {
        let mut live = self.fleet.gossip_keys();
        live.insert(self.compat_session_id);
        live
    }

    /// The fleet without this node: gossip members and 2.x-only peers.
    pub(crate) fn fleet_members(&self) -> Vec<MemberView> {
        self.fleet_members_selected(&Select::ALL)
    }

    /// [`Inner::fleet_members`] with at most `per_member` channels each,
    /// never copying more (the 2.x table is read in place).
    pub(crate) fn fleet_members_within(&self, per_member: usize) -> Vec<MemberView> {
        self.fleet_members_selected(&Select::first(per_member))
    }

    /// [`Inner::fleet_members`] with only the channels `channel` takes:
    /// what the node reads for itself (one channel's publishers, a
    /// service's servers), at the cost of those channels however many a
    /// stranger's members announce.
    pub(crate) fn fleet_members_on(&self, channel: &dyn Fn(&str) -> bool) -> Vec<MemberView> {
        self.fleet_members_selected(&Select {
            channel,
            ..Select::ALL
        })
    }

    /// The members and channels `select` takes, copied out of the tables
    /// in place.
    pub(crate) fn fleet_members_selected(&self, select: &Select<'_>) -> Vec<MemberView> {
        let membership = self.membership();
        let peers: Vec<&compat::Peer> = membership
            .peers()
            .filter(|p| p.session_id != self.compat_session_id)
            .collect();
        self.fleet.members(&peers, select)
    }

    /// Warns, once per channel and type, about members that publish another
    /// type on a channel than this node subscribes to it as: every message they send
    /// there is dropped (as [`DropReason::WrongType`]), and without this the
    /// subscriber would only see nothing arrive. Both types are named, from
    /// what discovery announces.
    fn warn_type_mismatches(&self) {
        let ours: Vec<(Arc<str>, TypeInfo)> = lock(&self.channels)
            .values()
            .filter(|c| c.announced_subscribers() > 0)
            .filter_map(|c| Some((Arc::clone(&c.name), lock(&c.message_type).clone()?)))
            .collect();
        if ours.is_empty() {
            return;
        }
        let mut said = 0;
        let named = |channel: &str| ours.iter().any(|(n, _)| **n == *channel);
        for member in self.fleet_members_on(&named) {
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
        let mut info = self.local_info();
        // The discovery socket is bound to every address; others see it
        // at the one its datagrams leave from.
        let port = self.fleet.local_address().map_or(0, |a| a.port());
        let address = SocketAddr::from((self.source_ip, port));
        // Moved, not copied: the view is read in wait loops, and a node's
        // channels are many.
        let channels = std::mem::take(&mut info.channels);
        let mut view = MemberView::from_info(&info, address);
        view.key = self.compat_session_id;
        view.channels = channels;
        view
    }

    /// Tells discovery that our announcement changed.
    pub(crate) fn announce_change(&self) {
        if let Some(d) = &self.fleet.discovery {
            d.changed.notify_one();
        }
    }
}

/// Heartbeats waiting for the heartbeat task, at most.
const HEARTBEAT_QUEUE: usize = 256;

/// Subscribes the heartbeat channel, joins the discovery group and spawns the
/// node's tasks.
fn start_tasks(inner: &Arc<Inner>) -> Result<()> {
    // The node's own subscriber of `__nodes`, not a user's `Subscription`:
    // it lives as long as the node.
    let nodes = inner.channel_state(compat::NODES_CHANNEL);
    // Heartbeats wait for the heartbeat task as copies, in a queue of
    // their own: a queued view would keep its whole 2 MiB receive buffer
    // alive, and a flood of 60 kB heartbeats queued as views held hundreds
    // of megabytes. At most `HEARTBEAT_QUEUE` copies (16 MiB of the largest
    // datagrams) wait; past them the oldest go, as a peer's next heartbeat
    // tells the same.
    let heartbeats = Arc::new(Queue::new(HEARTBEAT_QUEUE, QueuePolicy::DropOldest));
    let queued = Arc::clone(&heartbeats);
    let handler = Handler::new(move |mut message: RawMessage, _: &Counters| {
        message.payload = bytes::Bytes::copy_from_slice(&message.payload);
        queued.push(Queued::One(Some(message)));
        // The node's own: no message delivered to a user.
        false
    });
    let id = inner.subscribe_handler(&nodes, false, None, Arc::new(handler), false)?;
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
        let group = fleet::group(inner.port);
        let (index, opened) = lock(&inner.pool)
            .join(*group.ip())
            .map_err(Error::bind("joining the discovery group", inner.port))?;
        if index != 0 {
            // Only where the kernel lets a socket join a single group:
            // gossip is then taken by the second socket's receiver.
            inner.receivers.get(0).lock().set_gossip(false);
            inner.receivers.get(index).lock().set_gossip(true);
        }
        if let Some(socket) = opened {
            inner.receive_on(socket, inner.receivers.get(index));
        }
        let task = inner
            .runtime
            .spawn(fleet::discovery_loop(Arc::clone(inner)));
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

    /// Channels made on the fly and dropped are forgotten within a
    /// heartbeat period, with 2.x heartbeats or without; published ones
    /// stay (their sequence numbers go on).
    #[test]
    fn channels_nobody_holds_are_forgotten_without_2x_heartbeats_too() {
        for compat in [true, false] {
            let rt = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(1)
                .enable_all()
                .build()
                .unwrap();
            let node = rt
                .block_on(
                    crate::Node::new("forgets")
                        .port(crate::unused_port().unwrap())
                        .interface(Ipv4Addr::LOCALHOST)
                        .heartbeat_period(Duration::from_millis(20))
                        .compat_heartbeat(compat)
                        .keys_from_env(false)
                        .start(),
                )
                .unwrap();
            let inner = Arc::clone(node.runtime());
            let before = lock(&inner.channels).len();
            let held: Vec<_> = (0..500)
                .map(|i| node.channel(&format!("fly/c{i}")))
                .collect();
            node.channel("fly/published").publish(&1u8).unwrap();
            assert!(lock(&inner.channels).len() >= before + 500);
            drop(held);
            let deadline = Instant::now() + Duration::from_secs(10);
            while lock(&inner.channels).len() > before + 1 {
                assert!(
                    Instant::now() < deadline,
                    "compat {compat}: never forgotten"
                );
                std::thread::sleep(Duration::from_millis(20));
            }
            let kept = lock(&inner.channels)
                .keys()
                .any(|k| k.ends_with("fly/published"));
            assert!(kept, "compat {compat}: the published channel was forgotten");
            node.stop();
        }
    }
}

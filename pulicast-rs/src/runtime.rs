//! The runtime: the node's shared state ([`Inner`]) and the code that
//! drives the sans-IO core ([`crate::proto`], `pulicast_discovery`) with
//! sockets, tasks, threads and clocks. The API (`node`, `channel`,
//! `subscription`, `discovery`) reaches it through `Inner`'s `pub(crate)`
//! methods; nothing here imports the API.

use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use pulicast_discovery::compat::{self, Membership};
use tokio::task::JoinHandle;
use uuid::Uuid;

use crate::error::{Error, Result};
use crate::name::group_for;
use crate::proto::receiver::{KeyUse, RawMessage};
use crate::proto::view::{MemberView, Select};
use crate::queue::{Queue, QueuePolicy};
use crate::security::Security;
use crate::stats::{Counters, Stats};
pub(crate) use crate::sync::lock;
use fleet::{DiscoveryState, Fleet};
use pulicast_discovery::wire::MemberInfo;

pub(crate) mod asking;
pub(crate) mod calling;
mod channels;
mod delivery;
mod drive;
mod eligibility;
pub(crate) mod fleet;
mod legacy;
mod receive;
mod receivers;
mod send;
pub(crate) mod services;
pub(crate) mod serving;
mod start;
pub(crate) mod walking;

pub(crate) use channels::ChannelState;
use channels::Channels;
pub(crate) use delivery::{Handler, Queued};
use legacy::{heartbeat_loop, OwnSubscriber};
use receivers::Receiving;
pub(crate) use send::BatchingChannel;
use send::Sending;
pub(crate) use start::Settings;

fn compat_session_id(session: &Uuid) -> i64 {
    let bytes = session.as_bytes();
    let mut first = [0; 8];
    first.copy_from_slice(&bytes[..8]);
    i64::from_be_bytes(first)
}

/// State shared by a node's handles and tasks, in parts that each own
/// what they guard (the lock order between them is in
/// `docs/architecture.md`, "Locks").
pub(crate) struct Inner {
    identity: Identity,
    tuning: Tuning,
    channels: Channels,
    sending: Sending,
    receiving: Receiving,
    /// Gossip discovery, relaying and the fleet's event streams.
    fleet: Fleet,
    /// 2.x peers, from their heartbeats.
    membership: Mutex<Membership>,
    counters: Counters,
    /// The node's keys, if it has any.
    security: Option<Security>,
    /// Start-up values of settings (`NodeBuilder::settings_file`).
    start_values: start::StartValues,
    /// Calls in flight and this node's servers.
    services: services::Services,
    lifecycle: Lifecycle,
}

/// Who the node is, fixed at start.
struct Identity {
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
    /// The multicast port: every channel's and discovery's.
    port: u16,
    /// The unicast port data leaves from (the send socket's).
    data_port: u16,
    /// Where data leaves from, as far as the node knows: sealed datagrams
    /// carry it, so receivers refuse them relayed from elsewhere.
    origin: SocketAddrV4,
    /// The address other nodes see this node's datagrams come from, as
    /// well as it is known: what its own view of itself shows.
    source_ip: Ipv4Addr,
    /// The configuration it runs in, empty for none.
    config: String,
    /// What it announces beyond the fixed fields (its receive buffer).
    extensions: Vec<pulicast_discovery::wire::Extension>,
}

/// What the builder chose for how the node behaves, fixed at start.
struct Tuning {
    heartbeat_period: Duration,
    queue_capacity: usize,
    queue_policy: QueuePolicy,
    receive_spin: Duration,
    compat_heartbeat: bool,
}

/// The node's life: its runtime and tasks, and whether it stopped.
struct Lifecycle {
    stopped: AtomicBool,
    stop_signal: tokio::sync::Notify,
    runtime: tokio::runtime::Handle,
    /// A `start_blocking` node's runtime, which threads waiting in a
    /// blocking receive drive (see `runtime/drive.rs`).
    own_runtime: Option<Arc<drive::OwnRuntime>>,
    tasks: Mutex<Vec<JoinHandle<()>>>,
}

impl Lifecycle {
    fn is_stopped(&self) -> bool {
        self.stopped.load(Ordering::Acquire)
    }

    /// Keeps `task` to abort at the stop; aborts it now if the node
    /// stopped already.
    fn add_task(&self, task: JoinHandle<()>) {
        let mut tasks = lock(&self.tasks);
        if self.is_stopped() {
            task.abort();
        } else {
            tasks.push(task);
        }
    }

    /// Marks the node stopped; false if it was already.
    fn stop(&self) -> bool {
        !self.stopped.swap(true, Ordering::AcqRel)
    }

    /// Aborts the node's tasks.
    fn abort_tasks(&self) {
        for task in lock(&self.tasks).drain(..) {
            task.abort();
        }
    }

    /// Wakes whoever waits for the stop, and a `start_blocking` node's
    /// thread.
    fn stopped(&self) {
        self.stop_signal.notify_one();
        if let Some(own) = &self.own_runtime {
            own.stopped();
        }
    }
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
        &self.lifecycle.runtime
    }

    /// The node's name.
    pub(crate) fn name(&self) -> &str {
        &self.identity.name
    }

    /// The configuration the node runs in, empty for none.
    pub(crate) fn config(&self) -> &str {
        &self.identity.config
    }

    /// The host the node runs on, as it announces it.
    pub(crate) fn host(&self) -> &str {
        &self.identity.host
    }

    /// The node's session.
    pub(crate) fn session(&self) -> Uuid {
        self.identity.session
    }

    /// How long after its start a node has given discovery a fair chance
    /// to show the fleet: a 2.x peer is listed [`fleet::COMPAT_GRACE`]
    /// after its first heartbeat, which comes within its period (ours,
    /// three times over as 2.x counts a node dead after three); a gossip
    /// member within a digest interval and a pull, well inside that.
    pub(crate) fn fair_chance(&self) -> Duration {
        fleet::COMPAT_GRACE + 3 * self.tuning.heartbeat_period
    }

    /// The period of this node's 2.x heartbeats.
    pub(crate) fn heartbeat_period(&self) -> Duration {
        self.tuning.heartbeat_period
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
        self.identity.started.elapsed()
    }

    /// The 2.x session id (the first 8 bytes of the session).
    pub(crate) fn compat_session_id(&self) -> i64 {
        self.identity.compat_session_id
    }

    /// The node's counters, the receivers' summed in.
    pub(crate) fn stats(&self) -> Stats {
        let mut stats = self.counters.snapshot();
        stats.receive_sockets = self.receiving.sockets.load(Ordering::Relaxed);
        stats.late_answers = self.late_answers();
        let counts = self.receiving.receivers.counts();
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
        self.receiving.receivers.key_uses()
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
                let mut marker = lock(&self.channels.relay_marker);
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

/// Most type warnings one check (one a second) logs; the channels' table
/// bounds how many it remembers.
const TYPE_WARNINGS_PER_CHECK: usize = 4;

impl Inner {
    pub(crate) fn is_stopped(&self) -> bool {
        self.lifecycle.is_stopped()
    }

    fn membership(&self) -> MutexGuard<'_, Membership> {
        lock(&self.membership)
    }

    fn add_task(&self, task: JoinHandle<()>) {
        self.lifecycle.add_task(task);
    }

    pub(crate) async fn wait_stopped(&self) {
        if !self.is_stopped() {
            self.lifecycle.stop_signal.notified().await;
        }
    }

    pub(crate) fn stop(&self) {
        if !self.lifecycle.stop() {
            return;
        }
        self.fleet.leave();
        // What was published before the stop still goes out.
        self.sending.flusher.stop();
        for BatchingChannel { channel, .. } in self.sending.flusher.channels().iter().map(|c| &**c)
        {
            let _ = self.flush_batch(channel, None);
        }
        self.lifecycle.abort_tasks();
        // Dropping the senders closes every subscription. Under the pool's
        // lock, which subscribe() checks the flag under.
        self.receiving.close();
        self.lifecycle.stopped();
        tracing::debug!(node = %self.identity.name, "node stopped");
    }

    /// The state of a resolved channel, created on first use.
    pub(crate) fn channel_state(&self, name: &str) -> Arc<ChannelState> {
        let security = self.security.as_ref();
        self.channels.state(name, |name| {
            let sealer = security.and_then(|s| s.sealer(name, self.identity.origin));
            (
                SocketAddrV4::new(group_for(name), self.identity.port),
                sealer,
            )
        })
    }

    /// The sessions of this node and of the gossip members it knows: the
    /// callers whose calls a server remembers for as long as they live.
    pub(crate) fn live_sessions(&self) -> std::collections::HashSet<i64> {
        let mut live = self.fleet.gossip_keys();
        live.insert(self.identity.compat_session_id);
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
            .filter(|p| p.session_id != self.identity.compat_session_id)
            .collect();
        self.fleet.members(&peers, select)
    }

    /// Warns, once per channel and type, about members that publish another
    /// type on a channel than this node subscribes to it as: every message they send
    /// there is dropped (as [`DropReason::WrongType`]), and without this the
    /// subscriber would only see nothing arrive. Both types are named, from
    /// what discovery announces.
    fn warn_type_mismatches(&self) {
        let ours = self.channels.subscribed_types();
        if ours.is_empty() {
            return;
        }
        let mut said = 0;
        let named = |channel: &str| ours.iter().any(|(n, _)| **n == *channel);
        for member in self.fleet_members_on(&named) {
            if member.session == Some(self.identity.session) || !member.is_live() {
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
                if !self.channels.first_type_warning(name, theirs.fingerprint) {
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
        let channels = self.channels.infos();
        MemberInfo {
            session: *self.identity.session.as_bytes(),
            name: self.identity.name.clone(),
            namespace: self.identity.namespace.clone(),
            host: self.identity.host.clone(),
            pid: std::process::id(),
            start_time_ms: self.identity.start_time_ms,
            data_port: self.identity.data_port,
            channels,
            config: self.identity.config.clone(),
            extensions: self.identity.extensions.clone(),
        }
    }

    /// This node as others see it.
    pub(crate) fn local_view(&self) -> MemberView {
        let mut info = self.local_info();
        // The discovery socket is bound to every address; others see it
        // at the one its datagrams leave from.
        let port = self.fleet.local_address().map_or(0, |a| a.port());
        let address = SocketAddr::from((self.identity.source_ip, port));
        // Moved, not copied: the view is read in wait loops, and a node's
        // channels are many.
        let channels = std::mem::take(&mut info.channels);
        let mut view = MemberView::from_info(&info, address);
        view.key = self.identity.compat_session_id;
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
        .lifecycle
        .runtime
        .spawn(heartbeat_loop(Arc::clone(inner), nodes, heartbeats));
    inner.add_task(task);
    if inner.fleet.discovery.is_some() {
        let group = fleet::group(inner.identity.port);
        let (index, opened) =
            lock(&inner.receiving.pool)
                .join(*group.ip())
                .map_err(Error::bind(
                    "joining the discovery group",
                    inner.identity.port,
                ))?;
        if index != 0 {
            // Only where the kernel lets a socket join a single group:
            // gossip is then taken by the second socket's receiver.
            inner.receiving.receivers.get(0).lock().set_gossip(false);
            inner.receiving.receivers.get(index).lock().set_gossip(true);
        }
        if let Some(socket) = opened {
            inner.receive_on(socket, inner.receiving.receivers.get(index));
        }
        let task = inner
            .lifecycle
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
            let before = inner.channels.table().len();
            let held: Vec<_> = (0..500)
                .map(|i| node.channel(&format!("fly/c{i}")))
                .collect();
            node.channel("fly/published").publish(&1u8).unwrap();
            assert!(inner.channels.table().len() >= before + 500);
            drop(held);
            let deadline = Instant::now() + Duration::from_secs(10);
            while inner.channels.table().len() > before + 1 {
                assert!(
                    Instant::now() < deadline,
                    "compat {compat}: never forgotten"
                );
                std::thread::sleep(Duration::from_millis(20));
            }
            let kept = inner
                .channels
                .table()
                .keys()
                .any(|k| k.ends_with("fly/published"));
            assert!(kept, "compat {compat}: the published channel was forgotten");
            node.stop();
        }
    }
}

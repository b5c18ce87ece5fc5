//! The fleet view: gossip discovery driven on sockets, merged with the
//! Pulicast 2.x heartbeats (the API on top of it is [`crate::Discovery`]).
//!
//! The protocol itself lives in `pulicast-discovery` ([`pulicast_discovery::gossip`]),
//! free of I/O; this module owns its socket and its task, feeds it datagrams
//! and the clock, sends what it asks to send, and turns its events (and those
//! of the 2.x heartbeat table) into [`DiscoveryEvent`]s.

use std::borrow::Cow;
use std::collections::{HashMap, HashSet};
use std::net::{SocketAddr, SocketAddrV4};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use bytes::Bytes;
use pulicast_discovery::compat::Peer;
use pulicast_discovery::gossip::{self, Destination, Gossip, GossipConfig, Member, Via};
use pulicast_discovery::relay::{self, Relays};
use pulicast_discovery::wire::{
    MemberInfo, MemberState, Message, Relayed, RelayedMember, MAX_CHUNK,
};
use tokio::net::UdpSocket;
use tokio::sync::{broadcast, Notify};

use super::Inner;
use crate::proto::secure::Sealer;
use crate::proto::view::{self, DiscoveryEvent, MemberView, Select, EVENT_CHANNELS};
use crate::queue::{One, Pushed, Queue, QueuePolicy};
use crate::sync::lock;

use crate::wire::DISCOVERY_CHANNEL;

/// How soon after a member joins a node that relays members (a bridge)
/// sends them again, so the newcomer learns the other sites at once.
const RELAY_AFTER_JOIN: Duration = Duration::from_millis(100);

/// Multicast discovery datagrams waiting for the discovery task, at most.
const INBOUND_CAPACITY: usize = 512;

/// Of those, at most this many from one source: an eighth of the queue,
/// far more than a member sends in a heartbeat period.
const INBOUND_PER_SOURCE: usize = INBOUND_CAPACITY / 8;

/// How long a 2.x peer must be known without gossip before it counts as a
/// 2.x-only member: our own nodes send 2.x heartbeats too, and their gossip
/// state arrives within a digest interval and one round trip.
pub(crate) const COMPAT_GRACE: Duration = Duration::from_millis(250);

/// Options of the discovery layer, set through [`crate::NodeBuilder`].
#[derive(Debug, Clone)]
pub(crate) struct DiscoveryOptions {
    pub enabled: bool,
    pub port: u16,
    pub seeds: Vec<SocketAddr>,
}

impl Default for DiscoveryOptions {
    fn default() -> Self {
        Self {
            enabled: true,
            port: 0,
            seeds: Vec::new(),
        }
    }
}

/// The running discovery of one node.
pub(crate) struct DiscoveryState {
    gossip: Mutex<Gossip>,
    socket: Arc<UdpSocket>,
    group: SocketAddrV4,
    inbound: Queue<One<(SocketAddr, Bytes)>>,
    /// How many datagrams of each source wait in `inbound`: at most one
    /// entry per queued datagram, so bounded by the queue.
    pending: Mutex<HashMap<SocketAddr, usize>>,
    pub(super) changed: Notify,
    /// Seal what gossip sends when discovery has a key: one stream for
    /// multicast, bound to the node's address, and one for unicast.
    sealers: Option<(Mutex<Sealer>, Mutex<Sealer>)>,
    /// Members of other sites that bridges here relay. Locked after
    /// `gossip` when both are needed, never before.
    relays: Mutex<Relays>,
    /// What this node relays, if it is a bridge. Locked before `gossip`
    /// when both are needed, never after.
    relaying: Mutex<Relaying>,
}

/// The members this node relays (see [`crate::Discovery::relay`]) and when
/// it sends them next.
#[derive(Debug, Default)]
struct Relaying {
    /// Each with its encoded length, at most [`MAX_CHUNK`].
    members: Vec<(RelayedMember, usize)>,
    /// At once after a change; every [`relay::REFRESH`] otherwise.
    due: Option<Instant>,
}

/// Fleet-wide state shared by discovery and the 2.x table.
pub(crate) struct Fleet {
    pub(super) discovery: Option<DiscoveryState>,
    /// Taken when the node stops, which ends every event stream.
    events: Mutex<Option<broadcast::Sender<DiscoveryEvent>>>,
    /// 2.x peers already reported as members.
    announced_compat: Mutex<HashSet<i64>>,
}

impl Fleet {
    pub(crate) fn new(discovery: Option<DiscoveryState>) -> Self {
        Self {
            discovery,
            events: Mutex::new(Some(broadcast::channel(1024).0)),
            announced_compat: Mutex::new(HashSet::new()),
        }
    }

    /// Hands a multicast discovery datagram from the receive loop to the
    /// task; false if it was dropped instead.
    ///
    /// A full queue means the task is behind; dropping is what the network
    /// would do, and gossip recovers from it. But one sender may hold at
    /// most [`INBOUND_PER_SOURCE`] of the queue: a flood from one socket
    /// would otherwise fill it, and real members' digests and refutations
    /// would be dropped until they were taken for failed.
    pub(crate) fn inbound(&self, source: SocketAddr, datagram: &[u8]) -> bool {
        let Some(d) = &self.discovery else {
            return true;
        };
        let mut pending = lock(&d.pending);
        let held = pending.entry(source).or_insert(0);
        if *held >= INBOUND_PER_SOURCE {
            return false;
        }
        let pushed = d
            .inbound
            .push(One(Some((source, Bytes::copy_from_slice(datagram)))));
        if matches!(pushed, Pushed::Queued | Pushed::DroppedOldest) {
            *held += 1;
            return true;
        }
        if *held == 0 {
            pending.remove(&source);
        }
        false
    }

    fn emit(&self, event: DiscoveryEvent) {
        match &event {
            DiscoveryEvent::Suspicious { key, what } => {
                tracing::warn!(session = key, "suspicious discovery message: {what}");
            }
            other => tracing::debug!(?other, "fleet change"),
        }
        if let Some(events) = lock(&self.events).as_ref() {
            let _ = events.send(event);
        }
    }

    /// A new event stream; one that has already ended if the node stopped.
    pub(crate) fn subscribe(&self) -> broadcast::Receiver<DiscoveryEvent> {
        match lock(&self.events).as_ref() {
            Some(events) => events.subscribe(),
            None => broadcast::channel(1).1,
        }
    }

    /// Reports a 2.x heartbeat conflict (a session from a second address or
    /// renamed).
    pub(crate) fn compat_suspicious(&self, key: i64, what: String) {
        self.emit(DiscoveryEvent::Suspicious { key, what });
    }

    /// Keys of the gossip members, to hide their 2.x heartbeats.
    pub(crate) fn gossip_keys(&self) -> HashSet<i64> {
        self.discovery
            .as_ref()
            .map(|d| lock(&d.gossip).members().map(Member::key).collect())
            .unwrap_or_default()
    }

    /// Whether a heartbeat peer has been around long enough that, were it
    /// one of ours, gossip would know it by now.
    pub(crate) fn is_settled(&self, now: Instant, peer: &Peer) -> bool {
        now.saturating_duration_since(peer.first_seen) >= COMPAT_GRACE
    }

    /// Of the 2.x peers `settled`, those not announced yet and not known
    /// by gossip: the ones [`Fleet::update_compat`] would announce.
    pub(crate) fn unannounced_compat(&self, settled: &[i64]) -> Vec<i64> {
        let announced = lock(&self.announced_compat);
        let fresh: Vec<i64> = settled
            .iter()
            .copied()
            .filter(|id| !announced.contains(id))
            .collect();
        drop(announced);
        if fresh.is_empty() {
            return fresh;
        }
        let gossip = self.gossip_keys();
        fresh
            .into_iter()
            .filter(|id| !gossip.contains(id))
            .collect()
    }

    /// Reports 2.x-only peers that joined or expired.
    pub(crate) fn update_compat(&self, now: Instant, peers: &[Peer], expired: &[(i64, String)]) {
        let gossip = self.gossip_keys();
        let mut announced = lock(&self.announced_compat);
        for peer in peers {
            if self.is_settled(now, peer)
                && !gossip.contains(&peer.session_id)
                && announced.insert(peer.session_id)
            {
                self.emit(DiscoveryEvent::Joined(view::peer_view(
                    peer,
                    &Select::first(EVENT_CHANNELS),
                )));
            }
        }
        for (key, name) in expired {
            // A peer announced by its heartbeat before gossip knew it (a slow
            // start on a busy machine) and known to gossip since: gossip
            // reports how it ends (left or failed), not its heartbeats.
            if announced.remove(key) && !gossip.contains(key) {
                self.emit(DiscoveryEvent::Failed {
                    key: *key,
                    name: name.clone(),
                });
            }
        }
    }

    /// Every member known (live or recently gone), without this node. A
    /// member relayed from another site replaces what gossip remembers of
    /// it here if gossip no longer hears it (it moved), and only then.
    pub(crate) fn members(&self, compat_peers: &[&Peer], select: &Select<'_>) -> Vec<MemberView> {
        let mut out = Vec::new();
        let mut keys = HashSet::new();
        if let Some(d) = &self.discovery {
            let relayed: Vec<relay::Entry> = lock(&d.relays).members().cloned().collect();
            let relayed_keys: HashSet<i64> = relayed.iter().map(|e| e.key).collect();
            let mut bridges = Vec::new();
            {
                let gossip = lock(&d.gossip);
                for member in gossip.members() {
                    let live = matches!(member.state(), MemberState::Alive | MemberState::Suspect);
                    if !live && relayed_keys.contains(&member.key()) {
                        continue;
                    }
                    keys.insert(member.key());
                    if let Some(info) = member.info().filter(|_| (select.member)(member.key())) {
                        out.push(view::member_view(member, info, select));
                    }
                }
                for entry in &relayed {
                    if !keys.contains(&entry.key) {
                        bridges.push(gossip.member(entry.bridge).map(Member::address));
                    } else {
                        bridges.push(None);
                    }
                }
            }
            for (entry, bridge) in relayed.iter().zip(bridges) {
                if let Some(bridge) = bridge {
                    keys.insert(entry.key);
                    if (select.member)(entry.key) {
                        out.push(view::relayed_view(entry, bridge, select));
                    }
                }
            }
        }
        let announced = lock(&self.announced_compat);
        for peer in compat_peers {
            if !keys.contains(&peer.session_id)
                && announced.contains(&peer.session_id)
                && (select.member)(peer.session_id)
            {
                out.push(view::peer_view(peer, select));
            }
        }
        out
    }

    /// The address of this node's discovery socket.
    pub(crate) fn local_address(&self) -> Option<SocketAddr> {
        self.discovery.as_ref()?.socket.local_addr().ok()
    }

    /// Stops gossiping: tells the fleet we leave, at once, and ends the
    /// event streams.
    pub(crate) fn leave(&self) {
        if let Some(d) = &self.discovery {
            let mut gossip = lock(&d.gossip);
            gossip.leave();
            // Straight through the file descriptor: this may run while the
            // runtime shuts down, when tokio's readiness can't be relied on.
            let socket = socket2::SockRef::from(&*d.socket);
            while let Some(t) = gossip.poll_transmit() {
                let to = match t.destination {
                    Destination::Multicast => SocketAddr::V4(d.group),
                    Destination::Unicast(addr) => addr,
                };
                let sealed = d.seal(&t.payload, &t.destination);
                if let Err(e) = socket.send_to(&sealed, &to.into()) {
                    tracing::debug!(%to, "leave not sent: {e}");
                }
            }
        }
        lock(&self.events).take();
    }
}

impl DiscoveryState {
    /// The gossip protocol's counters.
    pub(crate) fn stats(&self) -> gossip::GossipStats {
        lock(&self.gossip).stats().clone()
    }

    /// The port of the discovery socket.
    pub(crate) fn local_port(&self) -> Option<u16> {
        self.socket.local_addr().ok().map(|a| a.port())
    }

    pub(crate) fn new(
        socket: UdpSocket,
        group: SocketAddrV4,
        info: MemberInfo,
        heartbeat: Duration,
        seeds: &[SocketAddr],
        sealers: Option<(Sealer, Sealer)>,
    ) -> std::io::Result<Self> {
        let port = socket.local_addr()?.port();
        let mut config = GossipConfig::for_heartbeat(heartbeat);
        config.seed = rand_seed();
        let mut gossip = Gossip::new(Instant::now(), info, port, config);
        for seed in seeds {
            gossip.add_seed(*seed);
        }
        // Bounded: a burst beyond this is dropped like the network would.
        let inbound = Queue::new(INBOUND_CAPACITY, QueuePolicy::DropNewest);
        Ok(Self {
            gossip: Mutex::new(gossip),
            socket: Arc::new(socket),
            group,
            inbound,
            pending: Mutex::new(HashMap::new()),
            changed: Notify::new(),
            sealers: sealers.map(|(m, u)| (Mutex::new(m), Mutex::new(u))),
            relays: Mutex::new(Relays::new(relay::RelayConfig::default())),
            relaying: Mutex::new(Relaying::default()),
        })
    }

    /// Replaces the members this node relays; they are sent at once. Each
    /// must fit one datagram: a member too large loses its types' schemas
    /// (tools can't decode its messages then, the rest holds), and one still
    /// too large is left out; beyond what a node takes from one bridge
    /// ([`relay::RelayConfig::max_per_bridge`]) the rest is left out. Both are
    /// said, here and once.
    pub(crate) fn relay(&self, members: Vec<RelayedMember>) {
        let most = relay::RelayConfig::default().max_per_bridge;
        if members.len() > most {
            tracing::warn!(
                members = members.len(),
                "relaying {most} members only: other nodes take no more from one bridge"
            );
        }
        let mut fitted = Vec::with_capacity(members.len().min(most));
        for mut member in members.into_iter().take(most) {
            let mut len = encoded_len(&member);
            if len > MAX_CHUNK {
                for channel in &mut member.info.channels {
                    if let Some(t) = &mut channel.message_type {
                        t.schema = Vec::new();
                    }
                }
                len = encoded_len(&member);
            }
            if len > MAX_CHUNK {
                tracing::warn!(
                    member = %member.info.name,
                    bytes = len,
                    "a relayed member's state does not fit one datagram; not relayed"
                );
                continue;
            }
            fitted.push((member, len));
        }
        let mut relaying = lock(&self.relaying);
        relaying.due = (!fitted.is_empty() || !relaying.members.is_empty()).then(Instant::now);
        relaying.members = fitted;
        drop(relaying);
        self.changed.notify_one();
    }

    /// Whether this node holds members that `bridge` relays.
    pub(crate) fn relayed_from(&self, bridge: i64) -> bool {
        lock(&self.relays).members().any(|e| e.bridge == bridge)
    }

    /// The relay table's counters.
    pub(crate) fn relay_stats(&self) -> relay::RelayStats {
        lock(&self.relays).stats().clone()
    }

    /// Takes a list of relayed members, if it comes from a live member's
    /// confirmed discovery address (the bridge): what a stranger could
    /// make others believe this way is what it could by joining.
    fn handle_relayed(&self, inner: &Inner, from: SocketAddr, datagram: &[u8]) {
        let relayed = match Message::decode(datagram) {
            Ok(Message::Relayed(r)) => r,
            Ok(_) => return,
            Err(e) => return inner.counters.drop_discovery(&e, from),
        };
        let Relayed { sender, members } = relayed;
        let gossip = lock(&self.gossip);
        if sender == gossip.key() {
            // Our own list, back by multicast.
            return;
        }
        // Heard itself (not only through others), from this address, and
        // nobody else claiming its session.
        let trusted = gossip.member(sender).is_some_and(|m| {
            m.address() == from
                && m.last_heard().is_some()
                && m.contested_by().is_none()
                && m.info().is_some()
                && matches!(m.state(), MemberState::Alive | MemberState::Suspect)
        });
        if !trusted {
            drop(gossip);
            return inner.counters.drop_relay(from, sender);
        }
        let mut heard: HashSet<i64> = gossip
            .members()
            .filter(|m| matches!(m.state(), MemberState::Alive | MemberState::Suspect))
            .map(Member::key)
            .collect();
        heard.insert(gossip.key());
        drop(gossip);
        lock(&self.relays).handle(Instant::now(), sender, members, |k| heard.contains(&k));
    }

    /// Sends what this node relays (if anything) within
    /// [`RELAY_AFTER_JOIN`]: a node that just joined learns the other
    /// sites' members a moment after it learned this one, instead of at
    /// the next [`relay::REFRESH`]. The moment lets it take this node for
    /// a member first, which a relayed list needs.
    fn relay_soon(&self) {
        let mut relaying = lock(&self.relaying);
        if relaying.members.is_empty() {
            return;
        }
        let soon = Instant::now() + RELAY_AFTER_JOIN;
        relaying.due = Some(relaying.due.map_or(soon, |due| due.min(soon)));
    }

    /// The relayed-member datagrams due now, if any.
    fn relayed_due(&self, now: Instant) -> Vec<Vec<u8>> {
        let mut relaying = lock(&self.relaying);
        if relaying.due.is_none_or(|due| due > now) {
            return Vec::new();
        }
        relaying.due = (!relaying.members.is_empty()).then(|| now + relay::REFRESH);
        let sender = lock(&self.gossip).key();
        let mut out = Vec::new();
        let mut batch: Vec<RelayedMember> = Vec::new();
        let mut size = 0;
        for (member, len) in &relaying.members {
            let len = *len;
            if size + len > MAX_CHUNK {
                let members = std::mem::take(&mut batch);
                out.push(Message::Relayed(Relayed { sender, members }).encode());
                size = 0;
            }
            size += len;
            batch.push(member.clone());
        }
        if !batch.is_empty() {
            out.push(
                Message::Relayed(Relayed {
                    sender,
                    members: batch,
                })
                .encode(),
            );
        }
        out
    }

    fn next_wake(&self) -> Option<Instant> {
        let gossip = lock(&self.gossip).poll_timeout();
        let relays = lock(&self.relays).poll_timeout();
        let relaying = lock(&self.relaying).due;
        [gossip, relays, relaying].into_iter().flatten().min()
    }

    /// A datagram of gossip as it goes out: sealed if discovery has a key,
    /// untouched otherwise.
    fn seal<'p>(&self, payload: &'p [u8], to: &Destination) -> Cow<'p, [u8]> {
        let sealer = match (&self.sealers, to) {
            (None, _) => return Cow::Borrowed(payload),
            (Some((multicast, _)), Destination::Multicast) => multicast,
            (Some((_, unicast)), _) => unicast,
        };
        Cow::Owned(lock(sealer).seal(payload, unix_ms()).to_vec())
    }

    /// Sends what gossip wants sent and reports its events.
    async fn flush(&self, fleet: &Fleet) {
        let (mut transmits, mut events) = {
            let mut gossip = lock(&self.gossip);
            let transmits: Vec<_> = std::iter::from_fn(|| gossip.poll_transmit()).collect();
            let mut events = Vec::new();
            let mut relays = lock(&self.relays);
            let mut joined = false;
            while let Some(event) = gossip.poll_event() {
                // A bridge that goes takes its relayed members with it; a
                // member heard here directly is no longer a relayed one.
                match &event {
                    gossip::Event::Failed { key, .. } | gossip::Event::Left { key, .. } => {
                        relays.bridge_gone(*key);
                    }
                    gossip::Event::Joined { key, .. } => {
                        relays.heard_directly(*key);
                        joined = true;
                    }
                    _ => {}
                }
                if let Some(e) = view::event_of(&gossip, event) {
                    events.push(e);
                }
            }
            drop(relays);
            drop(gossip);
            if joined {
                self.relay_soon();
            }
            (transmits, events)
        };
        events.extend(self.relay_events());
        transmits.extend(self.relayed_due(Instant::now()).into_iter().map(|payload| {
            gossip::Transmit {
                destination: Destination::Multicast,
                payload,
            }
        }));
        for t in transmits {
            let to = match t.destination {
                Destination::Multicast => SocketAddr::V4(self.group),
                Destination::Unicast(addr) => addr,
            };
            let sealed = self.seal(&t.payload, &t.destination);
            if let Err(e) = self.socket.send_to(&sealed, to).await {
                tracing::debug!(%to, "discovery send failed: {e}");
            }
        }
        for event in events {
            fleet.emit(event);
        }
    }
}

impl DiscoveryState {
    /// Notes that a datagram of `source` left the inbound queue.
    fn taken(&self, source: SocketAddr) {
        let mut pending = lock(&self.pending);
        if let Some(held) = pending.get_mut(&source) {
            *held = held.saturating_sub(1);
            if *held == 0 {
                pending.remove(&source);
            }
        }
    }
    /// The relay table's events, as the fleet reports them.
    fn relay_events(&self) -> Vec<DiscoveryEvent> {
        // The relay table is not held while the gossip table is taken
        // (the lock order is gossip, then relays).
        let raw: Vec<(gossip::Event, Option<relay::Entry>)> = {
            let mut relays = lock(&self.relays);
            let mut raw = Vec::new();
            while let Some(event) = relays.poll_event() {
                let entry = match &event {
                    gossip::Event::Joined { key, .. } => relays.member(*key).cloned(),
                    _ => None,
                };
                raw.push((event, entry));
            }
            raw
        };
        raw.into_iter()
            .filter_map(|(event, entry)| match (event, entry) {
                (gossip::Event::Joined { .. }, Some(entry)) => {
                    let bridge = self.bridge_address(entry.bridge)?;
                    Some(DiscoveryEvent::Joined(view::relayed_view(
                        &entry,
                        bridge,
                        &Select::first(EVENT_CHANNELS),
                    )))
                }
                (gossip::Event::Joined { .. }, None) => None,
                (other, _) => view::plain_event_of(other),
            })
            .collect()
    }

    /// Where a bridge speaks from (its gossip address).
    fn bridge_address(&self, bridge: i64) -> Option<SocketAddr> {
        lock(&self.gossip).member(bridge).map(Member::address)
    }
}

/// Runs discovery until the node stops.
pub(crate) async fn discovery_loop(inner: Arc<Inner>) {
    let Some(d) = inner.fleet.discovery.as_ref() else {
        return;
    };
    let mut buf = vec![0u8; 65536];
    d.flush(&inner.fleet).await;
    // Changes are applied at the next digest tick, so a burst of them (a
    // node subscribing 100 channels) is one new version, not a hundred.
    let mut dirty = false;
    loop {
        let wake = d.next_wake();
        let timer = async {
            match wake {
                Some(at) => tokio::time::sleep_until(at.into()).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = timer => {
                if std::mem::take(&mut dirty) {
                    let info = inner.local_info();
                    lock(&d.gossip).set_info(info);
                }
                let now = Instant::now();
                lock(&d.gossip).handle_timeout(now);
                lock(&d.relays).handle_timeout(now);
            }
            received = d.socket.recv_from(&mut buf) => match received {
                Ok((len, from)) => {
                    // Multicast gossip was opened by the receive loop; this
                    // is opened here, in the buffer it was received into.
                    if let Some(gossip) = inner.unseal_discovery(&mut buf[..len], from) {
                        handle(&inner, d, from, Via::Unicast, &buf[gossip]);
                    }
                }
                Err(e) => {
                    tracing::debug!("discovery receive failed: {e}");
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
            },
            received = d.inbound.recv() => match received {
                Some((from, datagram)) => {
                    d.taken(from);
                    handle(&inner, d, from, Via::Multicast, &datagram)
                }
                None => return,
            },
            _ = d.changed.notified() => dirty = true,
        }
        d.flush(&inner.fleet).await;
    }
}

/// Hands an opened gossip datagram to the protocol.
fn handle(inner: &Inner, d: &DiscoveryState, from: SocketAddr, via: Via, datagram: &[u8]) {
    if Message::is_relayed(datagram) {
        return d.handle_relayed(inner, from, datagram);
    }
    let result = lock(&d.gossip).handle_datagram(Instant::now(), from, via, datagram);
    if let Err(e) = result {
        inner.counters.drop_discovery(&e, from);
    }
}

/// The bytes a relayed member takes in a datagram.
fn encoded_len(member: &RelayedMember) -> usize {
    postcard::experimental::serialized_size(member).unwrap_or(usize::MAX)
}

/// Unique enough per process and start: gossip only needs its phases spread.
fn rand_seed() -> u64 {
    let t = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    t ^ (u64::from(std::process::id()) << 32)
}

/// Milliseconds since the Unix epoch, now.
pub(crate) fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

/// The host's name, for the fleet view.
pub(crate) fn host_name() -> String {
    gethostname::gethostname().to_string_lossy().into_owned()
}

/// The discovery group's address for `port`.
pub(crate) fn group(port: u16) -> SocketAddrV4 {
    SocketAddrV4::new(crate::group_for(DISCOVERY_CHANNEL), port)
}

#[cfg(test)]
mod tests {
    use super::*;
    use pulicast_discovery::compat::ChannelAnnouncement;

    fn peer(id: i64, at: Instant) -> Peer {
        Peer {
            name: format!("fake{id}"),
            session_id: id,
            address: SocketAddr::from(([127, 0, 0, 1], 1000 + id as u16)),
            channels: vec![
                ChannelAnnouncement {
                    name: "x".into(),
                    period_ns: 0,
                    is_published: true,
                    is_subscribed: false,
                };
                3000
            ],
            first_seen: at,
            last_seen: at,
            period: Duration::from_millis(100),
        }
    }

    /// What a 2.x heartbeat costs must not grow with every peer's channels:
    /// a settled peer is announced (its channels copied) once, and every
    /// later heartbeat finds nothing new to copy. (Each heartbeat copied
    /// every peer's channel list before, and 200 fake peers took a core.)
    #[test]
    fn a_settled_2x_peer_is_copied_once() {
        let fleet = Fleet::new(None);
        let mut events = fleet.subscribe();
        let t0 = Instant::now();
        let now = t0 + COMPAT_GRACE;
        let peers: Vec<Peer> = (0..200).map(|id| peer(id, t0)).collect();
        let settled: Vec<i64> = peers.iter().map(|p| p.session_id).collect();
        assert_eq!(fleet.unannounced_compat(&settled).len(), 200);
        fleet.update_compat(now, &peers, &[]);
        for _ in 0..1000 {
            assert!(fleet.unannounced_compat(&settled).is_empty());
        }
        let mut joined = 0;
        while let Ok(e) = events.try_recv() {
            joined += usize::from(matches!(e, DiscoveryEvent::Joined(_)));
        }
        assert_eq!(joined, 200);
    }
}

//! Pulicast 2.x liveness: the `__nodes` heartbeat.
//!
//! A 2.x node publishes a `pulicast_node` message on the `__nodes` channel once
//! per heartbeat period (100 ms by default). It carries the node's name, a 64-bit
//! session id and the full list of the node's channels. A node that misses three
//! periods is considered gone. [`Membership`] implements exactly that rule for
//! any number of peers; the byte encoding of [`Heartbeat`] lives in the `pulicast`
//! crate's wire module, next to the other ZCM messages.
//!
//! # Driving a [`Membership`]
//!
//! 1. Feed every decoded heartbeat with [`Membership::handle_heartbeat`].
//! 2. Call [`Membership::handle_timeout`] at (or after) the instant
//!    [`Membership::poll_timeout`] returns, to expire silent peers.
//! 3. Drain [`Membership::poll_event`] after either call.
//!
//! Nothing here reads the clock: `now` always comes from the caller, so tests can
//! run a whole fleet on a fake clock.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

/// The channel on which 2.x nodes announce themselves.
pub const NODES_CHANNEL: &str = "__nodes";

/// How many heartbeat periods may pass silently before a peer is forgotten.
pub const MISSED_HEARTBEATS: u32 = 3;

/// The heartbeat periods peers honour: announced periods outside this range
/// are clamped, so a hostile or
/// buggy peer can neither make itself immortal nor flap in and out.
pub const PERIOD_RANGE: (Duration, Duration) = (Duration::from_millis(10), Duration::from_secs(10));

/// Pending events beyond this are dropped oldest-first, so a membership nobody
/// drains stays bounded.
const MAX_PENDING_EVENTS: usize = 1024;

/// One channel as listed in a heartbeat.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct ChannelAnnouncement {
    /// Fully resolved channel name, e.g. `rover1/pose`.
    pub name: String,
    /// Observed publishing period in nanoseconds, 0 if unknown or not published.
    pub period_ns: i64,
    /// The node publishes on this channel.
    pub is_published: bool,
    /// The node subscribes to this channel.
    pub is_subscribed: bool,
}

/// The content of one `pulicast_node` heartbeat.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct Heartbeat {
    /// The node's name (free text, not unique).
    pub name: String,
    /// The node's session id, unique per node run.
    pub session_id: i64,
    /// Every channel the node publishes or subscribes, `__nodes` included.
    pub channels: Vec<ChannelAnnouncement>,
}

impl Heartbeat {
    /// The heartbeat period the node announces for its `__nodes` channel, if any.
    ///
    /// A 2.x node's very first heartbeat lists `__nodes` as not yet published
    /// but already carries the period, so the flag is not required.
    pub fn announced_period(&self) -> Option<Duration> {
        self.channels
            .iter()
            .find(|c| c.name == NODES_CHANNEL)
            .and_then(|c| u64::try_from(c.period_ns).ok())
            .filter(|ns| *ns > 0)
            .map(Duration::from_nanos)
    }
}

/// A live peer as known from its heartbeats.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Peer {
    /// The node's name.
    pub name: String,
    /// The node's session id.
    pub session_id: i64,
    /// Source address of its latest heartbeat.
    pub address: SocketAddr,
    /// Channels from its latest heartbeat.
    pub channels: Vec<ChannelAnnouncement>,
    /// When its first heartbeat arrived.
    pub first_seen: Instant,
    /// When its latest heartbeat arrived.
    pub last_seen: Instant,
    /// The heartbeat period used to judge its liveness.
    pub period: Duration,
}

impl Peer {
    /// The instant after which the peer counts as gone unless it is heard again.
    pub fn deadline(&self) -> Instant {
        self.last_seen + self.period * MISSED_HEARTBEATS
    }

    /// Names of the channels the peer publishes.
    pub fn publishes(&self) -> impl Iterator<Item = &str> {
        self.channels
            .iter()
            .filter(|c| c.is_published)
            .map(|c| c.name.as_str())
    }

    /// Names of the channels the peer subscribes.
    pub fn subscribes(&self) -> impl Iterator<Item = &str> {
        self.channels
            .iter()
            .filter(|c| c.is_subscribed)
            .map(|c| c.name.as_str())
    }
}

/// A change in membership.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum Event {
    /// A session was heard for the first time.
    Joined {
        /// Its session id.
        session_id: i64,
        /// Its name.
        name: String,
        /// Where its heartbeat came from.
        address: SocketAddr,
    },
    /// A session missed [`MISSED_HEARTBEATS`] periods and was forgotten.
    Expired {
        /// Its session id.
        session_id: i64,
        /// Its name.
        name: String,
    },
    /// A known session announced itself from another address or under another
    /// name. Honest nodes never do that; the newer announcement is kept.
    Suspicious {
        /// The session id concerned.
        session_id: i64,
        /// What changed, for a person to read.
        what: String,
    },
    /// A heartbeat was ignored because the table is full: in peers, or in
    /// bytes (a known peer then keeps its previous channel list).
    Rejected {
        /// The session id that was not admitted.
        session_id: i64,
    },
    /// A peer was dropped to make room, in bytes, for a smaller one.
    Evicted {
        /// Its session id.
        session_id: i64,
        /// Its name.
        name: String,
        /// What its entry held in memory.
        bytes: usize,
    },
}

/// The set of live peers, kept by the 2.x heartbeat rule. See the module docs
/// for the call order.
#[derive(Debug)]
pub struct Membership {
    peers: HashMap<i64, Peer>,
    default_period: Duration,
    capacity: usize,
    max_bytes: usize,
    /// The sum of `costs`.
    bytes: usize,
    /// Each peer's [`peer_cost`], kept so that making room never walks
    /// every peer's channels again.
    costs: HashMap<i64, usize>,
    /// Which peer each address speaks for.
    by_address: HashMap<SocketAddr, i64>,
    events: VecDeque<Event>,
    /// See [`Membership::generation`].
    generation: u64,
    /// The session behind each of the latest generations, oldest first
    /// (at most [`CHANGE_LOG`]): see [`Membership::changed_since`].
    changes: VecDeque<i64>,
}

/// How many of the latest changes [`Membership::changed_since`] can name.
pub const CHANGE_LOG: usize = 4096;

/// Most bytes the peer table holds by default ([`Membership::max_bytes`]).
pub const MAX_BYTES: usize = 16 << 20;

/// About how many bytes a peer's entry holds in memory: the byte bound
/// counts this, so heartbeats that are small on the wire and large decoded
/// (short channel names) can't grow memory without bound.
pub fn peer_cost(name: &str, channels: &[ChannelAnnouncement]) -> usize {
    std::mem::size_of::<Peer>()
        + crate::heap_bytes(name.len())
        + crate::heap_bytes(std::mem::size_of_val(channels))
        + channels
            .iter()
            .map(|c| crate::heap_bytes(c.name.capacity()))
            .sum::<usize>()
}

impl Membership {
    /// A table that judges peers who announce no period by `default_period` and
    /// admits at most 4096 peers.
    pub fn new(default_period: Duration) -> Self {
        Self::with_capacity(default_period, 4096)
    }

    /// Like [`Membership::new`] with a different bound on the number of peers.
    pub fn with_capacity(default_period: Duration, capacity: usize) -> Self {
        Self {
            peers: HashMap::new(),
            default_period,
            capacity,
            max_bytes: MAX_BYTES,
            bytes: 0,
            costs: HashMap::new(),
            by_address: HashMap::new(),
            events: VecDeque::new(),
            generation: 0,
            changes: VecDeque::new(),
        }
    }

    /// Bounds what the table holds in memory ([`peer_cost`] summed over the
    /// peers). A heartbeat that does not fit makes room by dropping larger
    /// peers, largest first ([`Event::Evicted`]); if there are none, it is
    /// refused ([`Event::Rejected`]).
    pub fn max_bytes(mut self, bytes: usize) -> Self {
        self.max_bytes = bytes;
        self
    }

    /// A number that changes whenever a peer joins, goes or announces other
    /// channels: what is derived from the peers' channels needs working
    /// out again only then, not on every heartbeat.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// The sessions that joined, went or announced other channels since
    /// [`Membership::generation`] was `generation`, oldest first (one may
    /// come more than once), so that what is derived from the table is
    /// worked out again for them alone. `None` when more changed than the
    /// last [`CHANGE_LOG`] changes, or `generation` is not one of this
    /// table's: the caller then works it out again in full.
    pub fn changed_since(&self, generation: u64) -> Option<impl Iterator<Item = i64> + '_> {
        let count = usize::try_from(self.generation.checked_sub(generation)?).ok()?;
        let skip = self.changes.len().checked_sub(count)?;
        Some(self.changes.iter().skip(skip).copied())
    }

    /// Counts a change of `session_id`'s entry.
    fn changed(&mut self, session_id: i64) {
        self.generation += 1;
        if self.changes.len() >= CHANGE_LOG {
            self.changes.pop_front();
        }
        self.changes.push_back(session_id);
    }

    /// What the table holds in memory now, at most its `max_bytes`.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Makes room for `session_id`'s entry of `cost` bytes (replacing its
    /// old one): drops larger peers, largest first, or nothing and false.
    fn make_room(&mut self, session_id: i64, cost: usize) -> bool {
        let held = self.costs.get(&session_id).copied().unwrap_or(0);
        let needed = (self.bytes - held + cost).saturating_sub(self.max_bytes);
        if needed == 0 {
            return true;
        }
        let mut larger: Vec<(usize, i64)> = self
            .costs
            .iter()
            .filter(|(id, c)| **id != session_id && **c > cost)
            .map(|(id, c)| (*c, *id))
            .collect();
        larger.sort_unstable_by(|a, b| b.cmp(a));
        let Some(victims) = crate::enough_to_free(larger, needed) else {
            return false;
        };
        for victim in victims {
            if let Some(peer) = self.peers.remove(&victim) {
                if self.by_address.get(&peer.address) == Some(&victim) {
                    self.by_address.remove(&peer.address);
                }
                let bytes = self.costs.remove(&victim).unwrap_or(0);
                self.bytes -= bytes;
                self.push_event(Event::Evicted {
                    session_id: victim,
                    name: peer.name,
                    bytes,
                });
            }
        }
        true
    }

    /// Records a heartbeat that arrived at `now` from `address`.
    pub fn handle_heartbeat(&mut self, now: Instant, address: SocketAddr, heartbeat: Heartbeat) {
        let period = heartbeat
            .announced_period()
            .unwrap_or(self.default_period)
            .clamp(PERIOD_RANGE.0, PERIOD_RANGE.1);
        let Heartbeat {
            name,
            session_id,
            mut channels,
        } = heartbeat;
        channels.shrink_to_fit();
        let cost = peer_cost(&name, &channels);

        // A node's heartbeats leave from its one socket: an address that
        // speaks for a live peer does not speak for another session too, so
        // one socket can't fill the table with made-up sessions, neither
        // new ones nor known ones moved onto it. Checked before room is
        // made, so a refused heartbeat evicts nobody.
        let other = self
            .by_address
            .get(&address)
            .copied()
            .filter(|o| *o != session_id && self.peers.contains_key(o));
        if let Some(other) = other {
            self.push_event(Event::Rejected { session_id });
            if self.peers.contains_key(&session_id) {
                let what = format!("heartbeat from {address}, which speaks for session {other}");
                self.push_event(Event::Suspicious { session_id, what });
            }
            return;
        }
        let room = self.peers.contains_key(&session_id) || self.peers.len() < self.capacity;
        let fits = room && self.make_room(session_id, cost);
        if let Some(peer) = self.peers.get_mut(&session_id) {
            let mut changes = Vec::new();
            if peer.address != address {
                changes.push(format!("address {} -> {}", peer.address, address));
            }
            if peer.name != name {
                changes.push(format!("name {:?} -> {:?}", peer.name, name));
            }
            if fits {
                self.bytes = self.bytes - self.costs.insert(session_id, cost).unwrap_or(0) + cost;
                peer.name = name;
                if peer.channels != channels {
                    peer.channels = channels;
                    self.changed(session_id);
                }
            } else {
                self.push_event(Event::Rejected { session_id });
            }
            let Some(peer) = self.peers.get_mut(&session_id) else {
                return;
            };
            if peer.address != address {
                if self.by_address.get(&peer.address) == Some(&session_id) {
                    self.by_address.remove(&peer.address);
                }
                self.by_address.insert(address, session_id);
            }
            peer.address = address;
            peer.last_seen = now;
            peer.period = period;
            if !changes.is_empty() {
                let what = changes.join(", ");
                self.push_event(Event::Suspicious { session_id, what });
            }
            return;
        }

        if self.peers.len() >= self.capacity || !fits {
            self.push_event(Event::Rejected { session_id });
            return;
        }
        self.bytes += cost;
        self.costs.insert(session_id, cost);
        self.by_address.insert(address, session_id);
        self.push_event(Event::Joined {
            session_id,
            name: name.clone(),
            address,
        });
        self.peers.insert(
            session_id,
            Peer {
                name,
                session_id,
                address,
                channels,
                first_seen: now,
                last_seen: now,
                period,
            },
        );
    }

    /// Forgets every peer whose deadline lies before `now`.
    pub fn handle_timeout(&mut self, now: Instant) {
        let expired: Vec<i64> = self
            .peers
            .values()
            .filter(|p| p.deadline() < now)
            .map(|p| p.session_id)
            .collect();
        for session_id in expired {
            if let Some(peer) = self.peers.remove(&session_id) {
                if self.by_address.get(&peer.address) == Some(&session_id) {
                    self.by_address.remove(&peer.address);
                }
                self.bytes -= self.costs.remove(&session_id).unwrap_or(0);
                self.push_event(Event::Expired {
                    session_id,
                    name: peer.name,
                });
            }
        }
    }

    /// The earliest instant at which [`Membership::handle_timeout`] has work to do.
    #[must_use]
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.peers.values().map(Peer::deadline).min()
    }

    /// The next pending event, oldest first.
    #[must_use]
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// The live peers, in no particular order.
    pub fn peers(&self) -> impl Iterator<Item = &Peer> {
        self.peers.values()
    }

    /// One peer by session id.
    pub fn peer(&self, session_id: i64) -> Option<&Peer> {
        self.peers.get(&session_id)
    }

    fn push_event(&mut self, event: Event) {
        match event {
            Event::Joined { session_id, .. }
            | Event::Expired { session_id, .. }
            | Event::Evicted { session_id, .. } => self.changed(session_id),
            Event::Rejected { .. } | Event::Suspicious { .. } => {}
        }
        if self.events.len() >= MAX_PENDING_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(event);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    fn hb(name: &str, session_id: i64, period_ms: Option<i64>) -> Heartbeat {
        let channels = period_ms
            .map(|ms| {
                vec![ChannelAnnouncement {
                    name: NODES_CHANNEL.into(),
                    period_ns: ms * 1_000_000,
                    is_published: true,
                    is_subscribed: false,
                }]
            })
            .unwrap_or_default();
        Heartbeat {
            name: name.into(),
            session_id,
            channels,
        }
    }

    fn drain(m: &mut Membership) -> Vec<Event> {
        std::iter::from_fn(|| m.poll_event()).collect()
    }

    #[test]
    fn join_refresh_and_expire_after_three_missed_periods() {
        let mut m = Membership::new(Duration::from_millis(100));
        let t0 = Instant::now();
        m.handle_heartbeat(t0, addr(1), hb("a", 1, Some(100)));
        assert!(matches!(
            drain(&mut m)[..],
            [Event::Joined { session_id: 1, .. }]
        ));

        m.handle_heartbeat(
            t0 + Duration::from_millis(100),
            addr(1),
            hb("a", 1, Some(100)),
        );
        assert!(drain(&mut m).is_empty(), "a refresh is not an event");
        assert_eq!(
            m.poll_timeout(),
            Some(t0 + Duration::from_millis(400)),
            "deadline is last heartbeat + 3 periods"
        );

        m.handle_timeout(t0 + Duration::from_millis(400));
        assert_eq!(
            m.peers().count(),
            1,
            "exactly at the deadline the peer lives"
        );
        m.handle_timeout(t0 + Duration::from_millis(401));
        assert_eq!(m.peers().count(), 0);
        assert!(matches!(
            drain(&mut m)[..],
            [Event::Expired { session_id: 1, .. }]
        ));
        assert_eq!(m.poll_timeout(), None);
    }

    #[test]
    fn announced_period_governs_liveness_within_bounds() {
        let mut m = Membership::new(Duration::from_millis(100));
        let t0 = Instant::now();
        m.handle_heartbeat(t0, addr(1), hb("slow", 1, Some(1000)));
        m.handle_heartbeat(t0, addr(2), hb("default", 2, None));
        m.handle_heartbeat(t0, addr(3), hb("immortal", 3, Some(i64::MAX / 1_000_000)));
        m.handle_heartbeat(t0, addr(4), hb("negative", 4, Some(-5)));
        let period = |s| m.peer(s).map(|p| p.period);
        assert_eq!(period(1), Some(Duration::from_secs(1)));
        assert_eq!(period(2), Some(Duration::from_millis(100)));
        assert_eq!(period(3), Some(PERIOD_RANGE.1));
        assert_eq!(period(4), Some(Duration::from_millis(100)));
    }

    #[test]
    fn address_or_name_change_is_suspicious_but_kept() {
        let mut m = Membership::new(Duration::from_millis(100));
        let t0 = Instant::now();
        m.handle_heartbeat(t0, addr(1), hb("a", 1, None));
        drain(&mut m);
        m.handle_heartbeat(t0, addr(2), hb("b", 1, None));
        let events = drain(&mut m);
        let [Event::Suspicious {
            session_id: 1,
            what,
        }] = &events[..]
        else {
            panic!("expected one suspicious event, got {events:?}");
        };
        assert!(what.contains("address") && what.contains("name"), "{what}");
        let peer = m.peer(1).expect("still known");
        assert_eq!((peer.name.as_str(), peer.address), ("b", addr(2)));
    }

    #[test]
    fn table_is_bounded() {
        let mut m = Membership::with_capacity(Duration::from_millis(100), 2);
        let t0 = Instant::now();
        for s in 0..5 {
            m.handle_heartbeat(t0, addr(1 + s as u16), hb("x", s, None));
        }
        assert_eq!(m.peers().count(), 2);
        let rejected = drain(&mut m)
            .into_iter()
            .filter(|e| matches!(e, Event::Rejected { .. }))
            .count();
        assert_eq!(rejected, 3);
    }

    #[test]
    fn pending_events_are_bounded() {
        let mut m = Membership::with_capacity(Duration::from_millis(100), usize::MAX);
        let t0 = Instant::now();
        for s in 0..(MAX_PENDING_EVENTS as i64 + 10) {
            m.handle_heartbeat(t0, addr(1 + s as u16), hb("x", s, None));
        }
        assert_eq!(drain(&mut m).len(), MAX_PENDING_EVENTS);
    }

    fn bulky(name: &str, session_id: i64, channels: usize) -> Heartbeat {
        Heartbeat {
            name: name.into(),
            session_id,
            channels: (0..channels)
                .map(|i| ChannelAnnouncement {
                    name: format!("c{i}"),
                    period_ns: 0,
                    is_published: true,
                    is_subscribed: false,
                })
                .collect(),
        }
    }

    /// Fake peers with large channel lists fill the table's bytes, never
    /// past its bound; a real peer with a small list still gets in (a
    /// larger one makes room), and a large newcomer is refused when only
    /// smaller peers are left.
    #[test]
    fn the_table_is_bounded_in_bytes_and_small_peers_get_in() {
        let t0 = Instant::now();
        let limit = 1 << 20;
        let mut m = Membership::new(Duration::from_millis(100)).max_bytes(limit);
        for s in 0..100 {
            m.handle_heartbeat(t0, addr(1000 + s as u16), bulky("fake", 1000 + s, 2000));
            assert!(m.bytes() <= limit, "{} bytes", m.bytes());
        }
        let held = m.peers().count();
        assert!((1..100).contains(&held), "{held} peers");
        let events = drain(&mut m);
        let rejected = events
            .iter()
            .filter(|e| matches!(e, Event::Rejected { .. }))
            .count();
        assert_eq!(rejected, 100 - held);

        m.handle_heartbeat(t0, addr(1), hb("real", 7, Some(100)));
        assert!(m.peer(7).is_some(), "the real peer is refused");
        assert!(m.bytes() <= limit);
        let evicted = drain(&mut m)
            .into_iter()
            .filter(|e| matches!(e, Event::Evicted { .. }))
            .count();
        assert!(evicted <= 1, "{evicted} evicted for one small peer");

        // A newcomer larger than every peer held is refused, and a known
        // peer's list does not grow past the bound either.
        m.handle_heartbeat(t0, addr(2), bulky("huge", 8, 20_000));
        assert!(
            m.peer(8).is_none(),
            "{} bytes, {} peers",
            m.bytes(),
            m.peers().count()
        );
        m.handle_heartbeat(t0, addr(1), bulky("real", 7, 20_000));
        assert_eq!(m.peer(7).map(|p| p.channels.len()), Some(1));
        assert!(m.bytes() <= limit);
        // Expiry gives the bytes back.
        m.handle_timeout(t0 + Duration::from_secs(60));
        assert_eq!((m.peers().count(), m.bytes()), (0, 0));
    }

    /// One socket, many made-up sessions: the first is a peer, the rest are
    /// refused while it lives; once it expires, the address may speak for a
    /// new session (a node restarted on the same port).
    #[test]
    fn one_address_speaks_for_one_peer() {
        let t0 = Instant::now();
        let mut m = Membership::new(Duration::from_millis(100));
        for s in 0..100 {
            m.handle_heartbeat(t0, addr(9), hb("fake", 5000 + s, Some(100)));
        }
        assert_eq!(m.peers().count(), 1);
        let rejected = drain(&mut m)
            .into_iter()
            .filter(|e| matches!(e, Event::Rejected { .. }))
            .count();
        assert_eq!(rejected, 99);
        m.handle_timeout(t0 + Duration::from_secs(1));
        m.handle_heartbeat(
            t0 + Duration::from_secs(1),
            addr(9),
            hb("restarted", 6000, Some(100)),
        );
        assert!(m.peer(6000).is_some());
    }

    /// Two sockets taking turns can't fill the table either: a known
    /// session moved onto an address that speaks for another live one is
    /// refused, and a refused heartbeat evicts nobody.
    #[test]
    fn sessions_moved_between_two_sockets_do_not_fill_the_table() {
        let t0 = Instant::now();
        let mut m = Membership::new(Duration::from_millis(100)).max_bytes(1 << 20);
        m.handle_heartbeat(t0, addr(1), bulky("s1", 1, 2000));
        m.handle_heartbeat(t0, addr(2), hb("s1", 1, Some(100)));
        m.handle_heartbeat(t0, addr(1), hb("s2", 2, Some(100)));
        // s2 moves onto addr(2), which speaks for s1: refused.
        m.handle_heartbeat(t0, addr(2), hb("s2", 2, Some(100)));
        assert_eq!(m.peer(2).map(|p| p.address), Some(addr(1)));
        for s in 3..100 {
            m.handle_heartbeat(t0, addr(1), hb("x", s, Some(100)));
            m.handle_heartbeat(t0, addr(2), hb("x", s, Some(100)));
        }
        assert_eq!(m.peers().count(), 2);
        let evicted = drain(&mut m)
            .into_iter()
            .filter(|e| matches!(e, Event::Evicted { .. }))
            .count();
        assert_eq!(evicted, 0);
    }

    /// What changed since a generation is named session by session, and
    /// past the log's length the answer is "work it all out again".
    #[test]
    fn changes_are_named_since_a_generation() {
        let t0 = Instant::now();
        let mut m = Membership::new(Duration::from_millis(100));
        let start = m.generation();
        assert_eq!(m.changed_since(start).map(Iterator::count), Some(0));
        m.handle_heartbeat(t0, addr(1), hb("a", 1, Some(100)));
        m.handle_heartbeat(t0, addr(2), hb("b", 2, Some(100)));
        let after_join = m.generation();
        // The same heartbeat again changes nothing.
        m.handle_heartbeat(t0, addr(2), hb("b", 2, Some(100)));
        assert_eq!(m.generation(), after_join);
        // Other channels are a change.
        m.handle_heartbeat(t0, addr(2), bulky("b", 2, 3));
        m.handle_timeout(t0 + Duration::from_secs(10));
        let named = |m: &Membership, since| m.changed_since(since).map(Iterator::collect::<Vec<_>>);
        let mut since_start = named(&m, start).unwrap_or_default();
        // The two expiries come in the table's own order.
        since_start[3..].sort_unstable();
        assert_eq!(since_start, [1, 2, 2, 1, 2]);
        assert_eq!(named(&m, after_join).map(|v| v.len()), Some(3));
        assert_eq!(named(&m, m.generation() + 1), None);
        for s in 0..CHANGE_LOG as i64 {
            m.handle_heartbeat(t0, addr(10), hb("c", 100 + s, Some(100)));
            m.handle_timeout(t0 + Duration::from_secs(20 + s as u64));
        }
        assert_eq!(named(&m, after_join), None);
        let recent = m.generation() - 2;
        assert_eq!(named(&m, recent), Some(vec![CHANGE_LOG as i64 + 99; 2]));
    }
}

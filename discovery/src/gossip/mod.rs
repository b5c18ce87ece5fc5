//! Gossip membership: who is alive, and what each member publishes and
//! subscribes, without a name server. See `docs/discovery.md` for the protocol
//! and its message diagram.
//!
//! # Driving a [`Gossip`]
//!
//! [`Gossip`] is a state machine without I/O and without a clock. Its driver
//! (the `pulicast` node) calls, in any order:
//!
//! - [`Gossip::handle_datagram`] for every discovery datagram received, with the
//!   time, the sender's address and whether it came by multicast or unicast;
//! - [`Gossip::handle_timeout`] whenever [`Gossip::poll_timeout`] has passed;
//! - [`Gossip::set_info`] when the local node's channels change, and
//!   [`Gossip::leave`] when it stops;
//!
//! and after each call drains [`Gossip::poll_transmit`] (datagrams to send) and
//! [`Gossip::poll_event`] (membership changes to report).

// This file keeps what the driver sees (the types, the entry points and
// the queues they drain); each file below adds the `Gossip` methods of one
// part of the protocol, so a rule and its bounds are read in one place.
mod digest;
mod failure;
mod rivals;
mod table;
mod transfer;

pub use table::{state_cost, Member};

use std::collections::{HashMap, VecDeque};
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::wire::{self, ChannelInfo, Leave, MemberInfo, MemberKey, Message, WireError};

use digest::{Queued, MAX_MEMBERS_PER_DATAGRAM};
use table::EvictionOrder;

/// Tuning of the protocol. [`GossipConfig::for_heartbeat`] derives all of it from
/// one heartbeat period.
#[derive(Debug, Clone)]
pub struct GossipConfig {
    /// How often a member sends its digest.
    pub digest_interval: Duration,
    /// Silence after which a directly heard member is suspected.
    pub suspect_after: Duration,
    /// Silence after which a directly heard member is declared dead, unless it
    /// refuted the suspicion.
    pub dead_after: Duration,
    /// Silence after which a member known only through others is declared
    /// dead (others vouch for it every `snapshot_interval`).
    pub indirect_dead_after: Duration,
    /// How many digests carry each membership update.
    pub gossip_retransmits: u32,
    /// Most updates piggybacked on one digest.
    pub max_updates_per_digest: usize,
    /// How often members that only hear us by unicast get the member list.
    pub snapshot_interval: Duration,
    /// How long dead and departed members are remembered (so stale gossip
    /// can't resurrect them) before they are forgotten.
    pub forget_after: Duration,
    /// Most members tracked.
    pub max_members: usize,
    /// Most bytes of full state being assembled at once, over all members.
    pub max_assembly_bytes: usize,
    /// Most bytes that the members' full states may hold in memory, decoded
    /// and encoded ([`state_cost`]), over all members. When a new state does
    /// not fit, larger states make room for it (dropped, counted and
    /// reported); if there are none, the new one is refused.
    pub max_state_bytes: usize,
    /// Most bytes one member's full state may hold in memory; a larger one
    /// is refused.
    pub max_member_state_bytes: usize,
    /// Seed for the randomness (digest phase).
    pub seed: u64,
}

impl GossipConfig {
    /// The tuning for a node whose 2.x heartbeat period is `period`: digests
    /// three times per period, suspicion after two silent periods, death after
    /// three, so a crash is seen within three periods plus one digest
    /// interval, while 20 % packet loss (six digests lost in a row: 6e-5) very
    /// rarely even raises a suspicion.
    pub fn for_heartbeat(period: Duration) -> Self {
        Self {
            digest_interval: period / 3,
            suspect_after: period * 2,
            dead_after: period * 3,
            indirect_dead_after: Duration::from_secs(3).max(period * 10),
            gossip_retransmits: 6,
            max_updates_per_digest: 8,
            snapshot_interval: Duration::from_secs(1),
            forget_after: Duration::from_secs(30),
            max_members: 4096,
            max_assembly_bytes: 32 << 20,
            max_state_bytes: 64 << 20,
            max_member_state_bytes: 4 << 20,
            seed: 0,
        }
    }
}

/// Where a datagram goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Destination {
    /// The discovery multicast group.
    Multicast,
    /// One peer's discovery socket.
    Unicast(SocketAddr),
}

/// How a datagram arrived.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Via {
    /// On the discovery multicast group.
    Multicast,
    /// Sent to our discovery socket directly.
    Unicast,
}

/// A datagram to send.
#[derive(Debug, Clone, PartialEq, Eq)]
#[must_use]
pub struct Transmit {
    /// Where to.
    pub destination: Destination,
    /// The datagram.
    pub payload: Vec<u8>,
}

/// A membership change.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Event {
    /// A member's full state arrived for the first time (or after it had
    /// been declared gone).
    Joined {
        /// Its key.
        key: MemberKey,
        /// What it told about itself.
        info: Arc<MemberInfo>,
    },
    /// A member left gracefully.
    Left {
        /// Its key.
        key: MemberKey,
        /// Its name, if known.
        name: String,
    },
    /// A member was declared dead.
    Failed {
        /// Its key.
        key: MemberKey,
        /// Its name, if known.
        name: String,
    },
    /// A member is suspected: silent, but not yet dead.
    Suspected {
        /// Its key.
        key: MemberKey,
        /// Its name, if known.
        name: String,
    },
    /// A suspected member proved alive.
    Recovered {
        /// Its key.
        key: MemberKey,
        /// Its name, if known.
        name: String,
    },
    /// A member announced a channel (or changed its role or type on it).
    ChannelAppeared {
        /// The member.
        key: MemberKey,
        /// The member's name.
        member: String,
        /// The channel.
        channel: ChannelInfo,
    },
    /// A member no longer announces a channel (or announces it differently).
    ChannelDisappeared {
        /// The member.
        key: MemberKey,
        /// The member's name.
        member: String,
        /// The channel as it was.
        channel: ChannelInfo,
    },
    /// Something no honest member does: a session announced from a second
    /// address, a name change within a session, forged state.
    Suspicious {
        /// The session concerned.
        key: MemberKey,
        /// What happened, for a person to read.
        what: String,
    },
}

/// Counters of one [`Gossip`].
#[derive(Debug, Clone, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct GossipStats {
    /// Datagrams handled.
    pub datagrams_in: u64,
    /// Their bytes.
    pub bytes_in: u64,
    /// Datagrams produced (a multicast counts once).
    pub datagrams_out: u64,
    /// Their bytes.
    pub bytes_out: u64,
    /// Datagrams that did not decode.
    pub malformed: u64,
    /// Messages refused as forged or inconsistent.
    pub suspicious: u64,
    /// New members not admitted because the table was full.
    pub rejected: u64,
    /// Times we refuted a suspicion about ourselves.
    pub refutations: u64,
    /// Pull requests sent.
    pub pulls_sent: u64,
    /// Events dropped because nobody drained them.
    pub events_dropped: u64,
    /// Full states refused because they were larger than
    /// `max_member_state_bytes`, or did not fit in `max_state_bytes`.
    pub states_refused: u64,
    /// Full states dropped to make room for a smaller one.
    pub states_evicted: u64,
}

/// Our own member state.
#[derive(Debug)]
struct Local {
    key: MemberKey,
    info: MemberInfo,
    encoded: Arc<Vec<u8>>,
    incarnation: u32,
    version: u32,
    port: u16,
    left: bool,
    /// When we last refuted a claim against us.
    refuted_at: Option<Instant>,
    /// When we last refuted our session being announced from another address.
    refuted_impostor: Option<Instant>,
}

/// Most pending events kept; older ones are dropped (and counted).
const MAX_EVENTS: usize = 4096;

/// The same kind of oddity about the same member is reported at most this often.
const SUSPICIOUS_REPEAT: Duration = Duration::from_secs(10);

/// The gossip state machine of one member. See the module docs for the call
/// order.
#[derive(Debug)]
pub struct Gossip {
    config: GossipConfig,
    me: Local,
    members: HashMap<MemberKey, Member>,
    seeds: Vec<SocketAddr>,
    queue: Vec<Queued>,
    transmits: VecDeque<Transmit>,
    events: VecDeque<Event>,
    next_digest: Instant,
    next_snapshot: Instant,
    replied: HashMap<(SocketAddr, MemberKey), Instant>,
    /// Which session each address last spoke for (checked against
    /// `members` when read; pruned with them).
    owners: HashMap<SocketAddr, MemberKey>,
    eviction: EvictionOrder,
    answered: HashMap<IpAddr, (Instant, usize)>,
    suspicious_seen: HashMap<(MemberKey, &'static str), Instant>,
    suspicious_pruned: Option<Instant>,
    /// The latest time the driver gave us.
    now: Instant,
    assembly_bytes: usize,
    /// The sum of the members' `cost`.
    state_bytes: usize,
    stats: GossipStats,
}

impl Gossip {
    /// A member announcing `info`, whose discovery socket listens on `port`.
    /// Its full state is multicast at once; its first digest follows within
    /// one digest interval (at a random phase, so members started together
    /// don't send in lockstep).
    pub fn new(now: Instant, info: MemberInfo, port: u16, config: GossipConfig) -> Self {
        let key = info.key();
        let mut rng = config.seed ^ (key as u64) ^ 0x9e37_79b9_7f4a_7c15;
        let phase = xorshift(&mut rng) % (config.digest_interval.as_nanos().max(1) as u64);
        let encoded = Arc::new(wire::encode_info(&info));
        let capacity = config.max_members;
        let mut gossip = Self {
            next_digest: now + Duration::from_nanos(phase),
            next_snapshot: now + config.snapshot_interval,
            config,
            me: Local {
                key,
                info,
                encoded,
                incarnation: 0,
                version: 1,
                port,
                left: false,
                refuted_at: None,
                refuted_impostor: None,
            },
            members: HashMap::new(),
            seeds: Vec::new(),
            queue: Vec::new(),
            transmits: VecDeque::new(),
            events: VecDeque::new(),
            replied: HashMap::new(),
            owners: HashMap::new(),
            eviction: EvictionOrder::new(rng ^ 0x2545_f491_4f6c_dd1d, capacity),
            answered: HashMap::new(),
            suspicious_seen: HashMap::new(),
            suspicious_pruned: None,
            now,
            assembly_bytes: 0,
            state_bytes: 0,
            stats: GossipStats::default(),
        };
        gossip.send_full(Destination::Multicast);
        gossip
    }

    /// Our key.
    pub fn key(&self) -> MemberKey {
        self.me.key
    }

    /// Our incarnation.
    pub fn incarnation(&self) -> u32 {
        self.me.incarnation
    }

    /// The version of our full state.
    pub fn version(&self) -> u32 {
        self.me.version
    }

    /// Our full state.
    pub fn info(&self) -> &MemberInfo {
        &self.me.info
    }

    /// The counters.
    pub fn stats(&self) -> &GossipStats {
        &self.stats
    }

    /// What the members' full states hold in memory now ([`state_cost`]),
    /// at most `max_state_bytes`.
    pub fn state_bytes(&self) -> usize {
        self.state_bytes
    }

    /// Every member known, in any state, without ourselves.
    pub fn members(&self) -> impl Iterator<Item = &Member> {
        self.members.values()
    }

    /// One member.
    pub fn member(&self, key: MemberKey) -> Option<&Member> {
        self.members.get(&key)
    }

    /// Adds a peer to send digests to by unicast, for links where multicast
    /// does not pass. Through it we learn the rest of the fleet.
    pub fn add_seed(&mut self, address: SocketAddr) {
        if !self.seeds.contains(&address) {
            self.seeds.push(address);
        }
    }

    /// Replaces our full state; peers learn of it at once (multicast and
    /// unicast peers) and through their pulls.
    pub fn set_info(&mut self, info: MemberInfo) {
        if info == self.me.info || self.me.left {
            return;
        }
        self.me.info = info;
        self.me.encoded = Arc::new(wire::encode_info(&self.me.info));
        self.me.version = self.me.version.wrapping_add(1);
        self.send_full(Destination::Multicast);
        for peer in self.unicast_peers(None) {
            self.send_full(Destination::Unicast(peer));
        }
    }

    /// Announces that we leave. Peers drop us at once; nothing more is sent.
    pub fn leave(&mut self) {
        if self.me.left {
            return;
        }
        self.me.left = true;
        let payload = Message::Leave(Leave {
            sender: self.me.key,
            incarnation: self.me.incarnation,
        })
        .encode();
        let mut destinations = vec![Destination::Multicast];
        destinations.extend(
            self.unicast_peers(None)
                .into_iter()
                .map(Destination::Unicast),
        );
        // Three copies: one lost datagram must not turn a leave into a failure.
        for _ in 0..3 {
            for destination in &destinations {
                self.push_transmit(*destination, payload.clone());
            }
        }
    }

    /// The next instant [`Gossip::handle_timeout`] has work to do.
    #[must_use]
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.me.left {
            return None;
        }
        Some(self.next_digest.min(self.next_snapshot))
    }

    /// The next datagram to send.
    #[must_use]
    pub fn poll_transmit(&mut self) -> Option<Transmit> {
        self.transmits.pop_front()
    }

    /// The next membership change.
    #[must_use]
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// Sends digests, detects failures, retries pulls and forgets old members.
    pub fn handle_timeout(&mut self, now: Instant) {
        self.now = self.now.max(now);
        if self.me.left {
            return;
        }
        if now >= self.next_digest {
            self.send_digest(now);
            self.detect_failures(now);
            self.retry_pulls(now);
            self.forget(now);
            let window = self.config.digest_interval;
            self.replied
                .retain(|_, t| now.saturating_duration_since(*t) < window);
            self.answered
                .retain(|_, (t, _)| now.saturating_duration_since(*t) < Duration::from_secs(1));
            self.next_digest += self.config.digest_interval;
            if self.next_digest <= now {
                // We were not polled for a while: don't send a burst to catch up.
                self.next_digest = now + self.config.digest_interval;
            }
        }
        if now >= self.next_snapshot {
            self.send_snapshots(now);
            self.vouch_for_unicast_peers(now);
            self.next_snapshot = now + self.config.snapshot_interval;
        }
    }

    /// Handles one received discovery datagram.
    pub fn handle_datagram(
        &mut self,
        now: Instant,
        from: SocketAddr,
        via: Via,
        datagram: &[u8],
    ) -> Result<(), WireError> {
        self.now = self.now.max(now);
        self.stats.datagrams_in += 1;
        self.stats.bytes_in += datagram.len() as u64;
        let message = match Message::decode(datagram) {
            Ok(m) => m,
            Err(e) => {
                self.stats.malformed += 1;
                return Err(e);
            }
        };
        if self.me.left {
            return Ok(());
        }
        self.handle_message(now, from, via, message);
        self.report_evicted();
        Ok(())
    }

    fn handle_message(&mut self, now: Instant, from: SocketAddr, via: Via, message: Message) {
        match message {
            Message::Digest(d) => self.on_digest(now, from, via, d),
            Message::Pull(p) => self.on_pull(now, from, p),
            Message::Full(f) => self.on_full(now, from, via, f),
            Message::Leave(l) => self.on_leave(now, from, l),
            Message::Members(list) => {
                for update in list.into_iter().take(MAX_MEMBERS_PER_DATAGRAM) {
                    self.apply_update(now, from, update, true);
                }
            }
            // Not gossip's business: the node hands these to its relay
            // table before they get here.
            Message::Relayed(_) => {}
        }
    }

    fn push_transmit(&mut self, destination: Destination, payload: Vec<u8>) {
        self.stats.datagrams_out += 1;
        self.stats.bytes_out += payload.len() as u64;
        self.transmits.push_back(Transmit {
            destination,
            payload,
        });
    }

    fn push_event(&mut self, event: Event) {
        if self.events.len() >= MAX_EVENTS {
            self.events.pop_front();
            self.stats.events_dropped += 1;
        }
        self.events.push_back(event);
    }

    /// Counts an oddity and reports it, at most once per kind and member
    /// per [`SUSPICIOUS_REPEAT`] (so a forger can't flood the events), in a
    /// table of bounded size; `what` is only written when reported.
    fn suspicious(&mut self, key: MemberKey, kind: &'static str, what: impl FnOnce() -> String) {
        self.stats.suspicious += 1;
        let now = self.now;
        if let Some(t) = self.suspicious_seen.get(&(key, kind)) {
            if now.saturating_duration_since(*t) < SUSPICIOUS_REPEAT {
                return;
            }
        }
        if self.suspicious_seen.len() >= 1024 {
            // Pruned at most once a second, not on every oddity.
            let due = self
                .suspicious_pruned
                .is_none_or(|t| now.saturating_duration_since(t) >= Duration::from_secs(1));
            if due {
                self.suspicious_pruned = Some(now);
                self.suspicious_seen
                    .retain(|_, t| now.saturating_duration_since(*t) < SUSPICIOUS_REPEAT);
            }
            if self.suspicious_seen.len() >= 1024 {
                return;
            }
        }
        self.suspicious_seen.insert((key, kind), now);
        let what = what();
        self.push_event(Event::Suspicious { key, what });
    }
}

fn xorshift(state: &mut u64) -> u64 {
    let mut x = (*state).max(1);
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    *state = x;
    x
}

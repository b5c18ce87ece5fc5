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

use crate::heap_bytes;
use std::collections::{HashMap, HashSet, VecDeque};
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::wire::{
    self, ChannelInfo, Digest, FullPart, Leave, MemberInfo, MemberKey, MemberState, Message, Pull,
    Update, WireError, MAX_CHUNK, MAX_PARTS,
};

/// Tuning of the protocol. [`Config::for_heartbeat`] derives all of it from
/// one heartbeat period.
#[derive(Debug, Clone)]
pub struct Config {
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

impl Config {
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

/// A member as known locally.
#[derive(Debug, Clone)]
pub struct Member {
    key: MemberKey,
    state: MemberState,
    incarnation: u32,
    address: SocketAddr,
    info: Option<Arc<MemberInfo>>,
    encoded: Option<Arc<Vec<u8>>>,
    /// What `info` and `encoded` hold in memory ([`state_cost`]).
    cost: usize,
    info_version: u32,
    last_direct: Option<Instant>,
    /// When `address` itself last spoke for the member (its digest or
    /// multicast full state); unlike `last_direct`, never cleared.
    last_own: Option<Instant>,
    /// Whether `address` came from the member itself (its digest, or its
    /// full state by multicast), not from gossip: from then on, messages in
    /// its name from elsewhere are suspicious.
    address_confirmed: bool,
    last_evidence: Instant,
    state_since: Instant,
    unicast_until: Option<Instant>,
    pull: Option<PendingPull>,
    assembly: Option<Assembly>,
    joined: bool,
    /// Highest state version the member itself announced (digest or
    /// multicast full state); others can't make us take a later one.
    owner_version: u32,
    /// A version whose full state we refused (undecodable, renamed, forged):
    /// not pulled again.
    refused_version: u32,
    /// When we last told it that we hold it dead, so it refutes.
    told_dead: Option<Instant>,
    /// Another address that speaks for the session directly (its digests or
    /// multicast full state), and when it last did: without keys nobody can
    /// tell which is the impostor, so the conflict is shown, not resolved.
    rival: Option<Rival>,
    /// The number of this entry (see [`EvictionOrder`]).
    entry: u64,
    /// When its full state was dropped to make room, if it was.
    state_dropped: Option<Instant>,
}

/// A second address that speaks for a member's session.
#[derive(Debug, Clone, Copy)]
struct Rival {
    address: SocketAddr,
    /// Since when it speaks for the session (without a pause long enough
    /// for it to expire).
    since: Instant,
    /// When it last spoke.
    last: Instant,
    /// The incarnation and version it announced last.
    incarnation: u32,
    version: u32,
}

#[derive(Debug, Clone)]
struct PendingPull {
    version: u32,
    /// Who told us of this version.
    from: SocketAddr,
    sent: Option<Instant>,
    /// Where the last pull went: only answers from there are taken.
    target: Option<SocketAddr>,
    attempts: u32,
}

#[derive(Debug, Clone)]
struct Assembly {
    version: u32,
    parts: Vec<Option<Vec<u8>>>,
    bytes: usize,
    started: Instant,
}

impl Member {
    /// Its key (the first 8 bytes of its session UUID).
    pub fn key(&self) -> MemberKey {
        self.key
    }

    /// Alive, suspect, dead or left.
    pub fn state(&self) -> MemberState {
        self.state
    }

    /// Its incarnation.
    pub fn incarnation(&self) -> u32 {
        self.incarnation
    }

    /// Its discovery socket's address.
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// Its full state, once received.
    pub fn info(&self) -> Option<&Arc<MemberInfo>> {
        self.info.as_ref()
    }

    /// The version of the full state held.
    pub fn info_version(&self) -> u32 {
        self.info_version
    }

    /// When its own digest last arrived, if it ever did (otherwise we know of
    /// it only through other members).
    pub fn last_heard(&self) -> Option<Instant> {
        self.last_direct
    }

    /// Since when it is in its current state.
    pub fn state_since(&self) -> Instant {
        self.state_since
    }

    /// Another address that also speaks for this session, directly and
    /// recently (within `dead_after`): one of the two is an impostor, and
    /// without keys nobody can tell which. The entry stays bound to
    /// [`Member::address`], the first heard, while that one speaks.
    pub fn contested_by(&self) -> Option<SocketAddr> {
        self.rival.map(|r| r.address)
    }

    fn name(&self) -> String {
        self.info
            .as_ref()
            .map(|i| i.name.clone())
            .unwrap_or_default()
    }

    fn is_live(&self) -> bool {
        matches!(self.state, MemberState::Alive | MemberState::Suspect)
    }

    fn heard_directly_within(&self, now: Instant, window: Duration) -> bool {
        self.last_direct
            .is_some_and(|t| now.saturating_duration_since(t) <= window)
    }

    /// Notes that `from`, not the address the member is bound to, spoke for
    /// it at `now`; returns since when it does so without a pause.
    fn hear_rival(
        &mut self,
        now: Instant,
        from: SocketAddr,
        incarnation: u32,
        version: u32,
    ) -> Instant {
        let since = self
            .rival
            .filter(|r| r.address == from)
            .map_or(now, |r| r.since);
        self.rival = Some(Rival {
            address: from,
            since,
            last: now,
            incarnation,
            version,
        });
        since
    }

    fn update(&self) -> Update {
        Update {
            member: self.key,
            incarnation: self.incarnation,
            version: self.info_version,
            state: self.state,
            address: self.address,
        }
    }
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

#[derive(Debug)]
struct Queued {
    update: Update,
    remaining: u32,
}

/// Most pending events kept; older ones are dropped (and counted).
const MAX_EVENTS: usize = 4096;
/// Most members asked for in one pull.
const MAX_WANTS: usize = 64;
/// Most entries in one members list datagram.
const MAX_MEMBERS_PER_DATAGRAM: usize = 1000;
/// How far ahead of the incarnation we know a gossiped claim may be. A
/// member bumps its incarnation once per refutation, so honest claims are
/// close; a forged claim far ahead would otherwise be final.
const INCARNATION_WINDOW: u32 = 16;
/// Bytes of full state we answer one requester (by IP) per second, so a
/// small forged pull can't make us flood someone.
const PULL_ANSWER_BUDGET: usize = 256 * 1024;
/// Most peers we send digests to by unicast.
const MAX_UNICAST_PEERS: usize = 64;
/// How long a full state dropped to make room is not pulled again: then it
/// is, in case the room is back (the attack over).
const STATE_RETRY: Duration = Duration::from_secs(10);
/// The same kind of oddity about the same member is reported at most this often.
const SUSPICIOUS_REPEAT: Duration = Duration::from_secs(10);

/// The gossip state machine of one member. See the module docs for the call
/// order.
#[derive(Debug)]
pub struct Gossip {
    config: Config,
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
    pub fn new(now: Instant, info: MemberInfo, port: u16, config: Config) -> Self {
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
            eviction: EvictionOrder {
                rng: rng ^ 0x2545_f491_4f6c_dd1d,
                capacity,
                ..EvictionOrder::default()
            },
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

    fn on_digest(&mut self, now: Instant, from: SocketAddr, via: Via, d: Digest) {
        if d.sender == self.me.key {
            // Our own digests come back by multicast from our port, never
            // ahead of us. (An impostor on another host that binds our port
            // number and echoes us exactly is seen by the others: two
            // addresses.)
            if from.port() != self.me.port
                || d.incarnation > self.me.incarnation
                || d.version > self.me.version
            {
                self.refute_impostor(now, from);
            }
            return;
        }
        if let Some(other) = self.speaks_for_another(now, from, d.sender) {
            // Reported once for the address's own session, however many
            // made-up keys it announces.
            let fake = d.sender;
            self.suspicious(other, "announces others", || {
                format!("{from} speaks for this session, and announced another one ({fake}) too")
            });
            return;
        }
        let (dead_after, indirect_dead_after) =
            (self.config.dead_after, self.config.indirect_dead_after);
        let Some(member) = self.member_entry(now, Newcomer::own(d.sender, from)) else {
            return;
        };
        if member.address_confirmed && member.address != from {
            // A second voice: keep the first, show the second. Its digests
            // are no evidence for the entry, so neither address keeps the
            // other alive; only if the first has been silent for as long as
            // it takes to declare it dead does the entry follow the second
            // (here, or in `detect_failures`, whichever comes first).
            let bound = member.address;
            let since = member.hear_rival(now, from, d.incarnation, d.version);
            // Followed here only if the member is still live (a member that
            // left or died stays so), its own address has been silent for
            // `dead_after`, and this one has spoken for it for as long as a
            // member known only through others takes to be declared dead.
            let follow = member.is_live()
                && member
                    .last_own
                    .is_none_or(|t| now.saturating_duration_since(t) > dead_after)
                && now.saturating_duration_since(since) >= indirect_dead_after;
            self.suspicious(d.sender, "second address", || {
                format!("session announced from {from}, but it is known at {bound}")
            });
            if !follow {
                return;
            }
            self.follow_rival(now, d.sender);
        }
        self.on_digest_from_owner(now, from, via, d);
    }

    /// Follows a member's rival address instead of declaring it dead: the
    /// address we knew went silent for `dead_after` while the other kept
    /// speaking for the session (the member itself speaking, not a claim by
    /// others), so an impostor heard first that stops can't make the real
    /// member fail. The state is pulled afresh from there, and the old
    /// address is shown as the rival until it expires.
    fn follow_rival(&mut self, now: Instant, key: MemberKey) {
        let Some(member) = self.members.get_mut(&key) else {
            return;
        };
        let Some(rival) = member.rival else {
            return;
        };
        let bound = member.address;
        member.rival = Some(Rival {
            address: bound,
            since: now,
            last: member.last_direct.unwrap_or(now),
            incarnation: member.incarnation,
            version: member.owner_version,
        });
        member.address = rival.address;
        member.address_confirmed = true;
        member.incarnation = rival.incarnation;
        member.owner_version = rival.version;
        member.info_version = 0;
        member.refused_version = 0;
        member.pull = None;
        member.last_direct = Some(rival.last);
        member.last_own = Some(rival.last);
        member.last_evidence = rival.last;
        bind_owner(&mut self.owners, &self.members, rival.address, key);
        self.set_state(now, key, MemberState::Alive);
        self.want_version(key, rival.version, rival.address);
        let to = rival.address;
        self.suspicious(key, "moved", || {
            format!("session moved from {bound}, silent, to {to}, which spoke for it meanwhile")
        });
    }

    /// The live session that `from` speaks for, if not `key`. An honest
    /// discovery socket speaks for one session, so a stranger's socket can't
    /// fill the table with made-up keys; a restarted node on a fixed port is
    /// taken once its old session is silent (or has left).
    fn speaks_for_another(
        &self,
        now: Instant,
        from: SocketAddr,
        key: MemberKey,
    ) -> Option<MemberKey> {
        let other = *self.owners.get(&from)?;
        let member = self.members.get(&other)?;
        let current = other != key
            && member.address == from
            && member.address_confirmed
            && member.is_live()
            && member.heard_directly_within(now, self.config.suspect_after);
        current.then_some(other)
    }

    /// Someone announces our session from another address: we bump our
    /// incarnation (so our own word is the latest) and say so; at most once
    /// per snapshot interval.
    fn refute_impostor(&mut self, now: Instant, from: SocketAddr) {
        self.suspicious(self.me.key, "impostor", || {
            format!(
                "our own session is announced from {from}: an impostor (or a second node with our session id)"
            )
        });
        // Not our full state: a small forged digest must not make us
        // multicast a large one.
        let due = self
            .me
            .refuted_impostor
            .is_none_or(|t| now.saturating_duration_since(t) >= self.config.snapshot_interval);
        if !due {
            return;
        }
        self.me.refuted_impostor = Some(now);
        self.me.incarnation = self.me.incarnation.saturating_add(1);
        self.stats.refutations += 1;
        let me = self.self_update();
        self.enqueue(me);
    }

    /// A digest from the address the member is bound to (or a new member).
    fn on_digest_from_owner(&mut self, now: Instant, from: SocketAddr, via: Via, d: Digest) {
        let dead_after = self.config.dead_after;
        let digest_interval = self.config.digest_interval;
        let Some(member) = self.members.get_mut(&d.sender) else {
            return;
        };
        if member.state == MemberState::Dead && d.incarnation <= member.incarnation {
            // We hold it dead, it says otherwise: tell it, so it refutes (a
            // healed partition would stay split once the gossip died down).
            let due = member
                .told_dead
                .is_none_or(|t| now.saturating_duration_since(t) >= digest_interval);
            if due {
                member.told_dead = Some(now);
                let payload = Message::Members(vec![member.update()]).encode();
                self.push_transmit(Destination::Unicast(from), payload);
            }
            return;
        }
        let first_contact = !member.address_confirmed && member.last_direct.is_none();
        member.owner_version = member.owner_version.max(d.version);
        member.address = from;
        member.address_confirmed = true;
        bind_owner(&mut self.owners, &self.members, from, d.sender);
        let Some(member) = self.members.get_mut(&d.sender) else {
            return;
        };
        member.last_direct = Some(now);
        member.last_own = Some(now);
        member.last_evidence = now;
        if via == Via::Unicast {
            member.unicast_until = Some(now + dead_after);
        }
        let key = d.sender;
        let refuted = d.incarnation > member.incarnation;
        if refuted || (d.incarnation == member.incarnation && member.state == MemberState::Suspect)
        {
            member.incarnation = d.incarnation;
            self.set_state(now, key, MemberState::Alive);
        }
        if refuted || first_contact {
            // Spread the news (a refutation, a newcomer) to those who can't
            // hear it themselves.
            if let Some(member) = self.members.get(&key) {
                let update = member.update();
                self.enqueue(update);
            }
        }
        self.want_version(key, d.version, from);
        for mut update in d
            .updates
            .into_iter()
            .take(self.config.max_updates_per_digest * 2)
        {
            if update.member == key {
                update.address = from;
            }
            self.apply_update(now, from, update, false);
        }
    }

    /// Applies a gossiped fact. `vouch` marks the periodic member lists that
    /// seeds send, which keep members we can't hear alive.
    fn apply_update(&mut self, now: Instant, from: SocketAddr, mut u: Update, vouch: bool) {
        if u.member == self.me.key {
            let against = matches!(
                u.state,
                MemberState::Suspect | MemberState::Dead | MemberState::Left
            );
            // A claim about our current incarnation may be an honest
            // mistake; one about the next was never true (forged), but
            // others may believe it, so it is refuted too. Either at most
            // once per digest interval: a datagram of claims at N, N+1, ...
            // must not run the incarnation up (others accept at most
            // INCARNATION_WINDOW ahead of what they know). Claims further
            // ahead are ignored by everyone.
            let claim = u.incarnation == self.me.incarnation
                || u.incarnation == self.me.incarnation.saturating_add(1);
            let due = self
                .me
                .refuted_at
                .is_none_or(|t| now.saturating_duration_since(t) >= self.config.digest_interval);
            if against && claim && due {
                self.me.refuted_at = Some(now);
                self.me.incarnation = u.incarnation.saturating_add(1);
                self.stats.refutations += 1;
                let me = self.self_update();
                self.enqueue(me);
            }
            return;
        }
        if u.address.ip().is_unspecified() {
            u.address = SocketAddr::new(from.ip(), u.address.port());
        }
        let known = self.members.contains_key(&u.member);
        let suspect_after = self.config.suspect_after;
        if !known && !matches!(u.state, MemberState::Alive | MemberState::Suspect) {
            return;
        }
        let Some(member) = self.member_entry(now, Newcomer::relayed(u.member, u.address)) else {
            return;
        };
        if !known {
            member.incarnation = u.incarnation;
            member.state = u.state;
            self.enqueue(u);
            self.want_version(u.member, u.version, from);
            return;
        }
        let direct_recently = member.heard_directly_within(now, suspect_after);
        if u.incarnation > member.incarnation.saturating_add(INCARNATION_WINDOW) {
            self.stats.suspicious += 1;
            return;
        }
        let newer = u.incarnation > member.incarnation;
        let same = u.incarnation == member.incarnation;
        if !member.address_confirmed {
            member.address = u.address;
        }
        let key = u.member;
        match u.state {
            MemberState::Alive if newer => {
                member.incarnation = u.incarnation;
                member.last_evidence = now;
                if !direct_recently {
                    // Alive, but not to our ears: our direct path to it is
                    // gone, so follow what others hear instead of suspecting
                    // it again every `suspect_after`.
                    member.last_direct = None;
                }
                self.set_state(now, key, MemberState::Alive);
                self.enqueue(u);
            }
            MemberState::Alive
                if same
                    && (vouch
                        || member.last_direct.is_none()
                        || member.state == MemberState::Suspect) =>
            {
                // Someone hears it (or, for members we never heard, still
                // lists it): that is evidence, and it clears a suspicion.
                member.last_evidence = now;
                if member.state == MemberState::Suspect {
                    if !direct_recently {
                        member.last_direct = None;
                    }
                    self.set_state(now, key, MemberState::Alive);
                }
            }
            MemberState::Suspect if (newer || same) && direct_recently => {
                // We hear it: vouch for it, so the suspicious peer recovers it
                // without waiting for a refutation.
                let vouch = Update {
                    state: MemberState::Alive,
                    ..member.update()
                };
                self.enqueue(vouch);
            }
            MemberState::Dead if (newer || same) && direct_recently => {
                // A death is final for its incarnation; only the member can
                // undo it, so pass the claim on until it reaches the member.
                self.enqueue(u);
            }
            MemberState::Suspect | MemberState::Dead if newer || same => {
                let current = member.state;
                let escalates = newer
                    || current == MemberState::Alive
                    || (current == MemberState::Suspect && u.state == MemberState::Dead);
                if escalates && current != MemberState::Left {
                    member.incarnation = u.incarnation;
                    self.set_state(now, key, u.state);
                    self.enqueue(u);
                }
            }
            MemberState::Left if (newer || same) && direct_recently => {
                // Only a member ends its own membership (its `Leave`, which
                // we would have heard too); said by others about a member we
                // hear, it is false, whoever relays it.
                self.stats.suspicious += 1;
            }
            MemberState::Left if (newer || same) && member.state != MemberState::Left => {
                member.incarnation = u.incarnation;
                self.set_state(now, key, MemberState::Left);
                self.enqueue(u);
            }
            _ => {}
        }
        self.want_version(key, u.version, from);
    }

    fn on_pull(&mut self, now: Instant, from: SocketAddr, pull: Pull) {
        for (key, version) in pull.wants.into_iter().take(MAX_WANTS) {
            // One answer per requester and member per digest interval: a pull
            // is small and full state is big, so unbounded answers would let
            // anyone amplify traffic.
            let recent = self
                .replied
                .get(&(from, key))
                .is_some_and(|t| now.saturating_duration_since(*t) < self.config.digest_interval);
            if recent {
                continue;
            }
            let size = if key == self.me.key {
                self.me.encoded.len()
            } else {
                self.members
                    .get(&key)
                    .and_then(|m| m.encoded.as_ref())
                    .map_or(0, |e| e.len())
            };
            if !self.spend_answer_budget(now, from.ip(), size) {
                continue;
            }
            if key == self.me.key {
                self.replied.insert((from, key), now);
                self.send_full(Destination::Unicast(from));
                continue;
            }
            let Some(member) = self.members.get(&key) else {
                continue;
            };
            let Some(encoded) = member.encoded.clone() else {
                continue;
            };
            if member.info_version < version || !member.is_live() {
                continue;
            }
            let (incarnation, held) = (member.incarnation, member.info_version);
            self.replied.insert((from, key), now);
            self.send_parts(Destination::Unicast(from), key, incarnation, held, &encoded);
        }
    }

    /// Charges `bytes` of answers to `requester`; false if over its budget.
    fn spend_answer_budget(&mut self, now: Instant, requester: IpAddr, bytes: usize) -> bool {
        let (since, spent) = self.answered.entry(requester).or_insert((now, 0));
        if now.saturating_duration_since(*since) >= Duration::from_secs(1) {
            *since = now;
            *spent = 0;
        }
        if *spent + bytes > PULL_ANSWER_BUDGET {
            return false;
        }
        *spent += bytes;
        true
    }

    fn on_full(&mut self, now: Instant, from: SocketAddr, via: Via, f: FullPart) {
        if f.member == self.me.key
            || f.parts == 0
            || f.parts > MAX_PARTS
            || f.part >= f.parts
            || f.chunk.len() > MAX_CHUNK
        {
            if f.member != self.me.key {
                self.stats.malformed += 1;
            }
            return;
        }
        let max_assembly = self.config.max_assembly_bytes;
        if via == Via::Multicast {
            if let Some(other) = self.speaks_for_another(now, from, f.member) {
                let fake = f.member;
                self.suspicious(other, "announces others", || {
                    format!("{from} speaks for this session, and multicast the state of another one ({fake}) too")
                });
                return;
            }
            // Bound below, unless the session is known at another address.
            let elsewhere = self
                .members
                .get(&f.member)
                .is_some_and(|m| m.address_confirmed && m.address != from);
            if !elsewhere {
                bind_owner(&mut self.owners, &self.members, from, f.member);
            }
        }
        let newcomer = match via {
            Via::Multicast => Newcomer::own(f.member, from),
            Via::Unicast => Newcomer::relayed(f.member, from),
        };
        let Some(member) = entry(
            &mut self.members,
            &mut self.stats,
            (&mut self.state_bytes, &mut self.assembly_bytes),
            &mut self.eviction,
            now,
            newcomer,
        ) else {
            return;
        };
        // Only the owner multicasts its full state (others answer pulls by
        // unicast), so a multicast part tells where the owner is.
        if via == Via::Multicast && member.address_confirmed && member.address != from {
            member.hear_rival(now, from, f.incarnation, f.version);
            let bound = member.address;
            self.suspicious(f.member, "second address", || {
                format!("full state multicast from {from}, but the session is at {bound}")
            });
            return;
        }
        if via == Via::Unicast {
            // By unicast we only take what we asked for, from whom we asked,
            // and, for members we hear, no version they never announced.
            let asked = member
                .pull
                .as_ref()
                .is_some_and(|p| p.target == Some(from) && p.version == f.version);
            let announced = !member.address_confirmed || f.version <= member.owner_version;
            if !asked || !announced {
                self.stats.suspicious += 1;
                return;
            }
        }
        if via == Via::Multicast {
            member.owner_version = member.owner_version.max(f.version);
            member.address = from;
            member.address_confirmed = true;

            // Heard from the member itself: watch it directly from now on, even
            // if it dies before its first digest reaches us.
            member.last_direct = Some(now);
            member.last_own = Some(now);
            member.last_evidence = now;
        }
        let assembly_bytes = &mut self.assembly_bytes;
        if f.version <= member.info_version && member.info.is_some() {
            return;
        }
        // Only a strictly newer version restarts an assembly, so stray parts
        // of other versions can't keep a big state from completing.
        let restart = member
            .assembly
            .as_ref()
            .is_none_or(|a| a.version < f.version);
        if restart {
            if let Some(old) = member.assembly.take() {
                *assembly_bytes -= old.bytes;
            }
            if member.assembly.is_none() {
                member.assembly = Some(Assembly {
                    version: f.version,
                    parts: vec![None; usize::from(f.parts)],
                    bytes: 0,
                    started: now,
                });
            }
        }
        let Some(assembly) = member.assembly.as_mut() else {
            return;
        };
        if assembly.version != f.version || assembly.parts.len() != usize::from(f.parts) {
            return;
        }
        let slot = &mut assembly.parts[usize::from(f.part)];
        if slot.is_some() {
            return;
        }
        if *assembly_bytes + f.chunk.len() > max_assembly {
            // Over budget: this part is dropped and pulled again later.
            return;
        }
        *assembly_bytes += f.chunk.len();
        assembly.bytes += f.chunk.len();
        *slot = Some(f.chunk);
        if assembly.parts.iter().any(Option::is_none) {
            return;
        }
        let Some(done) = member.assembly.take() else {
            return;
        };
        *assembly_bytes -= done.bytes;
        let bytes: Vec<u8> = done.parts.into_iter().flatten().flatten().collect();
        self.accept_info(f.member, done.version, bytes);
    }

    fn accept_info(&mut self, key: MemberKey, version: u32, bytes: Vec<u8>) {
        // Refused before decoding when its channels alone would not fit.
        let most = self.config.max_member_state_bytes / std::mem::size_of::<ChannelInfo>();
        let decoded = match wire::channel_count(&bytes) {
            Ok(n) if n > most => {
                if let Some(member) = self.members.get_mut(&key) {
                    member.pull = None;
                    member.refused_version = member.refused_version.max(version);
                }
                self.stats.states_refused += 1;
                let what = format!(
                    "full state refused: {n} channels would hold more than {} bytes",
                    self.config.max_member_state_bytes
                );
                self.suspicious(key, "state too large", move || what);
                return;
            }
            _ => wire::decode_info(&bytes),
        };
        let Some(member) = self.members.get_mut(&key) else {
            return;
        };
        // Whatever happens below, this version is settled: no more pulls.
        member.pull = None;
        let refuse =
            |member: &mut Member| member.refused_version = member.refused_version.max(version);
        let info = match decoded {
            Ok(info) => info,
            Err(_) => {
                refuse(member);
                self.stats.malformed += 1;
                return;
            }
        };
        if info.key() != key {
            refuse(member);
            let what = format!("full state of {key} carries session of {}", info.key());
            self.suspicious(key, "wrong session", move || what);
            return;
        }
        let renamed = member
            .info
            .as_ref()
            .filter(|old| old.name != info.name || old.session != info.session)
            .map(|old| old.name.clone());
        if let Some(old_name) = renamed {
            refuse(member);
            let what = format!(
                "name changed within the session: {old_name:?} -> {:?}",
                info.name
            );
            self.suspicious(key, "renamed", move || what);
            return;
        }
        // Decoding grows the channel list by doubling: give back the spare.
        let mut info = info;
        info.channels.shrink_to_fit();
        let cost = state_cost(&info, bytes.len());
        if !self.make_room(key, cost) {
            // Not for good: the room may come back (strangers gone), so
            // the state is pulled again after STATE_RETRY.
            let now = self.now;
            if let Some(member) = self.members.get_mut(&key) {
                refuse(member);
                member.state_dropped = Some(now);
            }
            self.stats.states_refused += 1;
            let what = format!(
                "full state refused: it would hold {cost} bytes, and the member state table \
                 (at most {} bytes, {} per member) has no room",
                self.config.max_state_bytes, self.config.max_member_state_bytes
            );
            self.suspicious(key, "state too large", move || what);
            return;
        }
        let Some(member) = self.members.get_mut(&key) else {
            return;
        };
        self.state_bytes = self.state_bytes - member.cost + cost;
        member.cost = cost;
        // After a (re)join every channel is new to those who follow events.
        let old = if member.joined {
            member.info.take()
        } else {
            None
        };
        let info = Arc::new(info);
        member.info = Some(Arc::clone(&info));
        member.encoded = Some(Arc::new(bytes));
        member.info_version = version;
        let announce_join = !member.joined && member.is_live();
        if announce_join {
            member.joined = true;
        }
        if announce_join {
            self.push_event(Event::Joined {
                key,
                info: Arc::clone(&info),
            });
        }
        let (old_channels, name) = match &old {
            Some(old) => (old.channels.as_slice(), info.name.clone()),
            None => (&[][..], info.name.clone()),
        };
        let identity = |c: &ChannelInfo| {
            (
                c.name.clone(),
                c.publishes,
                c.subscribes,
                c.message_type.clone(),
            )
        };
        let before: HashSet<_> = old_channels.iter().map(identity).collect();
        let after: HashSet<_> = info.channels.iter().map(identity).collect();
        for channel in old_channels
            .iter()
            .filter(|c| !after.contains(&identity(c)))
        {
            self.push_event(Event::ChannelDisappeared {
                key,
                member: name.clone(),
                channel: channel.clone(),
            });
        }
        for channel in info
            .channels
            .iter()
            .filter(|c| !before.contains(&identity(c)))
        {
            self.push_event(Event::ChannelAppeared {
                key,
                member: name.clone(),
                channel: channel.clone(),
            });
        }
    }

    /// Makes room in `max_state_bytes` for `key`'s new state of `cost`
    /// bytes (its old one is replaced), dropping larger states, largest
    /// first: a small state never gives way to a larger one, so a real node
    /// still gets in while strangers fill the table with big ones. False,
    /// and nothing dropped, if it can't fit.
    fn make_room(&mut self, key: MemberKey, cost: usize) -> bool {
        if cost > self.config.max_member_state_bytes {
            return false;
        }
        let held = self.members.get(&key).map_or(0, |m| m.cost);
        let needed = (self.state_bytes - held + cost).saturating_sub(self.config.max_state_bytes);
        if needed == 0 {
            return true;
        }
        // Members that are gone need no state: they go first, then live
        // ones with larger states, largest first. (Not those known only
        // through others as such: a stranger's own sockets would then strip
        // real members behind a seed of their state.)
        let mut candidates: Vec<(bool, usize, MemberKey)> = self
            .members
            .values()
            .filter(|m| m.key != key && m.cost > 0)
            .filter(|m| !m.is_live() || m.cost > cost)
            .map(|m| (!m.is_live(), m.cost, m.key))
            .collect();
        candidates.sort_unstable_by(|a, b| b.cmp(a));
        let candidates = candidates.into_iter().map(|(_, c, k)| (c, k));
        let Some(victims) = crate::enough_to_free(candidates, needed) else {
            return false;
        };
        for victim in victims {
            self.drop_state(victim, cost);
        }
        true
    }

    /// Drops a member's full state to make room; it stays a member, without
    /// channels, and that version is not pulled again for [`STATE_RETRY`].
    fn drop_state(&mut self, key: MemberKey, for_cost: usize) {
        let Some(member) = self.members.get_mut(&key) else {
            return;
        };
        let cost = member.cost;
        member.cost = 0;
        member.encoded = None;
        member.refused_version = member.refused_version.max(member.info_version);
        member.info_version = 0;
        member.state_dropped = Some(self.now);
        // A member that is gone took its channels with it already.
        let live = member.is_live();
        let (name, channels) = match member.info.take() {
            Some(info) if member.joined && live => (info.name.clone(), info.channels.clone()),
            _ => (String::new(), Vec::new()),
        };
        self.state_bytes -= cost;
        self.stats.states_evicted += 1;
        self.eviction.undescribed(key, &self.members);
        if !live {
            return;
        }
        let what = format!(
            "full state of {cost} bytes dropped to make room for one of {for_cost} bytes: the \
             member state table holds at most {} bytes",
            self.config.max_state_bytes
        );
        self.suspicious(key, "state evicted", move || what);
        for channel in channels {
            self.push_event(Event::ChannelDisappeared {
                key,
                member: name.clone(),
                channel,
            });
        }
    }

    fn on_leave(&mut self, now: Instant, from: SocketAddr, leave: Leave) {
        if leave.sender == self.me.key {
            return;
        }
        let Some(member) = self.members.get_mut(&leave.sender) else {
            return;
        };
        if member.rival.is_some_and(|r| r.address == from) {
            // The other voice of a contested session leaves; the one we
            // follow stays. Still a message from a second address: counted.
            member.rival = None;
            self.stats.suspicious += 1;
            return;
        }
        if member.last_direct.is_some() && member.address != from {
            let what = format!(
                "leave for the session sent from {from}, but it is at {}",
                member.address
            );
            self.suspicious(leave.sender, "second address", move || what);
            return;
        }
        if leave.incarnation < member.incarnation || member.state == MemberState::Left {
            return;
        }
        member.incarnation = leave.incarnation;
        let update = Update {
            state: MemberState::Left,
            ..member.update()
        };
        self.set_state(now, leave.sender, MemberState::Left);
        self.enqueue(update);
    }

    /// The member's entry, created if new and there is room.
    fn member_entry(&mut self, now: Instant, newcomer: Newcomer) -> Option<&mut Member> {
        entry(
            &mut self.members,
            &mut self.stats,
            (&mut self.state_bytes, &mut self.assembly_bytes),
            &mut self.eviction,
            now,
            newcomer,
        )
    }

    /// Reports members a full table dropped while they were live: their
    /// channels go, and a person is told why.
    fn report_evicted(&mut self) {
        for (key, name, channels) in std::mem::take(&mut self.eviction.evicted) {
            let max = self.eviction.capacity;
            let who = name.clone();
            self.suspicious(key, "dropped from a full table", || {
                format!(
                    "{who:?}, known only through others, was dropped to make room for a member \
                     heard from its own address: the table holds at most {max}"
                )
            });
            for channel in channels {
                self.push_event(Event::ChannelDisappeared {
                    key,
                    member: name.clone(),
                    channel,
                });
            }
        }
    }

    /// Moves a member to `state`, with the event that goes with it.
    fn set_state(&mut self, now: Instant, key: MemberKey, state: MemberState) {
        let Some(member) = self.members.get_mut(&key) else {
            return;
        };
        let before = member.state;
        if before == state {
            return;
        }
        member.state = state;
        member.state_since = now;
        let name = member.name();
        let joined = member.joined;
        let event = match (before, state) {
            (MemberState::Suspect, MemberState::Alive) => {
                joined.then_some(Event::Recovered { key, name })
            }
            (MemberState::Dead | MemberState::Left, MemberState::Alive) => {
                // Back from the dead with a new incarnation: a new join, with
                // its state pulled afresh (the old one is kept to check it).
                member.joined = false;
                member.last_evidence = now;
                member.info_version = 0;
                member.refused_version = 0;
                None
            }
            (_, MemberState::Suspect) => joined.then_some(Event::Suspected { key, name }),
            (_, MemberState::Dead) => joined.then_some(Event::Failed { key, name }),
            (_, MemberState::Left) => joined.then_some(Event::Left { key, name }),
            _ => None,
        };
        let gone = matches!(state, MemberState::Dead | MemberState::Left);
        if gone {
            member.unicast_until = None;
            member.pull = None;
        }
        if gone {
            self.eviction.gone(key, now, &self.members);
        }
        let Some(member) = self.members.get_mut(&key) else {
            return;
        };
        // A member that goes takes its channels with it.
        let channels = match (&member.info, gone && joined) {
            (Some(info), true) => info.channels.clone(),
            _ => Vec::new(),
        };
        if let Some(event) = event {
            self.push_event(event);
        }
        for channel in channels {
            self.push_event(Event::ChannelDisappeared {
                key,
                member: member_name_of(&self.members, key),
                channel,
            });
        }
    }

    /// Notes that `version` of a member's state exists at `from`; pulls it.
    fn want_version(&mut self, key: MemberKey, version: u32, from: SocketAddr) {
        let Some(member) = self.members.get_mut(&key) else {
            return;
        };
        // Others can't make us want a version the member itself, heard
        // directly, never announced: nobody could give it to us.
        let unannounced = member.address_confirmed && version > member.owner_version;
        if !member.is_live()
            || version <= member.info_version
            || version <= member.refused_version
            || unannounced
        {
            return;
        }
        if let Some(pull) = member.pull.as_mut() {
            if pull.version >= version {
                if pull.version == version {
                    pull.from = from;
                }
                return;
            }
        }
        member.pull = Some(PendingPull {
            version,
            from,
            sent: None,
            target: None,
            attempts: 0,
        });
    }

    fn retry_pulls(&mut self, now: Instant) {
        let retry = self.config.digest_interval * 2;
        let mut by_peer: HashMap<SocketAddr, Vec<(MemberKey, u32)>> = HashMap::new();
        for member in self.members.values_mut() {
            let Some(pull) = member.pull.as_mut() else {
                continue;
            };
            if pull
                .sent
                .is_some_and(|t| now.saturating_duration_since(t) < retry)
            {
                continue;
            }
            // Ask whoever told us; on retries alternate with the member itself.
            let target = if pull.attempts % 2 == 1 && member.address_confirmed {
                member.address
            } else {
                pull.from
            };
            pull.attempts += 1;
            pull.target = Some(target);
            pull.sent = Some(now);
            by_peer
                .entry(target)
                .or_default()
                .push((member.key, pull.version));
        }
        for (peer, wants) in by_peer {
            for chunk in wants.chunks(MAX_WANTS) {
                self.stats.pulls_sent += 1;
                let payload = Message::Pull(Pull {
                    sender: self.me.key,
                    wants: chunk.to_vec(),
                })
                .encode();
                self.push_transmit(Destination::Unicast(peer), payload);
            }
        }
    }

    fn detect_failures(&mut self, now: Instant) {
        let mut changes = Vec::new();
        let mut follow = Vec::new();
        for member in self.members.values() {
            let silent = now.saturating_duration_since(member.last_evidence);
            let direct = member.last_direct.is_some();
            let next = match member.state {
                MemberState::Alive if direct && silent > self.config.suspect_after => {
                    MemberState::Suspect
                }
                MemberState::Suspect
                    if direct
                        && silent > self.config.dead_after
                        && member.rival.is_some_and(|r| {
                            now.saturating_duration_since(r.last) <= self.config.suspect_after
                        }) =>
                {
                    follow.push(member.key);
                    continue;
                }
                MemberState::Suspect if direct && silent > self.config.dead_after => {
                    MemberState::Dead
                }
                MemberState::Alive | MemberState::Suspect
                    if !direct && silent > self.config.indirect_dead_after =>
                {
                    MemberState::Dead
                }
                _ => continue,
            };
            changes.push((member.key, next, direct));
        }
        for key in follow {
            self.follow_rival(now, key);
        }
        for (key, state, direct) in changes {
            self.set_state(now, key, state);
            // Only what we observed ourselves is worth spreading.
            if direct {
                if let Some(member) = self.members.get(&key) {
                    let update = member.update();
                    self.enqueue(update);
                }
            }
        }
        // Incomplete full state that stopped arriving is dropped, and so is
        // a rival address that stopped speaking.
        let stale = self.config.dead_after;
        let mut freed = 0;
        for member in self.members.values_mut() {
            if member
                .rival
                .is_some_and(|r| now.saturating_duration_since(r.last) > stale)
            {
                member.rival = None;
            }
            if member
                .state_dropped
                .is_some_and(|t| now.saturating_duration_since(t) > STATE_RETRY)
            {
                member.state_dropped = None;
                member.refused_version = 0;
            }
            if member
                .assembly
                .as_ref()
                .is_some_and(|a| now.saturating_duration_since(a.started) > stale)
            {
                freed += member.assembly.take().map_or(0, |a| a.bytes);
            }
        }
        self.assembly_bytes -= freed;
    }

    fn forget(&mut self, now: Instant) {
        let forget_after = self.config.forget_after;
        let mut freed = 0;
        let mut released = 0;
        self.members.retain(|_, m| {
            let keep = m.is_live() || now.saturating_duration_since(m.state_since) < forget_after;
            if !keep {
                freed += m.assembly.as_ref().map_or(0, |a| a.bytes);
                released += m.cost;
            }
            keep
        });
        self.assembly_bytes -= freed;
        self.state_bytes -= released;
        prune_owners(&mut self.owners, &self.members);
    }

    fn send_digest(&mut self, now: Instant) {
        let mut updates = Vec::new();
        for queued in self
            .queue
            .iter_mut()
            .take(self.config.max_updates_per_digest)
        {
            updates.push(queued.update);
            queued.remaining -= 1;
        }
        self.queue.retain(|q| q.remaining > 0);
        // Rotate, so a long queue spreads all its updates.
        let sent = updates.len().min(self.queue.len());
        self.queue.rotate_left(sent);
        let payload = Message::Digest(Digest {
            sender: self.me.key,
            incarnation: self.me.incarnation,
            version: self.me.version,
            updates,
        })
        .encode();
        self.push_transmit(Destination::Multicast, payload.clone());
        for peer in self.unicast_peers(Some(now)) {
            self.push_transmit(Destination::Unicast(peer), payload.clone());
        }
    }

    fn send_snapshots(&mut self, now: Instant) {
        let peers = self.unicast_peers(Some(now));
        if peers.is_empty() {
            return;
        }
        let mut list: Vec<Update> = self
            .members
            .values()
            .filter(|m| m.is_live())
            .map(Member::update)
            .collect();
        list.push(self.self_update());
        for chunk in list.chunks(MAX_MEMBERS_PER_DATAGRAM) {
            let payload = Message::Members(chunk.to_vec()).encode();
            for peer in &peers {
                self.push_transmit(Destination::Unicast(*peer), payload.clone());
            }
        }
    }

    /// Members that reach us only by unicast are heard by nobody else: keep
    /// them alive in everyone's view by gossiping that we hear them.
    fn vouch_for_unicast_peers(&mut self, now: Instant) {
        let heard: Vec<Update> = self
            .members
            .values()
            .filter(|m| m.state == MemberState::Alive && m.unicast_until.is_some_and(|t| t >= now))
            .map(Member::update)
            .collect();
        for update in heard {
            self.enqueue(update);
        }
    }

    /// Seeds, and members whose digests reach us by unicast.
    fn unicast_peers(&self, now: Option<Instant>) -> Vec<SocketAddr> {
        let mut peers = self.seeds.clone();
        for member in self.members.values() {
            let current = match (member.unicast_until, now) {
                (Some(until), Some(now)) => until >= now,
                (Some(_), None) => true,
                _ => false,
            };
            if current && !peers.contains(&member.address) && peers.len() < MAX_UNICAST_PEERS {
                peers.push(member.address);
            }
        }
        peers
    }

    fn self_update(&self) -> Update {
        Update {
            member: self.me.key,
            incarnation: self.me.incarnation,
            version: self.me.version,
            state: MemberState::Alive,
            address: SocketAddr::new(IpAddr::from([0, 0, 0, 0]), self.me.port),
        }
    }

    fn send_full(&mut self, destination: Destination) {
        let encoded = Arc::clone(&self.me.encoded);
        let (key, incarnation, version) = (self.me.key, self.me.incarnation, self.me.version);
        self.send_parts(destination, key, incarnation, version, &encoded);
    }

    fn send_parts(
        &mut self,
        destination: Destination,
        member: MemberKey,
        incarnation: u32,
        version: u32,
        encoded: &[u8],
    ) {
        let Some(parts) = wire::full_parts(member, incarnation, version, encoded) else {
            return;
        };
        for part in parts {
            self.push_transmit(destination, Message::Full(part).encode());
        }
    }

    fn enqueue(&mut self, update: Update) {
        self.queue.retain(|q| q.update.member != update.member);
        self.queue.push(Queued {
            update,
            remaining: self.config.gossip_retransmits.max(1),
        });
        // Bounded: the oldest facts go first.
        if self.queue.len() > self.config.max_members {
            self.queue.remove(0);
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

/// About how many bytes a member's full state holds in memory: decoded (its
/// strings, channels and types) and encoded (kept to answer pulls). The
/// byte bounds count this, so a stranger can't grow memory with states that
/// are small on the wire and large decoded (an empty channel name is one
/// byte on the wire and a whole [`ChannelInfo`] in memory).
pub fn state_cost(info: &MemberInfo, encoded: usize) -> usize {
    std::mem::size_of::<Member>() + info.memory_cost() + heap_bytes(encoded)
}

/// Notes that `address` speaks for `key`; the index stays within twice the
/// member table, whatever churn strangers cause.
fn bind_owner(
    owners: &mut HashMap<SocketAddr, MemberKey>,
    members: &HashMap<MemberKey, Member>,
    address: SocketAddr,
    key: MemberKey,
) {
    owners.insert(address, key);
    if owners.len() > 2 * members.len().max(64) {
        prune_owners(owners, members);
    }
}

fn prune_owners(owners: &mut HashMap<SocketAddr, MemberKey>, members: &HashMap<MemberKey, Member>) {
    owners.retain(|address, key| members.get(key).is_some_and(|m| m.address == *address));
}

fn member_name_of(members: &HashMap<MemberKey, Member>, key: MemberKey) -> String {
    members.get(&key).map(Member::name).unwrap_or_default()
}

/// A member's entry in `members`, created if new and there is room; a free
/// function so callers can keep using the other fields of [`Gossip`].
fn entry<'a>(
    members: &'a mut HashMap<MemberKey, Member>,
    stats: &mut GossipStats,
    (state_bytes, assembly_bytes): (&mut usize, &mut usize),
    order: &mut EvictionOrder,
    now: Instant,
    newcomer: Newcomer,
) -> Option<&'a mut Member> {
    let Newcomer { key, address, own } = newcomer;
    if !members.contains_key(&key) {
        if members.len() >= order.capacity {
            // Make room by forgetting the oldest entry that is gone, then the
            // oldest that never gave us its full state (a digest costs a
            // stranger nothing; a full state answers our pulls). Live,
            // described members stay, so a table filled with made-up keys
            // still takes real nodes: their full state arrives within a
            // round trip, while made-up keys keep being replaced.
            // Members known only through others give way only to one
            // heard from its own address: relayed lists, which anyone can
            // make up, can't push out real members.
            let evictable = order
                .oldest_gone(members)
                .or_else(|| order.oldest_undescribed(members))
                .or_else(|| own.then(|| order.oldest_unconfirmed(members)).flatten());
            match evictable {
                Some(old) => {
                    if let Some(old) = members.remove(&old) {
                        *state_bytes -= old.cost;
                        *assembly_bytes -= old.assembly.as_ref().map_or(0, |a| a.bytes);
                        if old.is_live() && old.joined {
                            if let Some(info) = &old.info {
                                order.evicted.push((
                                    old.key,
                                    info.name.clone(),
                                    info.channels.clone(),
                                ));
                            }
                        }
                    }
                }
                None => {
                    stats.rejected += 1;
                    return None;
                }
            }
        }
        members.insert(
            key,
            Member {
                key,
                state: MemberState::Alive,
                incarnation: 0,
                address,
                info: None,
                encoded: None,
                cost: 0,
                info_version: 0,
                last_direct: None,
                last_own: None,
                address_confirmed: false,
                last_evidence: now,
                state_since: now,
                unicast_until: None,
                pull: None,
                assembly: None,
                joined: false,
                owner_version: 0,
                refused_version: 0,
                told_dead: None,
                rival: None,
                entry: order.created,
                state_dropped: None,
            },
        );
        order.created += 1;
        order.undescribed(key, members);
        order.unconfirmed(key, members);
    }
    members.get_mut(&key)
}

/// The members a full table forgets first, oldest first: those gone, then
/// those without full state. Queues checked against the table when read,
/// so making room costs constant time (amortised), not a scan of the
/// table per new key while strangers flood it.
#[derive(Debug, Default)]
struct EvictionOrder {
    /// Members as they went (with when, to tell a later departure).
    gone: VecDeque<(MemberKey, Instant)>,
    /// Members as they were created, or lost their full state, with the
    /// number of their entry: a key forgotten and created again is a new
    /// entry, which an old place in the queue must not evict.
    undescribed: VecDeque<(MemberKey, u64)>,
    /// Members as they were created: those never heard from their own
    /// address (known only from what others say) go after the undescribed.
    unconfirmed: VecDeque<(MemberKey, u64)>,
    /// Entries created so far.
    created: u64,
    rng: u64,
    /// Most members the table holds.
    capacity: usize,
    /// Live members dropped to make room, to be reported (name, channels).
    evicted: Vec<(MemberKey, String, Vec<ChannelInfo>)>,
}

/// A member about to get an entry, and how we learn of it.
#[derive(Debug, Clone, Copy)]
struct Newcomer {
    key: MemberKey,
    address: SocketAddr,
    /// From its own address (its digest, its multicast full state), not
    /// from what others relay.
    own: bool,
}

impl Newcomer {
    fn own(key: MemberKey, address: SocketAddr) -> Self {
        Self {
            key,
            address,
            own: true,
        }
    }

    fn relayed(key: MemberKey, address: SocketAddr) -> Self {
        Self {
            key,
            address,
            own: false,
        }
    }
}

impl EvictionOrder {
    fn gone(&mut self, key: MemberKey, since: Instant, members: &HashMap<MemberKey, Member>) {
        self.gone.push_back((key, since));
        if self.gone.len() > 2 * members.len() + 64 {
            self.gone.retain(|(k, t)| {
                members
                    .get(k)
                    .is_some_and(|m| !m.is_live() && m.state_since == *t)
            });
        }
    }

    fn undescribed(&mut self, key: MemberKey, members: &HashMap<MemberKey, Member>) {
        let Some(entry) = members.get(&key).map(|m| m.entry) else {
            return;
        };
        self.undescribed.push_back((key, entry));
        if self.undescribed.len() > 2 * members.len() + 64 {
            self.undescribed.retain(|(k, e)| {
                members
                    .get(k)
                    .is_some_and(|m| m.entry == *e && m.info.is_none())
            });
        }
    }

    fn oldest_gone(&mut self, members: &HashMap<MemberKey, Member>) -> Option<MemberKey> {
        while let Some((key, since)) = self.gone.pop_front() {
            if members
                .get(&key)
                .is_some_and(|m| !m.is_live() && m.state_since == since)
            {
                return Some(key);
            }
        }
        None
    }

    fn unconfirmed(&mut self, key: MemberKey, members: &HashMap<MemberKey, Member>) {
        let Some(entry) = members.get(&key).map(|m| m.entry) else {
            return;
        };
        self.unconfirmed.push_back((key, entry));
        if self.unconfirmed.len() > 2 * members.len() + 64 {
            self.unconfirmed.retain(|(k, e)| {
                members
                    .get(k)
                    .is_some_and(|m| m.entry == *e && !m.address_confirmed)
            });
        }
    }

    /// One of the older half of the members without full state, at
    /// random: the newest (a real node whose state is on its way) are
    /// spared, and strangers who cycle through more made-up keys than the
    /// table holds don't make every one of them replace the next, as strict
    /// oldest-first would.
    fn oldest_undescribed(&mut self, members: &HashMap<MemberKey, Member>) -> Option<MemberKey> {
        pick_older_half(&mut self.undescribed, &mut self.rng, |key, entry| {
            members
                .get(&key)
                .is_some_and(|m| m.entry == entry && m.info.is_none())
        })
    }

    /// The same among members never heard from their own address: what
    /// anyone can make up by relaying `Members` lists.
    fn oldest_unconfirmed(&mut self, members: &HashMap<MemberKey, Member>) -> Option<MemberKey> {
        pick_older_half(&mut self.unconfirmed, &mut self.rng, |key, entry| {
            members
                .get(&key)
                .is_some_and(|m| m.entry == entry && !m.address_confirmed)
        })
    }
}

/// A random entry of the older half of `queue` that still `holds`, taken
/// out; entries that no longer hold are dropped on the way.
fn pick_older_half(
    queue: &mut VecDeque<(MemberKey, u64)>,
    rng: &mut u64,
    holds: impl Fn(MemberKey, u64) -> bool,
) -> Option<MemberKey> {
    while !queue.is_empty() {
        let half = queue.len().div_ceil(2);
        let i = (xorshift(rng) % half as u64) as usize;
        let (key, entry) = queue.swap_remove_front(i)?;
        if holds(key, entry) {
            return Some(key);
        }
    }
    None
}

fn xorshift(state: &mut u64) -> u64 {
    let mut x = (*state).max(1);
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    *state = x;
    x
}

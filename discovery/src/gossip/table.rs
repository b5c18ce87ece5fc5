//! The member table: an entry per session we know of, what their full
//! states hold in memory, and which entries and states give way when the
//! table is full. Its own room because these bounds are what keeps a
//! stranger from growing our memory, and they must hold whatever the
//! protocol rules in the other files decide.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::rivals::{prune_owners, Rival};
use super::transfer::{Assembly, PendingPull};
use super::{xorshift, Event, Gossip, GossipStats};
use crate::heap_bytes;
use crate::wire::{ChannelInfo, MemberInfo, MemberKey, MemberState, Update};

/// A member as known locally.
#[derive(Debug, Clone)]
pub struct Member {
    pub(super) key: MemberKey,
    pub(super) state: MemberState,
    pub(super) incarnation: u32,
    pub(super) address: SocketAddr,
    pub(super) info: Option<Arc<MemberInfo>>,
    pub(super) encoded: Option<Arc<Vec<u8>>>,
    /// What `info` and `encoded` hold in memory ([`state_cost`]).
    pub(super) cost: usize,
    pub(super) info_version: u32,
    pub(super) last_direct: Option<Instant>,
    /// When `address` itself last spoke for the member (its digest or
    /// multicast full state); unlike `last_direct`, never cleared.
    pub(super) last_own: Option<Instant>,
    /// Whether `address` came from the member itself (its digest, or its
    /// full state by multicast), not from gossip: from then on, messages in
    /// its name from elsewhere are suspicious.
    pub(super) address_confirmed: bool,
    pub(super) last_evidence: Instant,
    pub(super) state_since: Instant,
    pub(super) unicast_until: Option<Instant>,
    pub(super) pull: Option<PendingPull>,
    pub(super) assembly: Option<Assembly>,
    pub(super) joined: bool,
    /// Highest state version the member itself announced (digest or
    /// multicast full state); others can't make us take a later one.
    pub(super) owner_version: u32,
    /// A version whose full state we refused (undecodable, renamed, forged):
    /// not pulled again.
    pub(super) refused_version: u32,
    /// When we last told it that we hold it dead, so it refutes.
    pub(super) told_dead: Option<Instant>,
    /// Another address that speaks for the session directly (its digests or
    /// multicast full state), and when it last did: without keys nobody can
    /// tell which is the impostor, so the conflict is shown, not resolved.
    pub(super) rival: Option<Rival>,
    /// The number of this entry (see [`EvictionOrder`]).
    entry: u64,
    /// When its full state was dropped to make room, if it was.
    pub(super) state_dropped: Option<Instant>,
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

    pub(super) fn name(&self) -> String {
        self.info
            .as_ref()
            .map(|i| i.name.clone())
            .unwrap_or_default()
    }

    pub(super) fn is_live(&self) -> bool {
        matches!(self.state, MemberState::Alive | MemberState::Suspect)
    }

    pub(super) fn heard_directly_within(&self, now: Instant, window: Duration) -> bool {
        self.last_direct
            .is_some_and(|t| now.saturating_duration_since(t) <= window)
    }

    pub(super) fn update(&self) -> Update {
        Update {
            member: self.key,
            incarnation: self.incarnation,
            version: self.info_version,
            state: self.state,
            address: self.address,
        }
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

/// How long a full state dropped to make room is not pulled again: then it
/// is, in case the room is back (the attack over).
pub(super) const STATE_RETRY: Duration = Duration::from_secs(10);

impl Gossip {
    /// The member's entry, created if new and there is room.
    pub(super) fn member_entry(&mut self, now: Instant, newcomer: Newcomer) -> Option<&mut Member> {
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
    pub(super) fn report_evicted(&mut self) {
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

    /// Makes room in `max_state_bytes` for `key`'s new state of `cost`
    /// bytes (its old one is replaced), dropping larger states, largest
    /// first: a small state never gives way to a larger one, so a real node
    /// still gets in while strangers fill the table with big ones. False,
    /// and nothing dropped, if it can't fit.
    pub(super) fn make_room(&mut self, key: MemberKey, cost: usize) -> bool {
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

    pub(super) fn forget(&mut self, now: Instant) {
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
}

pub(super) fn member_name_of(members: &HashMap<MemberKey, Member>, key: MemberKey) -> String {
    members.get(&key).map(Member::name).unwrap_or_default()
}

/// A member's entry in `members`, created if new and there is room; a free
/// function so callers can keep using the other fields of [`Gossip`].
pub(super) fn entry<'a>(
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
pub(super) struct EvictionOrder {
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
pub(super) struct Newcomer {
    key: MemberKey,
    address: SocketAddr,
    /// From its own address (its digest, its multicast full state), not
    /// from what others relay.
    own: bool,
}

impl Newcomer {
    pub(super) fn own(key: MemberKey, address: SocketAddr) -> Self {
        Self {
            key,
            address,
            own: true,
        }
    }

    pub(super) fn relayed(key: MemberKey, address: SocketAddr) -> Self {
        Self {
            key,
            address,
            own: false,
        }
    }
}

impl EvictionOrder {
    /// An empty order for a table of at most `capacity` members, drawing
    /// its random picks from `rng`.
    pub(super) fn new(rng: u64, capacity: usize) -> Self {
        Self {
            rng,
            capacity,
            ..Self::default()
        }
    }

    pub(super) fn gone(
        &mut self,
        key: MemberKey,
        since: Instant,
        members: &HashMap<MemberKey, Member>,
    ) {
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

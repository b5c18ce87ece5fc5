//! Members of other sites, relayed by bridges.
//!
//! A bridge (`puli-bridge`) is an ordinary gossip member of its site that
//! also speaks for the members of other sites, which gossip can't reach
//! (no multicast between the sites). It sends [`Relayed`](crate::wire::Relayed) lists from its
//! discovery socket, each entry refreshing one remote member for
//! [`RelayConfig::lifetime`]; [`Relays`] keeps what they say, as a state machine
//! without I/O and clock, like [`crate::gossip::Gossip`].
//!
//! The rules, which the node's driver completes:
//!
//! - Only a live gossip member, from the address gossip has confirmed for it,
//!   is listened to (the driver checks; [`Relays::handle`] takes its word).
//!   So what a stranger can make others believe through a relay is what it
//!   could already by joining as a member (see the Trust section of
//!   `docs/discovery.md`).
//! - A member heard directly here (a gossip member) is never taken from a
//!   relay, and a relayed one that gossip comes to hear is handed over.
//! - A relayed member belongs to the first bridge that relays it while that
//!   bridge keeps refreshing it; two bridges on one site relaying the same
//!   member don't make it flap.
//! - A member not refreshed for [`RelayConfig::lifetime`] fails, and so do all of a
//!   bridge's members when the bridge fails or leaves
//!   ([`Relays::bridge_gone`]).
//! - The table is bounded in members and in bytes ([`RelayConfig`]); what does not
//!   fit is refused and counted.
//!
//! ```
//! use std::time::{Duration, Instant};
//! use pulicast_discovery::relay::{RelayConfig, Relays};
//! use pulicast_discovery::wire::{MemberInfo, MemberState, RelayedMember};
//!
//! let mut relays = Relays::new(RelayConfig::default());
//! let t0 = Instant::now();
//! let info = MemberInfo {
//!     session: [9; 16], name: "rover".into(), namespace: "rover1".into(),
//!     host: "a".into(), pid: 1, start_time_ms: 0, data_port: 4000, channels: vec![],
//!     config: String::new(),
//!     extensions: Vec::new(),
//! };
//! let member = RelayedMember { info, incarnation: 0, state: MemberState::Alive, site: "a".into() };
//! let bridge = 42;
//! relays.handle(t0, bridge, vec![member], |_| false);
//! assert_eq!(relays.members().count(), 1);
//!
//! // Not refreshed: it fails after the lifetime.
//! relays.handle_timeout(t0 + RelayConfig::default().lifetime);
//! assert_eq!(relays.members().count(), 0);
//! ```

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::gossip::{state_cost, Event};
use crate::wire::{ChannelInfo, MemberInfo, MemberKey, MemberState, RelayedMember};

/// Limits and timing of a [`Relays`] table.
#[derive(Debug, Clone)]
pub struct RelayConfig {
    /// How long one entry keeps a member present. Bridges refresh every
    /// member at least three times within it.
    pub lifetime: Duration,
    /// Most relayed members held, over all bridges.
    pub max_members: usize,
    /// Most bytes their states may hold in memory (as
    /// [`state_cost`] counts them), over all bridges.
    pub max_bytes: usize,
    /// Most entries of one datagram looked at.
    pub max_per_datagram: usize,
    /// Most members one bridge may relay: a member that relays made-up
    /// members can take this share of the table, not all of it.
    pub max_per_bridge: usize,
}

/// Longest site name taken, in bytes; an entry with a longer one is
/// refused.
pub const MAX_SITE_LEN: usize = 64;

impl Default for RelayConfig {
    fn default() -> Self {
        Self {
            lifetime: Duration::from_secs(3),
            max_members: 4096,
            max_bytes: 16 << 20,
            max_per_datagram: 1024,
            max_per_bridge: 2048,
        }
    }
}

/// How often a bridge should resend every member it relays, for the
/// default [`RelayConfig::lifetime`].
pub const REFRESH: Duration = Duration::from_secs(1);

/// Counters of a [`Relays`] table.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct RelayStats {
    /// Entries taken (new members and refreshes).
    pub accepted: u64,
    /// Entries about members heard here directly: ignored.
    pub shadowed: u64,
    /// Entries about a member another bridge relays: ignored.
    pub held_elsewhere: u64,
    /// Entries refused because the table was full (members or bytes).
    pub refused_full: u64,
    /// Entries that no honest bridge sends: about the bridge itself, or
    /// with a site name over [`MAX_SITE_LEN`].
    pub malformed: u64,
    /// Members that ended because nothing refreshed them in time.
    pub expired: u64,
}

/// One relayed member as this node holds it.
#[derive(Debug, Clone)]
pub struct Entry {
    /// Its key.
    pub key: MemberKey,
    /// The bridge that relays it.
    pub bridge: MemberKey,
    /// What it told its site (its `data_port` is the bridge's).
    pub info: Arc<MemberInfo>,
    /// Its incarnation there.
    pub incarnation: u32,
    /// Alive or suspect (ended members are not kept).
    pub state: MemberState,
    /// The site's name.
    pub site: String,
    refreshed: Instant,
    cost: usize,
}

/// The relayed members of every bridge this node hears.
#[derive(Debug)]
pub struct Relays {
    config: RelayConfig,
    entries: HashMap<MemberKey, Entry>,
    /// How many entries each bridge holds.
    per_bridge: HashMap<MemberKey, usize>,
    bytes: usize,
    events: VecDeque<Event>,
    stats: RelayStats,
}

impl Relays {
    /// An empty table.
    pub fn new(config: RelayConfig) -> Self {
        Self {
            config,
            entries: HashMap::new(),
            per_bridge: HashMap::new(),
            bytes: 0,
            events: VecDeque::new(),
            stats: RelayStats::default(),
        }
    }

    /// The members held.
    pub fn members(&self) -> impl Iterator<Item = &Entry> {
        self.entries.values()
    }

    /// One member, if relayed.
    pub fn member(&self, key: MemberKey) -> Option<&Entry> {
        self.entries.get(&key)
    }

    /// The counters.
    pub fn stats(&self) -> &RelayStats {
        &self.stats
    }

    /// Bytes held, as [`RelayConfig::max_bytes`] counts them.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// The next event to report.
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// When [`Relays::handle_timeout`] has work to do next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.entries
            .values()
            .map(|e| e.refreshed + self.config.lifetime)
            .min()
    }

    /// Takes one [`crate::wire::Relayed`] list from `bridge`, a live member
    /// of this site heard from its own address; `is_heard` says whether a
    /// key is a gossip member here (those are never taken from a relay).
    pub fn handle(
        &mut self,
        now: Instant,
        bridge: MemberKey,
        members: Vec<RelayedMember>,
        is_heard: impl Fn(MemberKey) -> bool,
    ) {
        for relayed in members.into_iter().take(self.config.max_per_datagram) {
            self.take(now, bridge, relayed, &is_heard);
        }
    }

    fn take(
        &mut self,
        now: Instant,
        bridge: MemberKey,
        relayed: RelayedMember,
        is_heard: &impl Fn(MemberKey) -> bool,
    ) {
        let key = relayed.info.key();
        if key == bridge || relayed.site.len() > MAX_SITE_LEN {
            self.stats.malformed += 1;
            return;
        }
        if is_heard(key) {
            self.stats.shadowed += 1;
            return;
        }
        if let Some(held) = self.entries.get(&key) {
            // The first bridge keeps it while it refreshes it: another one
            // takes over only once the entry has gone a third of its
            // lifetime unrefreshed (its bridge stopped relaying it).
            let stale = now.saturating_duration_since(held.refreshed) > self.config.lifetime / 3;
            if held.bridge != bridge && !stale {
                self.stats.held_elsewhere += 1;
                return;
            }
        }
        let RelayedMember {
            info,
            incarnation,
            state,
            site,
        } = relayed;
        if matches!(state, MemberState::Dead | MemberState::Left) {
            if self
                .entries
                .get(&key)
                .is_some_and(|held| held.bridge == bridge)
            {
                self.stats.accepted += 1;
                self.end(key, state);
            }
            return;
        }
        match self.entries.get_mut(&key) {
            Some(held) => {
                if held.bridge != bridge {
                    // Taken over from a bridge that stopped refreshing it.
                    if self.per_bridge.get(&bridge).copied().unwrap_or(0)
                        >= self.config.max_per_bridge
                    {
                        self.stats.refused_full += 1;
                        return;
                    }
                    let old = held.bridge;
                    held.bridge = bridge;
                    *self.per_bridge.entry(bridge).or_default() += 1;
                    Self::release_share(&mut self.per_bridge, old);
                }
                self.stats.accepted += 1;
                held.refreshed = now;
                if held.site != site {
                    // The site's name is part of the entry's cost.
                    self.bytes = self.bytes - held.site.capacity() + site.capacity();
                    held.cost = held.cost - held.site.capacity() + site.capacity();
                    held.site = site;
                }
                let was = std::mem::replace(&mut held.state, state);
                held.incarnation = incarnation;
                let name = held.info.name.clone();
                match (was, state) {
                    (MemberState::Alive, MemberState::Suspect) => {
                        self.events.push_back(Event::Suspected { key, name });
                    }
                    (MemberState::Suspect, MemberState::Alive) => {
                        self.events.push_back(Event::Recovered { key, name });
                    }
                    _ => {}
                }
                if *held.info != info {
                    self.replace_info(key, info);
                }
            }
            None => {
                let cost = cost(&info) + site.capacity();
                let share = self.per_bridge.get(&bridge).copied().unwrap_or(0);
                if self.entries.len() >= self.config.max_members
                    || share >= self.config.max_per_bridge
                    || self.bytes + cost > self.config.max_bytes
                {
                    self.stats.refused_full += 1;
                    return;
                }
                self.stats.accepted += 1;
                let info = Arc::new(info);
                self.bytes += cost;
                *self.per_bridge.entry(bridge).or_default() += 1;
                self.entries.insert(
                    key,
                    Entry {
                        key,
                        bridge,
                        info: info.clone(),
                        incarnation,
                        state,
                        site,
                        refreshed: now,
                        cost,
                    },
                );
                self.events.push_back(Event::Joined { key, info });
            }
        }
    }

    /// A held member told something new about itself: its channels' changes
    /// are reported as gossip reports them.
    fn replace_info(&mut self, key: MemberKey, info: MemberInfo) {
        let Some(held) = self.entries.get_mut(&key) else {
            return;
        };
        let new_cost = cost(&info) + held.site.capacity();
        if self.bytes - held.cost + new_cost > self.config.max_bytes {
            // Keep the old state rather than exceed the bound; the member
            // stays present.
            self.stats.refused_full += 1;
            return;
        }
        self.bytes = self.bytes - held.cost + new_cost;
        held.cost = new_cost;
        let old = std::mem::replace(&mut held.info, Arc::new(info));
        let member = held.info.name.clone();
        let before: HashSet<&ChannelInfo> = old.channels.iter().collect();
        let after: HashSet<&ChannelInfo> = held.info.channels.iter().collect();
        for gone in old.channels.iter().filter(|c| !after.contains(c)) {
            self.events.push_back(Event::ChannelDisappeared {
                key,
                member: member.clone(),
                channel: gone.clone(),
            });
        }
        for new in held.info.channels.iter().filter(|c| !before.contains(c)) {
            self.events.push_back(Event::ChannelAppeared {
                key,
                member: member.clone(),
                channel: new.clone(),
            });
        }
    }

    /// A member ends: reported as left or failed, with its channels gone.
    fn end(&mut self, key: MemberKey, how: MemberState) {
        let Some(entry) = self.entries.remove(&key) else {
            return;
        };
        self.bytes -= entry.cost;
        Self::release_share(&mut self.per_bridge, entry.bridge);
        let name = entry.info.name.clone();
        for channel in &entry.info.channels {
            self.events.push_back(Event::ChannelDisappeared {
                key,
                member: name.clone(),
                channel: channel.clone(),
            });
        }
        self.events.push_back(match how {
            MemberState::Left => Event::Left { key, name },
            _ => Event::Failed { key, name },
        });
    }

    /// A bridge failed or left: every member it relayed fails.
    pub fn bridge_gone(&mut self, bridge: MemberKey) {
        let keys: Vec<MemberKey> = self
            .entries
            .values()
            .filter(|e| e.bridge == bridge)
            .map(|e| e.key)
            .collect();
        for key in keys {
            self.end(key, MemberState::Dead);
        }
    }

    /// Gossip now hears `key` directly: the relayed entry, if any, is
    /// dropped without an event (the member did not go anywhere).
    pub fn heard_directly(&mut self, key: MemberKey) {
        if let Some(entry) = self.entries.remove(&key) {
            self.bytes -= entry.cost;
            Self::release_share(&mut self.per_bridge, entry.bridge);
        }
    }

    fn release_share(per_bridge: &mut HashMap<MemberKey, usize>, bridge: MemberKey) {
        if let Some(n) = per_bridge.get_mut(&bridge) {
            *n -= 1;
            if *n == 0 {
                per_bridge.remove(&bridge);
            }
        }
    }

    /// Ends the members nobody refreshed within the lifetime.
    pub fn handle_timeout(&mut self, now: Instant) {
        let lifetime = self.config.lifetime;
        let expired: Vec<MemberKey> = self
            .entries
            .values()
            .filter(|e| now.saturating_duration_since(e.refreshed) >= lifetime)
            .map(|e| e.key)
            .collect();
        for key in expired {
            self.stats.expired += 1;
            self.end(key, MemberState::Dead);
        }
    }
}

fn cost(info: &MemberInfo) -> usize {
    state_cost(info, 0) + std::mem::size_of::<Entry>()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::{Message, Relayed, TypeEncoding, TypeInfo};

    fn member(n: u8, channels: usize) -> RelayedMember {
        RelayedMember {
            info: MemberInfo {
                session: [n; 16],
                name: format!("m{n}"),
                namespace: String::new(),
                host: "far".into(),
                pid: 1,
                start_time_ms: 0,
                data_port: 7000,
                channels: (0..channels)
                    .map(|c| ChannelInfo {
                        name: format!("m{n}/c{c}"),
                        publishes: true,
                        subscribes: false,
                        period_ns: 0,
                        message_type: Some(TypeInfo {
                            encoding: TypeEncoding::Native,
                            name: "T".into(),
                            fingerprint: [1; 8],
                            schema: vec![0; 100],
                        }),
                    })
                    .collect(),
                config: String::new(),
                extensions: Vec::new(),
            },
            incarnation: 0,
            state: MemberState::Alive,
            site: "a".into(),
        }
    }

    fn events(relays: &mut Relays) -> Vec<Event> {
        std::iter::from_fn(|| relays.poll_event()).collect()
    }

    #[test]
    fn a_member_joins_changes_and_fails_with_its_bridge() {
        let mut relays = Relays::new(RelayConfig::default());
        let t0 = Instant::now();
        relays.handle(t0, 1, vec![member(2, 1)], |_| false);
        assert!(matches!(events(&mut relays)[..], [Event::Joined { .. }]));
        let mut more = member(2, 2);
        more.state = MemberState::Suspect;
        relays.handle(t0, 1, vec![more], |_| false);
        let ev = events(&mut relays);
        assert!(matches!(ev[0], Event::Suspected { .. }), "{ev:?}");
        assert!(matches!(ev[1], Event::ChannelAppeared { .. }), "{ev:?}");
        relays.bridge_gone(1);
        let ev = events(&mut relays);
        assert_eq!(ev.len(), 3, "{ev:?}");
        assert!(matches!(ev[2], Event::Failed { .. }));
        assert_eq!(relays.members().count(), 0);
        assert_eq!(relays.bytes(), 0);
    }

    #[test]
    fn a_second_bridge_does_not_take_a_refreshed_member() {
        let mut relays = Relays::new(RelayConfig::default());
        let t0 = Instant::now();
        relays.handle(t0, 1, vec![member(2, 0)], |_| false);
        relays.handle(t0, 3, vec![member(2, 0)], |_| false);
        assert_eq!(relays.member(member(2, 0).info.key()).unwrap().bridge, 1);
        assert_eq!(relays.stats().held_elsewhere, 1);
        // The second bridge's word about its end is not taken either.
        let mut dead = member(2, 0);
        dead.state = MemberState::Dead;
        relays.handle(t0, 3, vec![dead], |_| false);
        assert_eq!(relays.members().count(), 1);
        // Once the first stops refreshing it, the second takes it over
        // without the member failing.
        let later = t0 + RelayConfig::default().lifetime / 2;
        relays.handle(later, 3, vec![member(2, 0)], |_| false);
        assert_eq!(relays.member(member(2, 0).info.key()).unwrap().bridge, 3);
        relays.bridge_gone(1);
        assert_eq!(relays.members().count(), 1);
    }

    #[test]
    fn members_heard_here_and_the_bridge_itself_are_not_taken() {
        let mut relays = Relays::new(RelayConfig::default());
        let t0 = Instant::now();
        let heard = member(2, 0).info.key();
        let bridge = member(4, 0).info.key();
        relays.handle(t0, bridge, vec![member(2, 0), member(4, 0)], |k| k == heard);
        assert_eq!(relays.members().count(), 0);
        assert_eq!(relays.stats().shadowed, 1);
        assert_eq!(relays.stats().malformed, 1);
    }

    /// One datagram from a (member) attacker can't grow the table past its
    /// bound in bytes or members.
    #[test]
    fn the_table_is_bounded_in_members_and_bytes() {
        let config = RelayConfig {
            max_bytes: 200_000,
            max_members: 50,
            max_per_bridge: 40,
            ..RelayConfig::default()
        };
        let mut relays = Relays::new(config);
        let t0 = Instant::now();
        let big: Vec<RelayedMember> = (1..=200).map(|n| member(n, 20)).collect();
        let datagram = Message::Relayed(Relayed {
            sender: 0,
            members: big.clone(),
        })
        .encode();
        assert!(datagram.len() < 1_000_000);
        relays.handle(t0, 0, big, |_| false);
        assert!(relays.bytes() <= 200_000, "{}", relays.bytes());
        assert!(relays.members().count() <= 50);
        assert!(relays.stats().refused_full > 0);
        // Small ones still fit the member bound, and no more; one bridge
        // holds at most its share.
        let small: Vec<RelayedMember> = (201..=255).map(|n| member(n, 0)).collect();
        relays.handle(t0, 0, small.clone(), |_| false);
        assert!(relays.members().count() <= 40);
        relays.handle(t0, 9, small, |_| false);
        assert!(relays.members().count() <= 50);
        // A site name is part of the cost, and a long one is refused.
        let mut long = member(100, 0);
        long.site = "x".repeat(MAX_SITE_LEN + 1);
        let malformed = relays.stats().malformed;
        relays.handle(t0, 7, vec![long], |_| false);
        assert_eq!(relays.stats().malformed, malformed + 1);
    }

    /// Refreshes that change the site name keep the byte count exact, and
    /// every byte is given back when the members go.
    #[test]
    fn bytes_and_shares_are_given_back_exactly() {
        let mut relays = Relays::new(RelayConfig::default());
        let t0 = Instant::now();
        for round in 0..10 {
            let members: Vec<RelayedMember> = (1..=20)
                .map(|n| {
                    let mut m = member(n, round % 3);
                    m.site = "s".repeat(round * 6);
                    m
                })
                .collect();
            relays.handle(t0, 100, members, |_| false);
        }
        assert!(relays.bytes() > 0);
        relays.bridge_gone(100);
        assert_eq!(relays.bytes(), 0);
        assert!(relays.per_bridge.is_empty());
    }

    #[test]
    fn unrefreshed_members_expire_and_a_relayed_leave_is_a_leave() {
        let mut relays = Relays::new(RelayConfig::default());
        let t0 = Instant::now();
        relays.handle(t0, 1, vec![member(2, 0), member(3, 0)], |_| false);
        let later = t0 + Duration::from_secs(2);
        relays.handle(later, 1, vec![member(3, 0)], |_| false);
        events(&mut relays);
        assert_eq!(relays.poll_timeout(), Some(t0 + Duration::from_secs(3)));
        relays.handle_timeout(t0 + Duration::from_secs(3));
        assert!(matches!(events(&mut relays)[..], [Event::Failed { .. }]));
        let mut left = member(3, 0);
        left.state = MemberState::Left;
        relays.handle(later, 1, vec![left], |_| false);
        assert!(matches!(events(&mut relays)[..], [Event::Left { .. }]));
        assert_eq!(relays.stats().expired, 1);
        assert!(relays.poll_timeout().is_none());
    }
}

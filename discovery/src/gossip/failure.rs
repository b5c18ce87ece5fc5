//! Liveness: gossiped claims about members (alive, suspect, dead, left)
//! and our refutations of claims against us, the state changes and events
//! they bring, and the timeouts that suspect silent members and declare
//! them dead. Its own room because these rules decide which claim wins,
//! and only read together do they show that a forged claim can't kill a
//! member we hear.

use std::net::SocketAddr;
use std::time::Instant;

use super::table::{member_name_of, Newcomer, STATE_RETRY};
use super::{Event, Gossip};
use crate::wire::{Leave, MemberKey, MemberState, Update};

/// How far ahead of the incarnation we know a gossiped claim may be. A
/// member bumps its incarnation once per refutation, so honest claims are
/// close; a forged claim far ahead would otherwise be final.
const INCARNATION_WINDOW: u32 = 16;

impl Gossip {
    /// Applies a gossiped fact. `vouch` marks the periodic member lists that
    /// seeds send, which keep members we can't hear alive.
    pub(super) fn apply_update(
        &mut self,
        now: Instant,
        from: SocketAddr,
        mut u: Update,
        vouch: bool,
    ) {
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

    pub(super) fn on_leave(&mut self, now: Instant, from: SocketAddr, leave: Leave) {
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

    /// Moves a member to `state`, with the event that goes with it.
    pub(super) fn set_state(&mut self, now: Instant, key: MemberKey, state: MemberState) {
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

    pub(super) fn detect_failures(&mut self, now: Instant) {
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
}

//! Rival claims to a session: a second address that speaks for a member,
//! an address that speaks for several sessions, our own session announced
//! from elsewhere. Its own room because without keys nobody can tell the
//! impostor from the member: these rules show the conflict and settle it
//! only when one side falls silent, and that policy reads best in one
//! place.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::time::Instant;

use super::table::Member;
use super::Gossip;
use crate::wire::{MemberKey, MemberState};

/// A second address that speaks for a member's session.
#[derive(Debug, Clone, Copy)]
pub(super) struct Rival {
    pub(super) address: SocketAddr,
    /// Since when it speaks for the session (without a pause long enough
    /// for it to expire).
    since: Instant,
    /// When it last spoke.
    pub(super) last: Instant,
    /// The incarnation and version it announced last.
    incarnation: u32,
    version: u32,
}

impl Member {
    /// Notes that `from`, not the address the member is bound to, spoke for
    /// it at `now`; returns since when it does so without a pause.
    pub(super) fn hear_rival(
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
}

impl Gossip {
    /// The live session that `from` speaks for, if not `key`. An honest
    /// discovery socket speaks for one session, so a stranger's socket can't
    /// fill the table with made-up keys; a restarted node on a fixed port is
    /// taken once its old session is silent (or has left).
    pub(super) fn speaks_for_another(
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

    /// Follows a member's rival address instead of declaring it dead: the
    /// address we knew went silent for `dead_after` while the other kept
    /// speaking for the session (the member itself speaking, not a claim by
    /// others), so an impostor heard first that stops can't make the real
    /// member fail. The state is pulled afresh from there, and the old
    /// address is shown as the rival until it expires.
    pub(super) fn follow_rival(&mut self, now: Instant, key: MemberKey) {
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

    /// Someone announces our session from another address: we bump our
    /// incarnation (so our own word is the latest) and say so; at most once
    /// per snapshot interval.
    pub(super) fn refute_impostor(&mut self, now: Instant, from: SocketAddr) {
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
}

/// Notes that `address` speaks for `key`; the index stays within twice the
/// member table, whatever churn strangers cause.
pub(super) fn bind_owner(
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

pub(super) fn prune_owners(
    owners: &mut HashMap<SocketAddr, MemberKey>,
    members: &HashMap<MemberKey, Member>,
) {
    owners.retain(|address, key| members.get(key).is_some_and(|m| m.address == *address));
}

//! The digest round: what we send every digest interval (our incarnation
//! and version, with queued membership updates piggybacked), the member
//! lists for peers that only hear us by unicast, and what we take from the
//! digests of others. Its own room because it is the traffic that flows
//! unasked, the protocol's heartbeat, and the queue that feeds it.

use std::net::{IpAddr, SocketAddr};
use std::time::Instant;

use super::rivals::bind_owner;
use super::table::{Member, Newcomer};
use super::{Destination, Gossip, Via};
use crate::wire::{Digest, MemberState, Message, Update};

#[derive(Debug)]
pub(super) struct Queued {
    update: Update,
    remaining: u32,
}

/// Most entries in one members list datagram.
pub(super) const MAX_MEMBERS_PER_DATAGRAM: usize = 1000;

/// Most peers we send digests to by unicast.
const MAX_UNICAST_PEERS: usize = 64;

impl Gossip {
    pub(super) fn on_digest(&mut self, now: Instant, from: SocketAddr, via: Via, d: Digest) {
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

    pub(super) fn send_digest(&mut self, now: Instant) {
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

    pub(super) fn send_snapshots(&mut self, now: Instant) {
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
    pub(super) fn vouch_for_unicast_peers(&mut self, now: Instant) {
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
    pub(super) fn unicast_peers(&self, now: Option<Instant>) -> Vec<SocketAddr> {
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

    pub(super) fn self_update(&self) -> Update {
        Update {
            member: self.me.key,
            incarnation: self.me.incarnation,
            version: self.me.version,
            state: MemberState::Alive,
            address: SocketAddr::new(IpAddr::from([0, 0, 0, 0]), self.me.port),
        }
    }

    pub(super) fn enqueue(&mut self, update: Update) {
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
}

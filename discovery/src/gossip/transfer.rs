//! Full state transfer: pulls of the versions that digests announce, our
//! answers to the pulls of others, and the assembly of the parts that
//! arrive. Its own room because full state is the one large thing gossip
//! moves, so this is where traffic and memory are bounded against
//! amplification and floods.

use std::collections::{HashMap, HashSet};
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::rivals::bind_owner;
use super::table::{entry, state_cost, Member, Newcomer};
use super::{Destination, Event, Gossip, Via};
use crate::wire::{self, ChannelInfo, FullPart, MemberKey, Message, Pull, MAX_CHUNK, MAX_PARTS};

#[derive(Debug, Clone)]
pub(super) struct PendingPull {
    version: u32,
    /// Who told us of this version.
    from: SocketAddr,
    sent: Option<Instant>,
    /// Where the last pull went: only answers from there are taken.
    target: Option<SocketAddr>,
    attempts: u32,
}

#[derive(Debug, Clone)]
pub(super) struct Assembly {
    version: u32,
    parts: Vec<Option<Vec<u8>>>,
    pub(super) bytes: usize,
    pub(super) started: Instant,
}

/// Most members asked for in one pull.
const MAX_WANTS: usize = 64;

/// Bytes of full state we answer one requester (by IP) per second, so a
/// small forged pull can't make us flood someone.
const PULL_ANSWER_BUDGET: usize = 256 * 1024;

impl Gossip {
    /// Notes that `version` of a member's state exists at `from`; pulls it.
    pub(super) fn want_version(&mut self, key: MemberKey, version: u32, from: SocketAddr) {
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

    pub(super) fn retry_pulls(&mut self, now: Instant) {
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

    pub(super) fn on_pull(&mut self, now: Instant, from: SocketAddr, pull: Pull) {
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

    pub(super) fn on_full(&mut self, now: Instant, from: SocketAddr, via: Via, f: FullPart) {
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

    pub(super) fn send_full(&mut self, destination: Destination) {
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
}

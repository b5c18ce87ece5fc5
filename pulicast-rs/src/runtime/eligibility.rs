//! Which batching channels a Pulicast 2.x node subscribes: it can't read
//! batches, so those channels send one message per datagram. Sans-IO: the
//! runtime hands it the 2.x table, the gossip keys and the time.
//!
//! Kept up to date from what changed, never worked out again from the
//! whole table on a tick: a peer that joins, goes or announces other
//! channels costs a walk of that peer's channels, a session that joins or
//! leaves gossip the same, and a steady fleet costs nothing. Two things
//! walk the whole table once: channels that began batching since the last
//! update (all of them in one walk; only the node's own calls do that),
//! and more changes than the table's log names
//! ([`pulicast_discovery::compat::CHANGE_LOG`]), when a walk costs no more
//! than those changes would.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use pulicast_discovery::compat::{Membership, Peer};

/// One batching channel, as eligibility sees it.
#[derive(Default)]
struct Watched {
    /// The 2.x-only sessions that subscribe it, and when each was first
    /// heard.
    blockers: HashMap<i64, Instant>,
    /// Whether the log said already why it does not batch.
    logged: bool,
    /// Whether `Eligibility::due` holds it.
    queued: bool,
}

/// The batching channels and the 2.x-only sessions that subscribe each.
///
/// Memory: one entry per (batching channel, 2.x-only subscriber) pair, a
/// subset of the subscriptions the 2.x table holds (and bounds in bytes),
/// plus one per batching channel.
pub(crate) struct Eligibility {
    /// This node's own session in the 2.x table, never a blocker.
    own: i64,
    /// How long a blocker is heard before the log speaks of it: a node of
    /// ours whose heartbeat arrives before its gossip looks 2.x-only for a
    /// moment.
    grace: Duration,
    /// The table generation it was brought up to; `None` before the first
    /// update.
    generation: Option<u64>,
    /// The gossip member keys it was brought up to: those are not 2.x-only.
    gossip: HashSet<i64>,
    watched: HashMap<Arc<str>, Watched>,
    /// Per session, the watched channels it blocks.
    by_session: HashMap<i64, Vec<Arc<str>>>,
    /// Watched since the last update, not looked up yet.
    added: Vec<Arc<str>>,
    /// Watched already and watched again (batching turned off and on),
    /// whose flag the caller set from a guess: told again at the next
    /// update.
    again: Vec<Arc<str>>,
    /// When each blocked channel's earliest blocker passes the grace.
    due: BinaryHeap<Reverse<(Instant, Arc<str>)>>,
    /// Peers whose channel lists were walked, ever: what the updates cost.
    walked: u64,
}

impl Eligibility {
    /// Nothing watched yet, for the node whose 2.x session is `own`.
    pub(crate) fn new(own: i64, grace: Duration) -> Self {
        Self {
            own,
            grace,
            generation: None,
            gossip: HashSet::new(),
            watched: HashMap::new(),
            by_session: HashMap::new(),
            added: Vec::new(),
            again: Vec::new(),
            due: BinaryHeap::new(),
            walked: 0,
        }
    }

    /// Starts watching `name`, a channel that began to batch; the next
    /// [`Eligibility::update`] looks it up. A channel watched already
    /// (batching turned off and on) is told again at the next update, and
    /// looked at again for the log.
    pub(crate) fn watch(&mut self, name: &Arc<str>) {
        let watching = self.watched.len();
        match self.watched.get_mut(name) {
            None => {
                self.watched.insert(Arc::clone(name), Watched::default());
                self.added.push(Arc::clone(name));
            }
            Some(watched) => {
                // Its blockers are up to date: only the answer is told.
                if self.again.len() < watching {
                    self.again.push(Arc::clone(name));
                }
                let earliest = watched.blockers.values().min();
                if let Some(first) = earliest.filter(|_| !watched.logged && !watched.queued) {
                    let at = *first + self.grace;
                    watched.queued = true;
                    self.due.push(Reverse((at, Arc::clone(name))));
                }
            }
        }
    }

    /// Brings it up to date with `table` and the gossip member `keys`.
    /// Returns the channels whose answer may have changed, each with
    /// whether a 2.x-only node subscribes it now.
    pub(crate) fn update(
        &mut self,
        table: &Membership,
        keys: HashSet<i64>,
    ) -> Vec<(Arc<str>, bool)> {
        let mut dirty: HashSet<Arc<str>> = self.again.drain(..).collect();
        let changed = self.generation.and_then(|g| table.changed_since(g));
        match changed {
            Some(changed) => {
                let mut touched: HashSet<i64> = changed.collect();
                touched.extend(self.gossip.symmetric_difference(&keys).copied());
                self.gossip = keys;
                for session in touched {
                    self.forget(session, &mut dirty);
                    if let Some(peer) = table.peer(session) {
                        self.learn(peer, None, &mut dirty);
                    }
                }
                if !self.added.is_empty() {
                    let names: HashSet<Arc<str>> = self.added.drain(..).collect();
                    self.walk(table, Some(&names), &mut dirty);
                    dirty.extend(names);
                }
            }
            None => {
                // The first update, or more changed than the log names:
                // everything again, in one walk.
                self.gossip = keys;
                self.by_session.clear();
                self.added.clear();
                for (name, watched) in &mut self.watched {
                    watched.blockers.clear();
                    dirty.insert(Arc::clone(name));
                }
                self.walk(table, None, &mut dirty);
            }
        }
        self.generation = Some(table.generation());
        dirty
            .into_iter()
            .map(|name| {
                let blocked = self
                    .watched
                    .get(&name)
                    .is_some_and(|w| !w.blockers.is_empty());
                (name, blocked)
            })
            .collect()
    }

    /// The blocked channels whose earliest blocker has been heard for the
    /// grace, each with that blocker's session: each channel once ever,
    /// and only while `batching` says it batches (else at the next
    /// [`Eligibility::watch`]).
    pub(crate) fn settled(
        &mut self,
        now: Instant,
        batching: impl Fn(&str) -> bool,
    ) -> Vec<(Arc<str>, i64)> {
        let mut settled = Vec::new();
        while let Some(Reverse((at, _))) = self.due.peek() {
            if *at > now {
                break;
            }
            let Some(Reverse((_, name))) = self.due.pop() else {
                break;
            };
            let Some(watched) = self.watched.get_mut(&name) else {
                continue;
            };
            watched.queued = false;
            if watched.logged {
                continue;
            }
            let earliest = watched.blockers.iter().min_by_key(|(_, first)| **first);
            let Some((&session, &first)) = earliest else {
                continue;
            };
            let at = first + self.grace;
            if at > now {
                watched.queued = true;
                self.due.push(Reverse((at, name)));
            } else if batching(&name) {
                watched.logged = true;
                settled.push((name, session));
            }
        }
        settled
    }

    /// Peers whose channel lists were walked so far.
    #[cfg(test)]
    pub(crate) fn walked(&self) -> u64 {
        self.walked
    }

    /// Whether `peer` counts as 2.x-only: not this node, not a gossip
    /// member.
    fn is_legacy(&self, peer: &Peer) -> bool {
        peer.session_id != self.own && !self.gossip.contains(&peer.session_id)
    }

    /// Walks every 2.x-only peer of the table for the channels `names`
    /// (all watched ones if `None`).
    fn walk(
        &mut self,
        table: &Membership,
        names: Option<&HashSet<Arc<str>>>,
        dirty: &mut HashSet<Arc<str>>,
    ) {
        for peer in table.peers() {
            self.learn(peer, names, dirty);
        }
    }

    /// Records the watched channels (of `names`, if given) that `peer`
    /// subscribes, if it is 2.x-only.
    fn learn(
        &mut self,
        peer: &Peer,
        names: Option<&HashSet<Arc<str>>>,
        dirty: &mut HashSet<Arc<str>>,
    ) {
        if !self.is_legacy(peer) {
            return;
        }
        self.walked += 1;
        for channel in peer.channels.iter().filter(|c| c.is_subscribed) {
            let name = channel.name.as_str();
            if names.is_some_and(|n| !n.contains(name)) {
                continue;
            }
            let Some(name) = self.watched.get_key_value(name).map(|(k, _)| Arc::clone(k)) else {
                continue;
            };
            let Some(watched) = self.watched.get_mut(&name) else {
                continue;
            };
            if watched
                .blockers
                .insert(peer.session_id, peer.first_seen)
                .is_some()
            {
                continue;
            }
            if !watched.logged && !watched.queued {
                watched.queued = true;
                let at = peer.first_seen + self.grace;
                self.due.push(Reverse((at, Arc::clone(&name))));
            }
            self.by_session
                .entry(peer.session_id)
                .or_default()
                .push(Arc::clone(&name));
            dirty.insert(name);
        }
    }

    /// Removes `session` as a blocker of every channel.
    fn forget(&mut self, session: i64, dirty: &mut HashSet<Arc<str>>) {
        let Some(names) = self.by_session.remove(&session) else {
            return;
        };
        for name in names {
            if let Some(watched) = self.watched.get_mut(&name) {
                watched.blockers.remove(&session);
            }
            dirty.insert(name);
        }
    }
}

#[cfg(test)]
mod tests {
    use std::net::SocketAddr;

    use pulicast_discovery::compat::{ChannelAnnouncement, Heartbeat, CHANGE_LOG};

    use super::*;

    const GRACE: Duration = Duration::from_millis(250);

    fn heartbeat(session_id: i64, subscribes: &[String]) -> Heartbeat {
        Heartbeat {
            name: format!("node{session_id}"),
            session_id,
            channels: subscribes
                .iter()
                .map(|name| ChannelAnnouncement {
                    name: name.clone(),
                    period_ns: 100_000_000,
                    is_published: false,
                    is_subscribed: true,
                })
                .collect(),
        }
    }

    fn address(session: i64) -> SocketAddr {
        let port = u16::try_from(1000 + session).unwrap_or(u16::MAX);
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    fn names(prefix: &str, count: usize) -> Vec<String> {
        (0..count).map(|i| format!("{prefix}/{i}")).collect()
    }

    fn blocked(changes: &[(Arc<str>, bool)], name: &str) -> Option<bool> {
        changes.iter().find(|(n, _)| &**n == name).map(|(_, b)| *b)
    }

    /// A table of 2,000 2.x peers with 20 subscriptions each: after the
    /// first look, a change of one peer walks that peer alone, however
    /// large the table, and a steady table walks nothing.
    #[test]
    fn a_change_costs_the_peers_that_changed() {
        let t0 = Instant::now();
        let mut table = Membership::new(Duration::from_secs(1));
        for s in 1..=2000 {
            table.handle_heartbeat(t0, address(s), heartbeat(s, &names(&format!("n{s}"), 20)));
        }
        table.handle_heartbeat(t0, address(0), heartbeat(0, &["arm/pose".into()]));
        let mut view = Eligibility::new(-1, GRACE);
        view.watch(&Arc::from("arm/pose"));
        view.watch(&Arc::from("n7/3"));
        let first = view.update(&table, HashSet::new());
        assert_eq!(blocked(&first, "arm/pose"), Some(true));
        assert_eq!(blocked(&first, "n7/3"), Some(true));
        let after_first = view.walked();
        assert_eq!(after_first, 2001);

        assert!(view.update(&table, HashSet::new()).is_empty());
        assert_eq!(view.walked(), after_first);

        // Peer 7 stops subscribing n7/3; peer 9 starts.
        table.handle_heartbeat(t0, address(7), heartbeat(7, &names("n7", 2)));
        let mut nine = names("n9", 20);
        nine.push("n7/3".into());
        table.handle_heartbeat(t0, address(9), heartbeat(9, &nine));
        let changes = view.update(&table, HashSet::new());
        assert_eq!(blocked(&changes, "n7/3"), Some(true));
        assert_eq!(view.walked(), after_first + 2);

        // Peer 9 turns out to be one of ours (gossip knows it): n7/3 is free.
        let changes = view.update(&table, HashSet::from([9]));
        assert_eq!(blocked(&changes, "n7/3"), Some(false));
        assert_eq!(view.walked(), after_first + 2);
        // And back: it left gossip.
        let changes = view.update(&table, HashSet::new());
        assert_eq!(blocked(&changes, "n7/3"), Some(true));
        assert_eq!(view.walked(), after_first + 3);

        // Peer 0 stops subscribing: arm/pose is free.
        table.handle_heartbeat(t0 + Duration::from_secs(2), address(0), heartbeat(0, &[]));
        let changes = view.update(&table, HashSet::new());
        assert_eq!(blocked(&changes, "arm/pose"), Some(false));
        assert_eq!(view.walked(), after_first + 4);
    }

    /// Channels that begin batching together cost one walk of the table;
    /// more changes than the table's log names cost one walk too.
    #[test]
    fn new_channels_and_a_flood_of_changes_cost_one_walk() {
        let t0 = Instant::now();
        let mut table = Membership::new(Duration::from_secs(1));
        for s in 1..=100 {
            table.handle_heartbeat(t0, address(s), heartbeat(s, &names(&format!("n{s}"), 5)));
        }
        let mut view = Eligibility::new(-1, GRACE);
        view.update(&table, HashSet::new());
        assert_eq!(view.walked(), 100);
        for name in names("n5", 5).iter().chain(&names("n6", 5)) {
            view.watch(&Arc::from(name.as_str()));
        }
        let changes = view.update(&table, HashSet::new());
        assert_eq!(changes.len(), 10);
        assert!(changes.iter().all(|(_, b)| *b));
        assert_eq!(view.walked(), 200);

        // More changes than the log names: the fakes come and go.
        let later = t0 + Duration::from_secs(10);
        for s in 0..CHANGE_LOG as i64 {
            table.handle_heartbeat(later, address(500), heartbeat(5000 + s, &[]));
            table.handle_timeout(later + Duration::from_secs(10));
        }
        let changes = view.update(&table, HashSet::new());
        assert!(changes.iter().all(|(_, b)| !*b), "everyone expired");
        assert_eq!(view.walked(), 200);
    }

    /// The log speaks of a blocked channel once, after its blocker was
    /// heard for the grace, and only while the channel batches.
    #[test]
    fn the_log_speaks_once_after_the_grace() {
        let t0 = Instant::now();
        let mut table = Membership::new(Duration::from_secs(1));
        table.handle_heartbeat(t0, address(1), heartbeat(1, &["a".into(), "b".into()]));
        let mut view = Eligibility::new(-1, GRACE);
        view.watch(&Arc::from("a"));
        view.watch(&Arc::from("b"));
        view.update(&table, HashSet::new());
        assert!(view.settled(t0, |_| true).is_empty());
        let mut settled = view.settled(t0 + GRACE, |n| n == "a");
        settled.sort();
        assert_eq!(settled, [(Arc::from("a"), 1)]);
        assert!(view.settled(t0 + GRACE * 4, |_| true).is_empty());
        // b batches again.
        view.watch(&Arc::from("b"));
        assert_eq!(
            view.settled(t0 + GRACE * 4, |_| true),
            [(Arc::from("b"), 1)]
        );
        view.watch(&Arc::from("b"));
        assert!(view.settled(t0 + GRACE * 8, |_| true).is_empty());
    }

    /// Batching turned off and on again: the caller guessed its flag (a
    /// large table is not looked up at once), so the next update tells
    /// the answer again, though nothing in the table changed.
    #[test]
    fn a_channel_watched_again_is_told_again() {
        let t0 = Instant::now();
        let mut table = Membership::new(Duration::from_secs(1));
        table.handle_heartbeat(t0, address(1), heartbeat(1, &["b".into()]));
        let mut view = Eligibility::new(-1, GRACE);
        view.watch(&Arc::from("a"));
        view.watch(&Arc::from("b"));
        view.update(&table, HashSet::new());
        assert!(view.update(&table, HashSet::new()).is_empty());
        view.watch(&Arc::from("a"));
        view.watch(&Arc::from("b"));
        let mut told = view.update(&table, HashSet::new());
        told.sort();
        assert_eq!(told, [(Arc::from("a"), false), (Arc::from("b"), true)]);
        assert!(view.update(&table, HashSet::new()).is_empty());
    }
}

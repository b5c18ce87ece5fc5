//! Which of the channels a site offers a bridge carries, sans-IO: its
//! exports and its imports are each bounded in count, in total and per
//! member, so that a stranger announcing thousands of names costs a bridge
//! no more than the bound (each export is a subscription, a task and a
//! Zenoh publisher; each import a Zenoh subscriber and a task).
//!
//! While everything fits, every channel wanted is carried. When more are
//! wanted than fit, free slots go to the members holding the fewest, one at
//! a time, so a member with a few channels is served before one with
//! thousands; and slots that carried nothing for [`Limits::trial`] (a name
//! announced and never used) make room, their channels left out for
//! [`Limits::quiet`] before they are tried again. A channel that carries
//! messages keeps its slot: names that were never used don't crowd out
//! real traffic. A member that carries messages on any of its channels
//! (within [`Limits::quiet`]) goes first, and its idle channels make room
//! only for other such members': a real node's emergency stop, silent for
//! hours, is not pushed out by a stranger's names.
//!
//! ```
//! use std::collections::HashMap;
//! use std::time::{Duration, Instant};
//! use puli_bridge::slots::{Limits, Slots};
//!
//! let mut slots = Slots::new(Limits { total: 2, per_member: 2, ..Limits::default() });
//! let t = Instant::now();
//! let wanted = HashMap::from([("rover1/pose", 1), ("fake/a", 9), ("fake/b", 9)]);
//! let choice = slots.choose(&wanted, |_| None, t);
//! // One slot each: the member with fewest goes first.
//! assert_eq!(choice.start.len(), 2);
//! assert!(choice.start.contains(&"rover1/pose".to_string()));
//! assert_eq!(slots.left_out(), 1);
//! ```

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashMap, VecDeque};
use std::time::{Duration, Instant};

/// A bridge's bounds on one direction (exports, or imports).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Channels carried at once.
    pub total: usize,
    /// Channels carried for one member at once.
    pub per_member: usize,
    /// How long a slot may carry nothing before it makes room for a
    /// channel waiting (only while some wait).
    pub trial: Duration,
    /// How long a channel that made room waits before it is tried again.
    pub quiet: Duration,
    /// Channels started at most per [`Slots::choose`], so that a step
    /// stays short whatever a stranger announces at once (the others wait
    /// for the next steps).
    pub per_step: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            total: 4096,
            per_member: 1024,
            trial: Duration::from_secs(10),
            quiet: Duration::from_secs(60),
            per_step: 256,
        }
    }
}

/// What to change: channels to start carrying, and to stop.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Choice {
    /// Channels to start carrying.
    pub start: Vec<String>,
    /// Channels to stop carrying.
    pub stop: Vec<String>,
}

#[derive(Debug, Clone, Copy)]
struct Held {
    member: i64,
    since: Instant,
}

/// The most channels remembered as quiet: past it, a channel that made
/// room may be tried again sooner, which costs a slot's trial, no memory.
const MAX_QUIET: usize = 65_536;

/// The slots of one direction: see the module.
#[derive(Debug)]
pub struct Slots {
    limits: Limits,
    held: HashMap<String, Held>,
    quiet: HashMap<String, Instant>,
    left_out: usize,
}

impl Slots {
    /// No channel carried yet.
    pub fn new(limits: Limits) -> Self {
        Self {
            limits,
            held: HashMap::new(),
            quiet: HashMap::new(),
            left_out: 0,
        }
    }

    /// Chooses which of the channels `wanted` (each with the member it is
    /// carried for) are carried from `now` on. `used` tells when a channel
    /// carried its last message, if it did.
    pub fn choose(
        &mut self,
        wanted: &HashMap<&str, i64>,
        used: impl Fn(&str) -> Option<Instant>,
        now: Instant,
    ) -> Choice {
        let mut choice = Choice::default();
        self.held.retain(|name, _| {
            let keep = wanted.contains_key(name.as_str());
            if !keep {
                choice.stop.push(name.clone());
            }
            keep
        });
        self.quiet.retain(|_, until| *until > now);
        let mut count: HashMap<i64, usize> = HashMap::new();
        for held in self.held.values() {
            *count.entry(held.member).or_default() += 1;
        }
        let carrying = self.carrying(&used, now);
        let per_member = self.limits.per_member;
        let mut queues: HashMap<i64, VecDeque<&str>> = HashMap::new();
        for (&name, &member) in wanted {
            if self.held.contains_key(name) || self.quiet.contains_key(name) {
                continue;
            }
            queues.entry(member).or_default().push_back(name);
        }
        // Channels that could take a slot, of members that carry messages
        // and in all.
        let (mut waiting, mut waiting_carrying) = (0, 0);
        for (member, q) in &queues {
            let could = q
                .len()
                .min(per_member.saturating_sub(count.get(member).copied().unwrap_or(0)));
            waiting += could;
            if carrying.contains(member) {
                waiting_carrying += could;
            }
        }
        let free = self.limits.total.saturating_sub(self.held.len());
        if waiting > free {
            // Slots that carried nothing lately make room: those of members
            // that carry nothing for anyone waiting; those of members that
            // carry messages (a rarely used channel of a real node: an
            // emergency stop) only for other such members' channels.
            let trial = self.limits.trial;
            let mut idle: Vec<(bool, String)> = self
                .held
                .iter()
                .filter(|(name, held)| {
                    let last = used(name).map_or(held.since, |at| at.max(held.since));
                    now.saturating_duration_since(last) >= trial
                })
                .map(|(name, held)| (carrying.contains(&held.member), name.clone()))
                .collect();
            let idle_others = idle.iter().filter(|(c, _)| !c).count();
            if waiting_carrying <= free + idle_others {
                idle.retain(|(c, _)| !c);
            }
            for (_, name) in idle {
                if let Some(held) = self.held.remove(&name) {
                    if let Some(n) = count.get_mut(&held.member) {
                        *n -= 1;
                    }
                }
                if self.quiet.len() < MAX_QUIET {
                    self.quiet.insert(name.clone(), now + self.limits.quiet);
                }
                choice.stop.push(name);
            }
        }
        // Each queue in a stable order, so a member's first channels go
        // first whatever the hash order.
        for q in queues.values_mut() {
            q.make_contiguous().sort_unstable();
        }
        // Members that carry messages first, then those holding fewest.
        let mut turns: BinaryHeap<Reverse<(bool, usize, i64)>> = queues
            .keys()
            .map(|m| {
                let held = count.get(m).copied().unwrap_or(0);
                Reverse((!carrying.contains(m), held, *m))
            })
            .collect();
        let mut started = 0;
        while self.held.len() < self.limits.total && started < self.limits.per_step {
            let Some(Reverse((tier, held, member))) = turns.pop() else {
                break;
            };
            if held >= per_member {
                continue;
            }
            let Some(name) = queues.get_mut(&member).and_then(VecDeque::pop_front) else {
                continue;
            };
            self.held
                .insert(name.to_string(), Held { member, since: now });
            choice.start.push(name.to_string());
            started += 1;
            turns.push(Reverse((tier, held + 1, member)));
        }
        self.left_out = queues.values().map(VecDeque::len).sum();
        choice
    }

    /// The members one of whose channels carried a message within
    /// [`Limits::quiet`] of `now`: their channels go first, and their idle
    /// ones make room only for other such members' channels. A member
    /// that announces names and never sends on them is never one.
    pub fn carrying(
        &self,
        used: impl Fn(&str) -> Option<Instant>,
        now: Instant,
    ) -> std::collections::HashSet<i64> {
        self.held
            .iter()
            .filter(|(name, _)| {
                used(name).is_some_and(|at| now.saturating_duration_since(at) < self.limits.quiet)
            })
            .map(|(_, held)| held.member)
            .collect()
    }

    /// Channels wanted but not carried at the last [`Slots::choose`].
    pub fn left_out(&self) -> usize {
        self.left_out
    }

    /// Channels carried.
    pub fn len(&self) -> usize {
        self.held.len()
    }

    /// Whether no channel is carried.
    pub fn is_empty(&self) -> bool {
        self.held.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(total: usize, per_member: usize) -> Limits {
        Limits {
            total,
            per_member,
            ..Limits::default()
        }
    }

    #[test]
    fn everything_fits_everything_is_carried_and_nothing_is_evicted() {
        let mut slots = Slots::new(limits(10, 10));
        let t = Instant::now();
        let wanted = HashMap::from([("a", 1), ("b", 1), ("c", 2)]);
        assert_eq!(slots.choose(&wanted, |_| None, t).start.len(), 3);
        // Unused for far longer than a trial: kept, nobody waits.
        let later = t + Duration::from_secs(3600);
        assert_eq!(slots.choose(&wanted, |_| None, later), Choice::default());
        // A channel no longer wanted stops.
        let fewer = HashMap::from([("a", 1), ("c", 2)]);
        let choice = slots.choose(&fewer, |_| None, later);
        assert_eq!(choice.stop, ["b"]);
        assert_eq!(slots.len(), 2);
    }

    #[test]
    fn strangers_names_never_used_give_way_to_a_channel_that_carries() {
        let mut slots = Slots::new(limits(100, 50));
        let t = Instant::now();
        // The real channel first, then 16 strangers of 3000 names each.
        let mut wanted: HashMap<&str, i64> = HashMap::from([("rover1/pose", 1)]);
        assert_eq!(slots.choose(&wanted, |_| None, t).start, ["rover1/pose"]);
        let names: Vec<String> = (0..16)
            .flat_map(|s| (0..3000).map(move |i| format!("fake{s}/c{i}")))
            .collect();
        for (i, name) in names.iter().enumerate() {
            wanted.insert(name, 100 + (i / 3000) as i64);
        }
        let mut now = t;
        for _ in 0..30 {
            now += Duration::from_secs(1);
            let used_now = |name: &str| (name == "rover1/pose").then_some(now);
            let choice = slots.choose(&wanted, used_now, now);
            assert!(!choice.stop.iter().any(|n| n == "rover1/pose"));
            assert!(slots.len() <= 100);
        }
        assert!(slots.held.contains_key("rover1/pose"));
        // Every stranger holds at most its share.
        let mut per: HashMap<i64, usize> = HashMap::new();
        for held in slots.held.values() {
            *per.entry(held.member).or_default() += 1;
        }
        assert!(per.values().all(|n| *n <= 50));
        // A real member that joins during the attack gets a slot as soon as
        // an idle one is freed: within a trial.
        wanted.insert("rover2/pose", 2);
        let mut got = None;
        for s in 1..=11 {
            let at = now + Duration::from_secs(s);
            let used_now = |name: &str| name.ends_with("/pose").then_some(at);
            if slots
                .choose(&wanted, used_now, at)
                .start
                .iter()
                .any(|n| n == "rover2/pose")
            {
                got = Some(s);
                break;
            }
        }
        assert!(got.is_some(), "the newcomer was never carried");
        assert!(slots.left_out() > 0);
    }

    #[test]
    fn a_member_that_carries_messages_keeps_its_quiet_channels_and_goes_first() {
        let mut slots = Slots::new(Limits {
            total: 10,
            per_member: 10,
            trial: Duration::from_secs(1),
            quiet: Duration::from_secs(60),
            per_step: 100,
        });
        let t = Instant::now();
        let mut wanted: HashMap<&str, i64> = HashMap::from([("r/pose", 1), ("r/estop", 1)]);
        assert_eq!(slots.choose(&wanted, |_| None, t).start.len(), 2);
        // Five strangers of ten names each, never used; the real node's
        // pose carries messages, its emergency stop none.
        let names: Vec<String> = (0..5)
            .flat_map(|s| (0..10).map(move |i| format!("fake{s}/c{i}")))
            .collect();
        for (i, name) in names.iter().enumerate() {
            wanted.insert(name, 100 + (i / 10) as i64);
        }
        let mut now = t;
        for step in 0..40 {
            now += Duration::from_millis(500);
            if step == 20 {
                // The real node announces a channel during the attack.
                wanted.insert("r/new", 1);
            }
            let at = now;
            let choice = slots.choose(&wanted, |n| (n == "r/pose").then_some(at), at);
            assert!(
                !choice.stop.iter().any(|n| n.starts_with("r/")),
                "{choice:?}"
            );
            assert!(slots.len() <= 10);
        }
        assert!(slots.held.contains_key("r/estop"));
        assert!(
            slots.held.contains_key("r/new"),
            "the real node's new channel waits"
        );
        assert_eq!(
            slots.carrying(|n| (n == "r/pose").then_some(now), now),
            [1].into()
        );
        // Strangers' channels take turns in the other slots.
        let strangers = slots.held.values().filter(|h| h.member >= 100).count();
        assert!(strangers <= 7, "{strangers}");
    }

    #[test]
    fn a_member_gets_at_most_its_share_and_quiet_channels_wait() {
        let mut slots = Slots::new(Limits {
            total: 4,
            per_member: 2,
            trial: Duration::from_secs(1),
            quiet: Duration::from_secs(5),
            per_step: 100,
        });
        let t = Instant::now();
        let wanted = HashMap::from([("a1", 1), ("a2", 1), ("a3", 1), ("b1", 2)]);
        let choice = slots.choose(&wanted, |_| None, t);
        assert_eq!(choice.start.len(), 3, "{choice:?}");
        assert_eq!(slots.left_out(), 1);
        // Nobody waits that could take a slot: a3 is over its member's share.
        let later = t + Duration::from_secs(2);
        let choice = slots.choose(&wanted, |_| None, later);
        assert!(choice.stop.is_empty(), "{choice:?}");
        // Another member's channels waiting: idle slots make room, and the
        // channels that made room wait `quiet` before they come back.
        let more = HashMap::from([
            ("a1", 1),
            ("a2", 1),
            ("a3", 1),
            ("b1", 2),
            ("c1", 3),
            ("c2", 3),
        ]);
        let choice = slots.choose(&more, |n| (n == "a1").then_some(later), later);
        assert!(!choice.stop.contains(&"a1".to_string()), "{choice:?}");
        assert!(choice.start.contains(&"c1".to_string()), "{choice:?}");
        assert!(slots.len() <= 4);
        let stopped = choice.stop.clone();
        let soon = later + Duration::from_secs(1);
        let again = slots.choose(&more, |n| (n == "a1").then_some(soon), soon);
        assert!(
            again.start.iter().all(|n| !stopped.contains(n)),
            "{again:?}"
        );
    }
}

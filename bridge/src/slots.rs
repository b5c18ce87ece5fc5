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
//! hours, is not pushed out by a stranger's names. A channel whose member
//! left keeps its slot for [`Limits::linger`], so members that come and go
//! cost no churn. Imports can be told apart as listed or not
//! ([`Slots::choose_listed`]): the unlisted ones only fill free slots.
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
use std::collections::{BinaryHeap, HashMap, HashSet, VecDeque};
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
    /// How long a channel keeps its slot after it is no longer wanted (its
    /// member left): a node that restarts, or a member that expires and
    /// comes back, finds its channels still carried instead of torn down
    /// and set up again (a stranger's fakes that come and go every
    /// second would otherwise cost a bridge thousands of each per second).
    pub linger: Duration,
    /// The most channels carried at once that aren't listed (see
    /// [`Slots::choose_listed`]).
    pub unlisted: usize,
    /// The most distinct names ever carried, listed ones and the others:
    /// past it, a name never carried before is left out (counted in
    /// [`Slots::refused`]), however long the bridge runs. Imports need it:
    /// Zenoh keeps state for every key a subscriber was ever declared on,
    /// and the node a channel for every name it ever published.
    pub names: [usize; 2],
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            total: 4096,
            per_member: 1024,
            trial: Duration::from_secs(10),
            quiet: Duration::from_secs(60),
            per_step: 256,
            linger: Duration::from_secs(10),
            unlisted: 1024,
            names: [usize::MAX; 2],
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
    /// Since when it is no longer wanted, if it isn't.
    gone: Option<Instant>,
}

/// The most channels remembered as quiet: past it, a channel that made
/// room may be tried again sooner, which costs a slot's trial, no memory.
const MAX_QUIET: usize = 65_536;

/// What one [`Slots::choose_listed`] passes to each
/// [`Slots::fill`]: the channels held per member, the members that carry
/// messages, the time, and what was chosen so far.
struct Step<'a> {
    count: &'a mut HashMap<i64, usize>,
    carrying: &'a HashSet<i64>,
    now: Instant,
    choice: &'a mut Choice,
    started: usize,
}

/// The slots of one direction: see the module.
#[derive(Debug)]
pub struct Slots {
    limits: Limits,
    held: HashMap<String, Held>,
    quiet: HashMap<String, Instant>,
    /// Names ever carried, listed and not (see [`Limits::names`]); not
    /// kept when unbounded.
    tried: [HashSet<String>; 2],
    /// Waiting names left out at the last choice for [`Limits::names`].
    refused: usize,
    left_out: usize,
    /// Whether the last choice stopped at [`Limits::per_step`].
    more: bool,
}

impl Slots {
    /// No channel carried yet.
    pub fn new(limits: Limits) -> Self {
        Self {
            limits,
            held: HashMap::new(),
            quiet: HashMap::new(),
            tried: Default::default(),
            refused: 0,
            left_out: 0,
            more: false,
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
        self.choose_listed(wanted, used, |_| true, now)
    }

    /// [`Slots::choose`], where only channels that are `listed` (an import
    /// that another site's table lists a publisher of) go first and may
    /// make an idle one give way; the others take places left free, and
    /// never push one out. A Zenoh subscriber declared for a name that
    /// nobody publishes stays in Zenoh's routing tables after it is
    /// undeclared while a peer is connected, so taking turns among a
    /// stranger's names would cost a bridge memory for every name tried.
    pub fn choose_listed(
        &mut self,
        wanted: &HashMap<&str, i64>,
        used: impl Fn(&str) -> Option<Instant>,
        listed: impl Fn(&str) -> bool,
        now: Instant,
    ) -> Choice {
        let mut choice = Choice::default();
        let linger = self.limits.linger;
        self.held.retain(|name, held| {
            match wanted.get(name.as_str()) {
                Some(&member) => {
                    // Back, perhaps for a member that came back under
                    // another key (a restarted node).
                    held.gone = None;
                    held.member = member;
                    return true;
                }
                None => {
                    let gone = *held.gone.get_or_insert(now);
                    if now.saturating_duration_since(gone) < linger {
                        return true;
                    }
                }
            }
            choice.stop.push(name.clone());
            false
        });
        self.quiet.retain(|_, until| *until > now);
        let mut count: HashMap<i64, usize> = HashMap::new();
        for held in self.held.values() {
            *count.entry(held.member).or_default() += 1;
        }
        let carrying = self.carrying(&used, now);
        let per_member = self.limits.per_member;
        // Waiting channels by member: those listed, then the others.
        let mut queues: [HashMap<i64, VecDeque<&str>>; 2] = Default::default();
        self.refused = 0;
        // Names never carried queued so far, per tier.
        let mut fresh = [0usize; 2];
        for (&name, &member) in wanted {
            if self.held.contains_key(name) || self.quiet.contains_key(name) {
                continue;
            }
            let tier = usize::from(!listed(name));
            // Names never carried, past what their bound has left, wait
            // for nothing: they make no idle slot give way either.
            // Those queued fit the bound: `fill` starts no more than these.
            if !self.was_tried(name) {
                if self.tried[tier].len().saturating_add(fresh[tier]) >= self.limits.names[tier] {
                    self.refused += 1;
                    continue;
                }
                fresh[tier] += 1;
            }
            queues[tier].entry(member).or_default().push_back(name);
        }
        // Listed channels that could take a slot, of members that carry
        // messages and in all.
        let (mut waiting, mut waiting_carrying) = (0, 0);
        for (member, q) in &queues[0] {
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
            // Slots that carried nothing lately make room, as many as wait:
            // those of members that carry nothing for anyone waiting; those
            // of members that carry messages (a rarely used channel of a
            // real node: an emergency stop) only for other such members'
            // channels. The least lately used first.
            let trial = self.limits.trial;
            let mut idle: Vec<(bool, Instant, String)> = self
                .held
                .iter()
                .filter_map(|(name, held)| {
                    let last = used(name).map_or(held.since, |at| at.max(held.since));
                    (now.saturating_duration_since(last) >= trial)
                        .then(|| (carrying.contains(&held.member), last, name.clone()))
                })
                .collect();
            let idle_others = idle.iter().filter(|(c, ..)| !c).count();
            if waiting_carrying <= free + idle_others {
                idle.retain(|(c, ..)| !c);
            }
            idle.sort_unstable_by_key(|(carries, last, _)| (*carries, *last));
            idle.truncate(waiting - free);
            for (_, _, name) in idle {
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
        let [listed_queues, others] = &mut queues;
        let mut step = Step {
            count: &mut count,
            carrying: &carrying,
            now,
            choice: &mut choice,
            started: 0,
        };
        self.fill(&mut step, listed_queues, 0, usize::MAX);
        let unlisted = self.held.keys().filter(|n| !listed(n)).count();
        let room = self.limits.unlisted.saturating_sub(unlisted);
        self.fill(&mut step, others, 1, room);
        self.more = step.started >= self.limits.per_step;
        self.left_out = queues
            .iter()
            .flat_map(|q| q.values())
            .map(VecDeque::len)
            .sum();
        choice
    }

    /// Gives free slots, `room` at most, to the channels of `queues` (of
    /// `tier`, 0: listed), members that carry messages first, then those
    /// holding fewest, one at a time.
    fn fill(
        &mut self,
        step: &mut Step<'_>,
        queues: &mut HashMap<i64, VecDeque<&str>>,
        tier: usize,
        room: usize,
    ) {
        let Step {
            count,
            carrying,
            now,
            choice,
            started,
        } = step;
        let per_member = self.limits.per_member;
        // Each queue in a stable order, so a member's first channels go
        // first whatever the hash order.
        for q in queues.values_mut() {
            q.make_contiguous().sort_unstable();
        }
        let mut turns: BinaryHeap<Reverse<(bool, usize, i64)>> = queues
            .keys()
            .map(|m| {
                let held = count.get(m).copied().unwrap_or(0);
                Reverse((!carrying.contains(m), held, *m))
            })
            .collect();
        let mut given = 0;
        while self.held.len() < self.limits.total && *started < self.limits.per_step && given < room
        {
            let Some(Reverse((order, held, member))) = turns.pop() else {
                break;
            };
            if held >= per_member {
                continue;
            }
            let Some(name) = queues.get_mut(&member).and_then(VecDeque::pop_front) else {
                continue;
            };
            let bounded = self.limits.names[tier] != usize::MAX;
            if bounded && !self.was_tried(name) {
                self.tried[tier].insert(name.to_string());
            }
            self.held.insert(
                name.to_string(),
                Held {
                    member,
                    since: *now,
                    gone: None,
                },
            );
            *count.entry(member).or_default() += 1;
            choice.start.push(name.to_string());
            *started += 1;
            given += 1;
            turns.push(Reverse((order, held + 1, member)));
        }
    }

    /// The members one of whose channels carried a message within
    /// [`Limits::quiet`] of `now`: their channels go first, and their idle
    /// ones make room only for other such members' channels. A member
    /// that announces names and never sends on them is never one.
    pub fn carrying(&self, used: impl Fn(&str) -> Option<Instant>, now: Instant) -> HashSet<i64> {
        self.held
            .iter()
            .filter(|(name, _)| {
                used(name).is_some_and(|at| now.saturating_duration_since(at) < self.limits.quiet)
            })
            .map(|(_, held)| held.member)
            .collect()
    }

    /// Whether the last [`Slots::choose`] started [`Limits::per_step`]
    /// channels, so that more may be waiting for a free slot: choose
    /// again soon rather than at the next change.
    pub fn more_waiting(&self) -> bool {
        self.more
    }

    /// Channels wanted but not carried at the last [`Slots::choose`]
    /// ([`Slots::refused`] included).
    pub fn left_out(&self) -> usize {
        self.left_out + self.refused
    }

    /// Channels left out at the last [`Slots::choose`] because they were
    /// never carried and [`Limits::names`] is reached.
    pub fn refused(&self) -> usize {
        self.refused
    }

    /// Distinct names carried so far, listed and not, where
    /// [`Limits::names`] bounds them.
    pub fn names_tried(&self) -> [usize; 2] {
        [self.tried[0].len(), self.tried[1].len()]
    }

    /// Whether `name` was carried before, listed or not, where
    /// [`Limits::names`] bounds them.
    fn was_tried(&self, name: &str) -> bool {
        self.tried.iter().any(|t| t.contains(name))
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
        // A channel no longer wanted stops once it lingered.
        let fewer = HashMap::from([("a", 1), ("c", 2)]);
        assert_eq!(slots.choose(&fewer, |_| None, later), Choice::default());
        let linger = Limits::default().linger;
        let choice = slots.choose(&fewer, |_| None, later + linger);
        assert_eq!(choice.stop, ["b"]);
        assert_eq!(slots.len(), 2);
    }

    #[test]
    fn names_nobody_publishes_take_free_places_and_never_push_one_out() {
        // Imports: a stranger's members subscribe 3000 names that no site
        // publishes; a real subscriber's channel that another site lists a
        // publisher of comes later.
        let mut slots = Slots::new(limits(100, 100));
        let names: Vec<String> = (0..3)
            .flat_map(|s| (0..1000).map(move |i| format!("fake{s}/c{i:04}")))
            .collect();
        let mut wanted: HashMap<&str, i64> = names
            .iter()
            .enumerate()
            .map(|(i, n)| (n.as_str(), 100 + (i / 1000) as i64))
            .collect();
        let listed = |name: &str| name.starts_with("rover1/");
        let t = Instant::now();
        let (mut started, mut stopped) = (Vec::new(), Vec::new());
        for s in 0..60 {
            let choice = slots.choose_listed(&wanted, |_| None, listed, t + Duration::from_secs(s));
            started.extend(choice.start);
            stopped.extend(choice.stop);
        }
        // The free places are taken once; nobody listed waits, so no name
        // makes room for another (each would be a new Zenoh declaration).
        assert_eq!((started.len(), stopped.len()), (100, 0));
        wanted.insert("rover1/cmd", 1);
        for s in 60..80 {
            let choice = slots.choose_listed(&wanted, |_| None, listed, t + Duration::from_secs(s));
            started.extend(choice.start);
            stopped.extend(choice.stop);
        }
        assert!(started.iter().any(|n| n == "rover1/cmd"));
        assert_eq!(
            (started.len(), stopped.len()),
            (101, 1),
            "one idle place made room for the listed channel, no more"
        );
        assert!(slots.held.contains_key("rover1/cmd"));
        assert!(slots.left_out() > 0);
    }

    /// The attacker: a stranger whose fakes subscribe fresh names every
    /// round (unlisted), and one on another site that lists fresh names
    /// for an accomplice here (listed, so they take turns). Each new name
    /// would be Zenoh state for good; past [`Limits::names`] new names are
    /// left out, the names already tried still come and go, and a real
    /// channel carried before comes back.
    #[test]
    fn names_never_carried_past_their_bound_are_left_out_for_good() {
        let mut slots = Slots::new(Limits {
            unlisted: 5,
            names: [20, 5],
            ..limits(10, 10)
        });
        let t = Instant::now();
        let listed = |name: &str| !name.starts_with("fresh");
        let mut started: HashSet<String> = HashSet::new();
        let mut rounds: Vec<Vec<String>> = Vec::new();
        let real = "rover1/cmd".to_string();
        for round in 0..40u64 {
            // The real channel first, then 5 fresh unlisted names a round
            // and 40 listed names of which one is new every round; the
            // real channel comes back at the end.
            let mut names = Vec::new();
            if round == 0 || round >= 38 {
                names.push(real.clone());
            }
            if round > 0 {
                names.extend((0..5).map(|i| format!("fresh{round}/{i}")));
                names.extend((round..round + 40).map(|i| format!("listed/{i}")));
            }
            rounds.push(names);
            let names = &rounds[rounds.len() - 1];
            let wanted: HashMap<&str, i64> = names
                .iter()
                .map(|n| (n.as_str(), i64::from(n.starts_with("fresh"))))
                .collect();
            let at = t + Duration::from_secs(round * 11);
            let choice = slots.choose_listed(&wanted, |_| None, listed, at);
            started.extend(choice.start);
        }
        let fresh = started.iter().filter(|n| n.starts_with("fresh")).count();
        assert_eq!(fresh, 5, "unlisted names tried");
        assert_eq!(started.len() - fresh, 20, "listed names tried");
        assert_eq!(slots.names_tried(), [20, 5]);
        assert!(slots.refused() > 0);
        assert!(
            slots.held.contains_key(&real),
            "a channel carried before comes back"
        );
    }

    /// Names the bound refuses make no idle channel give way: with room
    /// for one more name, ten new ones waiting push out one idle channel,
    /// not ten.
    #[test]
    fn names_past_their_bound_push_nobody_out() {
        let mut slots = Slots::new(Limits {
            trial: Duration::from_secs(1),
            names: [5, usize::MAX],
            ..limits(4, 100)
        });
        let t = Instant::now();
        let mut wanted: HashMap<String, i64> = (0..4).map(|i| (format!("old{i}"), 1)).collect();
        let refs: HashMap<&str, i64> = wanted.iter().map(|(k, v)| (k.as_str(), *v)).collect();
        assert_eq!(slots.choose(&refs, |_| None, t).start.len(), 4);
        wanted.extend((0..10).map(|i| (format!("new{i}"), 2)));
        let refs: HashMap<&str, i64> = wanted.iter().map(|(k, v)| (k.as_str(), *v)).collect();
        let choice = slots.choose(&refs, |_| None, t + Duration::from_secs(5));
        assert_eq!(
            (choice.start.len(), choice.stop.len()),
            (1, 1),
            "{choice:?}"
        );
        assert_eq!(slots.refused(), 9);
    }

    #[test]
    fn channels_nobody_lists_take_at_most_their_share() {
        let mut slots = Slots::new(Limits {
            unlisted: 30,
            ..limits(100, 100)
        });
        let names: Vec<String> = (0..1000).map(|i| format!("fake/c{i:04}")).collect();
        let mut wanted: HashMap<&str, i64> = names.iter().map(|n| (n.as_str(), 9)).collect();
        wanted.extend([("rover1/a", 1), ("rover1/b", 1)]);
        let t = Instant::now();
        for s in 0..5 {
            slots.choose_listed(
                &wanted,
                |_| None,
                |n| n.starts_with("rover1/"),
                t + Duration::from_secs(s),
            );
        }
        assert_eq!(slots.len(), 32);
        assert!(slots.held.contains_key("rover1/a") && slots.held.contains_key("rover1/b"));
        assert!(!slots.more_waiting());
    }

    #[test]
    fn members_that_leave_and_come_back_within_the_linger_keep_their_channels() {
        // A stranger's 50 fakes of 100 names each, announcing a period they
        // don't keep: each expires between two heartbeats and comes back
        // with the next, every 2 s. Real nodes restart the same way.
        let mut slots = Slots::new(Limits {
            total: 10_000,
            per_member: 100,
            per_step: 10_000,
            ..Limits::default()
        });
        let names: Vec<String> = (0..50)
            .flat_map(|s| (0..100).map(move |i| format!("fake{s}/c{i:03}")))
            .collect();
        let all: HashMap<&str, i64> = names
            .iter()
            .enumerate()
            .map(|(i, n)| (n.as_str(), (i / 100) as i64))
            .collect();
        let none = HashMap::new();
        let t = Instant::now();
        let (mut started, mut stopped) = (0, 0);
        for cycle in 0..30u32 {
            let at = t + Duration::from_secs(2) * cycle;
            for (wanted, after) in [(&all, 0), (&none, 750)] {
                let choice = slots.choose(wanted, |_| None, at + Duration::from_millis(after));
                started += choice.start.len();
                stopped += choice.stop.len();
            }
        }
        // Each channel started once and kept (without the linger: 150,000
        // started and stopped).
        assert_eq!(slots.len(), 5000);
        assert_eq!((started, stopped), (5000, 0));
        // Gone for good: the slots are freed after the linger.
        let end = t + Duration::from_secs(60) + Limits::default().linger;
        assert_eq!(slots.choose(&none, |_| None, end).stop.len(), 5000);
        assert!(slots.is_empty());
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
            linger: Duration::ZERO,
            unlisted: 0,
            names: [usize::MAX; 2],
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
            linger: Duration::ZERO,
            unlisted: 0,
            names: [usize::MAX; 2],
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

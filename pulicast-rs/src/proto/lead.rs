//! Lead: how far a message is ahead of the last one seen from its source.
//!
//! For each source (the sender's socket address) of one channel the receiver
//! remembers the highest sequence number seen. A new message's lead is
//! `seq - highest`, computed modulo 2^32 so that the wrap from `u32::MAX` to 0
//! reads as `1`:
//!
//! | lead | meaning |
//! |------|---------|
//! | 1    | the next message, in order |
//! | > 1  | `lead - 1` messages were lost (or are still on their way) |
//! | <= 0 | late or duplicate |
//!
//! A publisher that restarts gets a new source port, so it starts a new entry
//! instead of looking late forever.

use std::collections::HashMap;
use std::net::SocketAddr;

/// The lead of one message; see the module docs.
pub type Lead = i64;

/// Per-source sequence tracking for one channel.
///
/// Holds at most `max_sources` entries; when a new source would exceed that,
/// the source heard from least recently is forgotten, so a flood of forged
/// source addresses costs bounded memory.
///
/// ```
/// use pulicast::proto::LeadTracker;
/// let src = "127.0.0.1:5000".parse().unwrap();
/// let mut leads = LeadTracker::new(16);
/// assert_eq!(leads.observe(src, 10), 1); // first message from a source
/// assert_eq!(leads.observe(src, 11), 1);
/// assert_eq!(leads.observe(src, 14), 3); // 12 and 13 missing
/// assert_eq!(leads.observe(src, 12), -2); // late
/// ```
#[derive(Debug, Clone)]
pub struct LeadTracker {
    sources: HashMap<SocketAddr, Source>,
    max_sources: usize,
    clock: u64,
}

#[derive(Debug, Clone, Copy)]
struct Source {
    highest: u32,
    last_used: u64,
}

impl LeadTracker {
    /// An empty tracker that remembers at most `max_sources` sources (at least one).
    pub fn new(max_sources: usize) -> Self {
        Self {
            sources: HashMap::new(),
            max_sources: max_sources.max(1),
            clock: 0,
        }
    }

    /// Records a message and returns its lead.
    ///
    /// The first message of a source has lead 1: nothing is known to be lost
    /// before it, and an ordered subscription must deliver it.
    pub fn observe(&mut self, source: SocketAddr, seq: u32) -> Lead {
        self.clock += 1;
        let clock = self.clock;
        if let Some(s) = self.sources.get_mut(&source) {
            // Reinterpreting the wrapped difference as signed makes the
            // u32::MAX -> 0 step read as +1 and old messages as negative.
            let lead = Lead::from(seq.wrapping_sub(s.highest) as i32);
            if lead > 0 {
                s.highest = seq;
            }
            s.last_used = clock;
            return lead;
        }
        if self.sources.len() >= self.max_sources {
            self.evict_least_recent();
        }
        self.sources.insert(
            source,
            Source {
                highest: seq,
                last_used: clock,
            },
        );
        1
    }

    /// Records `count` consecutive sequence numbers from `first` (a batch)
    /// with one lookup, and returns the lead of the first. The lead of
    /// message `i` of the run is then [`LeadTracker::lead_in_run`]`(first_lead, i)`,
    /// the same as `count` calls to [`LeadTracker::observe`] would give.
    ///
    /// ```
    /// use pulicast::proto::LeadTracker;
    /// let src = "127.0.0.1:5000".parse().unwrap();
    /// let mut leads = LeadTracker::new(16);
    /// leads.observe(src, 9);
    /// let first = leads.observe_run(src, 7, 5); // 7..=11: 7..=9 late, 10 and 11 new
    /// let run: Vec<i64> = (0..5).map(|i| LeadTracker::lead_in_run(first, i)).collect();
    /// assert_eq!(run, [-2, -1, 0, 1, 1]);
    /// assert_eq!(leads.observe(src, 12), 1);
    /// ```
    pub fn observe_run(&mut self, source: SocketAddr, first: u32, count: u16) -> Lead {
        let lead = self.observe(source, first);
        let last = Self::lead_in_run(lead, usize::from(count.max(1)) - 1);
        if count > 1 && last >= 1 {
            if let Some(s) = self.sources.get_mut(&source) {
                s.highest = first.wrapping_add(u32::from(count) - 1);
            }
        }
        lead
    }

    /// The lead of message `index` of a run whose first message had lead
    /// `first_lead`: see [`LeadTracker::observe_run`].
    pub fn lead_in_run(first_lead: Lead, index: usize) -> Lead {
        if index == 0 {
            first_lead
        } else if first_lead >= 1 {
            1
        } else {
            // Late messages catch up one by one until one is new.
            (first_lead + index as Lead).min(1)
        }
    }

    /// Number of sources currently remembered.
    pub fn len(&self) -> usize {
        self.sources.len()
    }

    /// Whether no source is remembered.
    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }

    fn evict_least_recent(&mut self) {
        if let Some(oldest) = self
            .sources
            .iter()
            .min_by_key(|(_, s)| s.last_used)
            .map(|(addr, _)| *addr)
        {
            self.sources.remove(&oldest);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr(port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    #[test]
    fn wraps_around_u32() {
        let mut t = LeadTracker::new(4);
        assert_eq!(t.observe(addr(1), u32::MAX - 1), 1);
        assert_eq!(t.observe(addr(1), u32::MAX), 1);
        assert_eq!(t.observe(addr(1), 0), 1);
        assert_eq!(t.observe(addr(1), 2), 2);
        assert_eq!(t.observe(addr(1), u32::MAX), -3);
        assert_eq!(t.observe(addr(1), 2), 0, "duplicate");
    }

    #[test]
    fn restarted_publisher_on_new_port_starts_fresh() {
        let mut t = LeadTracker::new(4);
        for seq in 0..100 {
            t.observe(addr(1), seq);
        }
        // The restarted process counts from 0 again, from another port.
        assert_eq!(t.observe(addr(2), 0), 1);
        assert_eq!(t.observe(addr(2), 1), 1);
        // The old source is unaffected.
        assert_eq!(t.observe(addr(1), 100), 1);
    }

    #[test]
    fn sources_are_bounded_and_least_recent_is_evicted() {
        let mut t = LeadTracker::new(2);
        t.observe(addr(1), 5);
        t.observe(addr(2), 5);
        t.observe(addr(1), 6);
        t.observe(addr(3), 5); // evicts 2, the least recently heard
        assert_eq!(t.len(), 2);
        assert_eq!(t.observe(addr(1), 7), 1, "1 was kept");
        assert_eq!(
            t.observe(addr(2), 9),
            1,
            "2 was forgotten, so it starts fresh"
        );
    }

    #[test]
    fn runs_lead_like_single_observations() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            (state >> 33) as u32
        };
        let (mut single, mut runs) = (LeadTracker::new(4), LeadTracker::new(4));
        let mut base = u32::MAX - 500;
        for _ in 0..5_000 {
            let first = base.wrapping_add(next() % 40).wrapping_sub(20);
            let count = (next() % 12 + 1) as u16;
            base = base.wrapping_add(next() % 8);
            let expected: Vec<Lead> = (0..count)
                .map(|i| single.observe(addr(1), first.wrapping_add(u32::from(i))))
                .collect();
            let lead = runs.observe_run(addr(1), first, count);
            let got: Vec<Lead> = (0..usize::from(count))
                .map(|i| LeadTracker::lead_in_run(lead, i))
                .collect();
            assert_eq!(got, expected, "run of {count} from {first}");
        }
    }

    #[test]
    fn matches_a_model_over_random_sequences() {
        // A tiny deterministic LCG, so the test needs no RNG crate.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            (state >> 33) as u32
        };
        let mut t = LeadTracker::new(8);
        let mut model: Option<u64> = None; // highest, unwrapped
        let mut unwrapped = u64::from(u32::MAX - 1000);
        for _ in 0..10_000 {
            let step = i64::from(next() % 7) - 2; // -2..=4
            let seq64 = (unwrapped as i64 + step).max(0) as u64;
            unwrapped = unwrapped.max(seq64);
            let lead = t.observe(addr(1), seq64 as u32);
            let expected = match model {
                None => 1,
                Some(h) => seq64 as i64 - h as i64,
            };
            assert_eq!(lead, expected);
            if model.is_none_or(|h| seq64 > h) {
                model = Some(seq64);
            }
        }
    }
}

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
//!
//! A jump of more than [`TENTATIVE_JUMP`] is taken as a loss, but only
//! tentatively: the message gets its lead, and the source's line stays where
//! it was until a message continues the jump. A message that continues the
//! old line instead contradicts it and is in order. So one datagram with a
//! forged source and a sequence number far ahead (anyone who can spoof an
//! address can send it) costs one apparent gap, not every later message of
//! the real publisher, which would otherwise all look late until its
//! numbers caught up (2^31 messages). A forged jump of at most
//! [`TENTATIVE_JUMP`] makes at most that many real messages look late.

use std::collections::HashMap;
use std::net::SocketAddr;

/// The lead of one message; see the module docs.
pub type Lead = i64;

/// Jumps larger than this are taken tentatively (see the module docs);
/// messages reordered by more than this look like a jump and back.
pub(super) const TENTATIVE_JUMP: i64 = 64;

/// Per-source sequence tracking for one channel.
///
/// Holds at most `max_sources` entries; when a new source would exceed that,
/// the source heard from least recently is forgotten, so a flood of forged
/// source addresses costs bounded memory.
///
/// ```
/// use pulicast_proto::LeadTracker;
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
    /// The highest number of a jump not confirmed yet.
    ahead: Option<u32>,
}

/// `seq - base` modulo 2^32, as a signed step.
fn step(seq: u32, base: u32) -> Lead {
    Lead::from(seq.wrapping_sub(base) as i32)
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
            s.last_used = clock;
            // Reinterpreting the wrapped difference as signed makes the
            // u32::MAX -> 0 step read as +1 and old messages as negative.
            let lead = step(seq, s.highest);
            if let Some(ahead) = s.ahead {
                let past_jump = step(seq, ahead);
                if (1..=TENTATIVE_JUMP).contains(&past_jump) {
                    // The jump goes on: it was real.
                    s.highest = seq;
                    s.ahead = None;
                    return past_jump;
                }
                if (1..=TENTATIVE_JUMP).contains(&lead) {
                    // The old line goes on: the jump was not real.
                    s.highest = seq;
                    s.ahead = None;
                    return lead;
                }
                if (-TENTATIVE_JUMP..=0).contains(&past_jump) {
                    return past_jump; // the jump's message again
                }
            }
            if lead > TENTATIVE_JUMP {
                s.ahead = Some(seq);
            } else if lead > 0 {
                s.highest = seq;
            }
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
                ahead: None,
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
    /// use pulicast_proto::LeadTracker;
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
                let end = first.wrapping_add(u32::from(count) - 1);
                // A tentative jump moves its own end, not the line.
                match s.ahead {
                    Some(ahead) if ahead == first => s.ahead = Some(end),
                    _ => s.highest = end,
                }
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
    fn a_forged_jump_costs_one_gap_and_a_real_one_holds() {
        let mut t = LeadTracker::new(4);
        for seq in 0..=10 {
            t.observe(addr(1), seq);
        }
        // A spoofed datagram far ahead: its lead, once...
        assert_eq!(t.observe(addr(1), 10 + (1 << 31) - 1), (1 << 31) - 1);
        // ... and the real publisher goes on in order.
        for seq in 11..200 {
            assert_eq!(t.observe(addr(1), seq), 1, "seq {seq}");
        }
        // A real loss of a thousand messages: the jump, then in order.
        assert_eq!(t.observe(addr(1), 1200), 1001);
        assert_eq!(t.observe(addr(1), 1201), 1);
        assert_eq!(t.observe(addr(1), 1199), -2, "late");
        // Its message again, before it is confirmed: a duplicate.
        assert_eq!(t.observe(addr(1), 5000), 3799);
        assert_eq!(t.observe(addr(1), 5000), 0);
        assert_eq!(t.observe(addr(1), 5001), 1);
        // A forged jump in a batch, then the old line.
        let first = t.observe_run(addr(1), 900_000, 5);
        assert_eq!(first, 900_000 - 5001);
        assert_eq!(t.observe(addr(1), 5002), 1);
        // A real jump in a batch, continued.
        let _ = t.observe_run(addr(1), 10_000, 5);
        assert_eq!(t.observe(addr(1), 10_005), 1);
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

//! Pacing a large message's fragments, so that a burst fits the
//! subscribers' receive buffers.
//!
//! A message of many fragments leaves as fast as the kernel takes them,
//! and a subscriber's socket holds what it has not read yet only up to
//! its receive buffer: past it, fragments are dropped, and one fragment
//! lost is the whole message lost. So a publisher sends a message's
//! fragments at most at a rate, in bursts of at most half the smallest
//! buffer its subscribers announce (discovery's
//! `MemberInfo::receive_buffer`; Linux reports twice the payload a buffer
//! holds, so half of it is what a burst may fill).
//!
//! The pacer is the generic cell rate algorithm over bytes: it keeps the
//! time at which everything sent so far would have left at the rate (its
//! theoretical arrival time, TAT), and a datagram waits until the TAT is
//! at most a burst's worth of time ahead of now. Sans-IO: the caller
//! gives the time and waits.

use std::time::{Duration, Instant};

/// A rate with bursts: how long each datagram waits.
#[derive(Debug, Clone)]
pub struct Pacer {
    /// Bytes a second.
    rate: u64,
    /// When everything sent so far would have left at `rate`.
    tat: Option<Instant>,
}

impl Pacer {
    /// A pacer of `rate` bytes a second (at least 1).
    pub fn new(rate: u64) -> Self {
        Self {
            rate: rate.max(1),
            tat: None,
        }
    }

    /// Its rate, in bytes a second.
    pub fn rate(&self) -> u64 {
        self.rate
    }

    /// How long a datagram of `bytes` waits at `now` before it is sent,
    /// with bursts of at most `burst` bytes; it is counted as sent then.
    /// A datagram larger than a burst waits until the pacer is idle.
    ///
    /// ```
    /// use std::time::{Duration, Instant};
    /// use pulicast_proto::pace::Pacer;
    /// let now = Instant::now();
    /// let mut pacer = Pacer::new(1_000_000); // 1 MB/s
    /// // A burst of 3000 bytes goes at once; then 1000 bytes a millisecond.
    /// for _ in 0..3 {
    ///     assert_eq!(pacer.delay(now, 1000, 3000), Duration::ZERO);
    /// }
    /// assert_eq!(pacer.delay(now, 1000, 3000), Duration::from_millis(1));
    /// ```
    pub fn delay(&mut self, now: Instant, bytes: usize, burst: usize) -> Duration {
        let cost = self.time_of(bytes);
        let allowance = self.time_of(burst.max(bytes));
        let base = self.tat.map_or(now, |t| t.max(now));
        // Past what an Instant holds (absurd rates and sizes): no wait.
        let Some(tat) = base.checked_add(cost) else {
            return Duration::ZERO;
        };
        self.tat = Some(tat);
        tat.saturating_duration_since(now).saturating_sub(allowance)
    }

    /// How long `bytes` take at the rate.
    fn time_of(&self, bytes: usize) -> Duration {
        let bytes = u128::try_from(bytes).unwrap_or(u128::MAX);
        let nanos = bytes.saturating_mul(1_000_000_000) / u128::from(self.rate);
        Duration::from_nanos(u64::try_from(nanos).unwrap_or(u64::MAX))
    }
}

/// The burst a message's fragments may make towards subscribers that
/// announce `buffers` (bytes, as Linux reports them): half the smallest,
/// and at least one datagram of `datagram` bytes (a buffer smaller than
/// one fragment can't be helped by waiting: it takes one at a time).
/// With no buffer announced, `fallback` (this host's default, read by
/// the caller) stands for each subscriber that announces none.
pub fn burst_for(
    buffers: impl IntoIterator<Item = Option<u32>>,
    fallback: usize,
    datagram: usize,
) -> Option<usize> {
    let smallest = buffers
        .into_iter()
        .map(|b| b.map_or(fallback, |b| b as usize))
        .min()?;
    Some((smallest / 2).max(datagram))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_message_larger_than_a_burst_leaves_at_the_rate_after_its_first_burst() {
        let start = Instant::now();
        let mut pacer = Pacer::new(100_000_000); // 100 MB/s
        let (fragment, burst) = (60_000, 1_000_000);
        // 16 MB in 60 kB fragments, each sent when its wait is over.
        let mut now = start;
        let mut sent = Vec::new();
        for _ in 0..267 {
            now += pacer.delay(now, fragment, burst);
            sent.push(now);
        }
        // The first burst's worth goes at once.
        let at_once = sent.iter().filter(|t| **t == start).count();
        assert_eq!(at_once, burst / fragment);
        // The whole takes what the rate says, less the first burst.
        let total = 267 * fragment;
        let expected = Duration::from_secs_f64((total - burst) as f64 / 100e6);
        let took = *sent.last().unwrap() - start;
        assert!(
            took + Duration::from_micros(1) >= expected
                && took <= expected + Duration::from_millis(1),
            "{took:?}"
        );
        // And at no moment is more than a burst ahead of the rate.
        for (i, t) in sent.iter().enumerate() {
            let bytes_by_then = (i + 1) * fragment;
            let allowed = burst + ((*t - start).as_secs_f64() * 100e6) as usize + fragment;
            assert!(bytes_by_then <= allowed, "{i}");
        }
    }

    #[test]
    fn an_idle_pacer_lets_a_burst_go_again() {
        let start = Instant::now();
        let mut pacer = Pacer::new(1_000_000);
        for _ in 0..10 {
            pacer.delay(start, 1000, 10_000);
        }
        assert!(pacer.delay(start, 1000, 10_000) > Duration::ZERO);
        // Ten milliseconds later the 11 kB have left: a burst again.
        let later = start + Duration::from_millis(11);
        for _ in 0..10 {
            assert_eq!(pacer.delay(later, 1000, 10_000), Duration::ZERO);
        }
    }

    #[test]
    fn a_datagram_larger_than_the_burst_waits_for_an_idle_pacer_only() {
        let start = Instant::now();
        let mut pacer = Pacer::new(1_000_000);
        assert_eq!(pacer.delay(start, 5000, 1000), Duration::ZERO);
        // The next waits until the first has left at the rate.
        assert_eq!(pacer.delay(start, 5000, 1000), Duration::from_millis(5));
    }

    #[test]
    fn the_burst_is_half_the_smallest_buffer_and_at_least_a_datagram() {
        assert_eq!(
            burst_for([Some(8 << 20), Some(4 << 20)], 0, 60_000),
            Some(2 << 20)
        );
        // One that announces none counts as the host's default.
        assert_eq!(
            burst_for([Some(8 << 20), None], 425_984, 60_000),
            Some(212_992)
        );
        assert_eq!(burst_for([Some(50_000)], 0, 60_000), Some(60_000));
        assert_eq!(burst_for([], 0, 60_000), None);
    }

    #[test]
    fn extreme_values_do_not_overflow() {
        let now = Instant::now();
        let mut pacer = Pacer::new(0);
        assert_eq!(pacer.rate(), 1);
        let d = pacer.delay(now, 1 << 20, usize::MAX);
        assert_eq!(d, Duration::ZERO);
        let mut fast = Pacer::new(u64::MAX);
        assert_eq!(fast.delay(now, usize::MAX, 0), Duration::ZERO);
    }
}

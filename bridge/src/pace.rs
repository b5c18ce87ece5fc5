//! How an imported message leaves on its site: at once, or in a batch.
//!
//! A bridge publishes what comes in from Zenoh with pulicast's batching,
//! but without its delay. A message of a channel that sent nothing for
//! [`QUIET`] leaves at once, in a datagram of its own (no wait, and no
//! batch for anyone to flush); the messages that follow it closely (Zenoh
//! hands over the samples of one of its batches one after the other) join
//! the channel's batch, and the first of them wakes the bridge's flusher,
//! which sends whatever gathered meanwhile. A busy channel so crosses the
//! local hop at batch rates, not one send per message.
//!
//! Lock-free, for the Zenoh callbacks of several links at once, and free of
//! clocks: the caller passes the time.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

/// A channel that sent nothing for this long is quiet.
pub const QUIET: Duration = Duration::from_micros(100);

/// One imported channel's pacing. Times are ns on any monotonic clock that
/// starts at or after 0 (a channel is quiet from the start).
#[derive(Debug, Default)]
pub struct Pacer {
    /// Messages wait in the batch and the flusher was woken for them.
    pending: AtomicBool,
    /// When a datagram (a message alone, or a batch) last left.
    sent_at: AtomicU64,
    /// Whether anything was sent yet.
    started: AtomicBool,
}

impl Pacer {
    /// Whether a message published at `now` leaves alone: the channel is
    /// quiet and no batch waits. Asked before publishing; changes nothing.
    pub fn alone(&self, now: u64) -> bool {
        let quiet = !self.started.load(Ordering::Relaxed)
            || now.saturating_sub(self.sent_at.load(Ordering::Relaxed)) > QUIET.as_nanos() as u64;
        quiet && !self.pending.load(Ordering::Acquire)
    }

    /// A message joined the batch (told after it is in it): whether the
    /// flusher must be woken (nobody asked it since it last took the
    /// batch). A flusher that took the batch before the message joined is
    /// so always asked again.
    pub fn batched(&self) -> bool {
        !self.pending.swap(true, Ordering::AcqRel)
    }

    /// A datagram left at `now`: a message alone, or a flushed batch.
    pub fn sent(&self, now: u64) {
        self.sent_at.store(now, Ordering::Relaxed);
        self.started.store(true, Ordering::Relaxed);
    }

    /// The flusher takes the batch, before it sends it: a message that
    /// joins after this wakes it again.
    pub fn flushing(&self) {
        self.pending.swap(false, Ordering::AcqRel);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const US: u64 = 1_000;

    #[test]
    fn a_quiet_channel_sends_at_once_and_a_busy_one_batches() {
        let pacer = Pacer::default();
        // The first message, and one after a quiet spell, leave alone.
        assert!(pacer.alone(0));
        pacer.sent(0);
        // Those that follow closely are batched; the first wakes the
        // flusher, the others find it on its way.
        assert!(!pacer.alone(US));
        assert!(pacer.batched());
        assert!(!pacer.alone(2 * US));
        assert!(!pacer.batched());
        assert!(!pacer.alone(500 * US), "a batch waits");
        assert!(!pacer.batched());
        // The flusher takes the batch and sends it.
        pacer.flushing();
        pacer.sent(501 * US);
        // Soon after a batch left: batched again, with a new wake-up.
        assert!(!pacer.alone(550 * US));
        assert!(pacer.batched());
        pacer.flushing();
        pacer.sent(560 * US);
        // Quiet for longer than QUIET: alone again.
        assert!(pacer.alone(561 * US + 100 * US));
    }

    #[test]
    fn a_message_that_joins_after_the_flusher_took_the_batch_wakes_it_again() {
        let pacer = Pacer::default();
        pacer.sent(0);
        assert!(!pacer.alone(US));
        assert!(pacer.batched(), "the first of a batch wakes the flusher");
        // A second message is decided "batched", but before it is in the
        // batch the flusher takes and sends the batch.
        assert!(!pacer.alone(2 * US));
        pacer.flushing();
        pacer.sent(3 * US);
        // It joins a new batch, and it is the one to wake the flusher.
        assert!(pacer.batched());
    }

    #[test]
    fn a_message_never_goes_alone_past_a_waiting_batch() {
        let pacer = Pacer::default();
        pacer.sent(0);
        assert!(!pacer.alone(US));
        assert!(pacer.batched());
        // The flusher is slow: the channel looks quiet by the clock, but a
        // batch waits, so the message joins it, and the flusher, already
        // woken, sends both in one datagram.
        assert!(!pacer.alone(10_000 * US));
        assert!(!pacer.batched());
    }
}

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

/// How a message leaves, as [`Pacer::leave`] decides.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Leave {
    /// At once, in a datagram of its own; then tell [`Pacer::sent`].
    Alone,
    /// Into the channel's batch; `wake`: the flusher must be woken (the
    /// first message of a batch), else it is on its way.
    Batched {
        /// Whether to wake the flusher.
        wake: bool,
    },
}

impl Pacer {
    /// How a message published at `now` leaves. Called before publishing;
    /// for [`Leave::Batched`] the message must be in the batch before the
    /// flusher is woken.
    pub fn leave(&self, now: u64) -> Leave {
        let quiet = !self.started.load(Ordering::Relaxed)
            || now.saturating_sub(self.sent_at.load(Ordering::Relaxed)) > QUIET.as_nanos() as u64;
        if quiet && !self.pending.load(Ordering::Acquire) {
            return Leave::Alone;
        }
        Leave::Batched {
            wake: !self.pending.swap(true, Ordering::AcqRel),
        }
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
        assert_eq!(pacer.leave(0), Leave::Alone);
        pacer.sent(0);
        // Those that follow closely are batched; the first wakes the
        // flusher, the others find it on its way.
        assert_eq!(pacer.leave(US), Leave::Batched { wake: true });
        assert_eq!(pacer.leave(2 * US), Leave::Batched { wake: false });
        assert_eq!(pacer.leave(500 * US), Leave::Batched { wake: false });
        // The flusher takes the batch and sends it.
        pacer.flushing();
        pacer.sent(501 * US);
        // Soon after a batch left: batched again, with a new wake-up.
        assert_eq!(pacer.leave(550 * US), Leave::Batched { wake: true });
        pacer.flushing();
        pacer.sent(560 * US);
        // Quiet for longer than QUIET: alone again.
        assert_eq!(pacer.leave(561 * US + 100 * US), Leave::Alone);
    }

    #[test]
    fn a_message_never_goes_alone_past_a_waiting_batch() {
        let pacer = Pacer::default();
        pacer.sent(0);
        assert_eq!(pacer.leave(US), Leave::Batched { wake: true });
        // The flusher is slow: the channel looks quiet by the clock, but a
        // batch waits, so the message joins it, and the flusher, already
        // woken, sends both in one datagram.
        assert_eq!(pacer.leave(10_000 * US), Leave::Batched { wake: false });
    }
}

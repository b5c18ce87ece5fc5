//! Opt-in batching on the publish side: the pending batch of each channel and
//! the thread that sends batches whose delay is up.
//!
//! The wire format is in [`crate::proto::batch`]. A publish on a batching
//! channel appends to the channel's pending batch and sends it when the next
//! message would not fit; a batch that stops filling is sent by the flusher
//! thread before its delay is up. The flusher is a plain thread waiting on a
//! condition variable rather than a tokio timer: tokio's timer wheel has 1 ms
//! granularity, too coarse for delays of a few hundred microseconds.

use std::sync::{Arc, Condvar, Mutex, Weak};
use std::time::{Duration, Instant};

use crate::node::{lock, ChannelState, Inner};
use crate::proto::batch::BatchBuilder;

/// The longest batching delay allowed: longer would hold messages past the
/// point where anyone would still call them live.
pub const MAX_BATCH_DELAY: Duration = Duration::from_secs(1);

/// The pending batch of one channel.
#[derive(Debug, Default)]
pub(crate) struct ChannelBatch {
    /// The configured delay; `None` while batching is off.
    pub max_delay: Option<Duration>,
    pub builder: BatchBuilder,
    /// When the oldest message of the pending batch was published.
    pub started: Option<Instant>,
}

impl ChannelBatch {
    /// When the pending batch must be sent, if there is one.
    ///
    /// A little ahead of the configured delay, so that the flusher's wake-up
    /// lag (the kernel's 50 µs timer slack plus scheduling) does not push a
    /// message past it.
    pub fn deadline(&self) -> Option<Instant> {
        let started = self.started?;
        let delay = self.max_delay.unwrap_or(Duration::ZERO);
        Some(started + delay - slack(delay))
    }
}

/// How long before a batch is due the flusher stops sleeping and polls.
const SPIN_AHEAD: Duration = Duration::from_micros(100);

/// How much earlier than its delay a batch is due.
fn slack(delay: Duration) -> Duration {
    (delay / 4).min(Duration::from_micros(250))
}

/// The channels that batch, and the thread that flushes them on time.
#[derive(Default)]
pub(crate) struct Flusher {
    state: Mutex<FlusherState>,
    wake: Condvar,
}

#[derive(Default)]
struct FlusherState {
    channels: Vec<Arc<ChannelState>>,
    /// The earliest deadline the thread knows of.
    next: Option<Instant>,
    started: bool,
    stopped: bool,
}

impl Flusher {
    /// Adds a channel to the ones flushed on time, starting the thread with
    /// the first.
    pub fn register(self: &Arc<Self>, inner: Weak<Inner>, channel: &Arc<ChannelState>) {
        let mut state = lock(&self.state);
        if state.stopped {
            return;
        }
        if !state.channels.iter().any(|c| Arc::ptr_eq(c, channel)) {
            state.channels.push(Arc::clone(channel));
        }
        if !state.started {
            let flusher = Arc::clone(self);
            let spawned = std::thread::Builder::new()
                .name("pulicast-flush".into())
                .spawn(move || flusher.run(inner));
            match spawned {
                Ok(_) => state.started = true,
                // Batches still go out when full or at the next publish after
                // their delay; only the timely flush of idle ones is lost.
                Err(e) => tracing::warn!("could not start the batch flusher thread: {e}"),
            }
        }
    }

    /// The channels that ever batched.
    pub fn channels(&self) -> Vec<Arc<ChannelState>> {
        lock(&self.state).channels.clone()
    }

    /// Whether any channel batches (cheap: for the heartbeat path).
    pub fn is_used(&self) -> bool {
        !lock(&self.state).channels.is_empty()
    }

    /// Tells the thread about a new batch due at `deadline`.
    pub fn schedule(&self, deadline: Instant) {
        let mut state = lock(&self.state);
        if state.next.is_none_or(|next| deadline < next) {
            state.next = Some(deadline);
            self.wake.notify_one();
        }
    }

    /// Ends the thread. Pending batches are the caller's to flush.
    pub fn stop(&self) {
        lock(&self.state).stopped = true;
        self.wake.notify_one();
    }

    fn run(&self, inner: Weak<Inner>) {
        let mut state = lock(&self.state);
        let mut last_error: Option<Instant> = None;
        loop {
            if state.stopped {
                return;
            }
            let Some(node) = inner.upgrade() else { return };
            let now = Instant::now();
            let mut next: Option<Instant> = None;
            for channel in &state.channels {
                let mut batch = lock(&channel.batch);
                match batch.deadline() {
                    Some(due) if due <= now => {
                        if let Err(e) = node.flush_batch(channel, &mut batch) {
                            if last_error.is_none_or(|at| now - at > Duration::from_secs(1)) {
                                tracing::warn!(channel = %channel.name, "{e}");
                                last_error = Some(now);
                            }
                        }
                    }
                    Some(due) => next = Some(next.map_or(due, |n| n.min(due))),
                    None => {}
                }
            }
            drop(node);
            state.next = next;
            let left = next.map(|due| due.saturating_duration_since(Instant::now()));
            state = match left {
                // A sleeping thread wakes up to a hundred µs late (timer
                // slack, an idle CPU's wake-up), which would eat short
                // delays: sleep until shortly before, then poll.
                Some(left) if left <= SPIN_AHEAD => {
                    drop(state);
                    std::thread::yield_now();
                    lock(&self.state)
                }
                Some(left) => {
                    self.wake
                        .wait_timeout(state, left.saturating_sub(SPIN_AHEAD))
                        .unwrap_or_else(|p| p.into_inner())
                        .0
                }
                None => self.wake.wait(state).unwrap_or_else(|p| p.into_inner()),
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_are_due_before_their_delay() {
        let start = Instant::now();
        let mut batch = ChannelBatch {
            max_delay: Some(Duration::from_millis(2)),
            started: Some(start),
            ..Default::default()
        };
        assert_eq!(
            batch.deadline(),
            Some(start + Duration::from_micros(2000 - 250))
        );
        batch.max_delay = Some(Duration::from_micros(100));
        assert_eq!(batch.deadline(), Some(start + Duration::from_micros(75)));
        // Batching turned off with messages pending: due at once.
        batch.max_delay = None;
        assert_eq!(batch.deadline(), Some(start));
        batch.started = None;
        assert_eq!(batch.deadline(), None);
    }
}

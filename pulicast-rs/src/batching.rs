//! Opt-in batching on the publish side: the pending batch of each channel and
//! the thread that sends batches whose delay is up.
//!
//! The wire format is in [`crate::wire::batch`]. A publish on a batching
//! channel appends to the channel's pending batch and sends it when the next
//! message would not fit; a batch that stops filling is sent by the flusher
//! thread before its delay is up. The flusher is a plain thread waiting on a
//! condition variable rather than a tokio timer: tokio's timer wheel has 1 ms
//! granularity, too coarse for delays of a few hundred microseconds.

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use crate::error::Error;
use crate::sync::lock;

/// How long before a batch is due the flusher stops sleeping and polls.
const SPIN_AHEAD: Duration = Duration::from_micros(100);

/// A channel the flusher sends the batches of: the node's side, so that
/// this module needs nothing of the node.
pub(crate) trait Flush: Send + Sync + 'static {
    /// Sends the channel's pending batch if it is due at `now`.
    fn flush_due(&self, now: Instant) -> Flushed;
    /// Whether `other` is the same channel.
    fn is(&self, other: &Self) -> bool;
    /// The channel's name, for the log.
    fn channel(&self) -> &str;
}

/// What [`Flush::flush_due`] did.
pub(crate) enum Flushed {
    /// Sent what was due; a batch still pending is due then.
    Pending(Option<Instant>),
    /// Sending failed.
    Failed(Error),
    /// The node is gone: the thread ends.
    Gone,
}

/// The channels that batch, and the thread that flushes them on time.
pub(crate) struct Flusher<F> {
    state: Mutex<FlusherState<F>>,
    wake: Condvar,
}

impl<F> Default for Flusher<F> {
    fn default() -> Self {
        Self {
            state: Mutex::new(FlusherState {
                channels: Vec::new(),
                next: None,
                started: false,
                stopped: false,
            }),
            wake: Condvar::new(),
        }
    }
}

struct FlusherState<F> {
    channels: Vec<Arc<F>>,
    /// The earliest deadline the thread knows of.
    next: Option<Instant>,
    started: bool,
    stopped: bool,
}

impl<F: Flush> Flusher<F> {
    /// Adds a channel to the ones flushed on time, starting the thread with
    /// the first.
    pub(crate) fn register(self: &Arc<Self>, channel: Arc<F>) {
        let mut state = lock(&self.state);
        if state.stopped {
            return;
        }
        if !state.channels.iter().any(|c| c.is(&channel)) {
            state.channels.push(channel);
        }
        if !state.started {
            let flusher = Arc::clone(self);
            let spawned = std::thread::Builder::new()
                .name("pulicast-flush".into())
                .spawn(move || flusher.run());
            match spawned {
                Ok(_) => state.started = true,
                // Batches still go out when full or at the next publish after
                // their delay; only the timely flush of idle ones is lost.
                Err(e) => tracing::warn!("could not start the batch flusher thread: {e}"),
            }
        }
    }

    /// The channels that ever batched.
    pub(crate) fn channels(&self) -> Vec<Arc<F>> {
        lock(&self.state).channels.clone()
    }

    /// Whether any channel batches (cheap: for the heartbeat path).
    pub(crate) fn is_used(&self) -> bool {
        !lock(&self.state).channels.is_empty()
    }

    /// Tells the thread about a new batch due at `deadline`.
    pub(crate) fn schedule(&self, deadline: Instant) {
        let mut state = lock(&self.state);
        if state.next.is_none_or(|next| deadline < next) {
            state.next = Some(deadline);
            self.wake.notify_one();
        }
    }

    /// Ends the thread. Pending batches are the caller's to flush.
    pub(crate) fn stop(&self) {
        lock(&self.state).stopped = true;
        self.wake.notify_one();
    }

    fn run(&self) {
        let mut state = lock(&self.state);
        let mut last_error: Option<Instant> = None;
        loop {
            if state.stopped {
                return;
            }
            let now = Instant::now();
            let mut next: Option<Instant> = None;
            for channel in &state.channels {
                match channel.flush_due(now) {
                    Flushed::Pending(Some(due)) => next = Some(next.map_or(due, |n| n.min(due))),
                    Flushed::Pending(None) => {}
                    Flushed::Failed(e) => {
                        if last_error.is_none_or(|at| now - at > Duration::from_secs(1)) {
                            tracing::warn!(channel = %channel.channel(), "{e}");
                            last_error = Some(now);
                        }
                    }
                    Flushed::Gone => return,
                }
            }
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

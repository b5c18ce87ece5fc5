//! Who drives a `start_blocking` node's runtime: the node's own thread, or
//! a thread that waits in a blocking receive.
//!
//! A blocking receive that parks on the queue's condition variable while
//! the node's thread reads the socket costs two wake-ups per message (the
//! node's thread by the datagram, then the consumer by the node's thread)
//! and a third busy thread on the CPUs. Instead, a thread that would wait
//! drives the runtime itself (`Runtime::block_on`): the datagram wakes it
//! directly, and the receive loop hands the message over on the same
//! thread, as a raw blocking `recv` would. The node's thread lets go of the
//! runtime when a consumer wants it, and takes it back once no consumer has
//! driven it for [`IDLE`], so timers and sockets are never left alone for
//! longer than that.

use std::sync::{Arc, Condvar, Mutex, Weak};
use std::time::{Duration, Instant};

use tokio::runtime::Runtime;

use super::Inner;
use crate::queue::{Entry, Items, Queue};
use crate::sync::lock;

/// How long after the last consumer left the node's thread takes the
/// runtime back: short enough for timers (heartbeats and gossip run at tens
/// of milliseconds), long enough that a consumer in a receive loop keeps it
/// between messages.
const IDLE: Duration = Duration::from_millis(2);

/// The runtime of a `start_blocking` node and who drives it.
pub(crate) struct OwnRuntime {
    /// The node's thread holds the runtime; consumers borrow it while they
    /// drive (and the last one to let go drops it outside any runtime).
    runtime: Weak<Runtime>,
    state: Mutex<Drivers>,
    /// Wakes the node's thread when consumers leave or the node stops.
    changed: Condvar,
    /// Tells the node's thread, inside `block_on`, to let go.
    wanted: tokio::sync::Notify,
}

struct Drivers {
    /// Consumers that drive, or wait to.
    consumers: usize,
    /// When the last consumer let go.
    last_left: Instant,
    /// Whether the node's thread is in (or about to enter) `block_on`.
    node_driving: bool,
    /// Whether the node's thread waits for a consumer to leave, without a
    /// time-out: the last to leave then wakes it. (While it waits with a
    /// time-out, leaving costs nothing: a consumer in a receive loop leaves
    /// once per message.)
    node_waits_untimed: bool,
}

impl OwnRuntime {
    pub(crate) fn new(runtime: &Arc<Runtime>) -> Arc<Self> {
        Arc::new(Self {
            runtime: Arc::downgrade(runtime),
            state: Mutex::new(Drivers {
                consumers: 0,
                last_left: Instant::now(),
                // The node's thread drives first.
                node_driving: true,
                node_waits_untimed: false,
            }),
            changed: Condvar::new(),
            wanted: tokio::sync::Notify::new(),
        })
    }

    /// The node's thread: drives the runtime until `inner` stops, letting
    /// consumers drive it while they wait.
    pub(crate) fn run(&self, runtime: &Runtime, inner: &Inner) {
        loop {
            runtime.block_on(async {
                tokio::select! {
                    _ = inner.wait_stopped() => {}
                    _ = self.wanted.notified() => {}
                }
            });
            lock(&self.state).node_driving = false;
            if inner.is_stopped() || !self.wait_for_idle(inner) {
                return;
            }
        }
    }

    /// Waits until no consumer has driven for [`IDLE`], then marks the
    /// node's thread as driving; false if the node stopped meanwhile.
    ///
    /// It looks every [`IDLE`] while consumers come and go, and waits
    /// without a time-out (costing nothing) once a consumer has stayed in
    /// for a whole [`IDLE`]: one waiting long in a blocking receive.
    fn wait_for_idle(&self, inner: &Inner) -> bool {
        let mut state = lock(&self.state);
        loop {
            if inner.is_stopped() {
                return false;
            }
            let idle = state.last_left.elapsed();
            if state.consumers == 0 {
                if idle >= IDLE {
                    state.node_driving = true;
                    return true;
                }
                state = self.wait(state, Some(IDLE - idle));
            } else if idle >= IDLE {
                state.node_waits_untimed = true;
                state = self.wait(state, None);
                state.node_waits_untimed = false;
                // Woken by the last consumer leaving: it may be back soon.
                state = self.wait(state, Some(IDLE));
            } else {
                state = self.wait(state, Some(IDLE - idle));
            }
        }
    }

    fn wait<'a>(
        &self,
        state: std::sync::MutexGuard<'a, Drivers>,
        timeout: Option<Duration>,
    ) -> std::sync::MutexGuard<'a, Drivers> {
        match timeout {
            None => self.changed.wait(state).unwrap_or_else(|p| p.into_inner()),
            Some(timeout) => {
                self.changed
                    .wait_timeout(state, timeout)
                    .unwrap_or_else(|p| p.into_inner())
                    .0
            }
        }
    }

    /// Wakes the node's thread if it waits for consumers (the node stopped).
    pub(crate) fn stopped(&self) {
        // Under the lock, so the wake can't fall between its check of the
        // stop and its wait.
        let _state = lock(&self.state);
        self.changed.notify_all();
    }

    /// Runs `wait` on the runtime from this thread, if it may drive it:
    /// `None` if it may not (the node's runtime is gone, or this thread is
    /// already in a runtime, where `block_on` is not allowed).
    fn drive<R>(&self, wait: impl std::future::Future<Output = R>) -> Option<R> {
        if tokio::runtime::Handle::try_current().is_ok() {
            return None;
        }
        let runtime = self.runtime.upgrade()?;
        {
            let mut state = lock(&self.state);
            state.consumers += 1;
            if state.node_driving {
                self.wanted.notify_one();
            }
        }
        let result = runtime.block_on(wait);
        {
            let mut state = lock(&self.state);
            state.consumers -= 1;
            state.last_left = Instant::now();
            if state.consumers == 0 && state.node_waits_untimed {
                self.changed.notify_one();
            }
        }
        Some(result)
    }
}

impl Inner {
    /// Waits, blocking the thread, until `take` finds something in `queue`
    /// or `deadline` passes; `None` on time out or once the queue is closed
    /// and empty. On a `start_blocking` node the waiting thread drives the
    /// node's runtime meanwhile (see the module's docs).
    pub(crate) fn wait_blocking<T: Entry, R>(
        &self,
        queue: &Queue<T>,
        deadline: Option<Instant>,
        mut take: impl FnMut(&mut Items<T>) -> Option<R>,
    ) -> Option<R> {
        if let Some(found) = queue.try_take(&mut take) {
            return Some(found);
        }
        if super::delivery::in_handler() {
            // This thread drives the node's receiving: waiting here would
            // stop what fills the queue. Say so, and don't wait.
            self.counters.blocking_receive_in_handler();
            return None;
        }
        let Some(own) = &self.lifecycle.own_runtime else {
            return queue.wait_for_blocking(deadline, take);
        };
        let wait = async {
            match deadline {
                None => queue.wait_for(&mut take).await,
                Some(deadline) => {
                    let deadline = tokio::time::Instant::from_std(deadline);
                    tokio::time::timeout_at(deadline, queue.wait_for(&mut take))
                        .await
                        .ok()
                        .flatten()
                }
            }
        };
        match own.drive(wait) {
            Some(found) => found,
            None => queue.wait_for_blocking(deadline, take),
        }
    }
}

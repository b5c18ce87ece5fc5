//! The bounded queue between the receive loop and one subscription.
//!
//! The receive loop never waits on it: when it is full, the policy decides
//! which message goes ([`QueuePolicy`]), and the drop is counted. The
//! subscriber waits asynchronously ([`Queue::recv`], through tokio's
//! `Notify`, which allocates nothing) or blocking ([`Queue::recv_blocking`],
//! through a condition variable).

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

/// What a full subscription queue does with a new message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[non_exhaustive]
pub enum QueuePolicy {
    /// Drop the oldest queued message to make room: a slow subscriber sees
    /// the latest data (the right choice for state such as poses).
    #[default]
    DropOldest,
    /// Drop the new message: a slow subscriber sees a contiguous prefix
    /// (the right choice for logs and event streams).
    DropNewest,
}

struct State<T> {
    items: VecDeque<T>,
    closed: bool,
    /// Threads waiting in `recv_blocking`: waking a condition variable is a
    /// system call, which a push pays only when someone waits there.
    blocked: usize,
}

/// A bounded multi-producer queue with one consumer.
pub(crate) struct Queue<T> {
    state: Mutex<State<T>>,
    capacity: usize,
    policy: QueuePolicy,
    notify: Notify,
    condvar: Condvar,
}

/// What happened to a pushed message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Pushed {
    /// Queued.
    Queued,
    /// Queued, and the oldest message dropped to make room.
    DroppedOldest,
    /// Not queued: the queue was full.
    DroppedNew,
    /// Not queued: the subscription is gone.
    Closed,
}

/// The deadline of a wait of `timeout` from now, for
/// [`Queue::recv_blocking`]: the queue is where waiting reads the clock.
pub(crate) fn deadline(timeout: Duration) -> Instant {
    Instant::now() + timeout
}

impl<T> Queue<T> {
    pub(crate) fn new(capacity: usize, policy: QueuePolicy) -> Self {
        Self {
            state: Mutex::new(State {
                items: VecDeque::with_capacity(capacity.min(1024)),
                closed: false,
                blocked: 0,
            }),
            capacity: capacity.max(1),
            policy,
            notify: Notify::new(),
            condvar: Condvar::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State<T>> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues `item` by the policy; never waits.
    pub(crate) fn push(&self, item: T) -> Pushed {
        match self.push_many(std::iter::once(item)) {
            None => Pushed::Closed,
            Some(0) => Pushed::Queued,
            Some(_) => match self.policy {
                QueuePolicy::DropOldest => Pushed::DroppedOldest,
                QueuePolicy::DropNewest => Pushed::DroppedNew,
            },
        }
    }

    /// Queues every item by the policy under one lock, waking the consumer
    /// once; returns how many were dropped (new or old), or `None` if the
    /// queue is closed.
    pub(crate) fn push_many(&self, items: impl IntoIterator<Item = T>) -> Option<usize> {
        let mut state = self.lock();
        if state.closed {
            return None;
        }
        let mut dropped = 0;
        for item in items {
            if state.items.len() >= self.capacity {
                dropped += 1;
                match self.policy {
                    QueuePolicy::DropOldest => {
                        state.items.pop_front();
                    }
                    QueuePolicy::DropNewest => continue,
                }
            }
            state.items.push_back(item);
        }
        let blocked = state.blocked > 0;
        drop(state);
        self.notify.notify_one();
        if blocked {
            self.condvar.notify_one();
        }
        Some(dropped)
    }

    /// Ends the queue: what is queued can still be taken, then `None`.
    pub(crate) fn close(&self) {
        self.lock().closed = true;
        self.notify.notify_one();
        self.condvar.notify_all();
    }

    /// The next item without waiting.
    pub(crate) fn try_recv(&self) -> Option<T> {
        self.lock().items.pop_front()
    }

    /// Items waiting.
    pub(crate) fn len(&self) -> usize {
        self.lock().items.len()
    }

    /// The next item; `None` once closed and empty.
    pub(crate) async fn recv(&self) -> Option<T> {
        self.wait_for(VecDeque::pop_front).await
    }

    /// Waits until items are queued, then moves up to `max` of them (at
    /// least one) to `out` under one lock; 0 once closed and empty.
    pub(crate) async fn recv_many(&self, out: &mut Vec<T>, max: usize) -> usize {
        if max == 0 {
            return 0;
        }
        self.wait_for(|items| take_many(items, out, max))
            .await
            .unwrap_or(0)
    }

    /// Moves up to `max` queued items to `out` without waiting.
    pub(crate) fn try_recv_many(&self, out: &mut Vec<T>, max: usize) -> usize {
        take_many(&mut self.lock().items, out, max).unwrap_or(0)
    }

    /// Blocks until the next item, or `deadline`; `None` on time out or
    /// once closed and empty. (Subscriptions wait through
    /// `Inner::wait_blocking`, which may drive the node's runtime instead.)
    #[cfg(test)]
    pub(crate) fn recv_blocking(&self, deadline: Option<Instant>) -> Option<T> {
        self.wait_for_blocking(deadline, VecDeque::pop_front)
    }

    /// Like [`Queue::recv_many`], blocking until `deadline`; 0 on time out.
    #[cfg(test)]
    pub(crate) fn recv_many_blocking(
        &self,
        out: &mut Vec<T>,
        max: usize,
        deadline: Option<Instant>,
    ) -> usize {
        if max == 0 {
            return 0;
        }
        self.wait_for_blocking(deadline, |items| take_many(items, out, max))
            .unwrap_or(0)
    }

    /// What `take` finds in the queue now, without waiting.
    pub(crate) fn try_take<R>(
        &self,
        take: impl FnOnce(&mut VecDeque<T>) -> Option<R>,
    ) -> Option<R> {
        take(&mut self.lock().items)
    }

    /// Waits until `take` finds something in the queue; `None` once closed
    /// and empty.
    pub(crate) async fn wait_for<R>(
        &self,
        mut take: impl FnMut(&mut VecDeque<T>) -> Option<R>,
    ) -> Option<R> {
        loop {
            // Register interest before looking, so a push in between wakes us
            // (a notify_one with nobody waiting leaves a permit anyway).
            let notified = self.notify.notified();
            {
                let mut state = self.lock();
                if let Some(found) = take(&mut state.items) {
                    return Some(found);
                }
                if state.closed {
                    return None;
                }
            }
            notified.await;
        }
    }

    /// Like [`Queue::wait_for`], blocking the thread until `deadline`.
    pub(crate) fn wait_for_blocking<R>(
        &self,
        deadline: Option<Instant>,
        mut take: impl FnMut(&mut VecDeque<T>) -> Option<R>,
    ) -> Option<R> {
        let mut state = self.lock();
        loop {
            if let Some(found) = take(&mut state.items) {
                return Some(found);
            }
            if state.closed {
                return None;
            }
            let left = match deadline {
                None => None,
                Some(deadline) => Some(deadline.checked_duration_since(Instant::now())?),
            };
            state.blocked += 1;
            state = match left {
                None => self.condvar.wait(state).unwrap_or_else(|p| p.into_inner()),
                Some(left) => {
                    self.condvar
                        .wait_timeout(state, left)
                        .unwrap_or_else(|p| p.into_inner())
                        .0
                }
            };
            state.blocked -= 1;
        }
    }
}

/// Moves up to `max` items from the front of `items` to `out`; `None` if
/// none was queued (or `max` is 0).
pub(crate) fn take_many<T>(items: &mut VecDeque<T>, out: &mut Vec<T>, max: usize) -> Option<usize> {
    let n = items.len().min(max);
    if n == 0 {
        return None;
    }
    out.extend(items.drain(..n));
    Some(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn policies() {
        let q = Queue::new(2, QueuePolicy::DropOldest);
        assert_eq!(q.push(1), Pushed::Queued);
        assert_eq!(q.push(2), Pushed::Queued);
        assert_eq!(q.push(3), Pushed::DroppedOldest);
        assert_eq!(
            (q.try_recv(), q.try_recv(), q.try_recv()),
            (Some(2), Some(3), None)
        );
        let q = Queue::new(2, QueuePolicy::DropNewest);
        for i in 1..=3 {
            let _ = q.push(i);
        }
        assert_eq!(
            (q.try_recv(), q.try_recv(), q.try_recv()),
            (Some(1), Some(2), None)
        );
        q.close();
        assert_eq!(q.push(4), Pushed::Closed);
        assert_eq!(q.recv_blocking(None), None);
    }

    #[test]
    fn pushing_many_follows_the_policy_like_single_pushes() {
        let q = Queue::new(3, QueuePolicy::DropOldest);
        assert_eq!(q.push_many(1..=5), Some(2));
        assert_eq!(
            (q.try_recv(), q.try_recv(), q.try_recv(), q.try_recv()),
            (Some(3), Some(4), Some(5), None)
        );
        let q = Queue::new(3, QueuePolicy::DropNewest);
        assert_eq!(q.push_many(1..=5), Some(2));
        assert_eq!(
            (q.try_recv(), q.try_recv(), q.try_recv(), q.try_recv()),
            (Some(1), Some(2), Some(3), None)
        );
        q.close();
        assert_eq!(q.push_many(1..=2), None);
    }

    #[test]
    fn blocking_receive_wakes_on_push_and_times_out() {
        let q = std::sync::Arc::new(Queue::new(4, QueuePolicy::DropOldest));
        let pusher = std::sync::Arc::clone(&q);
        let t = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(20));
            pusher.push(9)
        });
        assert_eq!(q.recv_blocking(None), Some(9));
        assert_eq!(t.join().unwrap(), Pushed::Queued);
        let soon = Instant::now() + std::time::Duration::from_millis(10);
        assert_eq!(q.recv_blocking(Some(soon)), None);
    }

    #[test]
    fn receiving_many_takes_what_is_queued_up_to_the_limit() {
        let q = Queue::new(8, QueuePolicy::DropOldest);
        let mut out = Vec::new();
        assert_eq!(q.try_recv_many(&mut out, 4), 0);
        let _ = q.push_many(1..=6);
        assert_eq!(q.try_recv_many(&mut out, 4), 4);
        assert_eq!(q.recv_many_blocking(&mut out, 0, Some(Instant::now())), 0);
        assert_eq!(q.recv_many_blocking(&mut out, 10, None), 2);
        assert_eq!(out, [1, 2, 3, 4, 5, 6]);
        let soon = Instant::now() + std::time::Duration::from_millis(10);
        assert_eq!(q.recv_many_blocking(&mut out, 10, Some(soon)), 0);
        let _ = q.push(7);
        q.close();
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        assert_eq!(rt.block_on(q.recv_many(&mut out, 10)), 1);
        assert_eq!(rt.block_on(q.recv_many(&mut out, 10)), 0);
        assert_eq!(out.last(), Some(&7));
    }

    #[tokio::test]
    async fn async_receive_wakes_on_push_and_ends_on_close() {
        let q = std::sync::Arc::new(Queue::new(4, QueuePolicy::DropOldest));
        let pusher = std::sync::Arc::clone(&q);
        tokio::spawn(async move {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
            pusher.push(5);
            pusher.close();
        });
        assert_eq!(q.recv().await, Some(5));
        assert_eq!(q.recv().await, None);
    }
}

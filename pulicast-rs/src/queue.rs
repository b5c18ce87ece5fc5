//! The bounded queue between the receive loop and one subscription.
//!
//! The receive loop never waits on it: when it is full, the policy decides
//! which message goes ([`QueuePolicy`]), and the drop is counted. The
//! subscriber waits asynchronously ([`Queue::recv`], through tokio's
//! `Notify`, which allocates nothing) or blocking (through a condition
//! variable, or by driving the node: `Inner::wait_blocking`).
//!
//! An entry may hold several messages (a batch datagram kept whole, see
//! [`Entry`]). The capacity counts entries, each at most one datagram's
//! worth of bytes: a batch takes one slot, as one message does, so a queue
//! holds the same bytes at most whether its publisher batches or not, and
//! a batching publisher's stream fits it. The policies drop whole entries.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

/// What a full subscription queue does with a new message.
///
/// # Example
///
/// ```no_run
/// # async fn demo() -> pulicast::Result<()> {
/// use pulicast::{DropReason, Node, QueuePolicy};
/// // A logger wants a gap-free prefix rather than the latest value:
/// let node = Node::new("logger")
///     .queue_capacity(4096)
///     .queue_policy(QueuePolicy::DropNewest)
///     .start()
///     .await?;
/// let mut events = node.channel("events").subscribe::<String>()?;
/// # let _ = events.try_recv();
/// println!("lost to overflow: {}", node.stats().dropped(DropReason::QueueOverflow));
/// # Ok(()) }
/// ```
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

/// One entry of a [`Queue`]: one message, or several taken out in order.
pub(crate) trait Entry: Sized {
    /// What a consumer takes out.
    type Message;
    /// Messages it holds: at least 1 when queued.
    fn messages(&self) -> usize;
    /// Takes its first message out; `None` once it holds none.
    fn pop(&mut self) -> Option<Self::Message>;
}

/// A queue's entries and how many messages they hold.
pub(crate) struct Items<T> {
    entries: VecDeque<T>,
    messages: usize,
}

impl<T: Entry> Items<T> {
    /// Takes the first message out.
    pub(crate) fn pop(&mut self) -> Option<T::Message> {
        loop {
            let front = self.entries.front_mut()?;
            if let Some(message) = front.pop() {
                self.messages -= 1;
                if front.messages() == 0 {
                    self.entries.pop_front();
                }
                return Some(message);
            }
            // An entry with nothing left (not kept by push): drop it.
            self.entries.pop_front();
        }
    }

    /// Moves up to `max` messages from the front to `out`; `None` if none
    /// was queued (or `max` is 0).
    pub(crate) fn take_many(&mut self, out: &mut Vec<T::Message>, max: usize) -> Option<usize> {
        let mut n = 0;
        while n < max {
            match self.pop() {
                Some(message) => out.push(message),
                None => break,
            }
            n += 1;
        }
        (n > 0).then_some(n)
    }

    /// Drops the first entry; returns the messages it held.
    fn drop_front(&mut self) -> usize {
        let held = self.entries.pop_front().map_or(0, |e| e.messages());
        self.messages -= held;
        held
    }
}

struct State<T> {
    items: Items<T>,
    closed: bool,
    /// Threads waiting in a blocking receive: waking a condition variable
    /// is a system call, which a push pays only when someone waits there.
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

/// The deadline of a wait of `timeout` from now, for a blocking receive
/// (the queue is where waiting reads the clock); `None`, no deadline, for
/// a timeout too long to add to the clock (`Duration::MAX`).
pub(crate) fn deadline(timeout: Duration) -> Option<Instant> {
    Instant::now().checked_add(timeout)
}

impl<T: Entry> Queue<T> {
    pub(crate) fn new(capacity: usize, policy: QueuePolicy) -> Self {
        Self {
            state: Mutex::new(State {
                items: Items {
                    // Grown as messages come: a subscription that never
                    // fills (most, and a bridge's thousands of exports) costs
                    // no more than a few entries.
                    entries: VecDeque::with_capacity(capacity.min(16)),
                    messages: 0,
                },
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

    /// Queues every entry by the policy under one lock, waking the consumer
    /// once; returns how many messages were dropped (new or old), or
    /// `None` if the queue is closed.
    pub(crate) fn push_many(&self, entries: impl IntoIterator<Item = T>) -> Option<usize> {
        let mut state = self.lock();
        if state.closed {
            return None;
        }
        let items = &mut state.items;
        let mut dropped = 0;
        for entry in entries {
            let held = entry.messages();
            if held == 0 {
                continue;
            }
            if items.entries.len() >= self.capacity {
                match self.policy {
                    QueuePolicy::DropOldest => dropped += items.drop_front(),
                    QueuePolicy::DropNewest => {
                        dropped += held;
                        continue;
                    }
                }
            }
            items.messages += held;
            items.entries.push_back(entry);
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

    /// The next message without waiting.
    pub(crate) fn try_recv(&self) -> Option<T::Message> {
        self.lock().items.pop()
    }

    /// Messages waiting.
    pub(crate) fn len(&self) -> usize {
        self.lock().items.messages
    }

    /// The next message; `None` once closed and empty.
    pub(crate) async fn recv(&self) -> Option<T::Message> {
        self.wait_for(Items::pop).await
    }

    /// Waits until messages are queued, then moves up to `max` of them (at
    /// least one) to `out` under one lock; 0 once closed and empty.
    pub(crate) async fn recv_many(&self, out: &mut Vec<T::Message>, max: usize) -> usize {
        if max == 0 {
            return 0;
        }
        self.wait_for(|items| items.take_many(out, max))
            .await
            .unwrap_or(0)
    }

    /// Moves up to `max` queued messages to `out` without waiting.
    pub(crate) fn try_recv_many(&self, out: &mut Vec<T::Message>, max: usize) -> usize {
        self.lock().items.take_many(out, max).unwrap_or(0)
    }

    /// Blocks until the next message, or `deadline`; `None` on time out or
    /// once closed and empty. (Subscriptions wait through
    /// `Inner::wait_blocking`, which may drive the node's runtime instead.)
    #[cfg(test)]
    pub(crate) fn recv_blocking(&self, deadline: Option<Instant>) -> Option<T::Message> {
        self.wait_for_blocking(deadline, Items::pop)
    }

    /// Like [`Queue::recv_many`], blocking until `deadline`; 0 on time out.
    #[cfg(test)]
    pub(crate) fn recv_many_blocking(
        &self,
        out: &mut Vec<T::Message>,
        max: usize,
        deadline: Option<Instant>,
    ) -> usize {
        if max == 0 {
            return 0;
        }
        self.wait_for_blocking(deadline, |items| items.take_many(out, max))
            .unwrap_or(0)
    }

    /// What `take` finds in the queue now, without waiting.
    pub(crate) fn try_take<R>(&self, take: impl FnOnce(&mut Items<T>) -> Option<R>) -> Option<R> {
        take(&mut self.lock().items)
    }

    /// Waits until `take` finds something in the queue; `None` once closed
    /// and empty.
    pub(crate) async fn wait_for<R>(
        &self,
        mut take: impl FnMut(&mut Items<T>) -> Option<R>,
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
        mut take: impl FnMut(&mut Items<T>) -> Option<R>,
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

/// A queue entry of one message of its own, for queues whose entries are
/// never batches.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct One<T>(pub(crate) Option<T>);

impl<T> Entry for One<T> {
    type Message = T;

    fn messages(&self) -> usize {
        usize::from(self.0.is_some())
    }

    fn pop(&mut self) -> Option<T> {
        self.0.take()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(v: i32) -> One<i32> {
        One(Some(v))
    }

    /// Several messages in one entry, as a batch is.
    #[derive(Debug)]
    struct Run(VecDeque<i32>);

    impl Entry for Run {
        type Message = i32;
        fn messages(&self) -> usize {
            self.0.len()
        }
        fn pop(&mut self) -> Option<i32> {
            self.0.pop_front()
        }
    }

    fn run(values: std::ops::RangeInclusive<i32>) -> Run {
        Run(values.collect())
    }

    fn drain<T: Entry>(q: &Queue<T>) -> Vec<T::Message> {
        std::iter::from_fn(|| q.try_recv()).collect()
    }

    #[test]
    fn policies() {
        let q = Queue::new(2, QueuePolicy::DropOldest);
        assert_eq!(q.push(one(1)), Pushed::Queued);
        assert_eq!(q.push(one(2)), Pushed::Queued);
        assert_eq!(q.push(one(3)), Pushed::DroppedOldest);
        assert_eq!(drain(&q), [2, 3]);
        let q = Queue::new(2, QueuePolicy::DropNewest);
        for i in 1..=3 {
            let _ = q.push(one(i));
        }
        assert_eq!(drain(&q), [1, 2]);
        q.close();
        assert_eq!(q.push(one(4)), Pushed::Closed);
        assert_eq!(q.recv_blocking(None), None);
    }

    #[test]
    fn pushing_many_follows_the_policy_like_single_pushes() {
        let q = Queue::new(3, QueuePolicy::DropOldest);
        assert_eq!(q.push_many((1..=5).map(one)), Some(2));
        assert_eq!(drain(&q), [3, 4, 5]);
        let q = Queue::new(3, QueuePolicy::DropNewest);
        assert_eq!(q.push_many((1..=5).map(one)), Some(2));
        assert_eq!(drain(&q), [1, 2, 3]);
        q.close();
        assert_eq!(q.push_many((1..=2).map(one)), None);
    }

    /// An entry of several messages takes one slot, and the policies drop
    /// whole entries (counting their messages); messages are taken out
    /// across entries, a part of one left for later.
    #[test]
    fn entries_of_several_messages_take_one_slot_each() {
        let q = Queue::new(2, QueuePolicy::DropOldest);
        assert_eq!(q.push_many([run(1..=3), run(4..=6)]), Some(0));
        assert_eq!(q.len(), 6);
        assert_eq!(q.push(run(7..=8)), Pushed::DroppedOldest);
        assert_eq!(q.len(), 5);
        assert_eq!(drain(&q), [4, 5, 6, 7, 8]);

        let q = Queue::new(2, QueuePolicy::DropNewest);
        assert_eq!(q.push_many([run(1..=3), run(4..=6), run(7..=8)]), Some(2));
        assert_eq!(drain(&q), [1, 2, 3, 4, 5, 6]);

        let q = Queue::new(10, QueuePolicy::DropOldest);
        let _ = q.push_many([run(1..=3), run(4..=6)]);
        let mut out = Vec::new();
        assert_eq!(q.try_recv_many(&mut out, 4), 4);
        assert_eq!((out, q.len()), (vec![1, 2, 3, 4], 2));
        // A partly taken entry still takes its slot, and goes first.
        let q2 = Queue::new(1, QueuePolicy::DropNewest);
        let _ = q2.push(run(1..=3));
        assert_eq!(q2.try_recv(), Some(1));
        assert_eq!(q2.push(run(4..=4)), Pushed::DroppedNew);
        assert_eq!(drain(&q2), [2, 3]);
        assert_eq!(drain(&q), [5, 6]);
        assert_eq!(q.len(), 0);
    }

    #[test]
    fn receiving_many_takes_what_is_queued_up_to_the_limit() {
        let q = Queue::new(8, QueuePolicy::DropOldest);
        let mut out = Vec::new();
        assert_eq!(q.try_recv_many(&mut out, 4), 0);
        let _ = q.push_many((1..=6).map(one));
        assert_eq!(q.try_recv_many(&mut out, 4), 4);
        assert_eq!(q.recv_many_blocking(&mut out, 0, Some(Instant::now())), 0);
        assert_eq!(q.recv_many_blocking(&mut out, 10, None), 2);
        assert_eq!(out, [1, 2, 3, 4, 5, 6]);
        let soon = Instant::now() + std::time::Duration::from_millis(10);
        assert_eq!(q.recv_many_blocking(&mut out, 10, Some(soon)), 0);
        let _ = q.push(one(7));
        q.close();
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        assert_eq!(rt.block_on(q.recv_many(&mut out, 10)), 1);
        assert_eq!(rt.block_on(q.recv_many(&mut out, 10)), 0);
        assert_eq!(out.last(), Some(&7));
    }

    #[test]
    fn blocking_receive_wakes_on_push_and_times_out() {
        let q = std::sync::Arc::new(Queue::new(4, QueuePolicy::DropOldest));
        let pusher = std::sync::Arc::clone(&q);
        let t = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(20));
            pusher.push(one(9))
        });
        assert_eq!(q.recv_blocking(None), Some(9));
        assert_eq!(t.join().unwrap(), Pushed::Queued);
        let soon = Instant::now() + std::time::Duration::from_millis(10);
        assert_eq!(q.recv_blocking(Some(soon)), None);
    }

    #[tokio::test]
    async fn async_receive_wakes_on_push_and_ends_on_close() {
        let q = std::sync::Arc::new(Queue::new(4, QueuePolicy::DropOldest));
        let pusher = std::sync::Arc::clone(&q);
        tokio::spawn(async move {
            tokio::time::sleep(std::time::Duration::from_millis(10)).await;
            pusher.push(one(5));
            pusher.close();
        });
        assert_eq!(q.recv().await, Some(5));
        assert_eq!(q.recv().await, None);
    }
}

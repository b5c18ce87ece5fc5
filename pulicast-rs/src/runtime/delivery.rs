//! Where received messages go: a subscription's queue or a handler. The
//! receiver fills a [`Delivery`] under its lock; handlers' messages wait
//! in an [`Outbox`] and are called once the lock is released, so a handler
//! may publish, subscribe and unsubscribe.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use crate::proto::receiver::{RawBatch, RawMessage, Sink};
use crate::queue::{Entry, Queue};
use crate::stats::Counters;
use crate::sync::lock;

/// Where a subscriber's messages go, as the receiver fills it: a
/// subscription's queue, or a handler's place in its receiver's outbox.
/// Dropped when the subscription is removed or the node stops: a queue
/// closes (the subscriber's `recv` ends), a handler is called no more.
pub(crate) enum Delivery {
    /// A [`crate::Subscription`]'s queue.
    Queue(Arc<Queue<Queued>>),
    /// A [`crate::CallbackSubscription`]'s handler, called by the receive
    /// loop once the receiver is unlocked ([`Inner::call_handlers`]).
    Handler {
        handler: Arc<Handler>,
        outbox: Arc<Mutex<Outbox>>,
    },
}

impl Drop for Delivery {
    fn drop(&mut self) {
        match self {
            Delivery::Queue(queue) => queue.close(),
            Delivery::Handler { handler, .. } => handler.end(),
        }
    }
}

impl Sink for Delivery {
    fn push_many(&mut self, messages: impl Iterator<Item = RawMessage>) -> usize {
        match self {
            Delivery::Queue(queue) => queue
                .push_many(messages.map(|m| Queued::One(Some(m))))
                .unwrap_or(0),
            Delivery::Handler { handler, outbox } => {
                let mut outbox = lock(outbox);
                outbox.messages.extend(messages);
                let end = outbox.messages.len();
                outbox.runs.push((Arc::clone(handler), Run::Messages(end)));
                0
            }
        }
    }

    fn push_batch(&mut self, batch: &RawBatch) -> usize {
        match self {
            Delivery::Handler { handler, outbox } => {
                // Kept whole: the handler's call takes the messages out, so
                // none is copied into the outbox.
                let run = Run::Batch(batch.clone());
                lock(outbox).runs.push((Arc::clone(handler), run));
                0
            }
            // One entry for the batch: no message is copied into the
            // queue, and it takes one slot, as one datagram.
            Delivery::Queue(queue) => queue
                .push_many(std::iter::once(Queued::Batch(batch.clone())))
                .unwrap_or(0),
        }
    }
}

/// What a [`Handler`] calls: it decodes (for a typed handler) and calls
/// the user's closure; true if it did (the message decoded).
type Call = Box<dyn FnMut(RawMessage, &Counters) -> bool + Send>;

/// An entry of a subscription's queue: one message, or a batch datagram
/// kept whole and taken apart as it is received.
pub(crate) enum Queued {
    One(Option<RawMessage>),
    Batch(RawBatch),
}

impl Entry for Queued {
    type Message = RawMessage;

    fn messages(&self) -> usize {
        match self {
            Queued::One(m) => usize::from(m.is_some()),
            Queued::Batch(batch) => batch.len(),
        }
    }

    fn pop(&mut self) -> Option<RawMessage> {
        match self {
            Queued::One(m) => m.take(),
            Queued::Batch(batch) => batch.pop(),
        }
    }
}

/// A callback subscription's handler, type-erased.
pub(crate) struct Handler {
    call: Mutex<Call>,
    /// Cleared when the subscription ends: messages still in an outbox are
    /// then not handed to it.
    live: AtomicBool,
}

impl Handler {
    pub(crate) fn new(call: impl FnMut(RawMessage, &Counters) -> bool + Send + 'static) -> Self {
        Self {
            call: Mutex::new(Box::new(call)),
            live: AtomicBool::new(true),
        }
    }

    /// Calls nothing more, from now on.
    pub(crate) fn end(&self) {
        self.live.store(false, Ordering::Release);
    }

    /// Hands `messages` to the closure, one by one, unless the subscription
    /// ended. A panic in the closure is caught and logged, so it can't stop
    /// the receive loop, which serves other subscriptions too.
    pub(super) fn call(&self, messages: impl Iterator<Item = RawMessage>, counters: &Counters) {
        let mut call = lock(&self.call);
        let mut delivered = 0;
        let called = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            IN_HANDLER.with(|h| h.set(true));
            for message in messages {
                // Per message: a subscription dropped during a long run
                // (by another thread, or by the handler itself) sees no
                // further call once its drop returned.
                if !self.live.load(Ordering::Acquire) {
                    break;
                }
                delivered += u64::from((*call)(message, counters));
            }
        }));
        IN_HANDLER.with(|h| h.set(false));
        // Once per run, not per message: the counter is shared.
        counters
            .messages_delivered
            .fetch_add(delivered, Ordering::Relaxed);
        if called.is_err() {
            counters.handler_panicked();
        }
    }
}

thread_local! {
    /// Whether this thread is running a subscription's handler: a blocking
    /// receive there must not wait (see [`in_handler`]).
    static IN_HANDLER: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Whether the calling thread is inside a subscription's handler. A
/// handler runs on the thread that drives the node, so a blocking receive
/// waiting there would stop the very loop that fills its queue.
pub(crate) fn in_handler() -> bool {
    IN_HANDLER.with(std::cell::Cell::get)
}

/// Messages for handlers, put here by the receiver (under its lock) and
/// taken by the receive loop after it unlocked it: handlers run without
/// the receiver's lock, so they may publish, subscribe, unsubscribe and
/// read stats.
#[derive(Default)]
pub(crate) struct Outbox {
    pub(super) messages: Vec<RawMessage>,
    /// What each handler is to be called with, in order.
    pub(super) runs: Vec<(Arc<Handler>, Run)>,
}

/// One handler's messages in an [`Outbox`].
pub(super) enum Run {
    /// Those of `messages` up to this end (from the previous run's end).
    Messages(usize),
    /// A whole batch.
    Batch(RawBatch),
}

/// Where a new subscriber's messages go.
pub(super) enum To {
    Queue(Arc<Queue<Queued>>),
    Handler(Arc<Handler>),
}

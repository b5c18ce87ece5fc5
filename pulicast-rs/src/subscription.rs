//! Receiving: subscriptions, their queues, and received messages.

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;

use crate::proto::receiver::Expected;
use crate::proto::receiver::RawMessage;
use crate::proto::Lead;
use crate::queue::Queue;
use crate::runtime::{ChannelState, Inner};
use crate::wire::DecodeError;

/// One received message.
#[derive(Debug, Clone, PartialEq)]
pub struct Message<T> {
    /// The decoded value.
    pub value: T,
    /// The sender's socket address; one node may send from several.
    pub source: SocketAddr,
    /// The message's lead: 1 in order, > 1 after losses, <= 0 late or duplicate.
    /// See [`crate::proto::LeadTracker`].
    pub lead: Lead,
    /// The sender's sequence number for this channel.
    pub seq: u32,
}

/// A subscription to one channel, yielding messages of type `T`.
///
/// Made by [`crate::Channel::subscribe`], [`crate::Channel::subscribe_ordered`]
/// and [`crate::Channel::subscribe_raw`]. Receive asynchronously with
/// [`Subscription::recv`], or from plain threads with
/// [`Subscription::recv_blocking`], [`Subscription::recv_timeout`] and
/// [`Subscription::try_recv`]. Messages of another type are dropped before
/// they are queued, so they never take a valid message's place; messages that
/// fail to decode as `T` are dropped when received. Both are counted in
/// [`crate::Node::stats`] (once per subscription that drops them), logged
/// (rate-limited) and skipped.
///
/// Dropping the subscription unsubscribes. Each subscription buffers up to the
/// node's queue capacity; when it is full the node's [`QueuePolicy`](crate::QueuePolicy) drops a
/// message (the oldest by default), counted as [`DropReason::QueueOverflow`](crate::DropReason::QueueOverflow).
pub struct Subscription<T> {
    rx: Arc<Queue<RawMessage>>,
    decode: fn(&Bytes) -> Result<T, DecodeError>,
    guard: Unsubscribe,
}

impl<T> std::fmt::Debug for Subscription<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Subscription")
            .field("channel", &self.channel())
            .field("queued", &self.rx.len())
            .finish()
    }
}

struct Unsubscribe {
    inner: Arc<Inner>,
    channel: Arc<ChannelState>,
    id: u64,
}

impl Drop for Unsubscribe {
    fn drop(&mut self) {
        self.inner.unsubscribe(&self.channel, self.id);
    }
}

impl<T> Subscription<T> {
    pub(crate) fn new(
        inner: Arc<Inner>,
        channel: Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
        decode: fn(&Bytes) -> Result<T, DecodeError>,
    ) -> crate::Result<Self> {
        let (id, rx) = inner.subscribe(&channel, ordered, expected)?;
        Ok(Self {
            rx,
            decode,
            guard: Unsubscribe { inner, channel, id },
        })
    }

    /// The resolved name of the subscribed channel.
    pub fn channel(&self) -> &str {
        self.guard.channel.name()
    }

    /// Waits for the next message; `None` once the node has stopped.
    pub async fn recv(&mut self) -> Option<Message<T>> {
        loop {
            let raw = self.rx.recv().await?;
            if let Some(message) = self.decode(raw) {
                return Some(message);
            }
        }
    }

    /// Blocks the thread until the next message; `None` once the node has
    /// stopped. Don't call it from async code: use [`Subscription::recv`].
    pub fn recv_blocking(&mut self) -> Option<Message<T>> {
        loop {
            let raw = self.rx.recv_blocking(None)?;
            if let Some(message) = self.decode(raw) {
                return Some(message);
            }
        }
    }

    /// Blocks up to `timeout` for the next message; `None` if none came in
    /// time or the node has stopped.
    pub fn recv_timeout(&mut self, timeout: Duration) -> Option<Message<T>> {
        let deadline = crate::queue::deadline(timeout);
        loop {
            let raw = self.rx.recv_blocking(Some(deadline))?;
            if let Some(message) = self.decode(raw) {
                return Some(message);
            }
        }
    }

    /// The next queued message, without waiting.
    pub fn try_recv(&mut self) -> Option<Message<T>> {
        loop {
            let raw = self.rx.try_recv()?;
            if let Some(message) = self.decode(raw) {
                return Some(message);
            }
        }
    }

    /// Messages waiting in the queue (not yet decoded).
    pub fn queued(&self) -> usize {
        self.rx.len()
    }

    fn decode(&self, raw: RawMessage) -> Option<Message<T>> {
        let counters = &self.guard.inner.counters();
        match (self.decode)(&raw.payload) {
            Ok(value) => {
                counters.messages_delivered.fetch_add(1, Ordering::Relaxed);
                Some(Message {
                    value,
                    source: raw.source,
                    lead: raw.lead,
                    seq: raw.seq,
                })
            }
            Err(e) => {
                counters.drop_decode(&e, Some(self.channel()), raw.source);
                None
            }
        }
    }
}

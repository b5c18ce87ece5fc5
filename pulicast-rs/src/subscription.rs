//! Receiving: subscriptions, their queues, and received messages.

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::Bytes;

use crate::proto::receiver::Expected;
use crate::proto::receiver::RawMessage;
use crate::proto::Lead;
use crate::queue::{Items, Queue};
use crate::runtime::{ChannelState, Handler, Inner, Queued};
use crate::stats::Counters;
use crate::wire::DecodeError;

/// How a subscription makes a `T` of a payload (the raw one takes it as
/// it is, without touching its reference count).
pub(crate) type Decode<T> = fn(Bytes) -> Result<T, DecodeError>;

/// One received message.
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::Message;
/// let mut temps = node.channel("engine/temp").subscribe::<f32>()?;
/// while let Some(Message { value, source, lead, seq }) = temps.recv().await {
///     match lead {
///         1 => println!("{value} from {source} (#{seq})"),
///         n if n > 1 => println!("{value}; {} lost before it", n - 1),
///         _ => println!("{value} came late or twice"),
///     }
/// }
/// # Ok(()) }
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct Message<T> {
    /// The decoded value.
    pub value: T,
    /// The sender's socket address; one node may send from several.
    pub source: SocketAddr,
    /// The message's lead: 1 in order, > 1 after losses, <= 0 late or duplicate.
    /// See [`Lead`](crate::Lead).
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
/// node's queue capacity (in datagrams' worth: a message, or a batch of
/// them); when it is full the node's [`QueuePolicy`](crate::QueuePolicy) drops one (the
/// oldest by default), its messages counted as [`DropReason::QueueOverflow`](crate::DropReason::QueueOverflow).
/// A consumer of a fast or batched stream takes everything queued per
/// wake-up with [`Subscription::recv_many`], or subscribes a handler
/// instead ([`crate::Channel::subscribe_with`]).
///
/// # Example
///
/// ```no_run
/// # fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use std::time::Duration;
/// let mut poses = node.channel("pose").subscribe::<f64>()?; // dropping it unsubscribes
/// while let Some(m) = poses.recv_timeout(Duration::from_secs(1)) {
///     println!("{} from {} (seq {}, lead {})", m.value, m.source, m.seq, m.lead);
///     for more in poses.try_iter() {                        // the rest, without waiting
///         println!("and {}", more.value);
///     }
/// }
/// # Ok(()) }
/// ```
pub struct Subscription<T> {
    rx: Arc<Queue<Queued>>,
    decode: Decode<T>,
    /// Where `recv_many` takes messages out of the queue before decoding
    /// them; kept, so draining allocates nothing once it has grown.
    taken: Vec<RawMessage>,
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
    quiet: bool,
}

impl Drop for Unsubscribe {
    fn drop(&mut self) {
        self.inner.unsubscribe(&self.channel, self.id, self.quiet);
    }
}

impl<T> Subscription<T> {
    pub(crate) fn new(
        inner: Arc<Inner>,
        channel: Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
        decode: Decode<T>,
        quiet: bool,
    ) -> crate::Result<Self> {
        let (id, rx) = inner.subscribe(&channel, ordered, expected, quiet)?;
        Ok(Self {
            rx,
            decode,
            taken: Vec::new(),
            guard: Unsubscribe {
                inner,
                channel,
                id,
                quiet,
            },
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
    ///
    /// On a node of [`crate::NodeBuilder::start_blocking`], a thread that
    /// waits here drives the node itself (its receive loops, timers and
    /// handlers run on this thread meanwhile), so a datagram wakes this
    /// thread directly, as a raw socket's blocking `recv` would, with no
    /// hand-off from the node's thread. The node's thread takes over again
    /// within a few milliseconds once no thread waits. On a node of
    /// [`crate::NodeBuilder::start`], or when called inside a tokio runtime,
    /// it waits for the node's tasks to hand the message over.
    pub fn recv_blocking(&mut self) -> Option<Message<T>> {
        loop {
            let raw = self.wait(None)?;
            if let Some(message) = self.decode(raw) {
                return Some(message);
            }
        }
    }

    /// Blocks up to `timeout` for the next message; `None` if none came in
    /// time or the node has stopped.
    pub fn recv_timeout(&mut self, timeout: Duration) -> Option<Message<T>> {
        // What is queued is taken without reading the clock: a consumer
        // behind a batching publisher finds messages waiting most times.
        if let Some(message) = self.try_recv() {
            return Some(message);
        }
        let deadline = crate::queue::deadline(timeout);
        loop {
            let raw = self.wait(deadline)?;
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

    /// Waits until messages are queued, then appends up to `max` of them to
    /// `out` and returns how many: one wake-up for everything that came
    /// meanwhile, which is how a consumer keeps up with a fast (or batched)
    /// publisher. Returns 0 once the node has stopped, or at once if `max`
    /// is 0; otherwise at least 1.
    ///
    /// ```
    /// # use std::net::Ipv4Addr;
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> pulicast::Result<()> {
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("imu_logger")
    ///     .interface(Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start()
    ///     .await?;
    /// let imu = node.channel("imu/raw");
    /// let mut samples = imu.subscribe::<f64>()?;
    /// for i in 0..10 {
    ///     imu.publish(&f64::from(i))?;
    /// }
    /// let mut batch = Vec::with_capacity(256);
    /// let mut total = 0;
    /// while total < 10 {
    ///     batch.clear();
    ///     total += samples.recv_many(&mut batch, 256).await;
    ///     // ... process the batch ...
    /// }
    /// # Ok(())
    /// # }
    /// ```
    pub async fn recv_many(&mut self, out: &mut Vec<Message<T>>, max: usize) -> usize {
        loop {
            if self.rx.recv_many(&mut self.taken, max).await == 0 {
                return 0;
            }
            if let n @ 1.. = self.decode_taken(out) {
                return n;
            }
        }
    }

    /// Like [`Subscription::recv_many`], blocking the thread; 0 once the
    /// node has stopped (or `max` is 0).
    pub fn recv_many_blocking(&mut self, out: &mut Vec<Message<T>>, max: usize) -> usize {
        loop {
            if self.wait_many(max, None) == 0 {
                return 0;
            }
            if let n @ 1.. = self.decode_taken(out) {
                return n;
            }
        }
    }

    /// Like [`Subscription::recv_many_blocking`], waiting up to `timeout`
    /// for the first message; 0 if none came in time.
    pub fn recv_many_timeout(
        &mut self,
        out: &mut Vec<Message<T>>,
        max: usize,
        timeout: Duration,
    ) -> usize {
        if let n @ 1.. = self.try_recv_many(out, max) {
            return n;
        }
        let deadline = crate::queue::deadline(timeout);
        loop {
            if self.wait_many(max, deadline) == 0 {
                return 0;
            }
            if let n @ 1.. = self.decode_taken(out) {
                return n;
            }
        }
    }

    /// Appends up to `max` queued messages to `out` without waiting;
    /// returns how many.
    pub fn try_recv_many(&mut self, out: &mut Vec<Message<T>>, max: usize) -> usize {
        self.rx.try_recv_many(&mut self.taken, max);
        self.decode_taken(out)
    }

    /// An iterator over the messages queued now; it ends when the queue is
    /// empty, without waiting.
    pub fn try_iter(&mut self) -> impl Iterator<Item = Message<T>> + '_ {
        std::iter::from_fn(move || self.try_recv())
    }

    /// Messages waiting in the queue (not yet decoded).
    pub fn queued(&self) -> usize {
        self.rx.len()
    }

    /// Whether nothing more will come: the node has stopped. What is
    /// queued can still be taken. A thread that waits in slices (with
    /// [`Subscription::recv_many_timeout`], say) looks here to end.
    pub fn is_finished(&self) -> bool {
        self.guard.inner.is_stopped()
    }

    /// Blocks until the next queued message, or `deadline`.
    fn wait(&self, deadline: Option<Instant>) -> Option<RawMessage> {
        let inner = &self.guard.inner;
        inner.wait_blocking(&self.rx, deadline, Items::pop)
    }

    /// Blocks until messages are queued, or `deadline`, and moves up to
    /// `max` of them to `taken`; returns how many.
    fn wait_many(&mut self, max: usize, deadline: Option<Instant>) -> usize {
        if max == 0 {
            return 0;
        }
        let taken = &mut self.taken;
        let take = |items: &mut Items<Queued>| items.take_many(taken, max);
        let inner = &self.guard.inner;
        inner.wait_blocking(&self.rx, deadline, take).unwrap_or(0)
    }

    /// Decodes what `recv_many` took into `out`; returns how many decoded.
    fn decode_taken(&mut self, out: &mut Vec<Message<T>>) -> usize {
        let mut taken = std::mem::take(&mut self.taken);
        let before = out.len();
        let (counters, channel) = (self.guard.inner.counters(), self.channel());
        let decoded = taken
            .drain(..)
            .filter_map(|raw| decode_message(raw, self.decode, counters, channel));
        out.extend(decoded);
        self.taken = taken;
        let n = out.len() - before;
        counters
            .messages_delivered
            .fetch_add(n as u64, Ordering::Relaxed);
        n
    }

    fn decode(&self, raw: RawMessage) -> Option<Message<T>> {
        let counters = self.guard.inner.counters();
        let message = decode_message(raw, self.decode, counters, self.channel());
        if message.is_some() {
            counters.messages_delivered.fetch_add(1, Ordering::Relaxed);
        }
        message
    }
}

/// Decodes a received message as `T`, or counts and logs why it could not
/// be. (The caller counts what it delivers, once per run of messages.)
fn decode_message<T>(
    raw: RawMessage,
    decode: Decode<T>,
    counters: &Counters,
    channel: &str,
) -> Option<Message<T>> {
    let RawMessage {
        payload,
        source,
        seq,
        lead,
    } = raw;
    match decode(payload) {
        Ok(value) => Some(Message {
            value,
            source,
            lead,
            seq,
        }),
        Err(e) => {
            counters.drop_decode(&e, Some(channel), source);
            None
        }
    }
}

/// A subscription whose handler is called with each message, on the
/// node's receive path: no queue, no wake-up, no copy.
///
/// Made by [`crate::Channel::subscribe_with`],
/// [`crate::Channel::subscribe_ordered_with`] and
/// [`crate::Channel::subscribe_raw_with`]. Messages are filtered and counted
/// as for a [`Subscription`]; there is no queue to overflow.
///
/// The contract:
/// - The handler runs on the task that reads the channel's socket: on a
///   node of [`crate::NodeBuilder::start`], a task of that runtime; on a
///   node of [`crate::NodeBuilder::start_blocking`], the node's own thread,
///   or a thread of yours while it waits in a blocking receive of that
///   node (which drives the node meanwhile, see
///   [`Subscription::recv_blocking`]). It is called for one message at a
///   time, in the order they arrived.
/// - Keep it short. While it runs, that socket is not read: datagrams wait
///   in the kernel's receive buffer (and are lost once it is full), and
///   other channels on the same socket wait too; on a `start_blocking` node
///   discovery waits as well. For slow work, hand the message to another
///   thread (a `std::sync::mpsc` channel, or a [`Subscription`] instead).
/// - It may publish, subscribe, drop subscriptions (its own included) and
///   read [`crate::Node::stats`]: it runs with nothing of the node locked.
///   A blocking receive inside it does not wait (it returns what is queued,
///   or `None`, and logs a warning): it runs on the thread that receives
///   for the node, so waiting there would stop the node.
/// - A panic in it is caught, counted in [`crate::Stats::handler_panics`]
///   and logged; the next message calls it again.
/// - Dropping the `CallbackSubscription` unsubscribes: once `drop`
///   returns, no further call starts (one already running finishes), even
///   for the rest of a batch being handed out.
///
/// ```
/// use std::sync::mpsc;
/// # use std::{net::Ipv4Addr, time::Duration};
/// # let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("controller")
///     .interface(Ipv4Addr::LOCALHOST)
/// #   .port(port)
///     .start_blocking()?;
/// // Keep the handler short; hand heavy work to another thread.
/// let (work, todo) = mpsc::channel();
/// let _pose = node.channel("pose").subscribe_with(move |m: pulicast::Message<f64>| {
///     let _ = work.send(m.value);
/// })?;
/// node.channel("pose").publish(&1.5f64)?;
/// assert_eq!(todo.recv_timeout(Duration::from_secs(5)), Ok(1.5));
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
#[must_use = "dropping a CallbackSubscription unsubscribes: keep it while its handler should run"]
pub struct CallbackSubscription {
    handler: Arc<Handler>,
    guard: Unsubscribe,
}

impl std::fmt::Debug for CallbackSubscription {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CallbackSubscription")
            .field("channel", &self.channel())
            .finish()
    }
}

impl CallbackSubscription {
    pub(crate) fn new<T: 'static>(
        inner: Arc<Inner>,
        channel: Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
        decode: Decode<T>,
        mut handler: impl FnMut(Message<T>) + Send + 'static,
        quiet: bool,
    ) -> crate::Result<Self> {
        let name = Arc::clone(channel.name());
        let handler = Arc::new(Handler::new(
            move |raw, counters: &Counters| match decode_message(raw, decode, counters, &name) {
                Some(message) => {
                    handler(message);
                    true
                }
                None => false,
            },
        ));
        let id =
            inner.subscribe_handler(&channel, ordered, expected, Arc::clone(&handler), quiet)?;
        Ok(Self {
            handler,
            guard: Unsubscribe {
                inner,
                channel,
                id,
                quiet,
            },
        })
    }

    /// The resolved name of the subscribed channel.
    pub fn channel(&self) -> &str {
        self.guard.channel.name()
    }
}

impl Drop for CallbackSubscription {
    fn drop(&mut self) {
        // Before the receiver lets go of it: messages already in an outbox
        // must not reach the handler once drop returns.
        self.handler.end();
    }
}

//! The node's receive path: subscriptions, the receive loops that read the
//! sockets, and the driver of the [`Receiver`] (clock reads, the lock,
//! handing gossip and drop details on).

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::BytesMut;
use tokio::net::UdpSocket;

use super::delivery::{Delivery, Handler, Outbox, Queued, Run, To};
use super::receivers::Shard;
use super::{fleet, ChannelState, Inner};
use crate::error::{Error, Result};
use crate::proto::fragment::{Landed, Loan};
use crate::proto::receiver::{Expected, Subscriber};
use crate::proto::Receiver;
use crate::queue::Queue;
use crate::sync::lock;
use crate::wire;
use crate::wire::MAX_DATAGRAM;

impl Inner {
    /// Registers a subscriber with a queue on `channel`, joining its group
    /// if needed; returns its id and queue. A `quiet` one is not announced
    /// in discovery.
    pub(crate) fn subscribe(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
        quiet: bool,
    ) -> Result<(u64, Arc<Queue<Queued>>)> {
        let queue = Arc::new(Queue::new(
            self.tuning.queue_capacity,
            self.tuning.queue_policy,
        ));
        let to = To::Queue(Arc::clone(&queue));
        let id = self.add_subscriber(channel, ordered, expected, to, quiet)?;
        Ok((id, queue))
    }

    /// Registers a subscriber whose messages go to `handler`; returns its
    /// id. A `quiet` one is not announced in discovery.
    pub(crate) fn subscribe_handler(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
        handler: Arc<Handler>,
        quiet: bool,
    ) -> Result<u64> {
        self.add_subscriber(channel, ordered, expected, To::Handler(handler), quiet)
    }

    fn add_subscriber(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
        to: To,
        quiet: bool,
    ) -> Result<u64> {
        let id = self.channels.next_subscriber();
        let mut pool = lock(&self.receiving.pool);
        // stop() sets the flag before it takes this lock to clear the
        // receivers, so checking here means no subscription outlives a stop.
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let joined = pool
            .socket_of(channel.group)
            .map(|index| self.receiving.receivers.get(index))
            .filter(|shard| shard.lock().subscribes(&channel.name));
        let shard = match joined {
            Some(shard) => shard,
            None => {
                // A new receive socket is registered with the node's
                // runtime, also when a plain thread subscribes (a node of
                // `start_blocking`).
                let _runtime = self.lifecycle.runtime.enter();
                let (index, opened) = pool
                    .join(channel.group)
                    .map_err(Error::bind("joining a multicast group", self.identity.port))?;
                let shard = self.receiving.receivers.get(index);
                // The channel may have been handled by another receiver
                // before (its group left, then joined on another socket):
                // its replay windows come along, so what was refused there
                // is refused here.
                for other in self.receiving.receivers.all() {
                    if Arc::ptr_eq(&other, &shard) {
                        continue;
                    }
                    let windows = other.lock().take_windows(&channel.name);
                    if !windows.is_empty() {
                        shard.lock().put_windows(&channel.name, windows);
                    }
                }
                if let Some(socket) = opened {
                    self.receive_on(socket, Arc::clone(&shard));
                }
                shard
            }
        };
        let sink = match to {
            To::Queue(queue) => Delivery::Queue(queue),
            To::Handler(handler) => Delivery::Handler {
                handler,
                outbox: Arc::clone(&shard.outbox),
            },
        };
        let subscriber = Subscriber {
            id,
            ordered,
            expected,
            sink,
        };
        let _first = shard
            .lock()
            .subscribe(&channel.name, channel.sealed, subscriber);
        drop(pool);
        // Quiet ones are not counted: discovery announces the count.
        if !quiet && channel.subscribers.fetch_add(1, Ordering::Relaxed) == 0 {
            self.announce_change();
        }
        Ok(id)
    }

    /// Registers a handler on `channel` with a receiver outside the pool
    /// (it reads a socket that joins no group); returns its id.
    pub(super) fn subscribe_other(
        &self,
        shard: &Arc<Shard>,
        channel: &ChannelState,
        handler: Arc<Handler>,
    ) -> Result<u64> {
        let id = self.channels.next_subscriber();
        // Under the pool's lock, as any subscription: none outlives a stop.
        let pool = lock(&self.receiving.pool);
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let subscriber = Subscriber {
            id,
            ordered: false,
            expected: None,
            sink: Delivery::Handler {
                handler,
                outbox: Arc::clone(&shard.outbox),
            },
        };
        let _first = shard
            .lock()
            .subscribe(&channel.name, channel.sealed, subscriber);
        drop(pool);
        Ok(id)
    }

    /// Starts reading a receive socket the pool opened, into `shard`.
    pub(super) fn receive_on(self: &Arc<Self>, socket: Arc<UdpSocket>, shard: Arc<Shard>) {
        self.receiving.sockets.fetch_add(1, Ordering::Relaxed);
        let task = self
            .lifecycle
            .runtime
            .spawn(receive_loop(Arc::clone(self), socket, shard));
        self.add_task(task);
    }

    /// Removes a subscriber; leaves the group when its channel has none left.
    pub(crate) fn unsubscribe(&self, channel: &ChannelState, id: u64, quiet: bool) {
        let mut pool = lock(&self.receiving.pool);
        let Some(index) = pool.socket_of(channel.group) else {
            return;
        };
        let shard = self.receiving.receivers.get(index);
        let Some(removed) = shard.lock().unsubscribe(&channel.name, id) else {
            return;
        };
        if removed.last {
            pool.leave(channel.group);
        }
        drop(pool);
        if !quiet && channel.subscribers.fetch_sub(1, Ordering::Relaxed) == 1 {
            self.announce_change();
        }
    }

    /// Runs `f` on `shard`, then hands on what it gave out, after
    /// unlocking it: gossip to discovery, drops to the log (so a log layer
    /// may call `Node::stats`).
    pub(super) fn with_receiver<R>(
        &self,
        shard: &Shard,
        f: impl FnOnce(&mut Receiver<Delivery>) -> R,
    ) -> R {
        let mut receiver = shard.lock();
        let result = f(&mut receiver);
        // Usually both are empty, and collecting nothing allocates nothing.
        let gossip: Vec<_> = std::iter::from_fn(|| receiver.poll_gossip()).collect();
        let drops: Vec<_> = std::iter::from_fn(|| receiver.poll_drop()).collect();
        drop(receiver);
        for (source, datagram) in gossip {
            if !self.fleet.inbound(source, &datagram) {
                self.counters.drop_discovery_backlog(source);
            }
        }
        for dropped in &drops {
            self.counters.log.log(dropped);
        }
        result
    }

    /// Handles a datagram read from the socket of `shard` (see
    /// [`Receiver::handle_datagram`]); also returns the messages that
    /// receiver delivered so far, which the receive loop paces itself by.
    pub(super) fn handle_datagram(
        &self,
        shard: &Shard,
        buf: &mut BytesMut,
        source: SocketAddr,
    ) -> (Option<Loan>, u64) {
        let now = Instant::now();
        // The wall clock only dates sealed datagrams: not read for the rest.
        let unix_ms = match wire::Kind::of(buf) {
            wire::Kind::Sealed => fleet::unix_ms(),
            _ => 0,
        };
        let handled = self.with_receiver(shard, |rx| {
            let loan = rx.handle_datagram(now, unix_ms, source, buf);
            (loan, rx.counts().messages)
        });
        self.call_handlers(shard);
        handled
    }

    /// Hands the messages the receiver put in `shard`'s outbox to their
    /// handlers, on this thread, with the receiver unlocked.
    fn call_handlers(&self, shard: &Shard) {
        // Most datagrams are for queues: one lock to see there is nothing.
        if lock(&shard.outbox).runs.is_empty() {
            return;
        }
        let mut calling = lock(&shard.calling);
        {
            let mut outbox = lock(&shard.outbox);
            if outbox.runs.is_empty() {
                return;
            }
            std::mem::swap(&mut *outbox, &mut *calling);
        }
        let Outbox { messages, runs } = &mut *calling;
        let mut drained = messages.drain(..);
        let mut start = 0;
        for (handler, run) in runs.drain(..) {
            match run {
                Run::Messages(end) => {
                    let mut own = drained.by_ref().take(end - start);
                    handler.call(&mut own, &self.counters);
                    // What the handler left (it ended, or panicked) is its
                    // own: never the next handler's.
                    own.for_each(drop);
                    start = end;
                }
                Run::Batch(batch) => handler.call(batch.messages(), &self.counters),
            }
        }
        drop(drained);
        // A burst of unbatched messages for many handlers grows the
        // outboxes; what is far above the usual is given back.
        const KEEP: usize = 4096;
        if messages.capacity() > KEEP {
            messages.shrink_to(KEEP);
        }
        if runs.capacity() > KEEP {
            runs.shrink_to(KEEP);
        }
    }

    /// Takes back a loan (see [`Receiver::repay`]).
    pub(super) fn repay(&self, shard: &Shard, loan: Loan, received: bool) -> Option<Loan> {
        let next = self.with_receiver(shard, |rx| rx.repay(loan, received));
        self.call_handlers(shard);
        next
    }

    /// Opens a discovery datagram received by unicast, where it lies, and
    /// returns where the gossip in it is (see [`Receiver::open_gossip`]).
    /// The receiver of the socket that carries the discovery group opens
    /// it, so one replay window per sender covers both ways gossip comes.
    pub(crate) fn unseal_discovery(
        &self,
        datagram: &mut [u8],
        source: SocketAddr,
    ) -> Option<std::ops::Range<usize>> {
        let group = *fleet::group(self.identity.port).ip();
        let index = lock(&self.receiving.pool).socket_of(group).unwrap_or(0);
        let shard = self.receiving.receivers.get(index);
        let unix_ms = fleet::unix_ms();
        self.with_receiver(&shard, |rx| rx.open_gossip(unix_ms, source, datagram))
    }

    /// Gives up on fragmented messages that stopped arriving, when due
    /// (the reassembly is shared: any receiver expires it, the first
    /// counts the losses).
    pub(super) fn expire_fragments(&self) {
        let now = Instant::now();
        let shard = self.receiving.receivers.get(0);
        self.with_receiver(&shard, |rx| {
            if rx.poll_timeout().is_some_and(|due| now > due) {
                rx.handle_timeout(now);
            }
        });
    }
}

/// Messages a receive loop delivers before it lets other tasks run.
const YIELD_EVERY: u64 = 256;

/// Bytes a receive loop takes in before it lets other tasks run: a fraction
/// of the receive buffers kept for reuse.
const YIELD_BYTES: usize = ReceiveBuffers::SIZE / 2;

/// Reads datagrams from one receive socket until the node stops.
pub(super) async fn receive_loop(inner: Arc<Inner>, socket: Arc<UdpSocket>, shard: Arc<Shard>) {
    let mut buffers = ReceiveBuffers::default();
    let mut delivered = 0;
    let mut bytes = 0;
    let mut spin = Spin::new(inner.tuning.receive_spin);
    let mut loan: Option<Loan> = None;
    loop {
        let (received, len, messages) = match loan.take() {
            Some(l) => {
                let (next, len) =
                    receive_into(&inner, &shard, &socket, l, &mut spin, &mut buffers).await;
                let messages = match next {
                    AfterLoan::Loan(l) => {
                        loan = Some(l);
                        None
                    }
                    AfterLoan::Other(source) => {
                        let (next, messages) =
                            inner.handle_datagram(&shard, &mut buffers.current, source);
                        loan = next;
                        Some(messages)
                    }
                    AfterLoan::Nothing => None,
                };
                (len.is_some(), len.unwrap_or(0), messages)
            }
            None => {
                if buffers.is_unused() {
                    // The first buffer is taken when the first datagram
                    // comes: of a bridge's or a recorder's thousands of
                    // channels (a socket per 20), those that never carry a
                    // message (a stranger's names) cost no buffer.
                    let _ = socket.readable().await;
                }
                let buf = buffers.next();
                match receive(&socket, buf, &mut spin).await {
                    Ok((len, source)) => {
                        let (next, messages) = inner.handle_datagram(&shard, buf, source);
                        loan = next;
                        (true, len, Some(messages))
                    }
                    Err(e) => {
                        // Errors here are transient (e.g. an interface going
                        // away); back off a little so a persistent one can't
                        // spin the CPU.
                        tracing::debug!("receive failed: {e}");
                        tokio::time::sleep(Duration::from_millis(10)).await;
                        (false, 0, None)
                    }
                }
            }
        };
        if !received {
            continue;
        }
        // On a single-threaded runtime the subscribers only run when this
        // loop yields. tokio's budget makes it yield every 128 datagrams,
        // which is too rare twice over: a batch delivers hundreds of
        // messages per datagram, more than a queue may hold, and 128 large
        // datagrams pin more receive buffers than are kept for reuse (so
        // fresh ones, with their page faults, would be needed). So yield by
        // messages and by bytes as well.
        bytes += len;
        let messages = messages.unwrap_or(delivered);
        if messages.wrapping_sub(delivered) >= YIELD_EVERY || bytes >= YIELD_BYTES {
            delivered = messages;
            bytes = 0;
            tokio::task::yield_now().await;
        } else {
            tokio::task::consume_budget().await;
        }
    }
}

/// Receives one datagram into `buf`, polling briefly before parking.
pub(super) async fn receive(
    socket: &UdpSocket,
    buf: &mut BytesMut,
    spin: &mut Spin,
) -> std::io::Result<(usize, SocketAddr)> {
    let received = loop {
        match socket.try_recv_buf_from(buf) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if !spin.wait(socket).await {
                    break socket.recv_buf_from(buf).await;
                }
            }
            other => break other,
        }
    };
    spin.arrived();
    received
}

/// What [`receive_into`] leaves to do.
pub(super) enum AfterLoan {
    /// The fragment came; here is the loan for the one after.
    Loan(Loan),
    /// Another datagram came, now in the current receive buffer: handle it
    /// the ordinary way.
    Other(SocketAddr),
    /// Nothing (the message completed, or receiving failed).
    Nothing,
}

/// Receives the next datagram straight into a lent message buffer. If it is
/// the fragment the loan waits for, its chunk lands in place and no copy is
/// made; anything else is copied out (see [`Loan::land`]). Returns what to
/// do next and the datagram's length.
pub(super) async fn receive_into(
    inner: &Inner,
    shard: &Shard,
    socket: &UdpSocket,
    mut loan: Loan,
    spin: &mut Spin,
    buffers: &mut ReceiveBuffers,
) -> (AfterLoan, Option<usize>) {
    let Some(landing) = loan.prepare() else {
        // Too little before the chunk to hold the header: receive normally.
        let _none = inner.repay(shard, loan, false);
        return (AfterLoan::Nothing, None);
    };
    let received = receive(socket, &mut loan.data, spin).await;
    if let Err(e) = &received {
        tracing::debug!("receive failed: {e}");
    }
    let received = received.ok();
    match loan.land(landing, received, buffers.next()) {
        Landed::Awaited => {
            let todo = match inner.repay(shard, loan, true) {
                Some(next) => AfterLoan::Loan(next),
                None => AfterLoan::Nothing,
            };
            (todo, received.map(|(n, _)| n))
        }
        Landed::Other { source, len } => {
            let _none = inner.repay(shard, loan, false);
            (AfterLoan::Other(source), Some(len))
        }
        Landed::Nothing => {
            let _none = inner.repay(shard, loan, false);
            (AfterLoan::Nothing, None)
        }
    }
}

/// Adaptive busy-polling of a receive socket.
///
/// A receiver that parks between datagrams makes every sender pay for
/// waking it (on loopback, inside its `sendto`), and pays an idle CPU's
/// wake-up time itself (15-30 µs on these machines). When datagrams come
/// closer together than the spin time, the loop polls a little before it
/// parks: the next datagram is then picked up without a wake-up. When they
/// come further apart, it parks at once, so a quiet node burns no CPU.
pub(super) struct Spin {
    limit: Duration,
    /// When the last datagram arrived.
    last: Instant,
    /// The gap before it.
    gap: Duration,
}

impl Spin {
    pub(super) fn new(limit: Duration) -> Self {
        Self {
            limit,
            last: Instant::now(),
            gap: Duration::MAX,
        }
    }

    /// Notes an arrival.
    pub(super) fn arrived(&mut self) {
        if self.limit.is_zero() {
            return;
        }
        let now = Instant::now();
        self.gap = now - self.last;
        self.last = now;
    }

    /// Polls until the socket is readable or the spin time is up, letting
    /// other tasks run between polls; true if it became readable. Only when
    /// the last gap was short: otherwise false at once.
    pub(super) async fn wait(&mut self, socket: &UdpSocket) -> bool {
        if self.gap >= self.limit {
            return false;
        }
        let deadline = self.last + self.limit;
        while Instant::now() < deadline {
            // Yielding lets the runtime poll its I/O driver (without
            // blocking), which marks the socket readable when data came.
            tokio::task::yield_now().await;
            if socket
                .try_io(tokio::io::Interest::READABLE, || Ok(()))
                .is_ok()
            {
                return true;
            }
        }
        false
    }
}

/// Where datagrams are received: large buffers handed out as views, so
/// delivering a message costs no copy.
///
/// When the current buffer has no room for a full datagram, a buffer whose
/// messages have all been dropped is taken back (its memory already mapped,
/// so no allocation and no page faults); only while messages still hold all
/// of them is a new one allocated. Buffers that messages still hold beyond
/// the last few are let go: their memory is freed with the last message.
///
/// The first buffer is small and each new one twice the last, up to
/// [`ReceiveBuffers::SIZE`]: a node has a receive socket per 20 groups
/// joined, and a bridge or recorder of thousands of channels, most of them
/// quiet, must not hold 2 MiB for each socket.
#[derive(Default)]
pub(super) struct ReceiveBuffers {
    current: BytesMut,
    spare: std::collections::VecDeque<BytesMut>,
    /// The size of the last buffer allocated (0 before the first).
    size: usize,
}

impl ReceiveBuffers {
    const SIZE: usize = 2 << 20;
    const FIRST: usize = 128 << 10;
    const SPARES: usize = 4;

    /// Whether no buffer was taken yet.
    pub(super) fn is_unused(&self) -> bool {
        self.size == 0
    }

    /// An empty buffer with room for one full datagram.
    pub(super) fn next(&mut self) -> &mut BytesMut {
        self.current.clear();
        if self.current.capacity() <= MAX_DATAGRAM {
            let reclaimable = self.spare.iter_mut().position(|b| {
                b.clear();
                b.try_reclaim(MAX_DATAGRAM + 1)
            });
            let fresh = match reclaimable.and_then(|i| self.spare.remove(i)) {
                Some(reclaimed) => reclaimed,
                None => {
                    self.size = (self.size * 2).clamp(Self::FIRST, Self::SIZE);
                    BytesMut::with_capacity(self.size)
                }
            };
            let old = std::mem::replace(&mut self.current, fresh);
            self.spare.push_back(old);
            if self.spare.len() > Self::SPARES {
                self.spare.pop_front();
            }
        }
        &mut self.current
    }
}

#[cfg(test)]
mod tests {
    use std::net::Ipv4Addr;

    use super::*;
    use crate::name::group_for;

    /// Two receive sockets (more groups than one socket may join), the
    /// receiver of the first held locked as a busy receive loop would hold
    /// it: a message on a channel of the second socket still arrives. With
    /// one node-wide receiver lock it would wait for the first.
    #[test]
    fn a_busy_receiver_does_not_hold_up_another_socket() {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let node = rt
            .block_on(
                crate::Node::new("shards")
                    .port(crate::unused_port().unwrap())
                    .interface(Ipv4Addr::LOCALHOST)
                    // Nothing but the test's message reaches either socket.
                    .discovery(false)
                    .compat_heartbeat(false)
                    .keys_from_env(false)
                    .start(),
            )
            .unwrap();
        let inner = Arc::clone(node.runtime());
        let mut subscriptions = Vec::new();
        // The kernel's limit is 20 groups per socket by default; stop at
        // 1024 (its largest usual setting) if it is higher.
        for i in 0..1024 {
            let name = format!("shard/ch{i}");
            let subscription = node.channel(&name).subscribe::<i64>().unwrap();
            subscriptions.push((name, subscription));
            if node.stats().receive_sockets >= 2 {
                break;
            }
        }
        assert!(
            node.stats().receive_sockets >= 2,
            "one socket took 1024 groups"
        );
        assert_eq!(
            lock(&inner.receiving.pool).socket_of(group_for("shard/ch0")),
            Some(0)
        );
        let on_second =
            |name: &str| lock(&inner.receiving.pool).socket_of(group_for(name)) == Some(1);
        let (name, subscription) = subscriptions
            .iter_mut()
            .find(|(name, _)| on_second(name))
            .unwrap();

        let first = inner.receiving.receivers.get(0);
        let busy = first.lock();
        node.channel(name.as_str()).publish(&7i64).unwrap();
        let message = subscription.recv_timeout(Duration::from_secs(10));
        drop(busy);
        assert_eq!(message.map(|m| m.value), Some(7));
        assert_eq!(inner.receiving.receivers.get(1).lock().counts().messages, 1);
        node.stop();
    }

    #[test]
    fn receive_buffers_are_taken_back_once_their_messages_are_dropped() {
        let mut buffers = ReceiveBuffers::default();
        let mut bases = std::collections::HashSet::new();
        for round in 0..400 {
            let buf = buffers.next();
            // A buffer at its start (not part way through).
            if buf.capacity().is_power_of_two() && buf.capacity() >= ReceiveBuffers::FIRST {
                bases.insert(buf.as_ptr() as usize);
            }
            buf.extend_from_slice(&[round as u8; 60_000]);
            let message = buf.split().freeze();
            assert_eq!(message.len(), 60_000);
            drop(message);
        }
        // 400 x 60 kB went through two small buffers, taking turns: a
        // socket whose messages are let go at once never needs more.
        assert!(bases.len() <= 2, "{} buffers", bases.len());
        assert!(
            buffers.size <= 2 * ReceiveBuffers::FIRST,
            "{}",
            buffers.size
        );

        // While messages are held, new buffers are taken, each twice the
        // last up to the largest, and let go of later.
        let held: Vec<bytes::Bytes> = (0..100)
            .map(|_| {
                let buf = buffers.next();
                buf.extend_from_slice(&[7; 60_000]);
                buf.split().freeze()
            })
            .collect();
        assert!(held.iter().all(|m| m.len() == 60_000));
        assert_eq!(buffers.size, ReceiveBuffers::SIZE);
        assert!(buffers.spare.len() <= ReceiveBuffers::SPARES);
    }
}

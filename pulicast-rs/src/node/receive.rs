//! The node's receive path: subscriptions, the receive loops that read the
//! sockets, and the driver of the [`Receiver`] (clock reads, the lock,
//! handing gossip and drop details on).

use super::*;
use crate::wire;

impl Inner {
    /// Registers a subscriber on `channel`, joining its group if needed.
    pub(crate) fn subscribe(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
        ordered: bool,
        expected: Option<Expected>,
    ) -> Result<(u64, Arc<Queue<RawMessage>>)> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let id = self.next_subscriber.fetch_add(1, Ordering::Relaxed);
        let queue = Arc::new(Queue::new(self.queue_capacity, self.queue_policy));
        let subscriber = Subscriber {
            id,
            ordered,
            expected,
            sink: QueueSink(Arc::clone(&queue)),
        };
        let mut receiver = lock(&self.receiver);
        // stop() sets the flag before it clears the table under this lock, so
        // checking again here means no subscription outlives a stop.
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        if !receiver.subscribes(&channel.name) {
            let opened = lock(&self.pool)
                .join(channel.group)
                .map_err(Error::bind("joining a multicast group", self.port))?;
            if let Some(socket) = opened {
                let task = self.runtime.spawn(receive_loop(Arc::clone(self), socket));
                self.add_task(task);
            }
        }
        let _first = receiver.subscribe(&channel.name, channel.sealed, subscriber);
        if channel.subscribers.fetch_add(1, Ordering::Relaxed) == 0 {
            self.announce_change();
        }
        Ok((id, queue))
    }

    /// Removes a subscriber; leaves the group when its channel has none left.
    pub(crate) fn unsubscribe(&self, channel: &ChannelState, id: u64) {
        let mut receiver = lock(&self.receiver);
        let Some(removed) = receiver.unsubscribe(&channel.name, id) else {
            return;
        };
        if channel.subscribers.fetch_sub(1, Ordering::Relaxed) == 1 {
            self.announce_change();
        }
        if removed.last {
            lock(&self.pool).leave(channel.group);
        }
    }

    /// Runs `f` on the receiver, then hands on what it gave out, after
    /// unlocking it: gossip to discovery, drops to the log (so a log layer
    /// may call `Node::stats`).
    pub(super) fn with_receiver<R>(&self, f: impl FnOnce(&mut Receiver<QueueSink>) -> R) -> R {
        let mut receiver = lock(&self.receiver);
        let result = f(&mut receiver);
        // Usually both are empty, and collecting nothing allocates nothing.
        let gossip: Vec<_> = std::iter::from_fn(|| receiver.poll_gossip()).collect();
        let drops: Vec<_> = std::iter::from_fn(|| receiver.poll_drop()).collect();
        drop(receiver);
        for (source, datagram) in gossip {
            self.fleet.inbound(source, &datagram);
        }
        for dropped in &drops {
            self.counters.log.log(dropped);
        }
        result
    }

    /// Handles a datagram read from a receive socket (see
    /// [`Receiver::handle_datagram`]); also returns the messages received
    /// so far, which the receive loop paces itself by.
    pub(super) fn handle_datagram(
        &self,
        buf: &mut BytesMut,
        source: SocketAddr,
    ) -> (Option<Loan>, u64) {
        let now = Instant::now();
        // The wall clock only dates sealed datagrams: not read for the rest.
        let unix_ms = match wire::Kind::of(buf) {
            wire::Kind::Sealed => discovery::unix_ms(),
            _ => 0,
        };
        self.with_receiver(|rx| {
            let loan = rx.handle_datagram(now, unix_ms, source, buf);
            (loan, rx.counts().messages)
        })
    }

    /// Takes back a loan (see [`Receiver::repay`]).
    pub(super) fn repay(&self, loan: Loan, received: bool) -> Option<Loan> {
        self.with_receiver(|rx| rx.repay(loan, received))
    }

    /// Opens a discovery datagram received by unicast, where it lies, and
    /// returns where the gossip in it is (see [`Receiver::open_gossip`]).
    pub(crate) fn unseal_discovery(
        &self,
        datagram: &mut [u8],
        source: SocketAddr,
    ) -> Option<std::ops::Range<usize>> {
        let unix_ms = discovery::unix_ms();
        self.with_receiver(|rx| rx.open_gossip(unix_ms, source, datagram))
    }

    /// Gives up on fragmented messages that stopped arriving, when due.
    pub(super) fn expire_fragments(&self) {
        let now = Instant::now();
        self.with_receiver(|rx| {
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
pub(super) async fn receive_loop(inner: Arc<Inner>, socket: Arc<UdpSocket>) {
    let mut buffers = ReceiveBuffers::default();
    let mut delivered = 0;
    let mut bytes = 0;
    let mut spin = Spin::new(inner.receive_spin);
    let mut loan: Option<Loan> = None;
    loop {
        let (received, len, messages) = match loan.take() {
            Some(l) => {
                let (next, len) = receive_into(&inner, &socket, l, &mut spin, &mut buffers).await;
                let messages = match next {
                    AfterLoan::Loan(l) => {
                        loan = Some(l);
                        None
                    }
                    AfterLoan::Other(source) => {
                        let (next, messages) = inner.handle_datagram(&mut buffers.current, source);
                        loan = next;
                        Some(messages)
                    }
                    AfterLoan::Nothing => None,
                };
                (len.is_some(), len.unwrap_or(0), messages)
            }
            None => {
                let buf = buffers.next();
                match receive(&socket, buf, &mut spin).await {
                    Ok((len, source)) => {
                        let (next, messages) = inner.handle_datagram(buf, source);
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
    socket: &UdpSocket,
    mut loan: Loan,
    spin: &mut Spin,
    buffers: &mut ReceiveBuffers,
) -> (AfterLoan, Option<usize>) {
    let Some(landing) = loan.prepare() else {
        // Too little before the chunk to hold the header: receive normally.
        let _none = inner.repay(loan, false);
        return (AfterLoan::Nothing, None);
    };
    let received = receive(socket, &mut loan.data, spin).await;
    if let Err(e) = &received {
        tracing::debug!("receive failed: {e}");
    }
    let received = received.ok();
    match loan.land(landing, received, buffers.next()) {
        Landed::Awaited => {
            let todo = match inner.repay(loan, true) {
                Some(next) => AfterLoan::Loan(next),
                None => AfterLoan::Nothing,
            };
            (todo, received.map(|(n, _)| n))
        }
        Landed::Other { source, len } => {
            let _none = inner.repay(loan, false);
            (AfterLoan::Other(source), Some(len))
        }
        Landed::Nothing => {
            let _none = inner.repay(loan, false);
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
#[derive(Default)]
pub(super) struct ReceiveBuffers {
    current: BytesMut,
    spare: std::collections::VecDeque<BytesMut>,
}

impl ReceiveBuffers {
    const SIZE: usize = 2 << 20;
    const SPARES: usize = 4;

    /// An empty buffer with room for one full datagram.
    pub(super) fn next(&mut self) -> &mut BytesMut {
        self.current.clear();
        if self.current.capacity() <= MAX_DATAGRAM {
            let reclaimable = self.spare.iter_mut().position(|b| {
                b.clear();
                b.try_reclaim(Self::SIZE)
            });
            let reclaimed = reclaimable.and_then(|i| self.spare.remove(i));
            let fresh = reclaimed.unwrap_or_else(|| BytesMut::with_capacity(Self::SIZE));
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
    use super::*;

    #[test]
    fn receive_buffers_are_taken_back_once_their_messages_are_dropped() {
        let mut buffers = ReceiveBuffers::default();
        let mut bases = std::collections::HashSet::new();
        for round in 0..400 {
            let buf = buffers.next();
            if buf.capacity() == ReceiveBuffers::SIZE {
                bases.insert(buf.as_ptr() as usize);
            }
            buf.extend_from_slice(&[round as u8; 60_000]);
            let message = buf.split().freeze();
            assert_eq!(message.len(), 60_000);
            drop(message);
        }
        // 400 x 60 kB went through a handful of buffers, not 12 new ones.
        assert!(bases.len() <= 2, "{} buffers", bases.len());

        // While messages are held, new buffers are taken, and let go of later.
        let held: Vec<bytes::Bytes> = (0..100)
            .map(|_| {
                let buf = buffers.next();
                buf.extend_from_slice(&[7; 60_000]);
                buf.split().freeze()
            })
            .collect();
        assert!(held.iter().all(|m| m.len() == 60_000));
        assert!(buffers.spare.len() <= ReceiveBuffers::SPARES);
    }
}

//! The node's send path: the driver of each channel's [`ChannelTx`]
//! (clock reads, the send socket, the flusher's schedule).

use std::io::IoSlice;
use std::net::SocketAddr;
use std::net::UdpSocket as StdUdpSocket;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use super::eligibility::Eligibility;
use super::{fleet, ChannelState, Inner};
use crate::batching::{Flush, Flushed, Flusher};
use crate::error::{Error, Result};
use crate::proto::pace::{burst_for, Pacer};
use crate::proto::ChannelTx;
use crate::sync::lock;

/// The send path of a node.
pub(super) struct Sending {
    /// Every data datagram leaves from here (and service replies come
    /// back to it).
    pub(super) socket: StdUdpSocket,
    /// Whether the last send failed (see `note_send`).
    pub(super) failing: AtomicBool,
    /// Sends the batches whose delay ran out.
    pub(super) flusher: Arc<Flusher<BatchingChannel>>,
    /// Which batching channels 2.x-only peers subscribe, as last worked out
    /// (see `update_batching_eligibility`).
    pub(super) batching_view: Mutex<Eligibility>,
    /// Whether a heartbeat was cut short of its channels (logged once).
    pub(super) heartbeat_truncated: AtomicBool,
    /// How messages in fragments are paced; `None`: they are not.
    pub(super) pacing: Option<Pacing>,
}

impl Sending {
    pub(super) fn new(
        socket: StdUdpSocket,
        batching_view: Eligibility,
        fragment_rate: Option<u64>,
    ) -> Self {
        Self {
            socket,
            failing: AtomicBool::new(false),
            flusher: Arc::default(),
            batching_view: Mutex::new(batching_view),
            heartbeat_truncated: AtomicBool::new(false),
            pacing: fragment_rate.map(Pacing::new),
        }
    }
}

/// How often a channel's burst is worked out again from its subscribers.
const BURST_AGAIN: Duration = Duration::from_millis(500);

/// The node's pacing of messages in fragments: one rate for all its
/// channels (they share the subscribers' buffers); each channel keeps
/// its burst (`ChannelState::burst`).
pub(super) struct Pacing {
    pacer: Mutex<Pacer>,
    /// What a subscriber that announces no buffer (a 2.x node) is taken
    /// to have: this host's default.
    fallback: usize,
}

impl Pacing {
    fn new(rate: u64) -> Self {
        Self {
            pacer: Mutex::new(Pacer::new(rate)),
            fallback: crate::transport::default_receive_buffer(),
        }
    }
}

/// A channel that batches, as the flusher thread sees it.
pub(crate) struct BatchingChannel {
    pub(super) inner: Weak<Inner>,
    pub(super) channel: Arc<ChannelState>,
}

impl Flush for BatchingChannel {
    fn flush_due(&self, now: Instant) -> Flushed {
        let Some(inner) = self.inner.upgrade() else {
            return Flushed::Gone;
        };
        match inner.flush_batch(&self.channel, Some(now)) {
            Ok(next) => Flushed::Pending(next),
            Err(e) => Flushed::Failed(e),
        }
    }

    fn is(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.channel, &other.channel)
    }

    fn channel(&self) -> &str {
        &self.channel.name
    }
}

impl Inner {
    /// Sends one message whose payload `encode` appends to the buffer it gets.
    pub(crate) fn publish_with(
        &self,
        channel: &ChannelState,
        encode: impl FnOnce(&mut Vec<u8>) -> Result<()>,
    ) -> Result<()> {
        thread_local! {
            static BUFFER: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
        }
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        BUFFER.with(|buffer| {
            // A fresh Vec if the buffer is somehow in use (a publish from inside
            // a Serialize impl); the common path reuses one allocation.
            let mut fallback = Vec::new();
            let mut guard = buffer.try_borrow_mut();
            let buf = match guard.as_deref_mut() {
                Ok(buf) => buf,
                Err(_) => &mut fallback,
            };
            buf.clear();
            encode(buf)?;
            let sent = self.publish_payload(channel, buf);
            // Keep the buffer, but not a giant one.
            if buf.capacity() > 1 << 20 {
                buf.clear();
                buf.shrink_to(1 << 20);
            }
            sent
        })
    }

    /// Publishes an encoded payload: batched, as one datagram, or as
    /// fragments (see [`ChannelTx::publish`]). The payload is never copied
    /// on its way to the kernel unless it joins a batch or is sealed.
    pub(crate) fn publish_payload(&self, channel: &ChannelState, payload: &[u8]) -> Result<()> {
        self.publish_payload_as(channel, payload, false)
    }

    /// [`Inner::publish_payload`], or with `alone` in a datagram of its
    /// own even while the channel batches ([`ChannelTx::publish_alone`]).
    pub(crate) fn publish_payload_as(
        &self,
        channel: &ChannelState,
        payload: &[u8],
        alone: bool,
    ) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let now = Instant::now();
        let mut tx = lock(&channel.tx);
        let unix_ms = wall_clock_for(&tx);
        let burst = match tx.fragments(payload.len()) {
            true => self.burst_for(channel, now),
            false => None,
        };
        let mut send = |parts: &[&[u8]]| {
            if let (Some(burst), Some(pacing)) = (burst, &self.sending.pacing) {
                let len = parts.iter().map(|p| p.len()).sum();
                let wait = lock(&pacing.pacer).delay(Instant::now(), len, burst);
                if !wait.is_zero() {
                    self.counters.paced.fetch_add(1, Ordering::Relaxed);
                    let ns = u64::try_from(wait.as_nanos()).unwrap_or(u64::MAX);
                    self.counters.paced_ns.fetch_add(ns, Ordering::Relaxed);
                    std::thread::sleep(wait);
                }
            }
            self.transmit(channel, parts)
        };
        let sent = match alone {
            false => tx.publish(now, unix_ms, payload, &mut send),
            true => tx
                .publish_alone(now, unix_ms, payload, &mut send)
                .map(|()| None),
        }
        .map_err(Error::from);
        drop(tx);
        self.note_send(&sent);
        if let Some(deadline) = sent? {
            self.sending.flusher.schedule(deadline);
        }
        if !channel.published.swap(true, Ordering::Relaxed) {
            self.announce_change();
        }
        if lock(&channel.period).record(now) {
            self.announce_change();
        }
        self.counters.messages_sent.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }

    /// The burst `channel`'s fragments may make: half the smallest
    /// receive buffer among its subscribers on this site (a member of
    /// another site is reached through its bridge, a subscriber here);
    /// `None` when pacing is off or no subscriber is known. Worked out
    /// again every [`BURST_AGAIN`], not for each message.
    fn burst_for(&self, channel: &ChannelState, now: Instant) -> Option<usize> {
        let pacing = self.sending.pacing.as_ref()?;
        let mut cached = lock(&channel.burst);
        if let Some((at, burst)) = *cached {
            if now.saturating_duration_since(at) < BURST_AGAIN {
                return burst;
            }
        }
        let name: &str = channel.name();
        let buffers: Vec<Option<u32>> = self
            .fleet_members_on(&|c| c == name)
            .iter()
            .filter(|m| m.remote.is_none() && m.is_live())
            .filter(|m| m.channels.iter().any(|c| c.subscribes))
            .map(|m| m.receive_buffer)
            .collect();
        let burst = burst_for(buffers, pacing.fallback, crate::wire::MAX_DATAGRAM);
        *cached = Some((now, burst));
        burst
    }

    /// Sends one datagram of `channel`, given in parts: gathered by the
    /// kernel, without joining them first.
    pub(super) fn transmit(&self, channel: &ChannelState, parts: &[&[u8]]) -> std::io::Result<()> {
        self.transmit_to(&channel.address, parts)
    }

    /// Sends one datagram, given in parts, to `address`.
    fn transmit_to(&self, address: &socket2::SockAddr, parts: &[&[u8]]) -> std::io::Result<()> {
        let socket = socket2::SockRef::from(&self.sending.socket);
        match parts {
            [one] => socket.send_to(one, address).map(drop),
            [a, b, c] => {
                let parts = [IoSlice::new(a), IoSlice::new(b), IoSlice::new(c)];
                socket.send_to_vectored(&parts, address).map(drop)
            }
            more => socket.send_to(&more.concat(), address).map(drop),
        }
    }

    /// Sends a server's frame on `channel` straight to the caller at `to`.
    /// Framed, fragmented and sealed as any message, never batched, and not
    /// announced as publishing: what a service announces is held apart
    /// ([`ChannelState::hold`]).
    pub(crate) fn send_frame(
        &self,
        channel: &ChannelState,
        payload: &[u8],
        to: SocketAddr,
    ) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        let address = socket2::SockAddr::from(to);
        let now = Instant::now();
        let mut tx = lock(&channel.tx);
        if tx.is_batching() {
            // Batches go to the group when they are flushed: a frame must
            // not wait there (nor go to the wrong place).
            return Err(Error::config(
                "batching",
                format!("{} carries service frames and can't batch", channel.name),
            ));
        }
        let unix_ms = wall_clock_for(&tx);
        let sent = tx
            .publish(now, unix_ms, payload, &mut |parts| {
                self.transmit_to(&address, parts)
            })
            .map_err(Error::from);
        drop(tx);
        self.note_send(&sent);
        sent.map(drop)
    }

    /// Logs once when sending starts failing (an interface went down, the
    /// route is gone) and once when it works again, however many sends fail
    /// in between: the errors themselves go to the callers.
    pub(super) fn note_send<T>(&self, sent: &Result<T>) {
        match sent {
            Ok(_) => {
                if self.sending.failing.load(Ordering::Relaxed)
                    && self.sending.failing.swap(false, Ordering::Relaxed)
                {
                    tracing::info!(node = %self.identity.name, "sending works again");
                }
            }
            Err(e @ Error::Io { .. }) => {
                if !self.sending.failing.swap(true, Ordering::Relaxed) {
                    tracing::warn!(node = %self.identity.name, "sending fails, will keep trying: {e}");
                }
            }
            // Not a send that failed (a payload too large, say).
            Err(_) => {}
        }
    }

    /// Sends the channel's pending batch if it is due at `now` (`None`:
    /// whatever its deadline); returns the deadline of one still pending.
    pub(crate) fn flush_batch(
        &self,
        channel: &ChannelState,
        now: Option<Instant>,
    ) -> Result<Option<Instant>> {
        let mut tx = lock(&channel.tx);
        let unix_ms = wall_clock_for(&tx);
        let mut send = |parts: &[&[u8]]| self.transmit(channel, parts);
        // Not noted in `note_send`: the flusher logs its own failures, and
        // a flush with nothing pending says nothing about sending.
        let sent = match now {
            Some(now) => tx.handle_timeout(now, unix_ms, &mut send),
            None => tx.flush(unix_ms, &mut send),
        };
        sent.map(|()| tx.poll_timeout()).map_err(Error::from)
    }

    /// Turns batching on for `channel` (`Some(delay)`) or off (`None`,
    /// sending what is pending).
    pub(crate) fn set_batching(
        self: &Arc<Self>,
        channel: &Arc<ChannelState>,
        max_delay: Option<Duration>,
    ) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        if let Some(delay) = max_delay {
            ChannelTx::check_batching_delay(delay)?;
            // Which 2.x nodes subscribe is known before the first message
            // may join a batch; in a huge 2.x table, the channel is taken
            // for one a 2.x node subscribes until the next tick tells, so
            // that registering (a bridge registers thousands) never walks
            // it.
            let blocked = self.legacy_subscribes_now(&channel.name).unwrap_or(true);
            lock(&channel.tx).set_legacy_subscriber(blocked);
            lock(&self.sending.batching_view).watch(&channel.name);
            self.sending.flusher.register(Arc::new(BatchingChannel {
                inner: Arc::downgrade(self),
                channel: Arc::clone(channel),
            }));
        }
        let mut tx = lock(&channel.tx);
        let unix_ms = wall_clock_for(&tx);
        let deadline = tx.set_batching(max_delay, unix_ms, &mut |parts| {
            self.transmit(channel, parts)
        })?;
        drop(tx);
        // A shorter delay may make a pending batch due sooner.
        if let Some(deadline) = deadline {
            self.sending.flusher.schedule(deadline);
        }
        Ok(())
    }

    /// Sends the channel's pending batch now.
    pub(crate) fn flush(&self, channel: &ChannelState) -> Result<()> {
        if self.is_stopped() {
            return Err(Error::NodeStopped);
        }
        self.flush_batch(channel, None).map(drop)
    }
}

/// The wall clock in ms for a channel's sealer; 0, unread, without one.
pub(super) fn wall_clock_for(tx: &ChannelTx) -> u64 {
    match tx.is_sealed() {
        true => fleet::unix_ms(),
        false => 0,
    }
}

//! One channel's send side as a state machine without sockets, tasks or
//! clocks: the one send path of every node.
//!
//! A [`ChannelTx`] owns what publishing a message on one channel needs:
//! the header prefixes, the sequence number, the pending batch and the
//! sealer. It turns a payload into datagrams (one packet, fragments, or a
//! place in a batch) and hands each to the caller's `send` in parts
//! (prefix, numbers, payload), so that a payload reaches the socket
//! without a copy unless it joins a batch or is sealed.
//!
//! # Call order
//!
//! 1. [`ChannelTx::publish`] for each message. When it starts a batch it
//!    returns the batch's deadline.
//! 2. [`ChannelTx::poll_timeout`] says when the pending batch is due;
//!    [`ChannelTx::handle_timeout`] sends it then. [`ChannelTx::flush`]
//!    sends it at once.
//! 3. [`ChannelTx::set_batching`] and [`ChannelTx::set_legacy_subscriber`]
//!    whenever the settings or the fleet change.
//!
//! Time comes in as `now` (monotonic, for batch deadlines) and `unix_ms`
//! (the wall clock, stamped into sealed datagrams; unused on channels
//! without a key).

use std::io;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::fragment::{Fragment, MAX_MESSAGE};
use super::secure::Sealer;
use crate::error::{Error, Result};
use crate::wire::batch::BatchBuilder;
use crate::wire::{Packet, MAX_DATAGRAM};

/// The longest batching delay allowed: longer would hold messages past the
/// point where anyone would still call them live.
pub const MAX_BATCH_DELAY: Duration = Duration::from_secs(1);

/// One channel's send side. See the [module docs](self) for the call order.
pub struct ChannelTx {
    name: Arc<str>,
    /// `PULI`, name length and name: every packet's header but the sequence.
    packet_prefix: Box<[u8]>,
    /// The same for fragments.
    fragment_prefix: Box<[u8]>,
    seq: u32,
    /// The configured batching delay; `None` while batching is off.
    max_delay: Option<Duration>,
    batch: BatchBuilder,
    /// When the oldest message of the pending batch was published.
    started: Option<Instant>,
    /// Whether a Pulicast 2.x node subscribes: it can't read batches.
    legacy_subscriber: bool,
    /// Seals every datagram when a key covers the channel.
    sealer: Option<Sealer>,
}

impl std::fmt::Debug for ChannelTx {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ChannelTx")
            .field("name", &self.name)
            .field("seq", &self.seq)
            .field("max_delay", &self.max_delay)
            .field("sealed", &self.sealer.is_some())
            .finish_non_exhaustive()
    }
}

impl ChannelTx {
    /// The send side of `name`, sealed by `sealer` if a key covers it.
    pub fn new(name: Arc<str>, sealer: Option<Sealer>) -> Self {
        // A sealed batch must still fit a datagram.
        let batch_limit = MAX_DATAGRAM - sealer.as_ref().map_or(0, Sealer::overhead);
        Self {
            packet_prefix: Packet::prefix(&name).into(),
            fragment_prefix: Fragment::prefix(&name).into(),
            name,
            seq: 0,
            max_delay: None,
            batch: BatchBuilder::with_limit(batch_limit),
            started: None,
            legacy_subscriber: false,
            sealer,
        }
    }

    /// The channel's name.
    pub fn name(&self) -> &Arc<str> {
        &self.name
    }

    /// Whether datagrams are sealed (and so need `unix_ms`).
    pub fn is_sealed(&self) -> bool {
        self.sealer.is_some()
    }

    /// Whether batching is on.
    pub fn is_batching(&self) -> bool {
        self.max_delay.is_some()
    }

    /// The sequence number the next message gets.
    pub fn next_seq(&self) -> u32 {
        self.seq
    }

    /// Sends `payload` as the channel's next message: into the pending
    /// batch when batching is on and it fits one, else as one datagram or
    /// as fragments (after the pending batch, so messages leave in order).
    /// Returns the deadline of a batch it started, for the caller's timer.
    pub fn publish(
        &mut self,
        now: Instant,
        unix_ms: u64,
        payload: &[u8],
        send: &mut impl FnMut(&[&[u8]]) -> io::Result<()>,
    ) -> Result<Option<Instant>> {
        self.publish_as(now, unix_ms, payload, false, send)
    }

    /// Sends `payload` as the channel's next message in a datagram (or
    /// fragments) of its own, even while batching: after the pending batch,
    /// so messages leave in order. Starts no batch, so there is no deadline
    /// to wait for.
    pub fn publish_alone(
        &mut self,
        now: Instant,
        unix_ms: u64,
        payload: &[u8],
        send: &mut impl FnMut(&[&[u8]]) -> io::Result<()>,
    ) -> Result<()> {
        self.publish_as(now, unix_ms, payload, true, send).map(drop)
    }

    fn publish_as(
        &mut self,
        now: Instant,
        unix_ms: u64,
        payload: &[u8],
        alone: bool,
        send: &mut impl FnMut(&[&[u8]]) -> io::Result<()>,
    ) -> Result<Option<Instant>> {
        if payload.len() > MAX_MESSAGE {
            return Err(Error::PayloadTooLarge {
                channel: self.name.to_string(),
                size: payload.len(),
                max: MAX_MESSAGE,
            });
        }
        let seq = self.seq;
        self.seq = self.seq.wrapping_add(1);
        let len = payload.len();
        let batchable = !alone
            && self.max_delay.is_some()
            && !self.legacy_subscriber
            && self.batch.fits_alone(&self.name, len);
        let due = self.poll_timeout().is_some_and(|due| due <= now);
        if !batchable || due || !self.batch.fits(len) {
            self.flush(unix_ms, send)?;
        }
        if !batchable {
            return self.send_message(unix_ms, payload, seq, send);
        }
        let first = self.batch.is_empty();
        if first {
            self.batch.start(&self.name, seq);
            self.started = Some(now);
        }
        self.batch.push(payload);
        Ok(if first { self.poll_timeout() } else { None })
    }

    /// Sends the pending batch, if any.
    pub fn flush(
        &mut self,
        unix_ms: u64,
        send: &mut impl FnMut(&[&[u8]]) -> io::Result<()>,
    ) -> Result<()> {
        if self.batch.is_empty() {
            return Ok(());
        }
        let datagram = self.batch.finish();
        let sent = match &mut self.sealer {
            Some(sealer) => send(&[sealer.seal(datagram, unix_ms)]),
            None => send(&[datagram]),
        };
        self.batch.clear();
        self.started = None;
        sent.map_err(Error::io("sending a batch"))
    }

    /// When the pending batch must be sent, if there is one.
    ///
    /// A little ahead of the configured delay, so that a timer's wake-up
    /// lag (the kernel's 50 µs timer slack plus scheduling) does not push a
    /// message past it.
    pub fn poll_timeout(&self) -> Option<Instant> {
        let started = self.started?;
        let delay = self.max_delay.unwrap_or(Duration::ZERO);
        Some(started + delay - slack(delay))
    }

    /// Sends the pending batch if it is due at `now`.
    pub fn handle_timeout(
        &mut self,
        now: Instant,
        unix_ms: u64,
        send: &mut impl FnMut(&[&[u8]]) -> io::Result<()>,
    ) -> Result<()> {
        match self.poll_timeout() {
            Some(due) if due <= now => self.flush(unix_ms, send),
            _ => Ok(()),
        }
    }

    /// Turns batching on (`Some(delay)`, at most [`MAX_BATCH_DELAY`]) or
    /// off (`None`, sending what is pending). Returns the pending batch's
    /// deadline, which a shorter delay may have brought forward.
    pub fn set_batching(
        &mut self,
        max_delay: Option<Duration>,
        unix_ms: u64,
        send: &mut impl FnMut(&[&[u8]]) -> io::Result<()>,
    ) -> Result<Option<Instant>> {
        match max_delay {
            Some(delay) => Self::check_batching_delay(delay)?,
            None => self.flush(unix_ms, send)?,
        }
        self.max_delay = max_delay;
        Ok(self.poll_timeout())
    }

    /// Whether `delay` is a batching delay [`ChannelTx::set_batching`]
    /// takes: above zero and at most [`MAX_BATCH_DELAY`].
    pub fn check_batching_delay(delay: Duration) -> Result<()> {
        if delay.is_zero() || delay > MAX_BATCH_DELAY {
            return Err(Error::config(
                "batching delay",
                format!("must be above 0 and at most {MAX_BATCH_DELAY:?}, not {delay:?}"),
            ));
        }
        Ok(())
    }

    /// Notes whether a Pulicast 2.x node subscribes the channel: while one
    /// does, messages go out one per datagram, which it can read.
    pub fn set_legacy_subscriber(&mut self, subscribes: bool) {
        self.legacy_subscriber = subscribes;
    }

    /// Whether a message of `len` bytes leaves as fragments (sealed or
    /// not, as this channel is): the publisher paces those.
    pub fn fragments(&self, len: usize) -> bool {
        let reserve = self.sealer.as_ref().map_or(0, Sealer::overhead);
        self.packet_prefix.len() + 4 + len + reserve > MAX_DATAGRAM
    }

    /// Sends one message as one datagram or as fragments. Headers come from
    /// the precomputed prefixes and a few bytes on the stack; sealed, the
    /// parts are sealed into one datagram.
    fn send_message(
        &mut self,
        unix_ms: u64,
        payload: &[u8],
        seq: u32,
        send: &mut impl FnMut(&[&[u8]]) -> io::Result<()>,
    ) -> Result<Option<Instant>> {
        let reserve = self.sealer.as_ref().map_or(0, Sealer::overhead);
        let fragmented = self.fragments(payload.len());
        let mut emit = |parts: &[&[u8]; 3]| match &mut self.sealer {
            Some(sealer) => send(&[sealer.seal_parts(parts, unix_ms)]),
            None => send(parts),
        };
        if !fragmented {
            emit(&[&self.packet_prefix, &seq.to_be_bytes(), payload])
                .map_err(Error::io("sending a datagram"))?;
            return Ok(None);
        }
        let count = Fragment::count_within(&self.name, payload.len(), reserve);
        // At most 64 MiB / ~65 kB, far below u16::MAX.
        let count = u16::try_from(count).map_err(|_| Error::PayloadTooLarge {
            channel: self.name.to_string(),
            size: payload.len(),
            max: MAX_MESSAGE,
        })?;
        for index in 0..count {
            let numbers = Fragment::numbers(seq, payload.len() as u32, index, count);
            let chunk = Fragment::chunk_of(payload, index, count);
            emit(&[&self.fragment_prefix, &numbers, chunk])
                .map_err(Error::io("sending a fragment"))?;
        }
        Ok(None)
    }
}

/// How much earlier than its delay a batch is due.
fn slack(delay: Duration) -> Duration {
    (delay / 4).min(Duration::from_micros(250))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::secure::{Key, Opener};
    use crate::wire::batch::Batch;

    /// Collects what would be sent, each datagram joined from its parts.
    fn collect(out: &mut Vec<Vec<u8>>) -> impl FnMut(&[&[u8]]) -> io::Result<()> + '_ {
        |parts| {
            out.push(parts.concat());
            Ok(())
        }
    }

    #[test]
    fn batches_are_due_before_their_delay() {
        let start = Instant::now();
        let mut tx = ChannelTx::new("a".into(), None);
        let mut out = Vec::new();
        let mut send = collect(&mut out);
        tx.set_batching(Some(Duration::from_millis(2)), 0, &mut send)
            .unwrap();
        let due = tx.publish(start, 0, b"x", &mut send).unwrap();
        assert_eq!(due, Some(start + Duration::from_micros(2000 - 250)));
        assert_eq!(tx.poll_timeout(), due);
        let shorter = tx.set_batching(Some(Duration::from_micros(100)), 0, &mut send);
        assert_eq!(shorter.unwrap(), Some(start + Duration::from_micros(75)));
        tx.handle_timeout(start, 0, &mut send).unwrap();
        tx.handle_timeout(start + Duration::from_micros(75), 0, &mut send)
            .unwrap();
        assert_eq!(tx.poll_timeout(), None);
        drop(send);
        assert_eq!(out.len(), 1);
        assert_eq!(Batch::decode(&out[0]).unwrap().count, 1);
    }

    #[test]
    fn a_message_sent_alone_follows_the_batch_and_starts_none() {
        let now = Instant::now();
        let mut tx = ChannelTx::new("a".into(), None);
        let mut out = Vec::new();
        let mut send = collect(&mut out);
        tx.set_batching(Some(Duration::from_millis(1)), 0, &mut send)
            .unwrap();
        tx.publish_alone(now, 0, b"zero", &mut send).unwrap();
        assert_eq!(tx.poll_timeout(), None, "no batch waits");
        tx.publish(now, 0, b"one", &mut send).unwrap();
        tx.publish(now, 0, b"two", &mut send).unwrap();
        tx.publish_alone(now, 0, b"three", &mut send).unwrap();
        assert_eq!(tx.poll_timeout(), None, "the batch went first");
        drop(send);
        // Alone, batched (one datagram with two), alone: in sequence.
        assert_eq!(out.len(), 3);
        assert!(Batch::decode(&out[0]).is_err());
        let batch = Batch::decode(&out[1]).unwrap();
        assert_eq!((batch.first_seq, batch.count), (1, 2));
        assert!(Batch::decode(&out[2]).is_err());
        let packet = crate::wire::Packet::decode(&out[2]).unwrap();
        assert_eq!((packet.seq, packet.payload), (3, &b"three"[..]));
    }

    #[test]
    fn messages_leave_in_sequence_whatever_their_path() {
        let now = Instant::now();
        let mut tx = ChannelTx::new("a".into(), None);
        let mut out = Vec::new();
        let mut send = collect(&mut out);
        tx.publish(now, 0, b"one", &mut send).unwrap();
        tx.set_batching(Some(Duration::from_millis(1)), 0, &mut send)
            .unwrap();
        tx.publish(now, 0, b"two", &mut send).unwrap();
        tx.publish(now, 0, b"three", &mut send).unwrap();
        // Too large to batch: the batch goes first, then its fragments.
        tx.publish(now, 0, &vec![7; 100_000], &mut send).unwrap();
        tx.set_legacy_subscriber(true);
        tx.publish(now, 0, b"five", &mut send).unwrap();
        assert!(tx
            .set_batching(Some(Duration::from_secs(2)), 0, &mut send)
            .is_err());
        assert!(tx
            .publish(now, 0, &vec![0; MAX_MESSAGE + 1], &mut send)
            .is_err());
        drop(send);
        let seqs: Vec<u32> = out
            .iter()
            .flat_map(|d| {
                if let Ok(b) = Batch::decode(d) {
                    (b.first_seq..b.first_seq + u32::from(b.count)).collect()
                } else if let Ok(f) = Fragment::decode(d) {
                    vec![f.header().seq]
                } else {
                    vec![Packet::decode(d).unwrap().seq]
                }
            })
            .collect();
        assert_eq!(seqs, [0, 1, 2, 3, 3, 4]);
        assert_eq!(tx.next_seq(), 5);
    }

    #[test]
    fn sealed_channels_seal_every_datagram() {
        let key = Key::from_bytes([3; 32]);
        let mut opener = Opener::new(None);
        opener.add_key("", &key).unwrap();
        let now = Instant::now();
        let mut tx = ChannelTx::new("a".into(), Some(Sealer::new(&key, "a", true)));
        let mut out = Vec::new();
        let mut send = collect(&mut out);
        tx.publish(now, 0, b"small", &mut send).unwrap();
        tx.publish(now, 0, &vec![1; 200_000], &mut send).unwrap();
        tx.set_batching(Some(Duration::from_millis(1)), 0, &mut send)
            .unwrap();
        tx.publish(now, 0, b"batched", &mut send).unwrap();
        tx.flush(0, &mut send).unwrap();
        drop(send);
        assert!(out.len() > 3);
        let from = "10.0.0.1:1".parse().unwrap();
        for d in &out {
            assert!(d.len() <= MAX_DATAGRAM);
            assert!(opener.open(d, from, 0).is_ok());
        }
    }
}

//! Messages larger than one datagram: their reassembly. The fragment
//! format itself is in [`crate::wire::fragment`] (re-exported here).
//!
//! A message too large for one datagram travels as fragments under their own
//! magic, so Pulicast 2.x nodes (which check for `PULI`) drop them silently:
//!
//! ```text
//! +--------+-------+------+----------+------------+-----------+-----------+-------+
//! | "PFRG" | n: u8 | name | seq: u32 | total: u32 | index: u16| count: u16| chunk |
//! +--------+-------+------+----------+------------+-----------+-----------+-------+
//! ```
//!
//! All integers are big-endian. `seq` is the message's sequence number on its
//! channel (the same counter as unfragmented messages), `total` the message
//! size. Every fragment but the last carries `ceil(total / count)` bytes, so
//! the offset of fragment `index` is `index * ceil(total / count)` and a
//! receiver can place fragments arriving in any order.
//!
//! [`Reassembler`] is bounded: per message ([`MAX_MESSAGE`]), per source, per
//! channel and in total, and each message has a deadline fixed by its first
//! fragment. When the total is full, the channel holding the most makes room
//! for one holding less, so fragments on one channel never keep another
//! channel's messages out. A lost fragment loses its message only, and is
//! counted.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::{Bytes, BytesMut};

pub use crate::wire::fragment::{Fragment, Header, HEADER_OVERHEAD, MAGIC, MAX_MESSAGE};
use crate::wire::MAX_DATAGRAM;

/// ReassemblyLimits of a [`Reassembler`].
#[derive(Debug, Clone, Copy)]
pub struct ReassemblyLimits {
    /// Bytes of incomplete messages one source may hold.
    pub per_source: usize,
    /// Bytes of incomplete messages one channel may hold.
    pub per_channel: usize,
    /// Bytes of incomplete messages in all.
    pub total: usize,
    /// A message is given up this long after its first fragment, plus the
    /// time its size takes at [`SLOWEST_RATE`]: a fixed deadline, so a
    /// trickle of fragments can't hold a message's memory forever.
    pub timeout: Duration,
}

impl Default for ReassemblyLimits {
    fn default() -> Self {
        Self {
            per_source: 2 * MAX_MESSAGE,
            per_channel: 2 * MAX_MESSAGE,
            total: 8 * MAX_MESSAGE,
            timeout: Duration::from_secs(2),
        }
    }
}

/// The slowest link a large message is given time for, in bytes per second
/// (64 Mbit/s: poor Wi-Fi): a 64 MiB message gets 8 s on top of the timeout.
pub const SLOWEST_RATE: u64 = 8 << 20;

impl ReassemblyLimits {
    /// How long after its first fragment a message of `size` bytes is given up.
    pub fn deadline_for(&self, size: usize) -> Duration {
        self.timeout + Duration::from_millis(size as u64 * 1000 / SLOWEST_RATE)
    }
}

/// What happened to a fragment.
#[derive(Debug, Clone, PartialEq, Eq)]
#[must_use]
pub enum Outcome {
    /// Stored; the message is not complete yet.
    Pending,
    /// The last missing fragment: here is the message.
    Complete {
        /// Its sequence number.
        seq: u32,
        /// Its bytes.
        message: Bytes,
    },
    /// Seen before (or of a message already complete or given up).
    Duplicate,
    /// Refused: the message would exceed the memory limits.
    OverBudget,
}

struct Assembly {
    /// The message so far, up to the end of the furthest fragment written:
    /// each is written at its offset (fragments in order are appended: one
    /// copy, no zero-filling; a short gap left by an early one is zeroed
    /// until its fragment comes).
    data: BytesMut,
    /// The first fragment not received.
    next: u16,
    /// Fragments that came while `data` was lent out, or far ahead of what
    /// is written (zeroing up to them would make a few datagrams cost the
    /// whole message in memory), until they can be written.
    early: std::collections::BTreeMap<u16, Bytes>,
    received: Vec<bool>,
    total: usize,
    missing: usize,
    /// When it is given up: fixed by its first fragment and its size.
    deadline: Instant,
    /// What it costs against the budgets: its size, the spare room a loan
    /// receives into, and its bookkeeping.
    charge: usize,
    /// Whether `data` is out on a [`Loan`].
    lent: bool,
    /// Tells this message from a later one under the same key (after this
    /// one timed out), so a loan comes back to the message it left.
    id: u64,
}

impl Assembly {
    /// Moves `next` past the fragments received, writing those kept aside
    /// that are now close enough.
    fn advance(&mut self) {
        while let Some(&index) = self.early.keys().next() {
            if self.offset(index) > self.data.len() + MAX_GAP * self.offset(1) {
                break;
            }
            if let Some(chunk) = self.early.remove(&index) {
                self.write(index, &chunk);
            }
        }
        while self.received.get(usize::from(self.next)) == Some(&true) {
            self.next += 1;
        }
    }

    /// Writes fragment `index` at its offset, or keeps it aside if it is
    /// more than [`MAX_GAP`] fragments past what is written.
    fn write(&mut self, index: u16, chunk: &[u8]) {
        let start = self.offset(index);
        if start == self.data.len() {
            // In order, the common case: appended.
            self.data.extend_from_slice(chunk);
        } else if start > self.data.len() + MAX_GAP * self.offset(1) {
            self.early.insert(index, Bytes::copy_from_slice(chunk));
        } else if start > self.data.len() {
            self.data.resize(start, 0);
            self.data.extend_from_slice(chunk);
        } else {
            // Fragments don't overlap, so one before the furthest received
            // ends within `data`.
            let end = (start + chunk.len()).min(self.data.len());
            self.data[start..end].copy_from_slice(&chunk[..end - start]);
        }
    }

    /// Where fragment `index` starts in the message.
    fn offset(&self, index: u16) -> usize {
        let size = Fragment::chunk_size(self.total as u32, self.received.len() as u16);
        (usize::from(index) * size).min(self.total)
    }
}

/// A message's buffer, lent out by [`Reassembler::lend`] so that the next
/// fragment is received straight into it instead of being copied there.
///
/// The receiver appends the whole datagram at the end of `data`, header
/// included; for the chunk to land in place, the header must overwrite the
/// last bytes of the previous chunk, which the receiver saves and puts back
/// (a few hundred bytes copied instead of a whole chunk). `data` always has
/// room for a full datagram past the message.
#[derive(Debug)]
pub struct Loan {
    /// The message so far: fragments `0..index`.
    pub data: BytesMut,
    /// The message's sequence number.
    pub seq: u32,
    /// The message's size.
    pub total: u32,
    /// The fragment expected next.
    pub index: u16,
    /// How many fragments the message has.
    pub count: u16,
    key: (Arc<str>, SocketAddr, u32),
    id: u64,
}

impl Loan {
    /// The message's channel.
    pub fn channel(&self) -> &Arc<str> {
        &self.key.0
    }

    /// The sender of the message.
    pub fn source(&self) -> SocketAddr {
        self.key.1
    }

    /// Makes `data` ready to receive the next datagram into: the bytes the
    /// awaited fragment's header will cover are saved and cut off, so that
    /// its chunk lands where it belongs. Receive into `data` (appending),
    /// then call [`Loan::land`]. `None` when too little of the message is
    /// here to hold the header: receive the ordinary way and repay the loan
    /// as not received.
    #[must_use]
    pub fn prepare(&mut self) -> Option<Landing> {
        let mut header = [0u8; Fragment::MAX_HEADER];
        let name = self.key.0.as_bytes();
        let name = &name[..name.len().min(255)];
        let numbers = Fragment::numbers(self.seq, self.total, self.index, self.count);
        let parts: [&[u8]; 4] = [&MAGIC, &[name.len() as u8], name, &numbers];
        let mut h = 0;
        for part in parts {
            header[h..h + part.len()].copy_from_slice(part);
            h += part.len();
        }
        let end = self.data.len();
        let start = end.checked_sub(h)?;
        let mut saved = [0u8; Fragment::MAX_HEADER];
        saved[..h].copy_from_slice(&self.data[start..]);
        self.data.truncate(start);
        Some(Landing {
            header,
            saved,
            len: h,
            start,
        })
    }

    /// Finishes receiving into `data` after [`Loan::prepare`]: `received`
    /// is the datagram's length and sender, `None` if receiving failed.
    /// The saved bytes are put back either way. If the datagram was the
    /// awaited fragment, its chunk is now in place: repay the loan as
    /// received. Otherwise it is moved to `other`, to be handled the
    /// ordinary way, and the loan is repaid as not received.
    pub fn land(
        &mut self,
        landing: Landing,
        received: Option<(usize, SocketAddr)>,
        other: &mut BytesMut,
    ) -> Landed {
        let Landing {
            header,
            saved,
            len: h,
            start,
        } = landing;
        let Some((n, source)) = received else {
            self.data.truncate(start);
            self.data.extend_from_slice(&saved[..h]);
            return Landed::Nothing;
        };
        let expected = Fragment::chunk_of_len(self.total, self.index, self.count);
        let awaited = source == self.source()
            && n == h + expected
            && self.data.get(start..start + h) == Some(&header[..h]);
        if awaited {
            self.data[start..start + h].copy_from_slice(&saved[..h]);
            return Landed::Awaited;
        }
        // Rare: another channel on the group, another sender, or a
        // fragment out of order.
        let end = (start + n).min(self.data.len());
        other.extend_from_slice(&self.data[start..end]);
        self.data.truncate(start);
        self.data.extend_from_slice(&saved[..h]);
        Landed::Other { source, len: n }
    }
}

/// What [`Loan::prepare`] saved: see [`Loan::land`].
#[derive(Debug)]
pub struct Landing {
    header: [u8; Fragment::MAX_HEADER],
    saved: [u8; Fragment::MAX_HEADER],
    len: usize,
    start: usize,
}

/// What [`Loan::land`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[must_use]
pub enum Landed {
    /// The awaited fragment, in place.
    Awaited,
    /// Another datagram, now in the buffer given.
    Other {
        /// Its sender.
        source: SocketAddr,
        /// Its length.
        len: usize,
    },
    /// Nothing was received.
    Nothing,
}

/// Puts fragments back together. Pure: time comes from the caller.
pub struct Reassembler {
    limits: ReassemblyLimits,
    assemblies: HashMap<(Arc<str>, SocketAddr, u32), Assembly>,
    /// Messages completed lately, so a late duplicate fragment does not
    /// start a message that can never complete.
    recent: std::collections::VecDeque<(Arc<str>, SocketAddr, u32)>,
    per_source: HashMap<SocketAddr, usize>,
    per_channel: HashMap<Arc<str>, usize>,
    /// The messages in progress per (channel, source), with when they
    /// started: the overtaken rule looks here instead of at every message.
    by_source: HashMap<Stream, Vec<(Instant, u32)>>,
    /// Messages refused for the budgets lately, so each counts once.
    refused: std::collections::VecDeque<(Arc<str>, SocketAddr, u32)>,
    /// No message times out before this.
    next_expiry: Option<Instant>,
    total: usize,
    lost: u64,
    reported: u64,
    /// Buffers of messages handed out lately, kept so that the next message
    /// can reuse their memory once its reader drops them: a fresh buffer
    /// costs a page fault every 4 KiB, which for large messages costs about
    /// as much as copying the fragments in.
    spare: std::collections::VecDeque<(usize, BytesMut)>,
    next_id: u64,
}

/// How many fragments past what is written an early fragment may be and
/// still be written in place (the gap zeroed until its fragments come).
const MAX_GAP: usize = 2;

/// One sender's messages on one channel.
type Stream = (Arc<str>, SocketAddr);

/// How many bytes of buffers a [`Reassembler`] keeps for reuse: enough for
/// three 16 MiB messages, since the next message starts before the reader
/// has dropped the last one.
const SPARE_BYTES: usize = 50 << 20;

impl std::fmt::Debug for Reassembler {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Reassembler")
            .field("incomplete", &self.assemblies.len())
            .field("bytes", &self.total)
            .field("lost", &self.lost)
            .finish()
    }
}

impl Reassembler {
    /// An empty reassembler with these limits.
    pub fn new(limits: ReassemblyLimits) -> Self {
        Self {
            limits,
            assemblies: HashMap::new(),
            recent: std::collections::VecDeque::new(),
            per_source: HashMap::new(),
            per_channel: HashMap::new(),
            by_source: HashMap::new(),
            refused: std::collections::VecDeque::new(),
            next_expiry: None,
            total: 0,
            lost: 0,
            reported: 0,
            spare: std::collections::VecDeque::new(),
            next_id: 0,
        }
    }

    /// An empty buffer for a message of `size` bytes: a spare one whose
    /// message has been dropped, or a new one.
    fn buffer(&mut self, size: usize) -> BytesMut {
        let reusable = self.spare.iter_mut().position(|(_, b)| b.try_reclaim(size));
        match reusable.and_then(|i| self.spare.remove(i)) {
            Some((_, buffer)) => buffer,
            // Reserved, not touched: pages are only mapped as fragments
            // fill them.
            None => BytesMut::with_capacity(size),
        }
    }

    /// Hands out a completed message, keeping its buffer for reuse within
    /// [`SPARE_BYTES`] (the newest are kept).
    fn hand_out(&mut self, mut data: BytesMut) -> Bytes {
        let allocation = data.capacity();
        let message = data.split().freeze();
        if allocation <= SPARE_BYTES {
            self.spare.push_back((allocation, data));
            while self.spare.iter().map(|(n, _)| n).sum::<usize>() > SPARE_BYTES {
                self.spare.pop_front();
            }
        }
        message
    }

    /// Messages given up (timed out or evicted) so far.
    pub fn lost(&self) -> u64 {
        self.lost
    }

    /// Messages given up since the last call: for counters that must see
    /// every loss once, wherever it happened.
    pub fn take_lost(&mut self) -> u64 {
        let new = self.lost - self.reported;
        self.reported = self.lost;
        new
    }

    /// Bytes held by incomplete messages.
    pub fn bytes(&self) -> usize {
        self.total
    }

    /// Adds fragment `f` (checked by [`Fragment::decode`]) with its bytes
    /// `chunk` from `source` of channel `channel`.
    pub fn push(
        &mut self,
        now: Instant,
        channel: &Arc<str>,
        source: SocketAddr,
        f: Header,
        chunk: &[u8],
    ) -> Outcome {
        self.expire(now);
        let key = (Arc::clone(channel), source, f.seq);
        if !self.assemblies.contains_key(&key)
            && (self.recent.contains(&key) || self.refused.contains(&key))
        {
            return Outcome::Duplicate;
        }
        if !self.assemblies.contains_key(&key) {
            // Datagrams from one sender mostly arrive in order: an older
            // message still incomplete when two newer ones have started has
            // lost a fragment. Give it up now instead of holding its memory
            // until the timeout.
            let stream = (Arc::clone(channel), source);
            let oldest = self
                .by_source
                .get(&stream)
                .filter(|started| started.len() >= 2)
                .and_then(|started| started.iter().min().copied());
            if let Some((_, seq)) = oldest {
                if self.remove(&(Arc::clone(channel), source, seq)).is_some() {
                    self.lost += 1;
                }
            }
            let size = f.total as usize;
            let charge = size + MAX_DATAGRAM + usize::from(f.count);
            let held = self.per_source.get(&source).copied().unwrap_or(0);
            let on_channel = self.per_channel.get(channel).copied().unwrap_or(0);
            if held + charge > self.limits.per_source
                || on_channel + charge > self.limits.per_channel
                || !self.make_room(channel, on_channel + charge, charge)
            {
                if self.refused.len() >= 256 {
                    self.refused.pop_front();
                }
                self.refused.push_back(key);
                return Outcome::OverBudget;
            }
            // Room for one more datagram, which a loan receives into.
            let data = self.buffer(size + MAX_DATAGRAM);
            self.assemblies.insert(
                key.clone(),
                Assembly {
                    data,
                    next: 0,
                    early: std::collections::BTreeMap::new(),
                    received: vec![false; usize::from(f.count)],
                    total: size,
                    missing: usize::from(f.count),
                    deadline: now + self.limits.deadline_for(size),
                    charge,
                    lent: false,
                    id: self.next_id,
                },
            );
            self.next_id += 1;
            self.by_source.entry(stream).or_default().push((now, f.seq));
            *self.per_source.entry(source).or_default() += charge;
            *self.per_channel.entry(Arc::clone(channel)).or_default() += charge;
            self.total += charge;
            let expiry = now + self.limits.deadline_for(size);
            self.next_expiry = Some(self.next_expiry.map_or(expiry, |e| e.min(expiry)));
        }
        let Some(a) = self.assemblies.get_mut(&key) else {
            return Outcome::Duplicate;
        };
        // A fragment that disagrees with the first one about the message's
        // shape belongs to no message we can build: treat it as a duplicate.
        let index = usize::from(f.index);
        let expected = Fragment::chunk_size(f.total, f.count)
            .min((f.total as usize).saturating_sub(index * Fragment::chunk_size(f.total, f.count)));
        if a.received.len() != usize::from(f.count)
            || a.total != f.total as usize
            || chunk.len() != expected
        {
            return Outcome::Duplicate;
        }
        if a.received[index] {
            return Outcome::Duplicate;
        }
        a.received[index] = true;
        a.missing -= 1;
        // While the buffer is lent out, fragments wait aside.
        if a.lent {
            a.early.insert(f.index, Bytes::copy_from_slice(chunk));
        } else {
            a.write(f.index, chunk);
            a.advance();
        }
        self.finish(key)
    }

    /// Lends out the buffer of the message `seq` from `source` on `channel`,
    /// so that its next fragment can be received straight into it (see
    /// [`Loan`]); `None` if no such message is being assembled, its buffer
    /// is already lent, or its next fragment is already here.
    pub fn lend(&mut self, channel: &Arc<str>, source: SocketAddr, seq: u32) -> Option<Loan> {
        let key = (Arc::clone(channel), source, seq);
        let a = self.assemblies.get_mut(&key)?;
        // The fragment after the furthest written goes at the end of
        // `data`. Fragment 0 has nothing before it for a header to overwrite.
        let size = Fragment::chunk_size(a.total as u32, a.received.len() as u16);
        let index = u16::try_from(a.data.len() / size.max(1)).unwrap_or(u16::MAX);
        if a.lent
            || index == 0
            || a.missing == 0
            || a.received.get(usize::from(index)).is_none_or(|&r| r)
            || a.data.len() != a.offset(index)
        {
            return None;
        }
        a.lent = true;
        Some(Loan {
            data: std::mem::take(&mut a.data),
            seq,
            total: a.total as u32,
            index,
            count: a.received.len() as u16,
            key,
            id: a.id,
        })
    }

    /// Takes a lent buffer back. `received` says whether the fragment the
    /// loan was for was appended to it; the message may then be complete.
    /// A message that timed out meanwhile is gone, and so is the buffer.
    pub fn repay(&mut self, loan: Loan, received: bool) -> Outcome {
        let Loan {
            data,
            key,
            index,
            id,
            ..
        } = loan;
        let Some(a) = self.assemblies.get_mut(&key).filter(|a| a.id == id) else {
            return Outcome::Duplicate;
        };
        a.data = data;
        a.lent = false;
        if received {
            if a.received[usize::from(index)] {
                // It also came the ordinary way meanwhile: keep one copy.
                a.early.remove(&index);
            } else {
                a.received[usize::from(index)] = true;
                a.missing -= 1;
            }
        }
        // Fragments that came while the buffer was out join now (or stay
        // aside if still far ahead).
        for (i, chunk) in std::mem::take(&mut a.early) {
            a.write(i, &chunk);
        }
        a.advance();
        self.finish(key)
    }

    /// Hands out the message under `key` if it is complete.
    fn finish(&mut self, key: (Arc<str>, SocketAddr, u32)) -> Outcome {
        // A lent-out message completes when its buffer comes back.
        if self
            .assemblies
            .get(&key)
            .is_none_or(|a| a.missing > 0 || a.lent)
        {
            return Outcome::Pending;
        }
        let Some(done) = self.remove(&key) else {
            return Outcome::Duplicate;
        };
        let seq = key.2;
        if self.recent.len() >= 256 {
            self.recent.pop_front();
        }
        self.recent.push_back(key);
        Outcome::Complete {
            seq,
            message: self.hand_out(done.data),
        }
    }

    /// The earliest deadline of a message being assembled: [`Reassembler::expire`]
    /// gives it up once `now` is past it.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.next_expiry
    }

    /// Drops incomplete messages past their deadline, counting them lost.
    /// Cheap when nothing can be due yet.
    pub fn expire(&mut self, now: Instant) {
        if self.next_expiry.is_none_or(|due| now < due) {
            return;
        }
        let stale: Vec<_> = self
            .assemblies
            .iter()
            .filter(|(_, a)| now > a.deadline)
            .map(|(k, _)| k.clone())
            .collect();
        for key in stale {
            if self.remove(&key).is_some() {
                self.lost += 1;
            }
        }
        self.next_expiry = self.assemblies.values().map(|a| a.deadline).min();
    }

    /// Makes room in the total budget for `charge` more bytes on `channel`,
    /// which would then hold `wanted`: the channel holding the most gives
    /// up its oldest messages, if it would still hold at least `wanted`
    /// after giving what is needed. False, and nothing given up, otherwise.
    /// Costs a pass over the channels, and one over the streams per message
    /// given up.
    fn make_room(&mut self, channel: &Arc<str>, wanted: usize, charge: usize) -> bool {
        let needed = (self.total + charge).saturating_sub(self.limits.total);
        if needed == 0 {
            return true;
        }
        let largest = self
            .per_channel
            .iter()
            .filter(|(c, _)| **c != *channel)
            .max_by_key(|(_, held)| **held)
            .map(|(c, held)| (Arc::clone(c), *held));
        let Some((largest, held)) = largest else {
            return false;
        };
        if held < wanted + needed {
            return false;
        }
        let mut freed = 0;
        while freed < needed {
            let oldest = self
                .by_source
                .iter()
                .filter(|((c, _), _)| *c == largest)
                .flat_map(|((c, source), started)| {
                    started
                        .iter()
                        .map(move |&(t, seq)| (t, (Arc::clone(c), *source, seq)))
                })
                .min_by_key(|(t, _)| *t);
            let Some((_, key)) = oldest else {
                break;
            };
            let Some(given_up) = self.remove(&key) else {
                break;
            };
            freed += given_up.charge;
            self.lost += 1;
        }
        freed >= needed
    }

    /// Takes a message out of every table and the budgets.
    fn remove(&mut self, key: &(Arc<str>, SocketAddr, u32)) -> Option<Assembly> {
        let a = self.assemblies.remove(key)?;
        let stream = (Arc::clone(&key.0), key.1);
        if let Some(started) = self.by_source.get_mut(&stream) {
            started.retain(|&(_, seq)| seq != key.2);
            if started.is_empty() {
                self.by_source.remove(&stream);
            }
        }
        self.total -= a.charge;
        if let Some(held) = self.per_source.get_mut(&key.1) {
            *held -= a.charge;
            if *held == 0 {
                self.per_source.remove(&key.1);
            }
        }
        if let Some(held) = self.per_channel.get_mut(&key.0) {
            *held -= a.charge;
            if *held == 0 {
                self.per_channel.remove(&key.0);
            }
        }
        Some(a)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fragments(channel: &str, seq: u32, message: &[u8]) -> Vec<Vec<u8>> {
        let count = Fragment::count_for(channel, message.len()) as u16;
        (0..count)
            .map(|i| {
                let mut out = Vec::new();
                Fragment::encode(channel, seq, message, i, count, &mut out);
                out
            })
            .collect()
    }

    fn message(len: usize) -> Vec<u8> {
        (0..len).map(|i| (i * 7 + i / 251) as u8).collect()
    }

    fn src(port: u16) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], port))
    }

    #[test]
    fn in_order_out_of_order_and_duplicates() {
        let ch: Arc<str> = "cam/image".into();
        let data = message(1 << 20);
        let mut frags = fragments(&ch, 9, &data);
        assert!(frags.iter().all(|f| f.len() <= MAX_DATAGRAM));
        frags.reverse();
        frags.insert(3, frags[1].clone());
        let mut r = Reassembler::new(ReassemblyLimits::default());
        let now = Instant::now();
        let mut done = None;
        for f in &frags {
            let f = Fragment::decode(f).unwrap();
            match r.push(now, &ch, src(1), f.header(), f.chunk) {
                Outcome::Complete { seq, message } => done = Some((seq, message)),
                Outcome::Pending | Outcome::Duplicate => {}
                Outcome::OverBudget => panic!("over budget"),
            }
        }
        let (seq, msg) = done.expect("complete");
        assert_eq!(seq, 9);
        assert_eq!(&msg[..], &data[..]);
        assert_eq!(r.bytes(), 0);
    }

    /// Pushes every fragment of `data` in order; the completed message.
    fn assemble(r: &mut Reassembler, ch: &Arc<str>, seq: u32, data: &[u8]) -> Bytes {
        let now = Instant::now();
        for f in fragments(ch, seq, data) {
            let f = Fragment::decode(&f).unwrap();
            if let Outcome::Complete { message, .. } = r.push(now, ch, src(1), f.header(), f.chunk)
            {
                return message;
            }
        }
        panic!("message {seq} did not complete");
    }

    #[test]
    fn buffers_are_reused_once_their_messages_are_dropped() {
        let ch: Arc<str> = "cam".into();
        let mut r = Reassembler::new(ReassemblyLimits::default());
        let (a, b) = (message(1 << 20), vec![9u8; 1 << 20]);
        let first = assemble(&mut r, &ch, 0, &a);
        let first_at = first.as_ptr();
        // Still held: the next message must not touch it.
        let second = assemble(&mut r, &ch, 1, &b);
        assert_ne!(second.as_ptr(), first_at);
        assert_eq!(&first[..], &a[..]);
        drop(first);
        let third = assemble(&mut r, &ch, 2, &a);
        assert_eq!(third.as_ptr(), first_at, "the dropped message's memory");
        assert_eq!(&third[..], &a[..]);
        assert_eq!(&second[..], &b[..]);
        // Kept spares stay within their budget.
        drop((second, third));
        for seq in 3..60 {
            drop(assemble(
                &mut r,
                &ch,
                seq,
                &b[..(1 << 17) + ((seq as usize % 8) << 16)],
            ));
        }
        assert!(r.spare.iter().map(|(n, _)| n).sum::<usize>() <= SPARE_BYTES);
    }

    #[test]
    fn loans_receive_in_place_and_give_way_to_ordinary_fragments() {
        let ch: Arc<str> = "cam".into();
        let data = message(300_000);
        let frags: Vec<Vec<u8>> = fragments(&ch, 4, &data);
        assert!(frags.len() >= 5);
        let decode = |i: usize| Fragment::decode(&frags[i]).unwrap();
        let mut r = Reassembler::new(ReassemblyLimits::default());
        let now = Instant::now();
        assert_eq!(
            r.push(now, &ch, src(1), decode(0).header(), decode(0).chunk),
            Outcome::Pending
        );
        // Fragment 1 received in place: the receiver appends its chunk.
        let mut loan = r.lend(&ch, src(1), 4).unwrap();
        assert_eq!((loan.index, loan.seq, loan.total), (1, 4, 300_000));
        assert!(loan.data.capacity() - loan.data.len() >= MAX_DATAGRAM);
        assert!(r.lend(&ch, src(1), 4).is_none(), "lent once at a time");
        loan.data.extend_from_slice(decode(1).chunk);
        assert_eq!(r.repay(loan, true), Outcome::Pending);
        // Fragment 3 comes the ordinary way while 2 is awaited in place,
        // then 2 does not come that way either (another datagram came).
        let loan = r.lend(&ch, src(1), 4).unwrap();
        assert_eq!(loan.index, 2);
        assert_eq!(
            r.push(now, &ch, src(1), decode(3).header(), decode(3).chunk),
            Outcome::Pending
        );
        assert_eq!(r.repay(loan, false), Outcome::Pending);
        // Fragment 3 was written in its place when the buffer came back
        // (the gap for 2 zeroed): the next loan is for 4, after the
        // furthest written, and 2 fills its gap the ordinary way.
        let mut loan = r.lend(&ch, src(1), 4).unwrap();
        assert_eq!(loan.index, 4);
        loan.data.extend_from_slice(decode(4).chunk);
        let mut outcome = r.repay(loan, true);
        assert_eq!(outcome, Outcome::Pending);
        outcome = r.push(now, &ch, src(1), decode(2).header(), decode(2).chunk);
        for i in 5..frags.len() {
            outcome = r.push(now, &ch, src(1), decode(i).header(), decode(i).chunk);
        }
        match outcome {
            Outcome::Complete { seq, message } => {
                assert_eq!(seq, 4);
                assert!(message[..] == data[..]);
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(r.bytes(), 0);
        // A loan on a message that timed out meanwhile comes back to nothing.
        assert_eq!(
            r.push(now, &ch, src(2), decode(0).header(), decode(0).chunk),
            Outcome::Pending
        );
        let loan = r.lend(&ch, src(2), 4).unwrap();
        let later = now + Duration::from_secs(10);
        r.expire(later);
        // The same key starts over meanwhile (a publisher restarted on the
        // same port): the stale loan must not land in the new message.
        assert_eq!(
            r.push(later, &ch, src(2), decode(0).header(), decode(0).chunk),
            Outcome::Pending
        );
        assert_eq!(r.repay(loan, false), Outcome::Duplicate);
        assert_eq!(r.lost(), 1);
        let mut outcome = Outcome::Pending;
        for i in 1..frags.len() {
            outcome = r.push(later, &ch, src(2), decode(i).header(), decode(i).chunk);
        }
        assert!(matches!(outcome, Outcome::Complete { message, .. } if message[..] == data[..]));
        // A fragment that arrives the ordinary way while the buffer is out
        // waits for the buffer to come back.
        let small = message(100_000);
        let two: Vec<Vec<u8>> = fragments(&ch, 5, &small);
        assert_eq!(two.len(), 2);
        let f = |i: usize| Fragment::decode(&two[i]).unwrap();
        assert_eq!(
            r.push(later, &ch, src(3), f(1).header(), f(1).chunk),
            Outcome::Pending
        );
        assert!(
            r.lend(&ch, src(3), 5).is_none(),
            "nothing before fragment 0 to receive over"
        );
        let mut r = Reassembler::new(ReassemblyLimits::default());
        assert_eq!(
            r.push(later, &ch, src(3), f(0).header(), f(0).chunk),
            Outcome::Pending
        );
        let loan = r.lend(&ch, src(3), 5).unwrap();
        assert_eq!(
            r.push(later, &ch, src(3), f(1).header(), f(1).chunk),
            Outcome::Pending
        );
        match r.repay(loan, false) {
            Outcome::Complete { message, .. } => assert!(message[..] == small[..]),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_lost_fragment_loses_only_its_message_after_the_timeout() {
        let ch: Arc<str> = "x".into();
        let mut r = Reassembler::new(ReassemblyLimits::default());
        let t0 = Instant::now();
        let first = fragments(&ch, 1, &message(200_000));
        for f in &first[1..] {
            let f = Fragment::decode(f).unwrap();
            assert_eq!(
                r.push(t0, &ch, src(1), f.header(), f.chunk),
                Outcome::Pending
            );
        }
        let second = fragments(&ch, 2, &message(150_000));
        let mut complete = 0;
        for f in &second {
            let f = Fragment::decode(f).unwrap();
            if let Outcome::Complete { .. } = r.push(t0, &ch, src(1), f.header(), f.chunk) {
                complete += 1;
            }
        }
        assert_eq!(complete, 1, "the next message is unaffected");
        assert!(r.bytes() >= 200_000);
        r.expire(t0 + Duration::from_secs(3));
        assert_eq!((r.lost(), r.bytes()), (1, 0));
    }

    #[test]
    fn a_message_overtaken_twice_is_given_up_at_once() {
        let ch: Arc<str> = "x".into();
        let mut r = Reassembler::new(ReassemblyLimits::default());
        let now = Instant::now();
        for seq in 0..3 {
            let frags = fragments(&ch, seq, &message(100_000));
            let f = Fragment::decode(&frags[0]).unwrap();
            assert_eq!(
                r.push(now, &ch, src(1), f.header(), f.chunk),
                Outcome::Pending
            );
        }
        assert_eq!(r.lost(), 1);
        // Two messages held, each charged its size, a datagram of room and
        // its bookkeeping.
        assert_eq!(r.bytes(), 2 * (100_000 + MAX_DATAGRAM + 2));
        assert_eq!(r.take_lost(), 1);
        assert_eq!(r.take_lost(), 0);
    }

    #[test]
    fn shapes_that_can_never_complete_are_refused_and_refusals_count_once() {
        // One byte in 65 535 fragments: the second fragment would be empty.
        let mut d = Vec::new();
        Fragment::encode_header("x", 0, 1, 0, u16::MAX, &mut d);
        d.push(7);
        assert!(Fragment::decode(&d).is_err());
        let mut d = Vec::new();
        Fragment::encode_header("x", 0, 10, 0, 4, &mut d); // 3 + 3 + 3 + 1
        d.extend_from_slice(&[1, 2, 3]);
        assert!(Fragment::decode(&d).is_ok());
        let mut d = Vec::new();
        Fragment::encode_header("x", 0, 9, 0, 4, &mut d); // 3 + 3 + 3 + 0
        d.extend_from_slice(&[1, 2, 3]);
        assert!(Fragment::decode(&d).is_err());
        // A message over budget is refused once, then ignored.
        let ch: Arc<str> = "x".into();
        let limits = ReassemblyLimits {
            per_source: 100_000,
            per_channel: 100_000,
            total: 100_000,
            timeout: Duration::from_secs(1),
        };
        let mut r = Reassembler::new(limits);
        let now = Instant::now();
        let frags = fragments(&ch, 1, &message(200_000));
        let outcomes: Vec<Outcome> = frags
            .iter()
            .map(|d| {
                let f = Fragment::decode(d).unwrap();
                r.push(now, &ch, src(1), f.header(), f.chunk)
            })
            .collect();
        assert_eq!(outcomes[0], Outcome::OverBudget);
        assert!(outcomes[1..].iter().all(|o| *o == Outcome::Duplicate));
    }

    #[test]
    fn a_message_is_given_up_at_a_deadline_fixed_by_its_first_fragment() {
        let ch: Arc<str> = "slow".into();
        let timeout = Duration::from_secs(1);
        let limits = ReassemblyLimits {
            timeout,
            ..ReassemblyLimits::default()
        };
        let data = message(400_000);
        let frags = fragments(&ch, 0, &data);
        let deadline = limits.deadline_for(data.len());
        let run = |gap: Duration| {
            let mut r = Reassembler::new(limits);
            let t0 = Instant::now();
            let mut done = None;
            for (i, d) in frags.iter().enumerate() {
                let now = t0 + gap * i as u32;
                r.expire(now);
                let f = Fragment::decode(d).unwrap();
                if let Outcome::Complete { message, .. } =
                    r.push(now, &ch, src(1), f.header(), f.chunk)
                {
                    done = Some(message);
                }
            }
            (done, r.lost())
        };
        // All its fragments within the deadline: complete.
        let steady = deadline / (frags.len() as u32);
        let (done, lost) = run(steady);
        assert!(done.is_some_and(|m| m[..] == data[..]));
        assert_eq!(lost, 0);
        // A trickle, one fragment every 0.9 s (never a second without
        // news: the rule before, under which it held its memory forever):
        // given up at the deadline.
        let gap = Duration::from_millis(900);
        assert!(gap * frags.len() as u32 > deadline);
        let mut r = Reassembler::new(limits);
        let t0 = Instant::now();
        for (i, d) in frags.iter().enumerate() {
            let now = t0 + gap * i as u32;
            if now > t0 + deadline {
                break;
            }
            let f = Fragment::decode(d).unwrap();
            assert_eq!(
                r.push(now, &ch, src(1), f.header(), f.chunk),
                Outcome::Pending
            );
        }
        assert!(r.bytes() > 0);
        r.expire(t0 + deadline + Duration::from_millis(1));
        assert_eq!((r.lost(), r.bytes()), (1, 0));
    }

    /// A fragment far ahead is kept aside, not written after a zeroed gap:
    /// two datagrams must not cost a whole large message in memory. Near
    /// ones are written in place, and the message still completes.
    #[test]
    fn a_fragment_far_ahead_costs_only_itself() {
        let ch: Arc<str> = "x".into();
        let data = message(5 << 20);
        let frags = fragments(&ch, 1, &data);
        let mut r = Reassembler::new(ReassemblyLimits::default());
        let now = Instant::now();
        let push = |r: &mut Reassembler, i: usize| {
            let f = Fragment::decode(&frags[i]).unwrap();
            r.push(now, &ch, src(1), f.header(), f.chunk)
        };
        let last = frags.len() - 1;
        assert_eq!(push(&mut r, 0), Outcome::Pending);
        assert_eq!(push(&mut r, last), Outcome::Pending);
        let written = |r: &Reassembler| r.assemblies.values().next().unwrap().data.len();
        let chunk = Fragment::decode(&frags[0]).unwrap().chunk.len();
        assert_eq!(written(&r), chunk, "zeroed up to a far fragment");
        assert_eq!(push(&mut r, 3), Outcome::Pending);
        assert_eq!(written(&r), 4 * chunk, "a near one is written in place");
        let mut outcome = Outcome::Pending;
        for i in (1..last).rev() {
            if i != 3 {
                outcome = push(&mut r, i);
            }
        }
        assert!(matches!(outcome, Outcome::Complete { message, .. } if message[..] == data[..]));
    }

    /// The total is full of messages on one channel (eight senders, as an
    /// attacker on an open channel): a message on another channel still
    /// gets in, and the full channel gives up its oldest.
    #[test]
    fn a_channel_full_of_fragments_makes_room_for_another_channel() {
        let open: Arc<str> = "open".into();
        let sealed: Arc<str> = "sealed".into();
        let limits = ReassemblyLimits {
            per_source: 1 << 20,
            per_channel: 3 << 20,
            total: 3 << 20,
            timeout: Duration::from_secs(1),
        };
        let mut r = Reassembler::new(limits);
        let now = Instant::now();
        let mut admitted = 0;
        for s in 0..8u16 {
            let frags = fragments(&open, 1, &message(900_000));
            let f = Fragment::decode(&frags[0]).unwrap();
            if r.push(now, &open, src(100 + s), f.header(), f.chunk) == Outcome::Pending {
                admitted += 1;
            }
        }
        assert_eq!(admitted, 3, "the open channel fills the total");
        let data = message(500_000);
        let mut done = None;
        for d in fragments(&sealed, 7, &data) {
            let f = Fragment::decode(&d).unwrap();
            match r.push(now, &sealed, src(1), f.header(), f.chunk) {
                Outcome::Complete { message, .. } => done = Some(message),
                Outcome::Pending => {}
                other => panic!("{other:?}"),
            }
        }
        assert!(done.is_some_and(|m| m[..] == data[..]));
        assert_eq!(r.lost(), 1, "one open message gave way");
        assert!(r.bytes() <= limits.total);
        // The open channel can't take the room back from itself, nor push
        // out a channel that holds less than it.
        let frags = fragments(&open, 2, &message(900_000));
        let f = Fragment::decode(&frags[0]).unwrap();
        assert_eq!(
            r.push(now, &open, src(200), f.header(), f.chunk),
            Outcome::Pending,
            "room is free again once the sealed message completed"
        );
        let f = Fragment::decode(&frags[0]).unwrap();
        assert_eq!(
            r.push(now, &open, src(201), f.header(), f.chunk),
            Outcome::OverBudget
        );
    }

    #[test]
    fn memory_is_bounded_per_source_and_in_total() {
        let ch: Arc<str> = "x".into();
        let limits = ReassemblyLimits {
            per_source: 1 << 20,
            per_channel: 3 << 19,
            total: 3 << 19,
            timeout: Duration::from_secs(1),
        };
        let mut r = Reassembler::new(limits);
        let now = Instant::now();
        let big = fragments(&ch, 1, &message(700_000));
        let f = Fragment::decode(&big[0]).unwrap();
        assert_eq!(
            r.push(now, &ch, src(1), f.header(), f.chunk),
            Outcome::Pending
        );
        let second = fragments(&ch, 2, &message(700_000));
        let f2 = Fragment::decode(&second[0]).unwrap();
        assert_eq!(
            r.push(now, &ch, src(1), f2.header(), f2.chunk),
            Outcome::OverBudget,
            "per source"
        );
        assert_eq!(
            r.push(now, &ch, src(2), f2.header(), f2.chunk),
            Outcome::Pending
        );
        let third = fragments(&ch, 3, &message(700_000));
        let f3 = Fragment::decode(&third[0]).unwrap();
        assert_eq!(
            r.push(now, &ch, src(3), f3.header(), f3.chunk),
            Outcome::OverBudget,
            "in total"
        );
        assert!(r.bytes() <= limits.total);
    }

    #[test]
    fn inconsistent_fragments_are_refused() {
        let good = fragments("c", 1, &message(100_000));
        let mut bad = good[0].clone();
        let n = bad.len();
        bad.truncate(n - 1);
        assert!(Fragment::decode(&bad).is_err(), "short chunk");
        let mut bad = good[0].clone();
        bad[4 + 1 + 1 + 4..4 + 1 + 1 + 8].copy_from_slice(&(u32::MAX).to_be_bytes());
        assert!(Fragment::decode(&bad).is_err(), "over 64 MiB");
        let mut bad = good[0].clone();
        bad[4 + 1 + 1 + 10..4 + 1 + 1 + 12].copy_from_slice(&1u16.to_be_bytes());
        assert!(Fragment::decode(&bad).is_err(), "count 1");
        for len in 0..30 {
            let _ = Fragment::decode(&good[0][..len.min(good[0].len())]);
        }
    }
}

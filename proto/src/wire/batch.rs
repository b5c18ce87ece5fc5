//! Batches: several small messages of one channel in one datagram.
//!
//! One datagram per message caps a publisher at the kernel's send rate (about
//! 0.2 M datagrams/s on a 2-core machine), whatever the message size. A
//! publisher that opts in packs consecutive messages of one channel into one
//! datagram under its own magic, so Pulicast 2.x nodes (which check for
//! `PULI`) drop batches silently:
//!
//! ```text
//! +--------+-------+------+----------------+-----------+----------------------------+
//! | "PBAT" | n: u8 | name | first_seq: u32 | count: u16| count x (len: u16 | bytes) |
//! +--------+-------+------+----------------+-----------+----------------------------+
//! ```
//!
//! All integers are big-endian. The messages carry the consecutive sequence
//! numbers `first_seq`, `first_seq + 1`, ... (wrapping), from the same counter
//! as unbatched messages, so lead tracking sees no difference. A batch whose
//! entries do not exactly fill the datagram is malformed as a whole: a
//! receiver delivers all of its messages or none.
//!
//! ```
//! use pulicast_proto::wire::batch::{Batch, BatchBuilder};
//!
//! let mut builder = BatchBuilder::new();
//! builder.start("rover1/odom", 41);
//! for message in [&b"a"[..], b"bc", b""] {
//!     assert!(builder.fits(message.len()));
//!     builder.push(message);
//! }
//! let datagram = builder.finish().to_vec();
//!
//! let batch = Batch::decode(&datagram).unwrap();
//! assert_eq!((batch.channel, batch.first_seq, batch.count), ("rover1/odom", 41, 3));
//! let messages: Vec<(u32, &[u8])> = batch
//!     .entries(&datagram)
//!     .map(|(seq, range)| (seq, &datagram[range]))
//!     .collect();
//! assert_eq!(messages, [(41, &b"a"[..]), (42, b"bc"), (43, b"")]);
//! ```

use std::ops::Range;

use crate::wire::{DecodeError, MAX_DATAGRAM};

/// The four bytes every batch starts with.
pub const MAGIC: [u8; 4] = crate::wire::BATCH_MAGIC;

/// Header bytes besides the channel name: magic, name length, first
/// sequence number and count.
pub const HEADER_OVERHEAD: usize = 4 + 1 + 4 + 2;

/// Bytes each message adds besides its own: its length.
pub const ENTRY_OVERHEAD: usize = 2;

/// A parsed and checked batch, borrowing its channel name from the datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Batch<'a> {
    /// Channel name.
    pub channel: &'a str,
    /// Sequence number of the first message.
    pub first_seq: u32,
    /// How many messages the batch holds (at least one).
    pub count: u16,
    /// Where the entries start in the datagram.
    body: usize,
}

impl<'a> Batch<'a> {
    /// Whether a datagram is a batch.
    pub fn is_batch(datagram: &[u8]) -> bool {
        datagram.starts_with(&MAGIC)
    }

    /// Parses a batch and checks every entry, so that delivering its
    /// messages afterwards cannot fail half way.
    pub fn decode(datagram: &'a [u8]) -> Result<Self, DecodeError> {
        let malformed = |what: &str| DecodeError::Malformed(format!("batch: {what}"));
        let too_short = DecodeError::TooShort {
            len: datagram.len(),
        };
        let (channel, rest) = crate::wire::split_name(datagram, &MAGIC)?;
        let (numbers, mut body) = rest.split_first_chunk::<6>().ok_or(too_short)?;
        let first_seq = u32::from_be_bytes([numbers[0], numbers[1], numbers[2], numbers[3]]);
        let count = u16::from_be_bytes([numbers[4], numbers[5]]);
        if count == 0 {
            return Err(malformed("no messages"));
        }
        for _ in 0..count {
            let (len, rest) = body
                .split_first_chunk::<2>()
                .ok_or_else(|| malformed("an entry's length runs past the end"))?;
            body = rest
                .get(usize::from(u16::from_be_bytes(*len))..)
                .ok_or_else(|| malformed("an entry runs past the end"))?;
        }
        if !body.is_empty() {
            return Err(DecodeError::TrailingBytes { count: body.len() });
        }
        Ok(Batch {
            channel,
            first_seq,
            count,
            body: HEADER_OVERHEAD + channel.len(),
        })
    }

    /// The messages as (sequence number, byte range in `datagram`), where
    /// `datagram` is the one this batch was decoded from. Ranges index the
    /// datagram so a receiver can hand out views of one shared buffer.
    pub fn entries<'d>(&self, datagram: &'d [u8]) -> Entries<'d> {
        self.layout().entries(datagram)
    }

    /// Where the messages are, without borrowing the datagram: a receiver
    /// can then freeze its buffer and walk the entries of the frozen bytes.
    pub fn layout(&self) -> Layout {
        Layout {
            first_seq: self.first_seq,
            count: self.count,
            body: self.body,
        }
    }
}

/// The shape of a checked [`Batch`]: see [`Batch::layout`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    first_seq: u32,
    count: u16,
    body: usize,
}

impl Layout {
    /// Sequence number of the first message.
    pub fn first_seq(&self) -> u32 {
        self.first_seq
    }

    /// How many messages the batch holds.
    pub fn count(&self) -> u16 {
        self.count
    }

    /// The messages of the batch in `datagram`; see [`Batch::entries`].
    pub fn entries<'d>(&self, datagram: &'d [u8]) -> Entries<'d> {
        Entries {
            datagram,
            offset: self.body,
            seq: self.first_seq,
            left: self.count,
        }
    }

    /// The first message, and the layout of the rest: a cursor that walks
    /// the batch one message at a time without borrowing the datagram.
    pub fn split_first(&self, datagram: &[u8]) -> Option<((u32, Range<usize>), Layout)> {
        let mut entries = self.entries(datagram);
        let first = entries.next()?;
        let rest = Layout {
            first_seq: entries.seq,
            count: entries.left,
            body: entries.offset,
        };
        Some((first, rest))
    }
}

/// The messages of a [`Batch`]; see [`Batch::entries`].
#[derive(Debug, Clone)]
pub struct Entries<'d> {
    datagram: &'d [u8],
    offset: usize,
    seq: u32,
    left: u16,
}

impl Iterator for Entries<'_> {
    type Item = (u32, Range<usize>);

    fn next(&mut self) -> Option<Self::Item> {
        if self.left == 0 {
            return None;
        }
        let len = self
            .datagram
            .get(self.offset..self.offset + ENTRY_OVERHEAD)?;
        let start = self.offset + ENTRY_OVERHEAD;
        let end = start + usize::from(u16::from_be_bytes([len[0], len[1]]));
        if end > self.datagram.len() {
            return None;
        }
        let item = (self.seq, start..end);
        self.offset = end;
        self.seq = self.seq.wrapping_add(1);
        self.left -= 1;
        Some(item)
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        (0, Some(usize::from(self.left)))
    }
}

/// Builds one batch datagram at a time in a buffer it keeps, so filling
/// batches allocates nothing once the buffer has grown.
#[derive(Debug)]
pub struct BatchBuilder {
    buf: Vec<u8>,
    count: u16,
    first_seq: u32,
    /// The largest batch datagram to build.
    limit: usize,
    /// The size of the batches lately: the largest, decaying by an
    /// eighth with each smaller one.
    peak: usize,
}

/// What a batch reserves at least: an Ethernet frame's payload.
const MIN_RESERVE: usize = 1472;

impl Default for BatchBuilder {
    fn default() -> Self {
        Self::with_limit(MAX_DATAGRAM)
    }
}

impl BatchBuilder {
    /// An empty builder.
    pub fn new() -> Self {
        Self::default()
    }

    /// An empty builder of batches of at most `limit` bytes (at most
    /// [`MAX_DATAGRAM`]), leaving room for what wraps a batch, such as a
    /// seal.
    pub fn with_limit(limit: usize) -> Self {
        Self {
            buf: Vec::new(),
            count: 0,
            first_seq: 0,
            limit: limit.min(MAX_DATAGRAM),
            peak: 0,
        }
    }

    /// Whether a message of `len` bytes on `channel` fits an empty batch.
    pub fn fits_alone(&self, channel: &str, len: usize) -> bool {
        HEADER_OVERHEAD + channel.len() + ENTRY_OVERHEAD + len <= self.limit
    }

    /// Begins a new batch on `channel` whose first message is `first_seq`,
    /// dropping whatever the builder held.
    pub fn start(&mut self, channel: &str, first_seq: u32) {
        self.buf.clear();
        // As much as the batches lately took, not the limit: a channel
        // whose batches hold a message or two holds no datagram's worth
        // for good, and one whose batches fill, even now and then, grows
        // to it once.
        self.buf.reserve(self.peak.max(MIN_RESERVE).min(self.limit));
        self.buf.extend_from_slice(&MAGIC);
        self.buf.push(channel.len().min(255) as u8);
        self.buf.extend_from_slice(channel.as_bytes());
        self.buf.extend_from_slice(&first_seq.to_be_bytes());
        self.buf.extend_from_slice(&[0, 0]);
        self.count = 0;
        self.first_seq = first_seq;
    }

    /// The sequence number the next message of the current batch takes:
    /// a batch numbers its messages consecutively.
    pub fn next_seq(&self) -> u32 {
        self.first_seq.wrapping_add(u32::from(self.count))
    }

    /// Messages in the current batch.
    pub fn len(&self) -> usize {
        usize::from(self.count)
    }

    /// Whether the current batch holds no message (or none was started).
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Whether a message of `len` bytes fits the current batch.
    pub fn fits(&self, len: usize) -> bool {
        self.count < u16::MAX && self.buf.len() + ENTRY_OVERHEAD + len <= self.limit
    }

    /// Appends a message; the caller checked [`BatchBuilder::fits`], and a
    /// message that does not fit is refused with `false`.
    pub fn push(&mut self, message: &[u8]) -> bool {
        let Ok(len) = u16::try_from(message.len()) else {
            return false;
        };
        if self.buf.len() < HEADER_OVERHEAD || !self.fits(message.len()) {
            return false;
        }
        self.buf.extend_from_slice(&len.to_be_bytes());
        self.buf.extend_from_slice(message);
        self.count += 1;
        true
    }

    /// The finished datagram. The builder keeps it until the next
    /// [`BatchBuilder::start`] or [`BatchBuilder::clear`].
    pub fn finish(&mut self) -> &[u8] {
        let at = self.count_offset();
        if let Some(slot) = self.buf.get_mut(at..at + 2) {
            slot.copy_from_slice(&self.count.to_be_bytes());
        }
        &self.buf
    }

    /// Forgets the current batch. The buffer is kept while it is at most
    /// twice the size batches lately took, and shrinks to that otherwise.
    pub fn clear(&mut self) {
        if self.count > 0 {
            self.peak = self.buf.len().max(self.peak - self.peak / 8);
        }
        self.buf.clear();
        if self.buf.capacity() > 2 * self.peak.max(MIN_RESERVE) {
            self.buf.shrink_to(self.peak);
        }
        self.count = 0;
    }

    fn count_offset(&self) -> usize {
        let name = self.buf.get(4).copied().map_or(0, usize::from);
        HEADER_OVERHEAD - 2 + name
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn batch(channel: &str, first: u32, messages: &[&[u8]]) -> Vec<u8> {
        let mut b = BatchBuilder::new();
        b.start(channel, first);
        for m in messages {
            assert!(b.push(m));
        }
        b.finish().to_vec()
    }

    #[test]
    fn sequence_numbers_wrap() {
        let d = batch("c", u32::MAX, &[b"x", b"y"]);
        let b = Batch::decode(&d).unwrap();
        let seqs: Vec<u32> = b.entries(&d).map(|(s, _)| s).collect();
        assert_eq!(seqs, [u32::MAX, 0]);
    }

    #[test]
    fn the_builder_fills_one_datagram_and_no_more() {
        let mut b = BatchBuilder::new();
        b.start("c", 0);
        let message = [7u8; 1000];
        let mut n = 0;
        while b.fits(message.len()) {
            assert!(b.push(&message));
            n += 1;
        }
        assert!(!b.push(&message));
        assert_eq!(n, (MAX_DATAGRAM - HEADER_OVERHEAD - 1) / 1002);
        let d = b.finish().to_vec();
        assert!(d.len() <= MAX_DATAGRAM);
        assert_eq!(Batch::decode(&d).unwrap().count as usize, n);
        assert!(b.fits_alone("c", MAX_DATAGRAM - HEADER_OVERHEAD - 3));
        assert!(!b.fits_alone("c", MAX_DATAGRAM - HEADER_OVERHEAD - 2));
    }

    #[test]
    fn a_limited_builder_leaves_room() {
        let mut b = BatchBuilder::with_limit(1000);
        b.start("c", 0);
        while b.fits(10) {
            assert!(b.push(&[1; 10]));
        }
        assert!(b.finish().len() <= 1000 && b.finish().len() > 1000 - 12);
        assert!(!b.fits_alone("c", 1000));
        let unlimited = BatchBuilder::with_limit(usize::MAX);
        assert!(unlimited.fits_alone("c", MAX_DATAGRAM - HEADER_OVERHEAD - 3));
    }

    #[test]
    fn inconsistent_batches_are_refused_whole() {
        let good = batch("ch", 5, &[b"abc", b"de"]);
        assert!(Batch::decode(&good).is_ok());
        // Every truncation is an error, never a partial batch.
        for cut in 0..good.len() {
            assert!(Batch::decode(&good[..cut]).is_err(), "cut at {cut}");
        }
        let mut trailing = good.clone();
        trailing.push(0);
        assert_eq!(
            Batch::decode(&trailing),
            Err(DecodeError::TrailingBytes { count: 1 })
        );
        let mut empty = batch("ch", 5, &[b"a"]);
        empty.truncate(HEADER_OVERHEAD + 2);
        assert!(matches!(
            Batch::decode(&empty),
            Err(DecodeError::Malformed(_))
        ));
        assert_eq!(Batch::decode(b"PULI\x00"), Err(DecodeError::BadMagic));
        assert!(!Batch::is_batch(b"PULI"));
    }

    #[test]
    fn a_builder_that_was_not_started_refuses_messages() {
        let mut b = BatchBuilder::new();
        assert!(!b.push(b"x"));
        assert!(b.is_empty());
    }

    /// A channel whose batches are small holds a small buffer, and one
    /// that filled a datagram gives the room back once its batches have
    /// stayed small a while (a bridge holds a builder for every channel it
    /// ever imported); batches that are full now and then keep theirs
    /// without growing it again each time.
    #[test]
    fn the_buffer_follows_the_batches_size() {
        let batch = |b: &mut BatchBuilder, seq: u32, len: usize| {
            b.start("ch", seq);
            while b.len() * 1000 < len && b.fits(1000) {
                assert!(b.push(&[1; 1000]));
            }
            let size = b.finish().len();
            b.clear();
            size
        };
        let mut b = BatchBuilder::new();
        batch(&mut b, 0, 40);
        assert!(b.buf.capacity() <= 2 * MIN_RESERVE, "{}", b.buf.capacity());
        let full = batch(&mut b, 1, usize::MAX);
        let held = b.buf.capacity();
        assert!(held >= full);
        for seq in 2..20 {
            batch(&mut b, seq, if seq % 2 == 0 { 40 } else { usize::MAX });
            assert_eq!(b.buf.capacity(), held, "full now and then: kept");
        }
        for seq in 20..80 {
            batch(&mut b, seq, 40);
        }
        assert!(b.buf.capacity() <= 2 * MIN_RESERVE, "{}", b.buf.capacity());
    }
}

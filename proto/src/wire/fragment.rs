//! The fragment format: a message larger than one datagram travels as
//! fragments under their own magic, so Pulicast 2.x nodes (which check for
//! `PULI`) drop them silently:
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
//! receiver can place fragments arriving in any order. Reassembly is
//! [`crate::fragment::Reassembler`].

use crate::wire::{DecodeError, MAX_DATAGRAM};

/// The four bytes every fragment starts with.
pub const MAGIC: [u8; 4] = crate::wire::FRAGMENT_MAGIC;

/// The largest message pulicast sends or reassembles: 64 MiB.
pub const MAX_MESSAGE: usize = 64 << 20;

/// Header bytes besides the channel name.
pub const HEADER_OVERHEAD: usize = 4 + 1 + 4 + 4 + 2 + 2;

/// One parsed fragment, borrowing from its datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fragment<'a> {
    /// Channel name.
    pub channel: &'a str,
    /// Message sequence number.
    pub seq: u32,
    /// Size of the whole message.
    pub total: u32,
    /// This fragment's index.
    pub index: u16,
    /// How many fragments the message has.
    pub count: u16,
    /// This fragment's bytes.
    pub chunk: &'a [u8],
}

/// A fragment's numbers, without its bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// Message sequence number.
    pub seq: u32,
    /// Size of the whole message.
    pub total: u32,
    /// This fragment's index.
    pub index: u16,
    /// How many fragments the message has.
    pub count: u16,
}

impl<'a> Fragment<'a> {
    /// The fragment's numbers.
    pub fn header(&self) -> Header {
        Header {
            seq: self.seq,
            total: self.total,
            index: self.index,
            count: self.count,
        }
    }

    /// Whether a datagram is a fragment.
    pub fn is_fragment(datagram: &[u8]) -> bool {
        datagram.starts_with(&MAGIC)
    }

    /// Bytes every fragment but the last carries.
    pub fn chunk_size(total: u32, count: u16) -> usize {
        (total as usize).div_ceil(usize::from(count.max(1)))
    }

    /// Parses a fragment and checks that it is consistent in itself.
    pub fn decode(datagram: &'a [u8]) -> Result<Self, DecodeError> {
        let malformed = |what: &str| DecodeError::Malformed(format!("fragment: {what}"));
        let (channel, rest) = crate::wire::split_name(datagram, &MAGIC)?;
        let (header, chunk) = rest.split_at_checked(12).ok_or(DecodeError::TooShort {
            len: datagram.len(),
        })?;
        let be32 = |b: &[u8]| u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
        let seq = be32(&header[0..4]);
        let total = be32(&header[4..8]);
        let index = u16::from_be_bytes([header[8], header[9]]);
        let count = u16::from_be_bytes([header[10], header[11]]);
        if total as usize > MAX_MESSAGE {
            return Err(malformed("message larger than 64 MiB"));
        }
        if count < 2 || index >= count {
            return Err(malformed("bad index or count"));
        }
        let size = Self::chunk_size(total, count);
        let offset = usize::from(index) * size;
        // Every fragment must carry bytes, the last one included: a shape
        // such as 1 byte in 65 535 fragments could never complete, and would
        // only pin memory.
        if size == 0 || (usize::from(count) - 1) * size >= total as usize {
            return Err(malformed("count does not fit the size"));
        }
        if offset >= total as usize {
            return Err(malformed("index past the end"));
        }
        let expected = size.min(total as usize - offset);
        if chunk.len() != expected {
            return Err(malformed("chunk length does not fit the size"));
        }
        Ok(Fragment {
            channel,
            seq,
            total,
            index,
            count,
            chunk,
        })
    }

    /// The largest chunk a fragment on `channel` can carry.
    pub fn max_chunk(channel: &str) -> usize {
        MAX_DATAGRAM - HEADER_OVERHEAD - channel.len()
    }

    /// The longest fragment header: magic, name length, a 255-byte name and
    /// the numbers.
    pub const MAX_HEADER: usize = HEADER_OVERHEAD + 255;

    /// Appends the header of fragment `index` of a `total`-byte message.
    pub fn encode_header(
        channel: &str,
        seq: u32,
        total: u32,
        index: u16,
        count: u16,
        out: &mut Vec<u8>,
    ) {
        out.extend_from_slice(&MAGIC);
        out.push(channel.len().min(255) as u8);
        out.extend_from_slice(channel.as_bytes());
        out.extend_from_slice(&Self::numbers(seq, total, index, count));
    }

    /// How many bytes fragment `index` of a `total`-byte message carries.
    pub fn chunk_of_len(total: u32, index: u16, count: u16) -> usize {
        let size = Self::chunk_size(total, count);
        (total as usize)
            .saturating_sub(usize::from(index) * size)
            .min(size)
    }

    /// Appends fragment `index` of `message` to `out`.
    pub fn encode(
        channel: &str,
        seq: u32,
        message: &[u8],
        index: u16,
        count: u16,
        out: &mut Vec<u8>,
    ) {
        Self::encode_header(channel, seq, message.len() as u32, index, count, out);
        out.extend_from_slice(Self::chunk_of(message, index, count));
    }

    /// The header up to the numbers: magic, name length and name, the same
    /// for every fragment of a channel.
    pub fn prefix(channel: &str) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_OVERHEAD + channel.len());
        Self::encode_header(channel, 0, 0, 0, 0, &mut out);
        out.truncate(out.len() - 12);
        out
    }

    /// The header after the name: sequence number, total size, index and
    /// count, big-endian.
    pub fn numbers(seq: u32, total: u32, index: u16, count: u16) -> [u8; 12] {
        let mut out = [0; 12];
        out[0..4].copy_from_slice(&seq.to_be_bytes());
        out[4..8].copy_from_slice(&total.to_be_bytes());
        out[8..10].copy_from_slice(&index.to_be_bytes());
        out[10..12].copy_from_slice(&count.to_be_bytes());
        out
    }

    /// The bytes of `message` that fragment `index` of `count` carries
    /// (empty for an index past the end).
    pub fn chunk_of(message: &[u8], index: u16, count: u16) -> &[u8] {
        let size = Self::chunk_size(message.len() as u32, count);
        let start = (usize::from(index) * size).min(message.len());
        let end = (start + size).min(message.len());
        &message[start..end]
    }

    /// How many fragments `len` bytes on `channel` need.
    pub fn count_for(channel: &str, len: usize) -> usize {
        Self::count_within(channel, len, 0)
    }

    /// How many fragments `len` bytes on `channel` need when each
    /// fragment must leave `reserve` bytes of the datagram free (for a
    /// seal around it). Receivers derive chunk sizes from the count, so
    /// any count this gives is understood.
    pub fn count_within(channel: &str, len: usize, reserve: usize) -> usize {
        len.div_ceil(Self::max_chunk(channel).saturating_sub(reserve).max(1))
    }
}

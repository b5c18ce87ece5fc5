//! The header of a sealed datagram, read without a key:
//!
//! ```text
//! | "PSEC" | n: u8 | name | flags: u8 | origin: ip [4], port u16 | stream: u64 | counter: u64 | sent_ms: u64 | inner datagram | tag: 16 |
//! ```
//!
//! Everything up to the inner datagram is authenticated but readable; the
//! inner datagram may be encrypted. Checking and opening is
//! [`crate::secure::Opener`]'s.

use std::net::{Ipv4Addr, SocketAddrV4};
use std::ops::Range;

use super::{split_name, DecodeError, SEALED_MAGIC};

/// Bytes of a tag.
pub const TAG_LEN: usize = 16;

/// The flag that says the inner datagram is encrypted.
pub const ENCRYPTED: u8 = 1;

/// A sealed datagram's header, borrowing from its datagram.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Sealed<'a> {
    /// The channel it was sealed for.
    pub channel: &'a str,
    /// Whether the inner datagram is encrypted.
    pub encrypted: bool,
    /// Where the sender says it sends from (unspecified parts unchecked).
    pub origin: SocketAddrV4,
    /// The sealer's stream id.
    pub stream: u64,
    /// The datagram's counter in its stream.
    pub counter: u64,
    /// When it was sealed, by the sender's wall clock, in ms.
    pub sent_ms: u64,
    /// Where the inner datagram lies in the datagram.
    pub inner: Range<usize>,
}

impl<'a> Sealed<'a> {
    /// Reads the header of a sealed datagram: the magic, the name, known
    /// flags only, and room for a tag.
    pub fn decode(datagram: &'a [u8]) -> Result<Self, DecodeError> {
        let (channel, rest) = split_name(datagram, &SEALED_MAGIC)?;
        let truncated = |needed: usize| DecodeError::Truncated {
            offset: datagram.len() - rest.len(),
            needed,
        };
        let (&flags, after_flags) = rest.split_first().ok_or_else(|| truncated(1))?;
        let (origin, after_origin) = after_flags
            .split_first_chunk::<6>()
            .ok_or_else(|| truncated(7))?;
        let (numbers, body) = after_origin
            .split_first_chunk::<24>()
            .ok_or_else(|| truncated(31))?;
        if body.len() < TAG_LEN {
            return Err(truncated(31 + TAG_LEN));
        }
        if flags & !ENCRYPTED != 0 {
            return Err(DecodeError::Malformed(format!(
                "unknown flags {flags:#04x}"
            )));
        }
        let be64 = |i: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&numbers[i..i + 8]);
            u64::from_be_bytes(b)
        };
        let header = datagram.len() - body.len();
        Ok(Self {
            channel,
            encrypted: flags & ENCRYPTED != 0,
            origin: SocketAddrV4::new(
                Ipv4Addr::new(origin[0], origin[1], origin[2], origin[3]),
                u16::from_be_bytes([origin[4], origin[5]]),
            ),
            stream: be64(0),
            counter: be64(8),
            sent_ms: be64(16),
            inner: header..datagram.len() - TAG_LEN,
        })
    }
}

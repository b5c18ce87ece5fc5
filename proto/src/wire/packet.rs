//! The Pulicast 2.x datagram.
//!
//! ```text
//!  0       4       5                5+n              9+n
//! +-------+-------+----------------+----------------+-------------+
//! | "PULI"| n: u8 | channel name   | sequence: u32  | payload ... |
//! |       |       | (n ASCII bytes)| (big-endian)   |             |
//! +-------+-------+----------------+----------------+-------------+
//! ```
//!
//! The sequence number counts per channel per sender, from 0, wrapping at 2^32.

use super::DecodeError;

/// The four bytes every Pulicast 2.x datagram starts with.
pub const MAGIC: [u8; 4] = *b"PULI";

/// The largest UDP payload over IPv4, and so the largest datagram we send.
pub const MAX_DATAGRAM: usize = 65507;

/// Header bytes besides the channel name: magic, name length and sequence.
pub const HEADER_OVERHEAD: usize = MAGIC.len() + 1 + 4;

/// A decoded datagram that borrows from the receive buffer.
///
/// ```
/// use pulicast_proto::wire::Packet;
/// let mut buf = Vec::new();
/// Packet { channel: "rover1/ctrl", seq: 7, payload: b"hi" }.encode(&mut buf);
/// let packet = Packet::decode(&buf).unwrap();
/// assert_eq!((packet.channel, packet.seq, packet.payload), ("rover1/ctrl", 7, &b"hi"[..]));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Packet<'a> {
    /// Resolved channel name.
    pub channel: &'a str,
    /// Sequence number of this message on this channel from this sender.
    pub seq: u32,
    /// The message bytes.
    pub payload: &'a [u8],
}

impl<'a> Packet<'a> {
    /// Parses one datagram.
    pub fn decode(buf: &'a [u8]) -> Result<Self, DecodeError> {
        let (channel, rest) = super::split_name(buf, &MAGIC)?;
        let Some((seq, payload)) = rest.split_first_chunk::<4>() else {
            return Err(DecodeError::TooShort { len: buf.len() });
        };
        Ok(Packet {
            channel,
            seq: u32::from_be_bytes(*seq),
            payload,
        })
    }

    /// Appends the encoded datagram to `out`.
    ///
    /// The caller guarantees a name of at most 255 bytes; the API layer checks it
    /// when the channel is created.
    pub fn encode(&self, out: &mut Vec<u8>) {
        Self::encode_header(self.channel, self.seq, out);
        out.extend_from_slice(self.payload);
    }

    /// The header up to the sequence number: magic, name length and name.
    /// A sender keeps it per channel and sends it with the sequence number
    /// and the payload in one vectored call.
    pub fn prefix(channel: &str) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_OVERHEAD + channel.len());
        Self::encode_header(channel, 0, &mut out);
        out.truncate(out.len() - 4);
        out
    }

    /// Appends only the header, so a payload can be encoded in place after it.
    pub fn encode_header(channel: &str, seq: u32, out: &mut Vec<u8>) {
        debug_assert!(channel.len() <= 255);
        out.extend_from_slice(&MAGIC);
        out.push(channel.len().min(255) as u8);
        out.extend_from_slice(channel.as_bytes());
        out.extend_from_slice(&seq.to_be_bytes());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn malformed_datagrams_are_errors() {
        let cases: &[(&[u8], DecodeError)] = &[
            (b"", DecodeError::TooShort { len: 0 }),
            (b"PUL", DecodeError::TooShort { len: 3 }),
            (b"PULI", DecodeError::TooShort { len: 4 }),
            (b"LCM2\x01a\0\0\0\0", DecodeError::BadMagic),
            (b"PULI\x05abc", DecodeError::NamePastEnd),
            (b"PULI\x01\xff\0\0\0\0", DecodeError::NonAsciiName),
            (b"PULI\x01a\0\0\0", DecodeError::TooShort { len: 9 }),
        ];
        for (bytes, expected) in cases {
            assert_eq!(Packet::decode(bytes).as_ref(), Err(expected), "{bytes:?}");
        }
    }

    #[test]
    fn empty_payload_and_empty_name_parse() {
        let p = Packet::decode(b"PULI\x00\0\0\0\x01").unwrap();
        assert_eq!((p.channel, p.seq, p.payload), ("", 1, &[][..]));
    }
}

//! Which kind of datagram a receiver holds: the one place that tells them
//! apart. Every kind starts with a 4-byte magic; the formats behind them
//! are in [`crate::wire::Packet`], [`crate::wire::batch`],
//! [`crate::fragment`], [`crate::secure`] and
//! `pulicast_discovery::wire`.

/// The magic of a batch of messages of one channel (our extension).
pub const BATCH_MAGIC: [u8; 4] = *b"PBAT";
/// The magic of a fragment of a message too large for one datagram (our
/// extension).
pub const FRAGMENT_MAGIC: [u8; 4] = *b"PFRG";
/// The magic of a sealed datagram, which carries one of the others.
pub const SEALED_MAGIC: [u8; 4] = *b"PSEC";

/// What a datagram is, told by its magic alone (nothing else is checked).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum Kind {
    /// A Pulicast 2.x packet (`PULI`).
    Packet,
    /// A batch (`PBAT`).
    Batch,
    /// A fragment (`PFRG`).
    Fragment,
    /// A sealed datagram (`PSEC`), carrying a packet, batch, fragment or gossip.
    Sealed,
    /// Discovery gossip (`PDSC`).
    Discovery,
    /// None of these (2.x nodes drop it too).
    Unknown,
}

impl Kind {
    /// The kind of `datagram`.
    pub fn of(datagram: &[u8]) -> Self {
        let Some(magic) = datagram.get(..4) else {
            return Kind::Unknown;
        };
        match magic {
            m if m == super::MAGIC => Kind::Packet,
            m if m == BATCH_MAGIC => Kind::Batch,
            m if m == FRAGMENT_MAGIC => Kind::Fragment,
            m if m == SEALED_MAGIC => Kind::Sealed,
            m if m == pulicast_discovery::wire::MAGIC => Kind::Discovery,
            _ => Kind::Unknown,
        }
    }

    /// Whether a datagram of this kind names a data channel after its magic
    /// (a length byte and the name), as packets, batches and fragments do.
    pub fn names_a_channel(self) -> bool {
        matches!(self, Kind::Packet | Kind::Batch | Kind::Fragment)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_magic_has_one_kind() {
        let cases: [(&[u8], Kind); 8] = [
            (b"PULI\x01c", Kind::Packet),
            (b"PBAT", Kind::Batch),
            (b"PFRGxyz", Kind::Fragment),
            (b"PSEC", Kind::Sealed),
            (b"PDSC\x01", Kind::Discovery),
            (b"PUL", Kind::Unknown),
            (b"", Kind::Unknown),
            (b"XXXX", Kind::Unknown),
        ];
        for (bytes, kind) in cases {
            assert_eq!(Kind::of(bytes), kind, "{bytes:?}");
        }
    }
}

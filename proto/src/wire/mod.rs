//! Bytes on the wire: Pulicast 2.x packets, ZCM messages and native messages.
//!
//! Everything here is pure: functions from bytes to typed values and back,
//! golden-tested against the reference implementation's vectors. Decoders never
//! trust a length field further than the bytes at hand and never panic.

pub mod batch;
mod datagram;
pub mod fragment;
mod kind;
mod native;
mod packet;
pub mod sealed;
pub mod service;
pub mod setting;
pub mod zcm;
pub mod zcm_types;

pub use datagram::Datagram;
pub use kind::{Kind, BATCH_MAGIC, FRAGMENT_MAGIC, SEALED_MAGIC};
pub use native::{
    decode_native, encode_native, fingerprint_of, is_raw_bytes, readable_name, type_info_of,
    EncodeError,
};
pub use packet::{Packet, HEADER_OVERHEAD, MAGIC, MAX_DATAGRAM};

use std::fmt;

/// A channel that a node announces as published, without sending on it,
/// while it relays other sites' members (a bridge, `Discovery::relay`):
/// a node joining waits for their list before it counts its view of the
/// fleet as settled (`Discovery::settle`).
pub const RELAYS_CHANNEL: &str = ".pulicast/relays";

/// The channel name whose group carries discovery datagrams (and under
/// which they are sealed).
pub const DISCOVERY_CHANNEL: &str = "__pulicast_discovery";

/// An 8-byte message type tag at the start of ZCM and native payloads.
///
/// Printed as 16 hex digits, the way the reference implementation shows it.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Fingerprint(pub [u8; 8]);

impl Fingerprint {
    /// Reads the fingerprint at the start of a payload.
    pub fn of_payload(payload: &[u8]) -> Option<Fingerprint> {
        payload.first_chunk::<8>().copied().map(Fingerprint)
    }
}

impl fmt::Display for Fingerprint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.iter().try_for_each(|b| write!(f, "{b:02x}"))
    }
}

impl fmt::Debug for Fingerprint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Fingerprint({self})")
    }
}

/// Splits `magic`, the name length and the channel name off the front of a
/// datagram: the start all our datagram formats share. Returns the name and
/// what follows it.
pub(crate) fn split_name<'a>(
    datagram: &'a [u8],
    magic: &[u8; 4],
) -> Result<(&'a str, &'a [u8]), DecodeError> {
    let too_short = || DecodeError::TooShort {
        len: datagram.len(),
    };
    let (found, rest) = datagram.split_first_chunk::<4>().ok_or_else(too_short)?;
    if found != magic {
        return Err(DecodeError::BadMagic);
    }
    let (&len, rest) = rest.split_first().ok_or_else(too_short)?;
    let (name, rest) = rest
        .split_at_checked(usize::from(len))
        .ok_or(DecodeError::NamePastEnd)?;
    if !name.is_ascii() {
        return Err(DecodeError::NonAsciiName);
    }
    // ASCII was checked just above, so this cannot fail.
    let name = std::str::from_utf8(name).map_err(|_| DecodeError::NonAsciiName)?;
    Ok((name, rest))
}

/// Why bytes could not be decoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeError {
    /// Shorter than the smallest valid packet.
    #[error("datagram too short ({len} bytes)")]
    TooShort {
        /// Datagram length.
        len: usize,
    },
    /// Does not start with `PULI`.
    #[error("wrong magic")]
    BadMagic,
    /// The name length points past the end of the datagram.
    #[error("channel name runs past the end of the datagram")]
    NamePastEnd,
    /// The channel name is not ASCII.
    #[error("channel name is not ASCII")]
    NonAsciiName,
    /// A payload ended before a field it announces.
    #[error("payload truncated: needed {needed} more bytes at offset {offset}")]
    Truncated {
        /// Where the missing field starts.
        offset: usize,
        /// How many bytes were missing.
        needed: usize,
    },
    /// The payload carries another type than the subscriber expects.
    #[error("wrong message type: expected {expected} ({expected_name}), got {found}")]
    WrongType {
        /// Fingerprint of the expected type.
        expected: Fingerprint,
        /// Name of the expected type.
        expected_name: &'static str,
        /// Fingerprint found in the payload.
        found: Fingerprint,
    },
    /// Bytes left over after a closed message.
    #[error("{count} unexpected trailing bytes")]
    TrailingBytes {
        /// How many bytes were left.
        count: usize,
    },
    /// A field holds a value its type does not allow.
    #[error("malformed payload: {0}")]
    Malformed(String),
}

/// The counted reasons for which received data is dropped.
///
/// Each [`DecodeError`] maps to one reason; `pulicast::Stats` counts per reason.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum DropReason {
    /// See [`DecodeError::TooShort`].
    TooShort,
    /// See [`DecodeError::BadMagic`].
    BadMagic,
    /// See [`DecodeError::NamePastEnd`].
    NamePastEnd,
    /// See [`DecodeError::NonAsciiName`].
    NonAsciiName,
    /// See [`DecodeError::Truncated`].
    TruncatedPayload,
    /// See [`DecodeError::WrongType`].
    WrongType,
    /// See [`DecodeError::TrailingBytes`] and [`DecodeError::Malformed`].
    MalformedPayload,
    /// A subscription's queue was full and its queue policy dropped a message.
    QueueOverflow,
    /// A discovery datagram that did not decode.
    MalformedDiscovery,
    /// A fragmented message that did not complete in time (a fragment was
    /// lost) or did not fit the reassembly memory limits.
    IncompleteMessage,
    /// A datagram that is not sealed, on a channel this node has a key for
    /// (see `pulicast::NodeBuilder::key`): anyone on the link may have sent
    /// it.
    Unauthenticated,
    /// A sealed datagram on a channel this node subscribes but has no key
    /// for.
    NoKey,
    /// A sealed datagram whose tag did not match: tampered with, sealed
    /// with another key, or carrying another channel than it was sealed for.
    Forged,
    /// A sealed datagram received before: a replay.
    Replayed,
    /// A sealed datagram sent longer ago (by the sender's clock) than the
    /// node accepts: a late replay, or clocks that disagree.
    Stale,
    /// A service frame for a call this node never made (another session's,
    /// or a counter it has not reached).
    UnknownCall,
    /// A service frame for a call of this node from an address other than
    /// the server the call went to.
    WrongSource,
    /// A list of relayed members (from a bridge) that did not come from a
    /// live member's own discovery address.
    UntrustedRelay,
    /// A discovery datagram that arrived while the discovery task was
    /// behind: its queue full, or the sender holding its share of the queue
    /// (one source may not crowd out the others).
    DiscoveryBacklog,
}

impl DropReason {
    /// Every reason, in the order `pulicast::Stats` stores them.
    pub const ALL: [DropReason; 19] = [
        DropReason::TooShort,
        DropReason::BadMagic,
        DropReason::NamePastEnd,
        DropReason::NonAsciiName,
        DropReason::TruncatedPayload,
        DropReason::WrongType,
        DropReason::MalformedPayload,
        DropReason::QueueOverflow,
        DropReason::MalformedDiscovery,
        DropReason::IncompleteMessage,
        DropReason::Unauthenticated,
        DropReason::NoKey,
        DropReason::Forged,
        DropReason::Replayed,
        DropReason::Stale,
        DropReason::UnknownCall,
        DropReason::WrongSource,
        DropReason::UntrustedRelay,
        DropReason::DiscoveryBacklog,
    ];

    /// A short snake_case label for logs and tools.
    pub fn label(self) -> &'static str {
        match self {
            DropReason::TooShort => "too_short",
            DropReason::BadMagic => "bad_magic",
            DropReason::NamePastEnd => "name_past_end",
            DropReason::NonAsciiName => "non_ascii_name",
            DropReason::TruncatedPayload => "truncated_payload",
            DropReason::WrongType => "wrong_type",
            DropReason::MalformedPayload => "malformed_payload",
            DropReason::QueueOverflow => "queue_overflow",
            DropReason::MalformedDiscovery => "malformed_discovery",
            DropReason::IncompleteMessage => "incomplete_message",
            DropReason::Unauthenticated => "unauthenticated",
            DropReason::NoKey => "no_key",
            DropReason::Forged => "forged",
            DropReason::Replayed => "replayed",
            DropReason::Stale => "stale",
            DropReason::UnknownCall => "unknown_call",
            DropReason::WrongSource => "wrong_source",
            DropReason::UntrustedRelay => "untrusted_relay",
            DropReason::DiscoveryBacklog => "discovery_backlog",
        }
    }

    /// The reason's position in [`DropReason::ALL`], for a table of
    /// counters indexed by reason.
    pub fn index(self) -> usize {
        self as usize
    }
}

impl DecodeError {
    /// The counter this error is tallied under.
    pub fn reason(&self) -> DropReason {
        match self {
            DecodeError::TooShort { .. } => DropReason::TooShort,
            DecodeError::BadMagic => DropReason::BadMagic,
            DecodeError::NamePastEnd => DropReason::NamePastEnd,
            DecodeError::NonAsciiName => DropReason::NonAsciiName,
            DecodeError::Truncated { .. } => DropReason::TruncatedPayload,
            DecodeError::WrongType { .. } => DropReason::WrongType,
            DecodeError::TrailingBytes { .. } | DecodeError::Malformed(_) => {
                DropReason::MalformedPayload
            }
        }
    }
}

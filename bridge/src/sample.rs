//! What a bridged message looks like on Zenoh, and the checks a sample
//! from the Zenoh side passes before it is published here.
//!
//! A channel's message is one Zenoh sample on the channel's key (see
//! [`crate::keys`]), whatever its size (a message fragmented on the local
//! link crosses whole):
//!
//! - **payload**: the message's payload exactly as pulicast carries it; a
//!   typed message starts with its type's 8-byte fingerprint.
//! - **attachment** (optional, [`Origin`], 21 bytes): version 1, the
//!   exporting bridge's session key (i64, big-endian), the publishing
//!   member's key (i64 BE, 0 if unknown), and its sequence number on the
//!   channel (u32 BE). A plain Zenoh application may leave it out.

use pulicast::MAX_MESSAGE;

/// Where a bridged message comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Origin {
    /// The bridge that put it on Zenoh.
    pub bridge: i64,
    /// The member that published it on its site (0: unknown).
    pub publisher: i64,
    /// Its sequence number there.
    pub seq: u32,
}

/// The attachment's length.
pub const ORIGIN_LEN: usize = 21;
const ORIGIN_VERSION: u8 = 1;

impl Origin {
    /// The attachment's bytes.
    pub fn encode(&self) -> [u8; ORIGIN_LEN] {
        let mut out = [0; ORIGIN_LEN];
        out[0] = ORIGIN_VERSION;
        out[1..9].copy_from_slice(&self.bridge.to_be_bytes());
        out[9..17].copy_from_slice(&self.publisher.to_be_bytes());
        out[17..21].copy_from_slice(&self.seq.to_be_bytes());
        out
    }

    /// Reads an attachment.
    pub fn decode(bytes: &[u8]) -> Result<Self, Refused> {
        let bytes: &[u8; ORIGIN_LEN] = bytes
            .try_into()
            .map_err(|_| Refused::BadAttachment("length"))?;
        if bytes[0] != ORIGIN_VERSION {
            return Err(Refused::BadAttachment("version"));
        }
        let i64_at = |at: usize| {
            let mut b = [0; 8];
            b.copy_from_slice(&bytes[at..at + 8]);
            i64::from_be_bytes(b)
        };
        let mut seq = [0; 4];
        seq.copy_from_slice(&bytes[17..21]);
        Ok(Self {
            bridge: i64_at(1),
            publisher: i64_at(9),
            seq: u32::from_be_bytes(seq),
        })
    }
}

/// Why a sample from Zenoh was not published here.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// Its key names no channel this site can have.
    BadChannel,
    /// Its attachment is not an [`Origin`].
    BadAttachment(&'static str),
    /// It was bridged out of this site: a loop.
    Loop,
    /// Larger than a pulicast message may be.
    TooLarge,
    /// Its type's fingerprint is none that this site's subscribers expect
    /// (or it is too short to carry one).
    UnknownFingerprint,
    /// Over the channel's rate limit.
    RateLimited,
    /// A message from the same publisher with the same sequence number (or
    /// an older one) came before: two sites bridged it out.
    Duplicate,
}

impl Refused {
    /// A label for counters and logs.
    pub fn label(self) -> &'static str {
        match self {
            Refused::BadChannel => "bad_channel",
            Refused::BadAttachment(_) => "bad_attachment",
            Refused::Loop => "loop",
            Refused::TooLarge => "too_large",
            Refused::UnknownFingerprint => "unknown_fingerprint",
            Refused::RateLimited => "rate_limited",
            Refused::Duplicate => "duplicate",
        }
    }

    /// Every reason, in [`Refused::index`] order.
    pub const LABELS: [&'static str; 7] = [
        "bad_channel",
        "bad_attachment",
        "loop",
        "too_large",
        "unknown_fingerprint",
        "rate_limited",
        "duplicate",
    ];

    /// The counter's index.
    pub fn index(self) -> usize {
        match self {
            Refused::BadChannel => 0,
            Refused::BadAttachment(_) => 1,
            Refused::Loop => 2,
            Refused::TooLarge => 3,
            Refused::UnknownFingerprint => 4,
            Refused::RateLimited => 5,
            Refused::Duplicate => 6,
        }
    }
}

/// Checks a sample for a channel imported here: `local_bridges` are the
/// bridges of this site (this one included), `fingerprints` the types this
/// site's subscribers of the channel announce (empty: any payload goes).
pub fn check(
    payload: &[u8],
    attachment: Option<&[u8]>,
    local_bridges: impl Fn(i64) -> bool,
    fingerprints: &[[u8; 8]],
) -> Result<Option<Origin>, Refused> {
    let origin = attachment.map(Origin::decode).transpose()?;
    if origin.is_some_and(|o| local_bridges(o.bridge)) {
        return Err(Refused::Loop);
    }
    if payload.len() > MAX_MESSAGE {
        return Err(Refused::TooLarge);
    }
    if !fingerprints.is_empty() {
        let found = payload.get(..8).ok_or(Refused::UnknownFingerprint)?;
        if !fingerprints.iter().any(|f| f[..] == *found) {
            return Err(Refused::UnknownFingerprint);
        }
    }
    Ok(origin)
}

/// Counts what a hop lost per publisher, from the sequence numbers the
/// samples carry (bounded: at most `MAX_ORIGINS` publishers are tracked).
#[derive(Debug, Default)]
pub struct Losses {
    last: std::collections::HashMap<i64, u32>,
    /// Messages missing between those received.
    pub lost: u64,
}

const MAX_ORIGINS: usize = 4096;

impl Losses {
    /// Notes a received message; returns how many before it went missing,
    /// or `None` if it is not newer than the last one of its publisher (a
    /// duplicate, or late).
    pub fn note(&mut self, origin: &Origin) -> Option<u32> {
        if origin.publisher == 0 {
            return Some(0);
        }
        if self.last.len() >= MAX_ORIGINS && !self.last.contains_key(&origin.publisher) {
            self.last.clear();
        }
        let gap = match self.last.get(&origin.publisher) {
            // Ahead by less than half the number space: newer. Anything
            // else is a late or repeated message, or a restart.
            Some(last) => {
                let ahead = origin.seq.wrapping_sub(*last);
                if ahead == 0 || ahead >= 1 << 31 {
                    return None;
                }
                ahead - 1
            }
            None => 0,
        };
        self.last.insert(origin.publisher, origin.seq);
        self.lost += u64::from(gap);
        Some(gap)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn origins_round_trip_and_bad_ones_are_refused() {
        let o = Origin {
            bridge: -5,
            publisher: 77,
            seq: u32::MAX,
        };
        assert_eq!(Origin::decode(&o.encode()), Ok(o));
        assert_eq!(
            Origin::decode(&o.encode()[..20]),
            Err(Refused::BadAttachment("length"))
        );
        let mut bad = o.encode();
        bad[0] = 2;
        assert_eq!(Origin::decode(&bad), Err(Refused::BadAttachment("version")));
    }

    #[test]
    fn loops_sizes_and_fingerprints_are_checked() {
        let here = |b: i64| b == 1;
        let from = |bridge| Origin {
            bridge,
            publisher: 9,
            seq: 1,
        };
        let typed = [[7u8; 8]];
        let payload = [[7u8; 8].as_slice(), b"body"].concat();
        assert!(check(&payload, Some(&from(2).encode()), here, &typed).is_ok());
        assert_eq!(
            check(&payload, Some(&from(1).encode()), here, &typed),
            Err(Refused::Loop)
        );
        assert_eq!(check(&payload, None, here, &[]), Ok(None));
        assert_eq!(
            check(b"short", None, here, &typed),
            Err(Refused::UnknownFingerprint)
        );
        assert_eq!(
            check(&[0; 16], None, here, &typed),
            Err(Refused::UnknownFingerprint)
        );
        assert_eq!(
            check(&vec![7; MAX_MESSAGE + 1], None, here, &[]),
            Err(Refused::TooLarge)
        );
        assert_eq!(
            check(&payload, Some(b"junk"), here, &[]),
            Err(Refused::BadAttachment("length"))
        );
    }

    #[test]
    fn losses_count_gaps_per_publisher_and_ignore_late_ones() {
        let mut losses = Losses::default();
        let at = |publisher, seq| Origin {
            bridge: 1,
            publisher,
            seq,
        };
        assert_eq!(losses.note(&at(5, 10)), Some(0));
        assert_eq!(losses.note(&at(5, 11)), Some(0));
        assert_eq!(losses.note(&at(5, 15)), Some(3));
        assert_eq!(losses.note(&at(6, 100)), Some(0));
        assert_eq!(losses.note(&at(5, 12)), None, "late");
        assert_eq!(losses.note(&at(5, 15)), None, "a duplicate");
        assert_eq!(losses.note(&at(5, 0)), None);
        assert_eq!(losses.lost, 3);
        // Wrapping past u32::MAX is in order.
        assert_eq!(losses.note(&at(7, u32::MAX)), Some(0));
        assert_eq!(losses.note(&at(7, 1)), Some(1));
        // Samples without a publisher are not tracked.
        assert_eq!(losses.note(&at(0, 1)), Some(0));
        assert_eq!(losses.note(&at(0, 1)), Some(0));
    }
}

//! Authenticated, optionally encrypted datagrams: the sans-IO core of
//! authenticated channels (opt-in per namespace, with a pre-shared key).
//!
//! A sealed datagram wraps a whole ordinary datagram (a packet or a batch)
//! under its own magic, so Pulicast 2.x nodes, and our nodes without the
//! key, drop it:
//!
//! ```text
//! +--------+-------+------+-----------+-------------------------+-------------+--------------+--------------+----------------+---------+
//! | "PSEC" | n: u8 | name | flags: u8 | origin: ip [4], port u16 | stream: u64 | counter: u64 | sent_ms: u64 | inner datagram | tag: 16 |
//! +--------+-------+------+-----------+-------------------------+-------------+--------------+--------------+----------------+---------+
//!  \__________________________ authenticated (associated data) ________________________________________/ \ encrypted if   /
//!                                                                                                           \ flags & 1     /
//! ```
//!
//! - The key of a channel is derived from its namespace's pre-shared key
//!   with HKDF-SHA256 over the channel name, so one namespace key serves
//!   many channels without two of them ever sharing a nonce.
//! - The AEAD is XChaCha20-Poly1305; its 24-byte nonce is the sealer's
//!   random 64-bit stream id, its 64-bit counter, and zeros. Every
//!   [`Sealer`] draws a new stream id, so no two sealers ever share a
//!   nonce, even for the same channel in the same process. Without
//!   encryption the inner datagram is authenticated as associated data and
//!   travels in the clear.
//! - The inner datagram must be a packet, batch or fragment naming the
//!   channel it was sealed for (or, sealed for
//!   [`crate::wire::DISCOVERY_CHANNEL`], a discovery datagram), so a key for one
//!   namespace can't vouch for a channel of another, and sealed datagrams
//!   don't nest.
//! - A namespace may have several keys during a key change: the first one
//!   seals, all of them open.
//! - `origin` is the address the sender sends from, as far as it knows it
//!   (zeros: unknown). Receivers refuse a datagram from another address, so
//!   a recorded datagram relayed from elsewhere does not pass for its
//!   sender.
//! - Replays are refused by a sliding window per (channel, stream) over the
//!   counter (the last 64 counters, as IPsec does), and, for streams the
//!   receiver has forgotten or never saw, by the sender's clock: `sent_ms`
//!   must be within the configured age.
//!
//! ```
//! use std::time::Duration;
//! use pulicast_proto::secure::{Key, Opener, Sealer, Opened};
//!
//! let key = Key::from_hex(&"11".repeat(32)).unwrap();
//! let mut sealer = Sealer::new(&key, "rover1/cmd", true);
//! let inner = b"PULI\x0arover1/cmd\x00\x00\x00\x00hello";
//! let datagram = sealer.seal(inner, 1_700_000_000_000).to_vec();
//!
//! let mut opener = Opener::new(Some(Duration::from_secs(30)));
//! opener.add_key("rover1", &key).unwrap();
//! let from = "10.0.0.7:8765".parse().unwrap();
//! let opened: Opened = opener.open(&datagram, from, 1_700_000_000_500).unwrap();
//! assert_eq!((&opened.inner[..], opened.stream), (&inner[..], sealer.stream()));
//! // The same datagram again is a replay.
//! assert!(opener.open(&datagram, from, 1_700_000_000_600).is_err());
//! ```

use chacha20poly1305::XNonce;

mod keys;
mod open;
mod seal;
mod window;

pub use keys::{parse_key, parse_keys, Key, KeyArg, KeyError};
pub use open::{OpenError, Opened, OpenedInPlace, Opener, MAX_KEYS_PER_NAMESPACE};
pub use seal::Sealer;
pub use window::ChannelWindows;

/// The four bytes every sealed datagram starts with.
pub const MAGIC: [u8; 4] = crate::wire::SEALED_MAGIC;

/// Header bytes besides the channel name.
pub const HEADER_OVERHEAD: usize = 4 + 1 + 1 + 6 + 8 + 8 + 8;

/// Bytes of the authentication tag at the end.
pub const TAG_LEN: usize = 16;

/// Flag bit: the inner datagram is encrypted.
const ENCRYPTED: u8 = 1;

fn nonce(stream: u64, counter: u64) -> XNonce {
    let mut n = [0u8; 24];
    n[..8].copy_from_slice(&stream.to_be_bytes());
    n[8..16].copy_from_slice(&counter.to_be_bytes());
    n.into()
}

#[cfg(test)]
mod tests {
    //! Sealing and opening together: each of these seals datagrams to
    //! open them, so they test the two halves as a pair.
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
    use std::time::Duration;

    const NOW: u64 = 1_700_000_000_000;
    const FROM: SocketAddr = SocketAddr::V4(SocketAddrV4::new(Ipv4Addr::new(10, 0, 0, 1), 4000));

    fn key(b: u8) -> Key {
        Key::from_bytes([b; 32])
    }

    /// A packet on `channel`: what a node seals.
    fn packet(channel: &str, payload: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        crate::wire::Packet {
            channel,
            seq: 0,
            payload,
        }
        .encode(&mut out);
        out
    }

    fn opener() -> Opener {
        let mut o = Opener::new(Some(Duration::from_secs(30)));
        o.add_key("rover1", &key(1)).unwrap();
        o
    }

    #[test]
    fn both_modes_open_and_only_encryption_hides_the_inner_datagram() {
        for encrypt in [false, true] {
            let mut s = Sealer::with_stream(&key(1), "rover1/cmd", 7, encrypt);
            let inner = packet("rover1/cmd", b"secret payload");
            let sealed = s.seal(&inner, NOW).to_vec();
            let visible = sealed.windows(6).any(|w| w == b"secret");
            assert_eq!(visible, !encrypt);
            assert_eq!(sealed.len(), inner.len() + s.overhead());
            let opened = opener().open(&sealed, FROM, NOW).unwrap();
            assert_eq!(opened.inner, inner);
            assert_eq!((&*opened.channel, opened.stream), ("rover1/cmd", 7));
        }
    }

    /// A channel's windows moved to another opener (its group moved to
    /// another receive socket) refuse there what they refused here, and
    /// merge with what that opener saw meanwhile.
    #[test]
    fn windows_handed_to_another_opener_still_refuse_replays() {
        let mut s = Sealer::with_stream(&key(1), "rover1/cmd", 7, false);
        let sealed: Vec<Vec<u8>> = (0..100)
            .map(|i| s.seal(&packet("rover1/cmd", &[i]), NOW).to_vec())
            .collect();
        let mut first = opener();
        for d in &sealed[..50] {
            first.open(d, FROM, NOW).unwrap();
        }
        // A fresh opener would take a recorded one it never saw.
        assert!(opener().open(&sealed[40], FROM, NOW).is_ok());
        let mut second = opener();
        // The second saw some of the stream on its own meanwhile.
        second.open(&sealed[60], FROM, NOW).unwrap();
        let windows = first.take_windows("rover1/cmd");
        assert!(!windows.is_empty());
        assert!(first.take_windows("rover1/cmd").is_empty());
        second.put_windows("rover1/cmd", windows);
        for replayed in [40, 49, 60, 10] {
            assert_eq!(
                second.open(&sealed[replayed], FROM, NOW),
                Err(OpenError::Replayed),
                "counter {replayed}"
            );
        }
        // Numbers between what each saw: the first marked none of 50..60
        // but the second, starting at 60, took everything before it as seen.
        assert_eq!(
            second.open(&sealed[55], FROM, NOW),
            Err(OpenError::Replayed)
        );
        assert!(second.open(&sealed[61], FROM, NOW).is_ok());
    }

    #[test]
    fn tampering_anywhere_is_detected() {
        for encrypt in [false, true] {
            let sealed = Sealer::with_stream(&key(1), "rover1/cmd", 7, encrypt)
                .seal(&packet("rover1/cmd", b"payload"), NOW)
                .to_vec();
            for i in 0..sealed.len() {
                let mut bad = sealed.clone();
                bad[i] ^= 0x01;
                assert!(
                    opener().open(&bad, FROM, NOW).is_err(),
                    "byte {i} flipped, encrypt {encrypt}"
                );
            }
            for cut in 0..sealed.len() {
                assert!(opener().open(&sealed[..cut], FROM, NOW).is_err());
            }
        }
    }

    #[test]
    fn other_keys_other_channels_and_strangers_are_refused() {
        let mut o = opener();
        let wrong_key = Sealer::with_stream(&key(2), "rover1/cmd", 1, false)
            .seal(&packet("rover1/cmd", b"x"), NOW)
            .to_vec();
        assert_eq!(o.open(&wrong_key, FROM, NOW), Err(OpenError::Forged));
        let no_key = Sealer::with_stream(&key(1), "rover2/cmd", 1, false)
            .seal(&packet("rover2/cmd", b"x"), NOW)
            .to_vec();
        assert_eq!(o.open(&no_key, FROM, NOW), Err(OpenError::UnknownKey));
        // A sealed datagram moved to another channel name fails too: the
        // channel key differs.
        let mut moved = Sealer::with_stream(&key(1), "rover1/aaa", 1, false)
            .seal(&packet("rover1/aaa", b"x"), NOW)
            .to_vec();
        moved[5..15].copy_from_slice(b"rover1/bbb");
        assert_eq!(o.open(&moved, FROM, NOW), Err(OpenError::Forged));
        assert!(format!("{:?}", key(9)).contains("redacted"));
        assert!(!format!("{:?}", key(9)).contains("09"));
    }

    #[test]
    fn replays_and_stale_datagrams_are_refused() {
        let mut o = opener();
        let mut s = Sealer::with_stream(&key(1), "rover1/cmd", 3, false);
        let m = packet("rover1/cmd", b"m");
        let sealed: Vec<Vec<u8>> = (0..100).map(|_| s.seal(&m, NOW).to_vec()).collect();
        // Out of order within the window is fine, once.
        for i in [5usize, 99, 60, 98, 61] {
            assert!(o.open(&sealed[i], FROM, NOW).is_ok(), "{i}");
        }
        // What comes before the first counter heard is refused: a node
        // that joins late can't be fed the stream's recorded past.
        for i in [0usize, 3, 4] {
            assert_eq!(
                o.open(&sealed[i], FROM, NOW),
                Err(OpenError::Replayed),
                "{i}"
            );
        }
        for i in [5usize, 99, 60] {
            assert_eq!(
                o.open(&sealed[i], FROM, NOW),
                Err(OpenError::Replayed),
                "{i}"
            );
        }
        // Too far behind the newest (99) to tell: refused.
        assert_eq!(o.open(&sealed[10], FROM, NOW), Err(OpenError::Replayed));
        // A used counter is refused before the tag is looked at: even a
        // tampered copy counts as a replay, and changes nothing.
        let mut tampered = sealed[98].clone();
        let last = tampered.len() - 1;
        tampered[last] ^= 1;
        assert_eq!(o.open(&tampered, FROM, NOW), Err(OpenError::Replayed));
        // A tampered datagram with a new counter still fails its tag, and
        // the counter stays free for the genuine one.
        let mut tampered = sealed[40].clone();
        tampered[last] ^= 1;
        assert_eq!(o.open(&tampered, FROM, NOW), Err(OpenError::Forged));
        assert!(o.open(&sealed[40], FROM, NOW).is_ok());
        // The same datagram from another address than the sealer's origin.
        let origin = SocketAddrV4::new(Ipv4Addr::new(10, 0, 0, 1), 4000);
        let mut bound = Sealer::with_stream(&key(1), "rover1/cmd", 9, true).with_origin(origin);
        let first = bound.seal(&m, NOW).to_vec();
        let relayed = SocketAddr::from(([10, 0, 0, 66], 4000));
        assert!(matches!(
            o.open(&first, relayed, NOW),
            Err(OpenError::WrongSource { .. })
        ));
        let other_port = SocketAddr::from(([10, 0, 0, 1], 4001));
        assert!(o.open(&first, other_port, NOW).is_err());
        assert!(o.open(&first, FROM, NOW).is_ok());
        // An unspecified IP checks the port only.
        let port_only = SocketAddrV4::new(Ipv4Addr::UNSPECIFIED, 4000);
        let mut s2 = Sealer::with_stream(&key(1), "rover1/cmd", 10, false).with_origin(port_only);
        assert!(o.open(s2.seal(&m, NOW), relayed, NOW).is_ok());
        assert!(o.open(s2.seal(&m, NOW), other_port, NOW).is_err());
        // A forgotten session replayed much later is stale.
        let mut fresh = opener();
        let late = NOW + 31_000;
        assert!(matches!(
            fresh.open(&sealed[1], FROM, late),
            Err(OpenError::Stale { .. })
        ));
        // A new session of the same sender starts a new window.
        let mut restarted = Sealer::with_stream(&key(1), "rover1/cmd", 4, false);
        assert!(o.open(restarted.seal(&m, NOW), FROM, NOW).is_ok());
        // A sealer made anew draws a new stream: no nonce is ever reused.
        assert_ne!(
            Sealer::new(&key(1), "rover1/cmd", false).stream(),
            Sealer::new(&key(1), "rover1/cmd", false).stream()
        );
    }

    #[test]
    fn a_key_can_only_vouch_for_its_own_channels() {
        let mut o = Opener::new(None);
        o.add_key("/", &key(1)).unwrap();
        o.add_key("/rover1/", &key(2)).unwrap();
        // The root key seals a packet for rover1/cmd under another name.
        let smuggled = Sealer::with_stream(&key(1), "x", 1, false)
            .seal(&packet("rover1/cmd", b"stop"), NOW)
            .to_vec();
        assert_eq!(o.open(&smuggled, FROM, NOW), Err(OpenError::WrongChannel));
        // Namespaces are resolved: "/rover1/" is rover1's key.
        let fine = Sealer::with_stream(&key(2), "rover1/cmd", 1, false)
            .seal(&packet("rover1/cmd", b"go"), NOW)
            .to_vec();
        assert!(o.open(&fine, FROM, NOW).is_ok());
        assert!(o.add_key("bad\u{7}", &key(3)).is_err());
        // A send time far off either way, authentic or not, never panics.
        let mut far = Opener::new(Some(Duration::from_secs(1)));
        far.add_key("", &key(1)).unwrap();
        let sealed = Sealer::with_stream(&key(1), "x", 1, false)
            .seal(&packet("x", b""), u64::MAX)
            .to_vec();
        assert!(matches!(
            far.open(&sealed, FROM, 0),
            Err(OpenError::Stale { .. })
        ));
    }

    #[test]
    fn a_namespace_opens_with_every_key_it_has_and_seals_with_its_first() {
        let mut o = Opener::new(None);
        o.add_key("rover1", &key(1)).unwrap();
        o.add_key("rover1", &key(2)).unwrap();
        o.add_key("rover1", &key(2)).unwrap();
        assert_eq!(o.key_for("rover1/cmd").map(|k| k.0[0]), Some(1));
        for (k, stream) in [(1, 1), (2, 2)] {
            let sealed = Sealer::with_stream(&key(k), "rover1/cmd", stream, true)
                .seal(&packet("rover1/cmd", b"x"), NOW)
                .to_vec();
            assert!(o.open(&sealed, FROM, NOW).is_ok(), "key {k}");
        }
        let third = Sealer::with_stream(&key(3), "rover1/cmd", 3, true)
            .seal(&packet("rover1/cmd", b"x"), NOW)
            .to_vec();
        assert_eq!(o.open(&third, FROM, NOW), Err(OpenError::Forged));
        o.add_key("rover1", &key(3)).unwrap();
        o.add_key("rover1", &key(4)).unwrap();
        assert!(o.add_key("rover1", &key(5)).is_err());
        assert!(o.covers("rover1/x") && !o.covers("rover2/x"));
    }

    #[test]
    fn only_datagrams_that_may_be_sealed_open() {
        let mut o = Opener::new(None);
        o.add_key("", &key(1)).unwrap();
        // A sealed datagram inside another.
        let inner = Sealer::with_stream(&key(1), "a", 1, false)
            .seal(&packet("a", b"x"), NOW)
            .to_vec();
        let nested = Sealer::with_stream(&key(1), "a", 2, false)
            .seal(&inner, NOW)
            .to_vec();
        assert_eq!(o.open(&nested, FROM, NOW), Err(OpenError::BadInner));
        // Discovery datagrams only under the discovery channel's name.
        let mut gossip = pulicast_discovery::wire::MAGIC.to_vec();
        gossip.extend_from_slice(b"\x01anything");
        let d = crate::wire::DISCOVERY_CHANNEL;
        let sealed = Sealer::with_stream(&key(1), d, 3, true)
            .seal(&gossip, NOW)
            .to_vec();
        assert_eq!(o.open(&sealed, FROM, NOW).unwrap().inner, gossip);
        let sealed = Sealer::with_stream(&key(1), "a", 4, true)
            .seal(&gossip, NOW)
            .to_vec();
        assert_eq!(o.open(&sealed, FROM, NOW), Err(OpenError::BadInner));
        let sealed = Sealer::with_stream(&key(1), d, 5, true)
            .seal(&packet(d, b""), NOW)
            .to_vec();
        assert_eq!(o.open(&sealed, FROM, NOW), Err(OpenError::BadInner));
        // Parts are sealed as if joined.
        let p = packet("a", b"payload");
        let mut s = Sealer::with_stream(&key(1), "a", 6, false);
        let joined = s.seal(&p, NOW).to_vec();
        let mut s = Sealer::with_stream(&key(1), "a", 6, false);
        assert_eq!(s.seal_parts(&[&p[..3], &p[3..]], NOW), &joined[..]);
        assert_eq!(joined.len(), p.len() + Sealer::overhead_for("a"));
    }
}

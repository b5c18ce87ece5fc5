//! Authenticated, optionally encrypted datagrams: the sans-IO core of
//! authenticated channels (opt-in per namespace, with a pre-shared key).
//!
//! A sealed datagram wraps a whole ordinary datagram (a packet or a batch)
//! under its own magic, so Pulicast 2.x nodes, and our nodes without the
//! key, drop it:
//!
//! ```text
//! +--------+-------+------+-----------+--------------+--------------+-----------------+-------------------+----------+
//! | "PSEC" | n: u8 | name | flags: u8 | session: u64 | counter: u64 | sent_ms: u64    | inner datagram    | tag: 16  |
//! +--------+-------+------+-----------+--------------+--------------+-----------------+-------------------+----------+
//!  \____________________ authenticated (associated data) _____________________/ \ encrypted if flags&1 /
//! ```
//!
//! - The key of a channel is derived from its namespace's pre-shared key
//!   with HKDF-SHA256 over the channel name, so one namespace key serves
//!   many channels without two of them ever sharing a nonce.
//! - The AEAD is XChaCha20-Poly1305; its 24-byte nonce is the sender's
//!   random 64-bit session, its 64-bit counter (per channel, never reused in
//!   a session), and zeros. Without encryption the inner datagram is
//!   authenticated as associated data and travels in the clear.
//! - Replays are refused by a sliding window per (channel, session) over the
//!   counter (the last 64 counters, as IPsec does), and, for sessions the
//!   receiver has forgotten or never saw, by the sender's clock: `sent_ms`
//!   must be within the configured age.
//!
//! ```
//! use std::time::Duration;
//! use pulicast::proto::secure::{Key, Opener, Sealer, Opened};
//!
//! let key = Key::from_hex(&"11".repeat(32)).unwrap();
//! let mut sealer = Sealer::new(&key, "rover1/cmd", 0xfeed, true);
//! let inner = b"PULI\x0arover1/cmd\x00\x00\x00\x00hello";
//! let datagram = sealer.seal(inner, 1_700_000_000_000);
//!
//! let mut opener = Opener::new(Some(Duration::from_secs(30)));
//! opener.add_key("rover1", &key);
//! let opened: Opened = opener.open(&datagram, 1_700_000_000_500).unwrap();
//! assert_eq!((&opened.inner[..], opened.session), (&inner[..], 0xfeed));
//! // The same datagram again is a replay.
//! assert!(opener.open(&datagram, 1_700_000_000_600).is_err());
//! ```

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use chacha20poly1305::aead::{AeadInPlace, KeyInit};
use chacha20poly1305::{Tag, XChaCha20Poly1305, XNonce};

/// The four bytes every sealed datagram starts with.
pub const MAGIC: [u8; 4] = *b"PSEC";

/// Header bytes besides the channel name.
pub const HEADER_OVERHEAD: usize = 4 + 1 + 1 + 8 + 8 + 8;

/// Bytes of the authentication tag at the end.
pub const TAG_LEN: usize = 16;

/// Flag bit: the inner datagram is encrypted.
const ENCRYPTED: u8 = 1;

/// A pre-shared key of 32 bytes. Its `Debug` shows no key material, and
/// the bytes are wiped when it is dropped.
#[derive(Clone)]
pub struct Key([u8; 32]);

impl std::fmt::Debug for Key {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Key(<redacted>)")
    }
}

impl Drop for Key {
    fn drop(&mut self) {
        // Volatile-free wipe: good enough against casual reuse of the
        // memory; the zeroize crate is what the AEAD itself uses.
        zeroize::Zeroize::zeroize(&mut self.0);
    }
}

/// Why a key could not be read.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum KeyError {
    /// Not 64 hex digits.
    #[error("a key is 64 hex digits (32 bytes)")]
    Format,
}

impl Key {
    /// A key from its 32 bytes.
    pub fn from_bytes(bytes: [u8; 32]) -> Self {
        Self(bytes)
    }

    /// A key from 64 hex digits, as in `PULICAST_KEYS` and `--key`.
    pub fn from_hex(hex: &str) -> Result<Self, KeyError> {
        let hex = hex.trim();
        if hex.len() != 64 || !hex.is_ascii() {
            return Err(KeyError::Format);
        }
        let mut bytes = [0u8; 32];
        for (i, byte) in bytes.iter_mut().enumerate() {
            *byte = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).map_err(|_| KeyError::Format)?;
        }
        Ok(Self(bytes))
    }

    /// The key of one channel: HKDF-SHA256 of this key over its name.
    fn for_channel(&self, channel: &str) -> XChaCha20Poly1305 {
        let hkdf = hkdf::Hkdf::<sha2::Sha256>::new(Some(b"pulicast channel key v1"), &self.0);
        let mut okm = [0u8; 32];
        // 32 bytes is far below HKDF-SHA256's limit of 8160: cannot fail.
        let _ = hkdf.expand(channel.as_bytes(), &mut okm);
        let cipher = XChaCha20Poly1305::new(&okm.into());
        zeroize::Zeroize::zeroize(&mut okm);
        cipher
    }
}

fn nonce(session: u64, counter: u64) -> XNonce {
    let mut n = [0u8; 24];
    n[..8].copy_from_slice(&session.to_be_bytes());
    n[8..16].copy_from_slice(&counter.to_be_bytes());
    n.into()
}

/// Seals the datagrams of one channel from one session.
pub struct Sealer {
    cipher: XChaCha20Poly1305,
    prefix: Vec<u8>,
    session: u64,
    counter: u64,
    encrypt: bool,
    out: Vec<u8>,
}

impl std::fmt::Debug for Sealer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sealer")
            .field("session", &self.session)
            .field("counter", &self.counter)
            .field("encrypt", &self.encrypt)
            .finish_non_exhaustive()
    }
}

impl Sealer {
    /// A sealer for `channel` (whose namespace's key is `key`) in the
    /// sender's `session`; `encrypt` hides the inner datagram too.
    pub fn new(key: &Key, channel: &str, session: u64, encrypt: bool) -> Self {
        let mut prefix = Vec::with_capacity(6 + channel.len());
        prefix.extend_from_slice(&MAGIC);
        prefix.push(channel.len().min(255) as u8);
        prefix.extend_from_slice(&channel.as_bytes()[..channel.len().min(255)]);
        prefix.push(if encrypt { ENCRYPTED } else { 0 });
        Self {
            cipher: key.for_channel(channel),
            prefix,
            session,
            counter: 0,
            encrypt,
            out: Vec::new(),
        }
    }

    /// Bytes a sealed datagram adds to its inner datagram.
    pub fn overhead(&self) -> usize {
        self.prefix.len() + 24 + TAG_LEN
    }

    /// Seals `inner` (a whole ordinary datagram) sent at `now_ms` (Unix
    /// time in milliseconds); the sealed datagram stays in the sealer until
    /// the next call.
    pub fn seal(&mut self, inner: &[u8], now_ms: u64) -> &[u8] {
        let counter = self.counter;
        self.counter += 1;
        let out = &mut self.out;
        out.clear();
        out.extend_from_slice(&self.prefix);
        out.extend_from_slice(&self.session.to_be_bytes());
        out.extend_from_slice(&counter.to_be_bytes());
        out.extend_from_slice(&now_ms.to_be_bytes());
        let header = out.len();
        out.extend_from_slice(inner);
        let nonce = nonce(self.session, counter);
        let tag = if self.encrypt {
            let (aad, body) = out.split_at_mut(header);
            self.cipher.encrypt_in_place_detached(&nonce, aad, body)
        } else {
            self.cipher.encrypt_in_place_detached(&nonce, out, &mut [])
        };
        // The AEAD refuses only messages beyond 256 GiB; ours end at 64 MiB.
        let tag: Tag = tag.unwrap_or_default();
        out.extend_from_slice(&tag);
        out
    }
}

/// Why a sealed datagram was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum OpenError {
    /// Not a sealed datagram, or cut short.
    #[error("malformed sealed datagram")]
    Malformed,
    /// No key for the channel's namespace.
    #[error("no key for this channel")]
    UnknownKey,
    /// The tag does not match: tampered, or sealed with another key.
    #[error("authentication failed")]
    Forged,
    /// Seen before, or older than the replay window.
    #[error("replayed")]
    Replayed,
    /// Sent longer ago (or further ahead) than the allowed age.
    #[error("stale: sent {age_ms} ms from now")]
    Stale {
        /// How far the sender's clock is from ours, in ms.
        age_ms: i64,
    },
}

/// An opened datagram.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Opened {
    /// The channel it was sealed for.
    pub channel: Arc<str>,
    /// The sender's session.
    pub session: u64,
    /// The inner datagram, decrypted if it was encrypted.
    pub inner: Vec<u8>,
}

/// Which counters of one (channel, session) have been seen.
#[derive(Debug, Clone, Copy, Default)]
struct Window {
    highest: u64,
    /// Bit i: counter `highest - i` seen.
    seen: u64,
    used: u64,
}

impl Window {
    /// Whether `counter` is new; marks it seen if so.
    fn accept(&mut self, counter: u64) -> bool {
        if self.seen == 0 || counter > self.highest {
            let shift = if self.seen == 0 {
                64
            } else {
                counter - self.highest
            };
            self.seen = if shift >= 64 { 0 } else { self.seen << shift };
            self.seen |= 1;
            self.highest = counter;
            return true;
        }
        let back = self.highest - counter;
        if back >= 64 || self.seen & (1 << back) != 0 {
            return false;
        }
        self.seen |= 1 << back;
        true
    }
}

/// Opens sealed datagrams: knows the keys of namespaces, caches channel
/// keys, and remembers a bounded number of (channel, session) windows.
pub struct Opener {
    keys: Vec<(String, Key)>,
    ciphers: HashMap<Arc<str>, Option<XChaCha20Poly1305>>,
    windows: HashMap<(Arc<str>, u64), Window>,
    max_age: Option<Duration>,
    clock: u64,
}

impl std::fmt::Debug for Opener {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let namespaces: Vec<&str> = self.keys.iter().map(|(ns, _)| ns.as_str()).collect();
        f.debug_struct("Opener")
            .field("namespaces", &namespaces)
            .field("windows", &self.windows.len())
            .finish_non_exhaustive()
    }
}

/// Most (channel, session) windows remembered; the least recently used go.
const MAX_WINDOWS: usize = 4096;
/// Most channel keys cached.
const MAX_CIPHERS: usize = 4096;

impl Opener {
    /// An opener without keys. `max_age` bounds how far a sealed datagram's
    /// send time may be from the receiver's clock (`None`: not checked, for
    /// fleets without synchronized clocks; replays of sessions the receiver
    /// forgot are then possible).
    pub fn new(max_age: Option<Duration>) -> Self {
        Self {
            keys: Vec::new(),
            ciphers: HashMap::new(),
            windows: HashMap::new(),
            max_age,
            clock: 0,
        }
    }

    /// Adds the key of `namespace` (`""` for the root: every channel
    /// without a more specific key).
    pub fn add_key(&mut self, namespace: &str, key: &Key) {
        self.keys.retain(|(ns, _)| ns != namespace);
        self.keys.push((namespace.to_string(), key.clone()));
        self.ciphers.clear();
    }

    /// The key for `channel`: that of its most specific namespace.
    pub fn key_for(&self, channel: &str) -> Option<&Key> {
        key_for(&self.keys, channel)
    }

    /// Checks and opens a sealed datagram received at `now_ms`.
    pub fn open(&mut self, datagram: &[u8], now_ms: u64) -> Result<Opened, OpenError> {
        let rest = datagram.strip_prefix(&MAGIC).ok_or(OpenError::Malformed)?;
        let (&len, rest) = rest.split_first().ok_or(OpenError::Malformed)?;
        let (name, rest) = rest
            .split_at_checked(usize::from(len))
            .ok_or(OpenError::Malformed)?;
        let channel = std::str::from_utf8(name).map_err(|_| OpenError::Malformed)?;
        let (&flags, rest) = rest.split_first().ok_or(OpenError::Malformed)?;
        let (numbers, rest) = rest.split_first_chunk::<24>().ok_or(OpenError::Malformed)?;
        if rest.len() < TAG_LEN || flags & !ENCRYPTED != 0 {
            return Err(OpenError::Malformed);
        }
        let be64 = |i: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&numbers[i..i + 8]);
            u64::from_be_bytes(b)
        };
        let (session, counter, sent_ms) = (be64(0), be64(8), be64(16));
        let header = datagram.len() - rest.len();
        let (body, tag) = rest.split_at(rest.len() - TAG_LEN);
        let channel: Arc<str> = match self.ciphers.get_key_value(channel) {
            Some((name, _)) => Arc::clone(name),
            None => channel.into(),
        };
        let cipher = self.cipher(&channel).ok_or(OpenError::UnknownKey)?;
        let nonce = nonce(session, counter);
        let tag = Tag::from_slice(tag);
        let mut inner = body.to_vec();
        let verified = if flags & ENCRYPTED != 0 {
            cipher.decrypt_in_place_detached(&nonce, &datagram[..header], &mut inner, tag)
        } else {
            cipher.decrypt_in_place_detached(&nonce, &datagram[..header + body.len()], &mut [], tag)
        };
        verified.map_err(|_| OpenError::Forged)?;
        // Only what is authentic may touch the windows.
        if let Some(max_age) = self.max_age {
            let age_ms = now_ms as i64 - sent_ms as i64;
            if age_ms.unsigned_abs() > max_age.as_millis() as u64 {
                return Err(OpenError::Stale { age_ms });
            }
        }
        self.clock += 1;
        let clock = self.clock;
        if self.windows.len() >= MAX_WINDOWS
            && !self.windows.contains_key(&(Arc::clone(&channel), session))
        {
            self.forget_least_recent();
        }
        let window = self
            .windows
            .entry((Arc::clone(&channel), session))
            .or_default();
        if !window.accept(counter) {
            return Err(OpenError::Replayed);
        }
        window.used = clock;
        Ok(Opened {
            channel,
            session,
            inner,
        })
    }

    fn cipher(&mut self, channel: &Arc<str>) -> Option<&XChaCha20Poly1305> {
        if !self.ciphers.contains_key(channel) {
            if self.ciphers.len() >= MAX_CIPHERS {
                self.ciphers.clear();
            }
            let cipher = key_for(&self.keys, channel).map(|k| k.for_channel(channel));
            self.ciphers.insert(Arc::clone(channel), cipher);
        }
        self.ciphers.get(channel)?.as_ref()
    }

    fn forget_least_recent(&mut self) {
        if let Some(oldest) = self
            .windows
            .iter()
            .min_by_key(|(_, w)| w.used)
            .map(|(k, _)| k.clone())
        {
            self.windows.remove(&oldest);
        }
    }
}

/// The key of the most specific namespace containing `channel`.
fn key_for<'k>(keys: &'k [(String, Key)], channel: &str) -> Option<&'k Key> {
    keys.iter()
        .filter(|(ns, _)| {
            ns.is_empty()
                || channel == ns
                || (channel.starts_with(ns.as_str())
                    && channel.as_bytes().get(ns.len()) == Some(&b'/'))
        })
        .max_by_key(|(ns, _)| ns.len())
        .map(|(_, key)| key)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    const NOW: u64 = 1_700_000_000_000;

    fn key(b: u8) -> Key {
        Key::from_bytes([b; 32])
    }

    fn opener() -> Opener {
        let mut o = Opener::new(Some(Duration::from_secs(30)));
        o.add_key("rover1", &key(1));
        o
    }

    #[test]
    fn both_modes_open_and_only_encryption_hides_the_inner_datagram() {
        for encrypt in [false, true] {
            let mut s = Sealer::new(&key(1), "rover1/cmd", 7, encrypt);
            let sealed = s.seal(b"PULI secret payload", NOW).to_vec();
            let visible = sealed.windows(6).any(|w| w == b"secret");
            assert_eq!(visible, !encrypt);
            assert_eq!(sealed.len(), 19 + s.overhead());
            let opened = opener().open(&sealed, NOW).unwrap();
            assert_eq!(opened.inner, b"PULI secret payload");
            assert_eq!((&*opened.channel, opened.session), ("rover1/cmd", 7));
        }
    }

    #[test]
    fn tampering_anywhere_is_detected() {
        for encrypt in [false, true] {
            let sealed = Sealer::new(&key(1), "rover1/cmd", 7, encrypt)
                .seal(b"PULIpayload", NOW)
                .to_vec();
            for i in 0..sealed.len() {
                let mut bad = sealed.clone();
                bad[i] ^= 0x01;
                assert!(
                    opener().open(&bad, NOW).is_err(),
                    "byte {i} flipped, encrypt {encrypt}"
                );
            }
            for cut in 0..sealed.len() {
                assert!(opener().open(&sealed[..cut], NOW).is_err());
            }
        }
    }

    #[test]
    fn other_keys_other_channels_and_strangers_are_refused() {
        let mut o = opener();
        let wrong_key = Sealer::new(&key(2), "rover1/cmd", 1, false)
            .seal(b"x", NOW)
            .to_vec();
        assert_eq!(o.open(&wrong_key, NOW), Err(OpenError::Forged));
        let no_key = Sealer::new(&key(1), "rover2/cmd", 1, false)
            .seal(b"x", NOW)
            .to_vec();
        assert_eq!(o.open(&no_key, NOW), Err(OpenError::UnknownKey));
        // A sealed datagram moved to another channel name fails too: the
        // channel key differs.
        let mut moved = Sealer::new(&key(1), "rover1/aaa", 1, false)
            .seal(b"x", NOW)
            .to_vec();
        moved[5..15].copy_from_slice(b"rover1/bbb");
        assert_eq!(o.open(&moved, NOW), Err(OpenError::Forged));
        assert!(format!("{:?}", key(9)).contains("redacted"));
        assert!(!format!("{:?}", key(9)).contains("09"));
    }

    #[test]
    fn replays_and_stale_datagrams_are_refused() {
        let mut o = opener();
        let mut s = Sealer::new(&key(1), "rover1/cmd", 3, false);
        let sealed: Vec<Vec<u8>> = (0..100).map(|_| s.seal(b"m", NOW).to_vec()).collect();
        // Out of order within the window is fine, once.
        for i in [5usize, 3, 4, 0, 99, 60, 98] {
            assert!(o.open(&sealed[i], NOW).is_ok(), "{i}");
        }
        for i in [5usize, 99, 60] {
            assert_eq!(o.open(&sealed[i], NOW), Err(OpenError::Replayed), "{i}");
        }
        // Too far behind the newest (99) to tell: refused.
        assert_eq!(o.open(&sealed[10], NOW), Err(OpenError::Replayed));
        assert!(o.open(&sealed[40], NOW).is_ok());
        // A forgotten session replayed much later is stale.
        let mut fresh = opener();
        let late = NOW + 31_000;
        assert!(matches!(
            fresh.open(&sealed[1], late),
            Err(OpenError::Stale { .. })
        ));
        // A new session of the same sender starts a new window.
        let mut restarted = Sealer::new(&key(1), "rover1/cmd", 4, false);
        assert!(o.open(restarted.seal(b"m", NOW), NOW).is_ok());
    }

    #[test]
    fn the_most_specific_namespace_key_applies() {
        let keys = vec![
            (String::new(), key(1)),
            ("rover1".to_string(), key(2)),
            ("rover1/arm".to_string(), key(3)),
        ];
        let which = |c: &str| key_for(&keys, c).map(|k| k.0[0]);
        assert_eq!(which("rover1/arm/pose"), Some(3));
        assert_eq!(which("rover1/armor"), Some(2));
        assert_eq!(which("rover1"), Some(2));
        assert_eq!(which("rover2/x"), Some(1));
        assert_eq!(key_for(&keys[1..], "rover2/x").map(|k| k.0[0]), None);
    }

    #[test]
    fn keys_read_from_hex() {
        assert!(Key::from_hex(&"ab".repeat(32)).is_ok());
        assert_eq!(Key::from_hex("abc").err(), Some(KeyError::Format));
        assert_eq!(
            Key::from_hex(&"zz".repeat(32)).err(),
            Some(KeyError::Format)
        );
    }
}

//! Authenticated, optionally encrypted datagrams: the sans-IO core of
//! authenticated channels (opt-in per namespace, with a pre-shared key).
//!
//! A sealed datagram wraps a whole ordinary datagram (a packet or a batch)
//! under its own magic, so Pulicast 2.x nodes, and our nodes without the
//! key, drop it:
//!
//! ```text
//! +--------+-------+------+-----------+--------------+--------------+-----------------+-------------------+----------+
//! | "PSEC" | n: u8 | name | flags: u8 | stream: u64  | counter: u64 | sent_ms: u64    | inner datagram    | tag: 16  |
//! +--------+-------+------+-----------+--------------+--------------+-----------------+-------------------+----------+
//!  \____________________ authenticated (associated data) _____________________/ \ encrypted if flags&1 /
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
//! - The inner datagram must name the channel it was sealed for, so a key
//!   for one namespace can't vouch for a channel of another.
//! - Replays are refused by a sliding window per (channel, stream) over the
//!   counter (the last 64 counters, as IPsec does), and, for streams the
//!   receiver has forgotten or never saw, by the sender's clock: `sent_ms`
//!   must be within the configured age.
//!
//! ```
//! use std::time::Duration;
//! use pulicast::proto::secure::{Key, Opener, Sealer, Opened};
//!
//! let key = Key::from_hex(&"11".repeat(32)).unwrap();
//! let mut sealer = Sealer::new(&key, "rover1/cmd", true);
//! let inner = b"PULI\x0arover1/cmd\x00\x00\x00\x00hello";
//! let datagram = sealer.seal(inner, 1_700_000_000_000).to_vec();
//!
//! let mut opener = Opener::new(Some(Duration::from_secs(30)));
//! opener.add_key("rover1", &key).unwrap();
//! let opened: Opened = opener.open(&datagram, 1_700_000_000_500).unwrap();
//! assert_eq!((&opened.inner[..], opened.stream), (&inner[..], sealer.stream()));
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
        if hex.len() != 64 || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
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

fn nonce(stream: u64, counter: u64) -> XNonce {
    let mut n = [0u8; 24];
    n[..8].copy_from_slice(&stream.to_be_bytes());
    n[8..16].copy_from_slice(&counter.to_be_bytes());
    n.into()
}

/// Seals the datagrams of one channel, as one stream.
pub struct Sealer {
    cipher: XChaCha20Poly1305,
    prefix: Vec<u8>,
    stream: u64,
    counter: u64,
    encrypt: bool,
    out: Vec<u8>,
}

impl std::fmt::Debug for Sealer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Sealer")
            .field("stream", &self.stream)
            .field("counter", &self.counter)
            .field("encrypt", &self.encrypt)
            .finish_non_exhaustive()
    }
}

impl Sealer {
    /// A sealer for `channel` (whose namespace's key is `key`), with a new
    /// random stream id; `encrypt` hides the inner datagram too.
    pub fn new(key: &Key, channel: &str, encrypt: bool) -> Self {
        let random = uuid::Uuid::new_v4();
        let mut stream = [0u8; 8];
        stream.copy_from_slice(&random.as_bytes()[..8]);
        Self::with_stream(key, channel, u64::from_be_bytes(stream), encrypt)
    }

    /// This sealer's stream id.
    pub fn stream(&self) -> u64 {
        self.stream
    }

    fn with_stream(key: &Key, channel: &str, stream: u64, encrypt: bool) -> Self {
        let mut prefix = Vec::with_capacity(6 + channel.len());
        prefix.extend_from_slice(&MAGIC);
        prefix.push(channel.len().min(255) as u8);
        prefix.extend_from_slice(&channel.as_bytes()[..channel.len().min(255)]);
        prefix.push(if encrypt { ENCRYPTED } else { 0 });
        Self {
            cipher: key.for_channel(channel),
            prefix,
            stream,
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
        out.extend_from_slice(&self.stream.to_be_bytes());
        out.extend_from_slice(&counter.to_be_bytes());
        out.extend_from_slice(&now_ms.to_be_bytes());
        let header = out.len();
        out.extend_from_slice(inner);
        let nonce = nonce(self.stream, counter);
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
    /// Authentic, but the inner datagram is for another channel than the
    /// one it was sealed for.
    #[error("sealed for another channel than it carries")]
    WrongChannel,
    /// Seen before, or older than the replay window.
    #[error("replayed")]
    Replayed,
    /// Sent longer ago (or further ahead) than the allowed age.
    #[error("stale: sent {age_ms} ms from now")]
    Stale {
        /// How far the send time is behind our clock, in ms (negative: ahead).
        age_ms: i64,
    },
}

/// An opened datagram.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Opened {
    /// The channel it was sealed for.
    pub channel: Arc<str>,
    /// The sealer's stream id.
    pub stream: u64,
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
    /// Replay windows per (channel, stream).
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

    /// Adds the key of `namespace` (`""` or `/` for the root: every
    /// channel without a more specific key). The namespace is resolved
    /// like any other (`/rover1/` is `rover1`); a bad one is an error.
    pub fn add_key(&mut self, namespace: &str, key: &Key) -> crate::Result<()> {
        let namespace = crate::name::resolve_path(namespace, "")?;
        self.keys.retain(|(ns, _)| *ns != namespace);
        self.keys.push((namespace, key.clone()));
        self.ciphers.clear();
        Ok(())
    }

    /// The key for `channel`: that of its most specific namespace.
    pub fn key_for(&self, channel: &str) -> Option<&Key> {
        key_for(&self.keys, channel)
    }

    /// Checks and opens a sealed datagram received at `now_ms`.
    pub fn open(&mut self, datagram: &[u8], now_ms: u64) -> Result<Opened, OpenError> {
        let (channel, rest) =
            crate::wire::split_name(datagram, &MAGIC).map_err(|_| OpenError::Malformed)?;
        let name = channel.as_bytes();
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
        let (stream, counter, sent_ms) = (be64(0), be64(8), be64(16));
        let header = datagram.len() - rest.len();
        let (body, tag) = rest.split_at(rest.len() - TAG_LEN);
        let channel: Arc<str> = match self.ciphers.get_key_value(channel) {
            Some((name, _)) => Arc::clone(name),
            None => channel.into(),
        };
        let cipher = self.cipher(&channel).ok_or(OpenError::UnknownKey)?;
        let nonce = nonce(stream, counter);
        let tag = Tag::from_slice(tag);
        let mut inner = body.to_vec();
        let verified = if flags & ENCRYPTED != 0 {
            cipher.decrypt_in_place_detached(&nonce, &datagram[..header], &mut inner, tag)
        } else {
            cipher.decrypt_in_place_detached(&nonce, &datagram[..header + body.len()], &mut [], tag)
        };
        verified.map_err(|_| OpenError::Forged)?;
        // Every inner format (packet, batch, fragment) names its channel at
        // the same place: after a 4-byte magic, a length and the name.
        if inner.get(4).map(|&n| usize::from(n)) != Some(name.len())
            || inner.get(5..5 + name.len()) != Some(name)
        {
            return Err(OpenError::WrongChannel);
        }
        // Only what is authentic may touch the windows.
        if let Some(max_age) = self.max_age {
            let off = now_ms.abs_diff(sent_ms);
            if off > max_age.as_millis() as u64 {
                let age_ms = i64::try_from(off).unwrap_or(i64::MAX);
                return Err(OpenError::Stale {
                    age_ms: if now_ms >= sent_ms { age_ms } else { -age_ms },
                });
            }
        }
        self.clock += 1;
        let clock = self.clock;
        if self.windows.len() >= MAX_WINDOWS
            && !self.windows.contains_key(&(Arc::clone(&channel), stream))
        {
            self.forget_least_recent();
        }
        let window = self
            .windows
            .entry((Arc::clone(&channel), stream))
            .or_default();
        if !window.accept(counter) {
            return Err(OpenError::Replayed);
        }
        window.used = clock;
        Ok(Opened {
            channel,
            stream,
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
            let opened = opener().open(&sealed, NOW).unwrap();
            assert_eq!(opened.inner, inner);
            assert_eq!((&*opened.channel, opened.stream), ("rover1/cmd", 7));
        }
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
        let wrong_key = Sealer::with_stream(&key(2), "rover1/cmd", 1, false)
            .seal(&packet("rover1/cmd", b"x"), NOW)
            .to_vec();
        assert_eq!(o.open(&wrong_key, NOW), Err(OpenError::Forged));
        let no_key = Sealer::with_stream(&key(1), "rover2/cmd", 1, false)
            .seal(&packet("rover2/cmd", b"x"), NOW)
            .to_vec();
        assert_eq!(o.open(&no_key, NOW), Err(OpenError::UnknownKey));
        // A sealed datagram moved to another channel name fails too: the
        // channel key differs.
        let mut moved = Sealer::with_stream(&key(1), "rover1/aaa", 1, false)
            .seal(&packet("rover1/aaa", b"x"), NOW)
            .to_vec();
        moved[5..15].copy_from_slice(b"rover1/bbb");
        assert_eq!(o.open(&moved, NOW), Err(OpenError::Forged));
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
        let mut restarted = Sealer::with_stream(&key(1), "rover1/cmd", 4, false);
        assert!(o.open(restarted.seal(&m, NOW), NOW).is_ok());
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
        assert_eq!(o.open(&smuggled, NOW), Err(OpenError::WrongChannel));
        // Namespaces are resolved: "/rover1/" is rover1's key.
        let fine = Sealer::with_stream(&key(2), "rover1/cmd", 1, false)
            .seal(&packet("rover1/cmd", b"go"), NOW)
            .to_vec();
        assert!(o.open(&fine, NOW).is_ok());
        assert!(o.add_key("bad\u{7}", &key(3)).is_err());
        // A send time far off either way, authentic or not, never panics.
        let mut far = Opener::new(Some(Duration::from_secs(1)));
        far.add_key("", &key(1)).unwrap();
        let sealed = Sealer::with_stream(&key(1), "x", 1, false)
            .seal(&packet("x", b""), u64::MAX)
            .to_vec();
        assert!(matches!(far.open(&sealed, 0), Err(OpenError::Stale { .. })));
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

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

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use chacha20poly1305::aead::{AeadInPlace, KeyInit};
use chacha20poly1305::{Tag, XChaCha20Poly1305, XNonce};

use crate::wire::sealed::Sealed;
use crate::wire::DropReason;

/// The four bytes every sealed datagram starts with.
pub const MAGIC: [u8; 4] = crate::wire::SEALED_MAGIC;

/// Header bytes besides the channel name.
pub const HEADER_OVERHEAD: usize = 4 + 1 + 1 + 6 + 8 + 8 + 8;

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
    /// An entry of a key list is not `NAMESPACE=KEY`.
    #[error("key list entry {entry} is not NAMESPACE=KEY")]
    Entry {
        /// Its position, from 1.
        entry: usize,
    },
    /// The key of an entry is not 64 hex digits.
    #[error("the key of key list entry {entry}{namespace} is not 64 hex digits (32 bytes)")]
    Key {
        /// Its position, from 1.
        entry: usize,
        /// ` (namespace "...")`, or empty where what stands before the `=`
        /// might be key material itself (a base64 key holds `=`).
        namespace: String,
    },
    /// One `NAMESPACE=KEY` was expected, and the text holds none or more.
    #[error("one NAMESPACE=KEY is expected, not a list")]
    NotOne,
    /// A key file could not be read.
    #[error("key file {path}: {reason}")]
    File {
        /// The file.
        path: String,
        /// What went wrong.
        reason: String,
    },
}

/// The namespace of a key list entry as an error may show it: only a short
/// valid name, since a key written without a namespace (base64 ends in
/// `=`) would otherwise land in the message.
fn shown_namespace(namespace: &str) -> String {
    let valid = crate::name::resolve_path(namespace, "").is_ok();
    if valid && namespace.len() <= 24 {
        format!(" (namespace {namespace:?})")
    } else {
        String::new()
    }
}

/// Reads exactly one `NAMESPACE=KEY` (a command line's `--key`, say), as
/// [`parse_keys`] reads them; errors never repeat key material.
pub fn parse_key(text: &str) -> Result<(String, Key), KeyError> {
    let mut keys = parse_keys(text)?;
    match (keys.pop(), keys.is_empty()) {
        (Some(key), true) => Ok(key),
        _ => Err(KeyError::NotOne),
    }
}

/// One `NAMESPACE=KEY` as a command line gives it (`--key`), kept as text
/// until [`KeyArg::parse`] reads it. An argument parser's errors repeat
/// the value they failed on, and a derived `Debug` would print it: this
/// type does neither (its `Debug` is redacted, its text zeroed when
/// dropped), so a tool's flags can hold keys and be logged. clap takes it
/// through `From<String>`.
#[derive(Clone)]
pub struct KeyArg(String);

impl KeyArg {
    /// The namespace and key it names, read as [`parse_key`] reads them;
    /// the error never repeats key material.
    pub fn parse(&self) -> Result<(String, Key), KeyError> {
        parse_key(&self.0)
    }
}

impl From<String> for KeyArg {
    fn from(text: String) -> Self {
        Self(text)
    }
}

impl std::fmt::Debug for KeyArg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("KeyArg(<redacted>)")
    }
}

impl Drop for KeyArg {
    fn drop(&mut self) {
        zeroize::Zeroize::zeroize(&mut self.0);
    }
}

/// Reads a key list: `NAMESPACE=KEY` entries separated by commas or white
/// space, as in `PULICAST_KEYS` and `--key`. A key is 64 hex digits, or
/// `@` and the path of a file that holds them (so the key stays out of
/// the environment and the process list). `/` or an empty namespace is
/// the root. Errors never contain key material.
pub fn parse_keys(text: &str) -> Result<Vec<(String, Key)>, KeyError> {
    let entries = text
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|e| !e.is_empty());
    let mut keys = Vec::new();
    for (i, entry) in entries.enumerate() {
        let (namespace, value) = entry
            .split_once('=')
            .ok_or(KeyError::Entry { entry: i + 1 })?;
        let key = match value.strip_prefix('@') {
            Some(path) => {
                let mut text = std::fs::read_to_string(path).map_err(|e| KeyError::File {
                    path: path.to_string(),
                    reason: e.to_string(),
                })?;
                let key = Key::from_hex(&text);
                zeroize::Zeroize::zeroize(&mut text);
                key.map_err(|_| KeyError::File {
                    path: path.to_string(),
                    reason: "does not hold 64 hex digits".into(),
                })?
            }
            None => Key::from_hex(value).map_err(|_| KeyError::Key {
                entry: i + 1,
                namespace: shown_namespace(namespace),
            })?,
        };
        keys.push((namespace.to_string(), key));
    }
    Ok(keys)
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
        // 64 random bits: a v4 UUID's bytes without its version and
        // variant bits (bytes 6 and 8).
        let random = uuid::Uuid::new_v4().into_bytes();
        let mut stream = [0u8; 8];
        for (to, from) in stream.iter_mut().zip([0, 1, 2, 3, 4, 5, 7, 9]) {
            *to = random[from];
        }
        Self::with_stream(key, channel, u64::from_be_bytes(stream), encrypt)
    }

    /// Sets the address this sealer's datagrams are sent from, for
    /// receivers to check (an unspecified IP or port: not checked).
    pub fn with_origin(mut self, origin: std::net::SocketAddrV4) -> Self {
        let at = self.prefix.len() - 6;
        self.prefix[at..at + 4].copy_from_slice(&origin.ip().octets());
        self.prefix[at + 4..].copy_from_slice(&origin.port().to_be_bytes());
        self
    }

    /// This sealer's stream id.
    pub fn stream(&self) -> u64 {
        self.stream
    }

    fn with_stream(key: &Key, channel: &str, stream: u64, encrypt: bool) -> Self {
        let name = &channel.as_bytes()[..channel.len().min(255)];
        // Everything of the header up to the numbers: magic, name, flags
        // and origin.
        let mut prefix = Vec::with_capacity(HEADER_OVERHEAD - 24 + name.len());
        prefix.extend_from_slice(&MAGIC);
        prefix.push(name.len() as u8);
        prefix.extend_from_slice(name);
        prefix.push(if encrypt { ENCRYPTED } else { 0 });
        prefix.extend_from_slice(&[0; 6]);
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
        HEADER_OVERHEAD + usize::from(self.prefix[MAGIC.len()]) + TAG_LEN
    }

    /// Bytes a sealed datagram on `channel` adds to its inner datagram.
    pub fn overhead_for(channel: &str) -> usize {
        HEADER_OVERHEAD + channel.len().min(255) + TAG_LEN
    }

    /// Seals `inner` (a whole ordinary datagram) sent at `now_ms` (Unix
    /// time in milliseconds); the sealed datagram stays in the sealer until
    /// the next call.
    pub fn seal(&mut self, inner: &[u8], now_ms: u64) -> &[u8] {
        self.seal_parts(&[inner], now_ms)
    }

    /// Seals the inner datagram made of `parts` one after the other (a
    /// header and a payload, say), without joining them first.
    pub fn seal_parts(&mut self, parts: &[&[u8]], now_ms: u64) -> &[u8] {
        let counter = self.counter;
        self.counter += 1;
        let out = &mut self.out;
        out.clear();
        out.extend_from_slice(&self.prefix);
        out.extend_from_slice(&self.stream.to_be_bytes());
        out.extend_from_slice(&counter.to_be_bytes());
        out.extend_from_slice(&now_ms.to_be_bytes());
        let header = out.len();
        for part in parts {
            out.extend_from_slice(part);
        }
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
    /// Authentic, but what it carries is not a datagram that may be sealed
    /// (another sealed datagram, say).
    #[error("sealed datagram carries an unexpected format")]
    BadInner,
    /// The tag does not match: tampered, or sealed with another key.
    #[error("authentication failed")]
    Forged,
    /// Authentic, but the inner datagram is for another channel than the
    /// one it was sealed for.
    #[error("sealed for another channel than it carries")]
    WrongChannel,
    /// Seen before, or older than the replay window. A counter the stream
    /// has used is refused before its tag is checked, so replaying recorded
    /// traffic costs the receiver a lookup, not a cipher.
    #[error("replayed")]
    Replayed,
    /// Authentic, but received from another address than its sender
    /// seals from: relayed, or replayed from elsewhere.
    #[error("sealed by a sender at {origin}, received from {from}")]
    WrongSource {
        /// Where the sender says it sends from.
        origin: std::net::SocketAddrV4,
        /// Where it came from.
        from: std::net::SocketAddr,
    },
    /// Sent longer ago (or further ahead) than the allowed age.
    #[error("stale: sent {age_ms} ms from now")]
    Stale {
        /// How far the send time is behind our clock, in ms (negative: ahead).
        age_ms: i64,
    },
}

impl OpenError {
    /// The counter this error is tallied under.
    pub fn reason(&self) -> DropReason {
        match self {
            OpenError::Malformed => DropReason::MalformedPayload,
            OpenError::UnknownKey => DropReason::NoKey,
            OpenError::Replayed | OpenError::WrongSource { .. } => DropReason::Replayed,
            OpenError::Stale { .. } => DropReason::Stale,
            OpenError::BadInner | OpenError::Forged | OpenError::WrongChannel => DropReason::Forged,
        }
    }
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

/// A datagram opened in place by [`Opener::open_in_place`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OpenedInPlace {
    /// The channel it was sealed for.
    pub channel: Arc<str>,
    /// The sealer's stream id.
    pub stream: u64,
    /// Where the inner datagram (decrypted if it was encrypted) lies.
    pub inner: std::ops::Range<usize>,
}

/// The replay windows of one channel, taken out of one [`Opener`] to go
/// into another ([`Opener::take_windows`], [`Opener::put_windows`]): a
/// channel handled by another receiver keeps what it saw.
#[derive(Debug, Default)]
pub struct ChannelWindows(Vec<(u64, Window)>);

impl ChannelWindows {
    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
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
    /// Marks `counter` seen; the caller checked it is new
    /// ([`Window::refuses`]).
    fn mark(&mut self, counter: u64) {
        debug_assert!(!self.refuses(counter));
        if self.seen == 0 || counter > self.highest {
            // A stream's first counter marks everything before it seen: a
            // receiver that joins late must not take recorded earlier ones.
            self.seen = if self.seen == 0 {
                u64::MAX
            } else {
                let shift = counter - self.highest;
                (if shift >= 64 { 0 } else { self.seen << shift }) | 1
            };
            self.highest = counter;
            return;
        }
        self.seen |= 1 << (self.highest - counter);
    }

    /// Takes in what `other` saw of the same stream: afterwards this
    /// window refuses every counter either of them refused.
    fn merge(&mut self, other: &Window) {
        if other.seen == 0 {
            return;
        }
        if self.seen == 0 {
            *self = Window {
                used: self.used,
                ..*other
            };
            return;
        }
        let highest = self.highest.max(other.highest);
        let aligned = |w: &Window| {
            let shift = highest - w.highest;
            if shift >= 64 {
                0
            } else {
                w.seen << shift
            }
        };
        self.seen = aligned(self) | aligned(other);
        self.highest = highest;
    }

    /// Whether `counter` was seen already, or is too old to tell.
    fn refuses(&self, counter: u64) -> bool {
        if self.seen == 0 || counter > self.highest {
            return false;
        }
        let back = self.highest - counter;
        back >= 64 || self.seen & (1 << back) != 0
    }
}

/// Opens sealed datagrams: knows the keys of namespaces, caches channel
/// keys, and remembers a bounded number of (channel, session) windows.
pub struct Opener {
    keys: Vec<(String, Key)>,
    /// Per channel, the ciphers of its namespace's keys, sealing key first
    /// (empty: no key).
    ciphers: HashMap<Arc<str>, Vec<XChaCha20Poly1305>>,
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
/// Most keys one namespace may have at once (a key change needs two).
pub const MAX_KEYS_PER_NAMESPACE: usize = 4;

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

    /// Adds a key of `namespace` (`""` or `/` for the root: every channel
    /// without a more specific key). The namespace is resolved like any
    /// other (`/rover1/` is `rover1`); a bad one is an error, and so is a
    /// namespace with more than [`MAX_KEYS_PER_NAMESPACE`] keys.
    ///
    /// A namespace's first key is the one that seals; keys added after it
    /// open too, which is how a fleet changes keys without a gap (see
    /// `docs/security.md`). Adding a key it already has does nothing.
    pub fn add_key(&mut self, namespace: &str, key: &Key) -> crate::Result<()> {
        let namespace = crate::name::resolve_path(namespace, "")?;
        let same_namespace = self.keys.iter().filter(|(ns, _)| *ns == namespace);
        if same_namespace.clone().any(|(_, k)| k.0 == key.0) {
            return Ok(());
        }
        if same_namespace.count() >= MAX_KEYS_PER_NAMESPACE {
            return Err(crate::Error::config(
                "keys",
                format!("more than {MAX_KEYS_PER_NAMESPACE} for namespace {namespace:?}"),
            ));
        }
        self.keys.push((namespace, key.clone()));
        self.ciphers.clear();
        Ok(())
    }

    /// An opener with the same keys and age limit, and nothing seen yet.
    pub fn with_same_keys(&self) -> Self {
        Self {
            keys: self.keys.clone(),
            ..Self::new(self.max_age)
        }
    }

    /// The key that seals `channel`: the first of its most specific
    /// namespace's keys.
    pub fn key_for(&self, channel: &str) -> Option<&Key> {
        key_for(&self.keys, channel)
    }

    /// The namespaces this opener has keys for, each once, in the order
    /// their first key was added (`""` is the root).
    pub fn namespaces(&self) -> Vec<&str> {
        let mut namespaces: Vec<&str> = Vec::new();
        for (ns, _) in &self.keys {
            if !namespaces.contains(&ns.as_str()) {
                namespaces.push(ns);
            }
        }
        namespaces
    }

    /// Whether any key covers `channel`: datagrams on it must be sealed.
    pub fn covers(&self, channel: &str) -> bool {
        self.key_for(channel).is_some()
    }

    /// Checks and opens a sealed datagram received from `from` at `now_ms`.
    pub fn open(
        &mut self,
        datagram: &[u8],
        from: SocketAddr,
        now_ms: u64,
    ) -> Result<Opened, OpenError> {
        let mut copy = datagram.to_vec();
        let opened = self.open_in_place(&mut copy, from, now_ms)?;
        copy.truncate(opened.inner.end);
        copy.drain(..opened.inner.start);
        Ok(Opened {
            channel: opened.channel,
            stream: opened.stream,
            inner: copy,
        })
    }

    /// Checks and opens a sealed datagram received at `now_ms` where it
    /// lies: an encrypted inner datagram is decrypted in place, and the
    /// range it takes is returned. The header is never changed, and a
    /// datagram whose tag fails is left as it was.
    pub fn open_in_place(
        &mut self,
        datagram: &mut [u8],
        from: SocketAddr,
        now_ms: u64,
    ) -> Result<OpenedInPlace, OpenError> {
        let sealed = Sealed::decode(datagram).map_err(|_| OpenError::Malformed)?;
        let (channel, origin, inner) = (sealed.channel, sealed.origin, sealed.inner);
        let (stream, counter, sent_ms) = (sealed.stream, sealed.counter, sealed.sent_ms);
        let (encrypted, header) = (sealed.encrypted, inner.start);
        if !self.ciphers.contains_key(channel) {
            self.cache_ciphers(channel);
        }
        let (channel, ciphers) = match self.ciphers.get_key_value(channel) {
            Some((name, ciphers)) => (Arc::clone(name), ciphers.as_slice()),
            None => return Err(OpenError::UnknownKey),
        };
        let key = (Arc::clone(&channel), stream);
        let window = self.windows.get_mut(&key);
        // A counter this stream has already used is refused before any
        // cryptography, so replaying recorded traffic costs a lookup. It
        // changes nothing, so a forgery gains nothing from reaching it.
        if window.as_ref().is_some_and(|w| w.refuses(counter)) {
            return Err(OpenError::Replayed);
        }
        if ciphers.is_empty() {
            return Err(OpenError::UnknownKey);
        }
        let nonce = nonce(stream, counter);
        let (authenticated, tag) = datagram.split_at_mut(inner.end);
        let tag = Tag::from_slice(tag);
        // The tag is checked before anything is decrypted, so a failed
        // attempt leaves the bytes as they were for the next key.
        let verified = ciphers.iter().any(|cipher| {
            if encrypted {
                let (aad, body) = authenticated.split_at_mut(header);
                cipher.decrypt_in_place_detached(&nonce, aad, body, tag)
            } else {
                cipher.decrypt_in_place_detached(&nonce, authenticated, &mut [], tag)
            }
            .is_ok()
        });
        if !verified {
            return Err(OpenError::Forged);
        }
        check_inner(&datagram[inner.clone()], channel.as_bytes())?;
        let ip_differs = !origin.ip().is_unspecified() && from.ip() != *origin.ip();
        let port_differs = origin.port() != 0 && from.port() != origin.port();
        if ip_differs || port_differs {
            return Err(OpenError::WrongSource { origin, from });
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
        let window = match window {
            Some(window) => window,
            None => {
                if self.windows.len() >= MAX_WINDOWS {
                    self.forget_least_recent();
                }
                self.windows.entry(key).or_default()
            }
        };
        window.mark(counter);
        window.used = self.clock;
        Ok(OpenedInPlace {
            channel,
            stream,
            inner,
        })
    }

    /// Takes out the replay windows of `channel` (see [`ChannelWindows`]).
    pub fn take_windows(&mut self, channel: &str) -> ChannelWindows {
        let keys: Vec<(Arc<str>, u64)> = self
            .windows
            .keys()
            .filter(|(c, _)| &**c == channel)
            .cloned()
            .collect();
        ChannelWindows(
            keys.into_iter()
                .filter_map(|key| Some((key.1, self.windows.remove(&key)?)))
                .collect(),
        )
    }

    /// Adds windows another opener took out for `channel`: what either
    /// refused, this one refuses.
    pub fn put_windows(&mut self, channel: &str, windows: ChannelWindows) {
        let channel: Arc<str> = channel.into();
        for (stream, window) in windows.0 {
            let key = (Arc::clone(&channel), stream);
            if let Some(mine) = self.windows.get_mut(&key) {
                mine.merge(&window);
                continue;
            }
            if self.windows.len() >= MAX_WINDOWS {
                self.forget_least_recent();
            }
            self.clock += 1;
            self.windows.insert(
                key,
                Window {
                    used: self.clock,
                    ..window
                },
            );
        }
    }

    /// Derives and caches the ciphers of `channel` (none: no key covers it).
    fn cache_ciphers(&mut self, channel: &str) {
        if self.ciphers.len() >= MAX_CIPHERS {
            self.ciphers.clear();
        }
        let ciphers = keys_for(&self.keys, channel)
            .map(|k| k.for_channel(channel))
            .collect();
        self.ciphers.insert(channel.into(), ciphers);
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

/// Checks that an opened datagram is one that may be sealed, for the
/// channel it was sealed for.
fn check_inner(inner: &[u8], channel: &[u8]) -> Result<(), OpenError> {
    if channel == crate::wire::DISCOVERY_CHANNEL.as_bytes() {
        return match inner.starts_with(&pulicast_discovery::wire::MAGIC) {
            true => Ok(()),
            false => Err(OpenError::BadInner),
        };
    }
    if !crate::wire::Kind::of(inner).names_a_channel() {
        return Err(OpenError::BadInner);
    }
    // Each of these formats names its channel at the same place: after the
    // magic, a length and the name.
    if inner.get(4).map(|&n| usize::from(n)) != Some(channel.len())
        || inner.get(5..5 + channel.len()) != Some(channel)
    {
        return Err(OpenError::WrongChannel);
    }
    Ok(())
}

/// The keys of the most specific namespace containing `channel`, the
/// sealing key first.
fn keys_for<'k>(keys: &'k [(String, Key)], channel: &str) -> impl Iterator<Item = &'k Key> {
    let most_specific = most_specific(keys, channel);
    keys.iter()
        .filter(move |(ns, _)| most_specific == Some(ns.as_str()))
        .map(|(_, key)| key)
}

/// The most specific namespace of `keys` that contains `channel`.
fn most_specific<'k>(keys: &'k [(String, Key)], channel: &str) -> Option<&'k str> {
    keys.iter()
        .filter(|(ns, _)| crate::name::in_namespace(ns, channel))
        .map(|(ns, _)| ns.as_str())
        .max_by_key(|ns| ns.len())
}

/// The key that seals `channel`: the first of its most specific namespace.
fn key_for<'k>(keys: &'k [(String, Key)], channel: &str) -> Option<&'k Key> {
    keys_for(keys, channel).next()
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::net::{Ipv4Addr, SocketAddrV4};

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
    fn window_merge_is_the_union_of_what_either_refuses() {
        // Gaps come from datagrams out of order: 101..=104 after 105, and
        // 101, 102, 104..=109 after 103 and 110.
        let mut a = Window::default();
        for c in [100, 105] {
            a.mark(c);
        }
        let mut b = Window::default();
        for c in [100, 103, 110] {
            b.mark(c);
        }
        let mut merged = a;
        merged.merge(&b);
        for c in 0..=200u64 {
            assert_eq!(
                merged.refuses(c),
                a.refuses(c) || b.refuses(c),
                "counter {c}"
            );
        }
        assert!(!merged.refuses(104) && merged.refuses(103) && merged.refuses(105));
        let mut empty = Window::default();
        empty.merge(&a);
        assert!(empty.refuses(105) && !empty.refuses(104));
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

    #[test]
    fn key_lists_parse_without_showing_keys() {
        let a = "ab".repeat(32);
        let keys = parse_keys(&format!(" /={a},rover1={a}\nrover1={}\n", "cd".repeat(32))).unwrap();
        let names: Vec<&str> = keys.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["/", "rover1", "rover1"]);
        assert_eq!(keys[2].1 .0[0], 0xcd);
        assert_eq!(parse_keys("").unwrap().len(), 0);
        assert_eq!(parse_keys("x").err(), Some(KeyError::Entry { entry: 1 }));
        let secretish = "a".repeat(63);
        let err = parse_keys(&format!("rover1={secretish}")).unwrap_err();
        assert!(!err.to_string().contains(&secretish));
        assert!(err.to_string().contains("\"rover1\""), "{err}");
        // A base64 key given without a namespace: what precedes its `=`
        // is key material, and is not shown.
        let base64 = "q83vASNFZ4mrze8BI0VniavN7wEjRWeJq83vASNFZ4k=";
        let err = parse_keys(&format!("/={},{base64}", "ab".repeat(32))).unwrap_err();
        assert!(err.to_string().contains("entry 2"), "{err}");
        assert!(!err.to_string().contains(&base64[..20]), "{err}");
        let dir = std::env::temp_dir().join(format!("pulicast-keys-{}", std::process::id()));
        std::fs::write(&dir, format!("{a}\n")).unwrap();
        let keys = parse_keys(&format!("r=@{}", dir.display())).unwrap();
        assert_eq!(keys[0].1 .0[0], 0xab);
        std::fs::write(&dir, "not a key").unwrap();
        assert!(matches!(
            parse_keys(&format!("r=@{}", dir.display())),
            Err(KeyError::File { .. })
        ));
        std::fs::remove_file(&dir).unwrap();
        // Said as the system says it for any other missing file.
        let missing = parse_keys("r=@/nonexistent/pulicast-key").unwrap_err();
        assert!(
            matches!(missing, KeyError::File { .. })
                && missing.to_string().contains("No such file or directory"),
            "{missing}"
        );
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

//! The receiving side: the `Opener` checks and opens sealed datagrams
//! (tag, channel, source, age, replay), with what it can refuse and why.
//! Its replay windows are in `window.rs`.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use chacha20poly1305::aead::AeadInPlace;
use chacha20poly1305::{Tag, XChaCha20Poly1305};

use super::keys::{key_for, keys_for, Key};
use super::nonce;
use super::window::{ChannelWindows, Window};
use crate::wire::sealed::Sealed;
use crate::wire::DropReason;

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

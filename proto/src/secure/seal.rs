//! The sending side: a `Sealer` seals one channel's datagrams as one
//! stream, with a random stream id and a counter, so no two datagrams
//! sealed anywhere share a nonce.

use chacha20poly1305::aead::AeadInPlace;
use chacha20poly1305::{Tag, XChaCha20Poly1305};

use super::keys::Key;
use super::{nonce, ENCRYPTED, HEADER_OVERHEAD, MAGIC, TAG_LEN};

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

    pub(super) fn with_stream(key: &Key, channel: &str, stream: u64, encrypt: bool) -> Self {
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

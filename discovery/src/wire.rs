//! The gossip discovery wire format.
//!
//! Every discovery datagram starts with its own magic, so Pulicast 2.x nodes
//! (which check for `PULI`) drop it silently, and our data path tells it apart
//! from data packets at the first four bytes:
//!
//! ```text
//! +--------+-------------+----------------------------------+
//! | "PDSC" | version: u8 | postcard-encoded [`Message`]     |
//! +--------+-------------+----------------------------------+
//! ```
//!
//! The body is closed: trailing bytes are an error. Datagrams are at most
//! 65507 bytes, which bounds every length the decoder can meet.

use std::net::SocketAddr;

use crate::heap_bytes;
use serde::{Deserialize, Serialize};

/// The first four bytes of every discovery datagram.
pub const MAGIC: [u8; 4] = *b"PDSC";

/// The protocol version this crate speaks. Version 2 added
/// [`MemberInfo::config`], version 3 [`MemberInfo::extensions`]; a node of
/// one version refuses another's datagrams as a version it does not speak,
/// so nodes of two versions see each other only through their 2.x
/// heartbeats. Properties added later go in extensions, which need no new
/// version.
pub const VERSION: u8 = 3;

/// Largest chunk of an encoded [`MemberInfo`] carried by one [`FullPart`],
/// leaving room for the header below the 65507-byte datagram limit.
pub const MAX_CHUNK: usize = 60_000;

/// A member's identity on the wire: the first eight bytes of its session UUID,
/// big-endian, which is also the session id of its Pulicast 2.x heartbeat.
pub type MemberKey = i64;

/// What a peer believes about a member.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum MemberState {
    /// Heard from recently.
    Alive,
    /// Not heard from for a while; dead unless it refutes.
    Suspect,
    /// Declared failed.
    Dead,
    /// Left gracefully.
    Left,
}

/// One discovery datagram's content.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Message {
    /// The periodic, constant-size announcement of a member, with piggybacked
    /// membership updates.
    Digest(Digest),
    /// A request for members' full state.
    Pull(Pull),
    /// One part of a member's full state.
    Full(FullPart),
    /// A member leaving gracefully.
    Leave(Leave),
    /// A list of members, sent to peers that only hear us by unicast.
    Members(Vec<Update>),
    /// Members of other sites that a bridge makes present here (see
    /// [`crate::relay`]). The gossip state machine ignores it; the node
    /// hands it to its [`crate::relay::Relays`].
    Relayed(Relayed),
}

/// Members that a bridge (`puli-bridge`) relays from other sites: it
/// speaks for them on this site, and their data comes from it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Relayed {
    /// The bridge, a gossip member of this site.
    pub sender: MemberKey,
    /// Some or all of the members it relays; each entry refreshes that
    /// member for [`crate::relay::RelayConfig::lifetime`].
    pub members: Vec<RelayedMember>,
}

/// One member of another site, as a bridge relays it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RelayedMember {
    /// What the member told its own site, except `data_port`: the port of
    /// the bridge's data socket, where its messages come from here.
    pub info: MemberInfo,
    /// Its incarnation on its own site.
    pub incarnation: u32,
    /// Its state there: alive or suspect to keep it, dead or left to end it.
    pub state: MemberState,
    /// The name of the site it is on, for people to read.
    pub site: String,
}

/// The postcard variant index of [`Message::Relayed`], the sixth byte of
/// its datagrams (the fifth is the version).
const RELAYED_VARIANT: u8 = 5;

impl Message {
    /// Whether a discovery datagram (after [`MAGIC`] and the version)
    /// carries [`Message::Relayed`], read without decoding it.
    pub fn is_relayed(bytes: &[u8]) -> bool {
        bytes.starts_with(&MAGIC) && bytes.get(5) == Some(&RELAYED_VARIANT)
    }
}

/// The periodic announcement of one member.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Digest {
    /// Who sends it.
    pub sender: MemberKey,
    /// The sender's incarnation; it only grows, and refutes suspicion.
    pub incarnation: u32,
    /// The version of the sender's full state; a peer holding an older one pulls.
    pub version: u32,
    /// Membership changes being spread (SWIM-style piggybacking).
    pub updates: Vec<Update>,
}

/// A membership fact being gossiped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Update {
    /// The member it is about.
    pub member: MemberKey,
    /// Its incarnation the fact refers to.
    pub incarnation: u32,
    /// The version of its full state the sender knows of.
    pub version: u32,
    /// The state claimed.
    pub state: MemberState,
    /// Where the member's discovery socket is, so peers that can't hear it
    /// directly can pull from it.
    pub address: SocketAddr,
}

/// A request for full state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Pull {
    /// Who asks.
    pub sender: MemberKey,
    /// The members (and the versions) wanted.
    pub wants: Vec<(MemberKey, u32)>,
}

/// One chunk of a member's encoded [`MemberInfo`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FullPart {
    /// Whose state.
    pub member: MemberKey,
    /// Its incarnation.
    pub incarnation: u32,
    /// The version of the state.
    pub version: u32,
    /// This chunk's index, from 0.
    pub part: u16,
    /// How many chunks make the state.
    pub parts: u16,
    /// The bytes.
    #[serde(with = "serde_bytes_compat")]
    pub chunk: Vec<u8>,
}

/// A member leaving.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Leave {
    /// Who leaves.
    pub sender: MemberKey,
    /// Its final incarnation.
    pub incarnation: u32,
}

/// Everything a member tells about itself.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct MemberInfo {
    /// The full session UUID (its first 8 bytes are the [`MemberKey`]).
    pub session: [u8; 16],
    /// The node's name.
    pub name: String,
    /// The node's default namespace.
    pub namespace: String,
    /// The host's name.
    pub host: String,
    /// The node's process id.
    pub pid: u32,
    /// When the node started, in milliseconds since the Unix epoch.
    pub start_time_ms: u64,
    /// The UDP port its data packets come from (its address's IP, this port).
    pub data_port: u16,
    /// Its channels.
    pub channels: Vec<ChannelInfo>,
    /// The configuration it runs in (`alice`, a simulation run), empty for
    /// none: providers are searched in the caller's configuration first,
    /// then among those of none (as DROS searches its name server).
    pub config: String,
    /// Further properties, each a kind and its bytes ([`Extension`]): at
    /// most [`MAX_EXTENSIONS`] (a state with more does not decode).
    #[serde(with = "bounded_extensions")]
    pub extensions: Vec<Extension>,
}

/// Most [`Extension`]s a [`MemberInfo`] may carry. An empty one is two
/// bytes on the wire and a whole `Extension` in memory: bounded at
/// decoding, before the memory is taken.
pub const MAX_EXTENSIONS: usize = 32;

/// A property of a member in [`MemberInfo::extensions`]: a kind and its
/// bytes. A kind a node does not know is kept in the state as it came
/// (and relayed on with it) and otherwise ignored, so a new property
/// needs no new protocol version, and nodes that know it work beside
/// nodes that don't.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Extension {
    /// What the bytes say ([`EXT_RECEIVE_BUFFER`], ...).
    pub kind: u16,
    /// The property, encoded as its kind says.
    #[serde(with = "serde_bytes_compat")]
    pub data: Vec<u8>,
}

impl Extension {
    /// The [`EXT_RECEIVE_BUFFER`] extension of `bytes`.
    pub fn receive_buffer(bytes: u32) -> Self {
        Self {
            kind: EXT_RECEIVE_BUFFER,
            data: bytes.to_le_bytes().to_vec(),
        }
    }
}

/// [`Extension`] kind: the receive buffer the kernel granted the member's
/// data sockets, in bytes (`SO_RCVBUF` as Linux reports it, twice the
/// payload it holds), a little-endian `u32`. A publisher of messages in
/// fragments paces them so that a burst fits its subscribers' buffers.
pub const EXT_RECEIVE_BUFFER: u16 = 1;

impl MemberInfo {
    /// About how many bytes this state holds in memory: the struct, its
    /// strings, channels and types, as an allocator rounds them. Discovery's
    /// byte bounds count this plus their own bookkeeping per member (the
    /// tables are bounded in bytes decoded, not on the wire: an empty
    /// channel name is one byte on the wire and a whole [`ChannelInfo`] in
    /// memory); a program keeping members of its own can bound its tables
    /// by it too.
    pub fn memory_cost(&self) -> usize {
        let channels: usize = self
            .channels
            .iter()
            .map(|c| {
                heap_bytes(c.name.capacity())
                    + c.message_type.as_ref().map_or(0, |t| {
                        heap_bytes(t.name.capacity()) + heap_bytes(t.schema.capacity())
                    })
            })
            .sum();
        std::mem::size_of::<MemberInfo>()
            + heap_bytes(self.name.capacity())
            + heap_bytes(self.namespace.capacity())
            + heap_bytes(self.host.capacity())
            + heap_bytes(self.config.capacity())
            + heap_bytes(self.channels.capacity() * std::mem::size_of::<ChannelInfo>())
            + channels
            + heap_bytes(self.extensions.capacity() * std::mem::size_of::<Extension>())
            + self
                .extensions
                .iter()
                .map(|e| heap_bytes(e.data.capacity()))
                .sum::<usize>()
    }

    /// The receive buffer it announces ([`EXT_RECEIVE_BUFFER`]), if it
    /// announces one that reads as such.
    ///
    /// ```
    /// # use pulicast_discovery::wire::MemberInfo;
    /// # fn demo(mut info: MemberInfo) {
    /// info.set_receive_buffer(8 << 20);
    /// assert_eq!(info.receive_buffer(), Some(8 << 20));
    /// # }
    /// ```
    pub fn receive_buffer(&self) -> Option<u32> {
        let e = self
            .extensions
            .iter()
            .find(|e| e.kind == EXT_RECEIVE_BUFFER)?;
        Some(u32::from_le_bytes(e.data.as_slice().try_into().ok()?))
    }

    /// Announces `bytes` as its receive buffer ([`EXT_RECEIVE_BUFFER`]),
    /// in place of any it announced.
    pub fn set_receive_buffer(&mut self, bytes: u32) {
        self.extensions.retain(|e| e.kind != EXT_RECEIVE_BUFFER);
        self.extensions.push(Extension::receive_buffer(bytes));
    }

    /// The key this info belongs to.
    pub fn key(&self) -> MemberKey {
        key_of(&self.session)
    }
}

/// The [`MemberKey`] of a session UUID.
pub fn key_of(session: &[u8; 16]) -> MemberKey {
    let mut first = [0; 8];
    first.copy_from_slice(&session[..8]);
    i64::from_be_bytes(first)
}

/// One channel of a member.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ChannelInfo {
    /// Resolved channel name.
    pub name: String,
    /// The member publishes on it.
    pub publishes: bool,
    /// The member subscribes to it.
    pub subscribes: bool,
    /// Measured publishing period in nanoseconds, 0 if unknown.
    pub period_ns: u64,
    /// The message type, if the member uses a typed API on it.
    pub message_type: Option<TypeInfo>,
}

/// A message type as announced in discovery, enough for a tool to decode it.
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TypeInfo {
    /// How messages of this type are encoded.
    pub encoding: TypeEncoding,
    /// The type's name (`string_msg`, `Pose`, ...).
    pub name: String,
    /// The 8-byte fingerprint its messages start with.
    pub fingerprint: [u8; 8],
    /// For native types, the postcard-encoded `postcard_schema` description.
    #[serde(with = "serde_bytes_compat")]
    pub schema: Vec<u8>,
}

/// How a [`TypeInfo`]'s messages are encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum TypeEncoding {
    /// A ZCM message (the 2.x primitives).
    Zcm,
    /// Fingerprint + postcard.
    Native,
}

/// Why a discovery datagram was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WireError {
    /// Not a discovery datagram.
    BadMagic,
    /// A protocol version we don't speak.
    UnsupportedVersion(u8),
    /// The body did not decode.
    Malformed(String),
    /// Bytes after the message.
    TrailingBytes(usize),
}

impl std::fmt::Display for WireError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            WireError::BadMagic => f.write_str("not a discovery datagram"),
            WireError::UnsupportedVersion(v) => write!(f, "unsupported discovery version {v}"),
            WireError::Malformed(e) => write!(f, "malformed discovery message: {e}"),
            WireError::TrailingBytes(n) => {
                write!(f, "{n} trailing bytes after a discovery message")
            }
        }
    }
}

impl std::error::Error for WireError {}

impl Message {
    /// Encodes the datagram.
    ///
    /// ```
    /// use pulicast_discovery::wire::{Leave, Message};
    /// let msg = Message::Leave(Leave { sender: 7, incarnation: 2 });
    /// assert_eq!(Message::decode(&msg.encode()).unwrap(), msg);
    /// ```
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(64);
        out.extend_from_slice(&MAGIC);
        out.push(VERSION);
        // Serializing our own plain data into a Vec cannot fail.
        postcard::to_extend(self, out).unwrap_or_default()
    }

    /// Decodes a datagram.
    pub fn decode(bytes: &[u8]) -> Result<Message, WireError> {
        let Some(rest) = bytes.strip_prefix(&MAGIC) else {
            return Err(WireError::BadMagic);
        };
        let Some((&version, body)) = rest.split_first() else {
            return Err(WireError::Malformed("no version byte".into()));
        };
        if version != VERSION {
            return Err(WireError::UnsupportedVersion(version));
        }
        let (message, trailing) = postcard::take_from_bytes::<Message>(body)
            .map_err(|e| WireError::Malformed(e.to_string()))?;
        if !trailing.is_empty() {
            return Err(WireError::TrailingBytes(trailing.len()));
        }
        Ok(message)
    }

    /// Whether these bytes claim to be a discovery datagram.
    pub fn is_discovery(bytes: &[u8]) -> bool {
        bytes.starts_with(&MAGIC)
    }
}

/// Encodes member info for [`FullPart`] chunks.
pub fn encode_info(info: &MemberInfo) -> Vec<u8> {
    postcard::to_stdvec(info).unwrap_or_default()
}

/// Most parts one member's full state may have.
pub const MAX_PARTS: u16 = 16;

/// A member's encoded [`MemberInfo`] cut into the [`FullPart`]s that carry
/// it (at least one, even when empty); `None` if it needs more than
/// [`MAX_PARTS`].
pub fn full_parts(
    member: MemberKey,
    incarnation: u32,
    version: u32,
    encoded: &[u8],
) -> Option<Vec<FullPart>> {
    let chunks: Vec<&[u8]> = if encoded.is_empty() {
        vec![&[][..]]
    } else {
        encoded.chunks(MAX_CHUNK).collect()
    };
    let parts = u16::try_from(chunks.len())
        .ok()
        .filter(|n| *n <= MAX_PARTS)?;
    let parts = chunks
        .into_iter()
        .enumerate()
        .map(|(part, chunk)| FullPart {
            member,
            incarnation,
            version,
            part: part as u16,
            parts,
            chunk: chunk.to_vec(),
        })
        .collect();
    Some(parts)
}

/// Decodes member info assembled from [`FullPart`] chunks.
pub fn decode_info(bytes: &[u8]) -> Result<MemberInfo, WireError> {
    let (info, trailing) = postcard::take_from_bytes::<MemberInfo>(bytes)
        .map_err(|e| WireError::Malformed(e.to_string()))?;
    if !trailing.is_empty() {
        return Err(WireError::TrailingBytes(trailing.len()));
    }
    Ok(info)
}

/// How many channels an encoded [`MemberInfo`] lists, read without decoding
/// them: a receiver refuses a state too large for its memory bound before
/// it costs that memory (5 bytes on the wire can decode to a whole
/// [`ChannelInfo`]).
pub fn channel_count(bytes: &[u8]) -> Result<usize, WireError> {
    type Head<'a> = ([u8; 16], &'a str, &'a str, &'a str, u32, u64, u16);
    let malformed = |e: postcard::Error| WireError::Malformed(e.to_string());
    let (_, rest) = postcard::take_from_bytes::<Head<'_>>(bytes).map_err(malformed)?;
    let (count, _) = postcard::take_from_bytes::<u64>(rest).map_err(malformed)?;
    usize::try_from(count).map_err(|_| WireError::Malformed("channel count".into()))
}

/// [`MemberInfo::extensions`], refused at decoding when there are more
/// than [`MAX_EXTENSIONS`] (postcard says the count first).
mod bounded_extensions {
    use super::{Extension, MAX_EXTENSIONS};
    use serde::de::{Error, SeqAccess, Visitor};
    use serde::{Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(extensions: &[Extension], s: S) -> Result<S::Ok, S::Error> {
        extensions.serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<Extension>, D::Error> {
        struct Bounded;
        impl<'de> Visitor<'de> for Bounded {
            type Value = Vec<Extension>;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "at most {MAX_EXTENSIONS} extensions")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
                if seq.size_hint().is_some_and(|n| n > MAX_EXTENSIONS) {
                    return Err(A::Error::custom("too many extensions"));
                }
                let mut out = Vec::with_capacity(seq.size_hint().unwrap_or(0));
                while let Some(e) = seq.next_element()? {
                    if out.len() == MAX_EXTENSIONS {
                        return Err(A::Error::custom("too many extensions"));
                    }
                    out.push(e);
                }
                Ok(out)
            }
        }
        d.deserialize_seq(Bounded)
    }
}

/// Byte vectors as postcard byte strings (length + bytes) instead of a
/// sequence of integers: same size for postcard, but borrowed on decode.
mod serde_bytes_compat {
    use serde::{Deserializer, Serializer};

    pub fn serialize<S: Serializer>(bytes: &[u8], s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(bytes)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = Vec<u8>;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("bytes")
            }
            fn visit_bytes<E: serde::de::Error>(self, v: &[u8]) -> Result<Vec<u8>, E> {
                Ok(v.to_vec())
            }
            fn visit_byte_buf<E: serde::de::Error>(self, v: Vec<u8>) -> Result<Vec<u8>, E> {
                Ok(v)
            }
        }
        d.deserialize_bytes(Visitor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn addr() -> SocketAddr {
        SocketAddr::from(([10, 0, 0, 1], 4000))
    }

    #[test]
    fn digest_is_small_and_constant() {
        let digest = |version| {
            Message::Digest(Digest {
                sender: i64::MIN,
                incarnation: 3,
                version,
                updates: vec![],
            })
            .encode()
        };
        // magic, version, variant, 8-byte key (varint zigzag: up to 10), inc, version, empty vec
        assert!(digest(1).len() <= 20, "{}", digest(1).len());
        assert_eq!(digest(1).len(), digest(100).len());
    }

    #[test]
    fn every_message_round_trips_and_every_truncation_fails() {
        let info = MemberInfo {
            session: [7; 16],
            name: "rover".into(),
            namespace: "rover1".into(),
            host: "h".into(),
            pid: 42,
            start_time_ms: 1,
            data_port: 5000,
            channels: vec![ChannelInfo {
                name: "rover1/pose".into(),
                publishes: true,
                subscribes: false,
                period_ns: 100,
                message_type: Some(TypeInfo {
                    encoding: TypeEncoding::Native,
                    name: "Pose".into(),
                    fingerprint: [1; 8],
                    schema: vec![1, 2, 3],
                }),
            }],
            config: String::new(),
            extensions: vec![Extension {
                kind: 999,
                data: vec![1, 2],
            }],
        };
        assert_eq!(decode_info(&encode_info(&info)).unwrap(), info);
        // A kind this node does not know is kept, and the known one read.
        let mut known = info.clone();
        assert_eq!(known.receive_buffer(), None);
        known.set_receive_buffer(4 << 20);
        known.set_receive_buffer(8 << 20);
        let back = decode_info(&encode_info(&known)).unwrap();
        assert_eq!(back.receive_buffer(), Some(8 << 20));
        assert_eq!(back.extensions.len(), 2);
        assert!(back.memory_cost() > info.memory_cost());
        // One of the wrong length reads as none.
        let mut odd = info.clone();
        odd.extensions.push(Extension {
            kind: EXT_RECEIVE_BUFFER,
            data: vec![1, 2, 3],
        });
        assert_eq!(odd.receive_buffer(), None);
        // More than MAX_EXTENSIONS: refused, even empty ones.
        let mut many_ext = info.clone();
        many_ext.extensions = vec![
            Extension {
                kind: 7,
                data: Vec::new()
            };
            MAX_EXTENSIONS + 1
        ];
        assert!(decode_info(&encode_info(&many_ext)).is_err());
        many_ext.extensions.pop();
        assert_eq!(decode_info(&encode_info(&many_ext)).unwrap(), many_ext);
        let mut many = info.clone();
        many.channels = vec![info.channels[0].clone(); 300];
        assert_eq!(channel_count(&encode_info(&info)).unwrap(), 1);
        assert_eq!(channel_count(&encode_info(&many)).unwrap(), 300);
        assert!(channel_count(&encode_info(&info)[..20]).is_err());
        let update = Update {
            member: 5,
            incarnation: 1,
            version: 2,
            state: MemberState::Suspect,
            address: addr(),
        };
        let messages = [
            Message::Digest(Digest {
                sender: 1,
                incarnation: 2,
                version: 3,
                updates: vec![update],
            }),
            Message::Pull(Pull {
                sender: 1,
                wants: vec![(2, 3)],
            }),
            Message::Full(FullPart {
                member: 1,
                incarnation: 0,
                version: 1,
                part: 0,
                parts: 1,
                chunk: encode_info(&info),
            }),
            Message::Leave(Leave {
                sender: 1,
                incarnation: 9,
            }),
            Message::Members(vec![update, update]),
            Message::Relayed(Relayed {
                sender: 3,
                members: vec![RelayedMember {
                    info: info.clone(),
                    incarnation: 2,
                    state: MemberState::Alive,
                    site: "site-a".into(),
                }],
            }),
        ];
        for m in messages {
            let bytes = m.encode();
            assert_eq!(
                Message::is_relayed(&bytes),
                matches!(m, Message::Relayed(_))
            );
            assert_eq!(Message::decode(&bytes).unwrap(), m);
            for len in 0..bytes.len() {
                assert!(
                    Message::decode(&bytes[..len]).is_err(),
                    "{m:?} cut at {len}"
                );
            }
            let mut longer = bytes.clone();
            longer.push(0);
            assert_eq!(Message::decode(&longer), Err(WireError::TrailingBytes(1)));
        }
        assert_eq!(Message::decode(b"PULI\x01"), Err(WireError::BadMagic));
        assert_eq!(
            Message::decode(b"PDSC\x09"),
            Err(WireError::UnsupportedVersion(9))
        );
    }
}

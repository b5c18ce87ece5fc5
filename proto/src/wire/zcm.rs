//! ZCM messages as Pulicast 2.x speaks them.
//!
//! A ZCM payload is an 8-byte type fingerprint followed by the fields in
//! declaration order, big-endian. Strings are a `u32` length that counts a
//! trailing NUL, the bytes, then the NUL. Nested structs carry no fingerprint.
//!
//! ```text
//! string_msg("Go LEFT!"):
//! +------------------+-------------+------------------+----+
//! | d6e27694111b653f | 00000009    | "Go LEFT!"       | 00 |
//! | fingerprint      | len incl. \0| bytes            | \0 |
//! +------------------+-------------+------------------+----+
//!
//! pulicast_node:
//! +-------------+-------------+-----------------+----------------+----------------------+
//! | fingerprint | name: string| session_id: i64 | n: i16         | n x pulicast_channel |
//! +-------------+-------------+-----------------+----------------+----------------------+
//! pulicast_channel: name: string | period_ns: i64 | is_published: u8 | is_subscribed: u8
//! ```
//!
//! Python's `float` travels as `double_msg`, `int` as `int64_msg`, `str` as
//! `string_msg` and `bool` as `boolean_msg`. Note that `float_msg` carries an
//! 8-byte double on the wire, like the reference implementation sends it.

use pulicast_discovery::compat::{ChannelAnnouncement, Heartbeat};
use serde::ser::{self, Impossible, Serialize};

use super::{DecodeError, Fingerprint};

macro_rules! fingerprints {
    ($($(#[$doc:meta])* $name:ident = $hex:literal;)*) => {
        /// Fingerprints of the ZCM messages the reference implementation defines.
        pub mod fingerprint {
            use super::Fingerprint;
            $($(#[$doc])* pub const $name: Fingerprint = Fingerprint(u64::to_be_bytes($hex));)*
        }
    };
}

fingerprints! {
    /// `boolean_msg { boolean value }`
    BOOLEAN_MSG = 0x8959a74e6bf4095d;
    /// `byte_msg { byte value }`
    BYTE_MSG = 0xc6ef92aac4f05796;
    /// `double_msg { double value }`
    DOUBLE_MSG = 0xe31c78a2031fd917;
    /// `float_msg`, an 8-byte double on the wire.
    FLOAT_MSG = 0xbe870a8c944f1d31;
    /// `int8_msg { int8_t value }`
    INT8_MSG = 0xb28cae5a705675df;
    /// `int16_msg { int16_t value }`
    INT16_MSG = 0x5bcd63ce1cd5ff91;
    /// `int32_msg { int32_t value }`
    INT32_MSG = 0x5bc553ca24d5ff91;
    /// `int64_msg { int64_t value }`
    INT64_MSG = 0x5bb95bc420d5ff91;
    /// `string_msg { string value }`
    STRING_MSG = 0xd6e27694111b653f;
    /// `pulicast_node`, the heartbeat on `__nodes`.
    PULICAST_NODE = 0x253c9f63a90c4dfb;
    /// `pulicast_channel`, nested in `pulicast_node`.
    PULICAST_CHANNEL = 0xf466a777ab4b7ae9;
}

/// The single-value ZCM messages that Rust primitives map to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PrimitiveKind {
    /// `boolean_msg`, Rust `bool`.
    Bool,
    /// `byte_msg`, Rust `u8`.
    Byte,
    /// `int8_msg`, Rust `i8`.
    I8,
    /// `int16_msg`, Rust `i16`.
    I16,
    /// `int32_msg`, Rust `i32`.
    I32,
    /// `int64_msg`, Rust `i64`.
    I64,
    /// `float_msg`, Rust `f32`.
    Float,
    /// `double_msg`, Rust `f64`.
    Double,
    /// `string_msg`, Rust `String` and `&str`.
    String,
}

impl PrimitiveKind {
    /// Every kind.
    pub const ALL: [PrimitiveKind; 9] = [
        PrimitiveKind::Bool,
        PrimitiveKind::Byte,
        PrimitiveKind::I8,
        PrimitiveKind::I16,
        PrimitiveKind::I32,
        PrimitiveKind::I64,
        PrimitiveKind::Float,
        PrimitiveKind::Double,
        PrimitiveKind::String,
    ];

    /// The message's fingerprint.
    pub const fn fingerprint(self) -> Fingerprint {
        match self {
            PrimitiveKind::Bool => fingerprint::BOOLEAN_MSG,
            PrimitiveKind::Byte => fingerprint::BYTE_MSG,
            PrimitiveKind::I8 => fingerprint::INT8_MSG,
            PrimitiveKind::I16 => fingerprint::INT16_MSG,
            PrimitiveKind::I32 => fingerprint::INT32_MSG,
            PrimitiveKind::I64 => fingerprint::INT64_MSG,
            PrimitiveKind::Float => fingerprint::FLOAT_MSG,
            PrimitiveKind::Double => fingerprint::DOUBLE_MSG,
            PrimitiveKind::String => fingerprint::STRING_MSG,
        }
    }

    /// The message's ZCM type name.
    pub const fn type_name(self) -> &'static str {
        match self {
            PrimitiveKind::Bool => "boolean_msg",
            PrimitiveKind::Byte => "byte_msg",
            PrimitiveKind::I8 => "int8_msg",
            PrimitiveKind::I16 => "int16_msg",
            PrimitiveKind::I32 => "int32_msg",
            PrimitiveKind::I64 => "int64_msg",
            PrimitiveKind::Float => "float_msg",
            PrimitiveKind::Double => "double_msg",
            PrimitiveKind::String => "string_msg",
        }
    }

    /// The Rust type that travels as this message, as a user writes it.
    pub const fn rust_name(self) -> &'static str {
        match self {
            PrimitiveKind::Bool => "bool",
            PrimitiveKind::Byte => "u8",
            PrimitiveKind::I8 => "i8",
            PrimitiveKind::I16 => "i16",
            PrimitiveKind::I32 => "i32",
            PrimitiveKind::I64 => "i64",
            PrimitiveKind::Float => "f32",
            PrimitiveKind::Double => "f64",
            PrimitiveKind::String => "String",
        }
    }

    /// The kind whose fingerprint this is.
    pub fn from_fingerprint(fp: Fingerprint) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.fingerprint() == fp)
    }
}

/// A decoded single-value ZCM message.
#[derive(Debug, Clone, PartialEq)]
pub enum Primitive {
    /// `boolean_msg`
    Bool(bool),
    /// `byte_msg`
    Byte(u8),
    /// `int8_msg`
    I8(i8),
    /// `int16_msg`
    I16(i16),
    /// `int32_msg`
    I32(i32),
    /// `int64_msg`
    I64(i64),
    /// `float_msg` (a double on the wire)
    Float(f64),
    /// `double_msg`
    Double(f64),
    /// `string_msg`
    String(String),
}

impl Primitive {
    /// Which message this is.
    pub fn kind(&self) -> PrimitiveKind {
        match self {
            Primitive::Bool(_) => PrimitiveKind::Bool,
            Primitive::Byte(_) => PrimitiveKind::Byte,
            Primitive::I8(_) => PrimitiveKind::I8,
            Primitive::I16(_) => PrimitiveKind::I16,
            Primitive::I32(_) => PrimitiveKind::I32,
            Primitive::I64(_) => PrimitiveKind::I64,
            Primitive::Float(_) => PrimitiveKind::Float,
            Primitive::Double(_) => PrimitiveKind::Double,
            Primitive::String(_) => PrimitiveKind::String,
        }
    }

    /// Appends fingerprint and value to `out`.
    pub fn encode(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.kind().fingerprint().0);
        let mut w = Writer(out);
        match self {
            Primitive::Bool(v) => w.bool(*v),
            Primitive::Byte(v) => w.0.push(*v),
            Primitive::I8(v) => w.0.extend_from_slice(&v.to_be_bytes()),
            Primitive::I16(v) => w.0.extend_from_slice(&v.to_be_bytes()),
            Primitive::I32(v) => w.0.extend_from_slice(&v.to_be_bytes()),
            Primitive::I64(v) => w.i64(*v),
            Primitive::Float(v) | Primitive::Double(v) => w.0.extend_from_slice(&v.to_be_bytes()),
            Primitive::String(v) => w.string(v),
        }
    }

    /// Decodes a payload whose fingerprint names one of the primitive messages.
    pub fn decode(payload: &[u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(payload);
        let fp = r.fingerprint()?;
        let Some(kind) = PrimitiveKind::from_fingerprint(fp) else {
            return Err(DecodeError::Malformed(format!(
                "fingerprint {fp} is not a primitive message"
            )));
        };
        Self::decode_body(kind, &mut r)
    }

    /// Decodes a payload that must carry `kind`.
    pub fn decode_as(kind: PrimitiveKind, payload: &[u8]) -> Result<Self, DecodeError> {
        let mut r = Reader::new(payload);
        r.expect_fingerprint(kind.fingerprint(), kind.type_name())?;
        Self::decode_body(kind, &mut r)
    }

    fn decode_body(kind: PrimitiveKind, r: &mut Reader<'_>) -> Result<Self, DecodeError> {
        let value = match kind {
            PrimitiveKind::Bool => Primitive::Bool(r.bool()?),
            PrimitiveKind::Byte => Primitive::Byte(r.array::<1>()?[0]),
            PrimitiveKind::I8 => Primitive::I8(i8::from_be_bytes(r.array()?)),
            PrimitiveKind::I16 => Primitive::I16(i16::from_be_bytes(r.array()?)),
            PrimitiveKind::I32 => Primitive::I32(i32::from_be_bytes(r.array()?)),
            PrimitiveKind::I64 => Primitive::I64(r.i64()?),
            PrimitiveKind::Float => Primitive::Float(f64::from_be_bytes(r.array()?)),
            PrimitiveKind::Double => Primitive::Double(f64::from_be_bytes(r.array()?)),
            PrimitiveKind::String => Primitive::String(r.string()?.to_owned()),
        };
        r.finish()?;
        Ok(value)
    }
}

/// Encodes a heartbeat as a `pulicast_node` payload.
pub fn encode_heartbeat(hb: &Heartbeat, out: &mut Vec<u8>) {
    out.extend_from_slice(&fingerprint::PULICAST_NODE.0);
    let mut w = Writer(out);
    w.string(&hb.name);
    w.i64(hb.session_id);
    // The count is an i16 on the wire; a node with more channels announces the
    // first 32767, which is also far more than one datagram holds.
    let n = hb.channels.len().min(i16::MAX as usize);
    w.0.extend_from_slice(&(n as i16).to_be_bytes());
    for c in &hb.channels[..n] {
        w.string(&c.name);
        w.i64(c.period_ns);
        w.bool(c.is_published);
        w.bool(c.is_subscribed);
    }
}

/// Decodes a `pulicast_node` payload.
pub fn decode_heartbeat(payload: &[u8]) -> Result<Heartbeat, DecodeError> {
    /// The smallest encoded channel: empty name (length + NUL), period, two flags.
    const MIN_CHANNEL_LEN: usize = 4 + 1 + 8 + 1 + 1;
    let mut r = Reader::new(payload);
    r.expect_fingerprint(fingerprint::PULICAST_NODE, "pulicast_node")?;
    let name = r.string()?.to_owned();
    let session_id = r.i64()?;
    let n = i16::from_be_bytes(r.array()?);
    let n = usize::try_from(n)
        .map_err(|_| DecodeError::Malformed(format!("negative channel count {n}")))?;
    // Never reserve more than the remaining bytes can hold.
    let mut channels = Vec::with_capacity(n.min(r.remaining() / MIN_CHANNEL_LEN));
    for _ in 0..n {
        channels.push(ChannelAnnouncement {
            name: r.string()?.to_owned(),
            period_ns: r.i64()?,
            is_published: r.bool()?,
            is_subscribed: r.bool()?,
        });
    }
    r.finish()?;
    Ok(Heartbeat {
        name,
        session_id,
        channels,
    })
}

/// Encodes `value` as a primitive ZCM message if its serde form is one of the
/// primitives; returns `false` (and leaves `out` untouched) otherwise.
pub(crate) fn encode_serde_primitive<T: Serialize + ?Sized>(value: &T, out: &mut Vec<u8>) -> bool {
    let start = out.len();
    if value.serialize(PrimitiveSerializer(out)).is_ok() {
        return true;
    }
    out.truncate(start);
    false
}

/// A bounds-checked big-endian cursor.
pub(crate) struct Reader<'a> {
    buf: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(buf: &'a [u8]) -> Self {
        Self { buf, pos: 0 }
    }

    fn remaining(&self) -> usize {
        self.buf.len() - self.pos
    }

    pub(super) fn take(&mut self, n: usize) -> Result<&'a [u8], DecodeError> {
        let truncated = DecodeError::Truncated {
            offset: self.pos,
            needed: n.saturating_sub(self.remaining()),
        };
        let end = self.pos.checked_add(n).ok_or(truncated.clone())?;
        let bytes = self.buf.get(self.pos..end).ok_or(truncated)?;
        self.pos = end;
        Ok(bytes)
    }

    pub(super) fn array<const N: usize>(&mut self) -> Result<[u8; N], DecodeError> {
        let bytes = self.take(N)?;
        let mut out = [0; N];
        out.copy_from_slice(bytes);
        Ok(out)
    }

    pub(crate) fn fingerprint(&mut self) -> Result<Fingerprint, DecodeError> {
        self.array().map(Fingerprint)
    }

    pub(crate) fn expect_fingerprint(
        &mut self,
        expected: Fingerprint,
        expected_name: &'static str,
    ) -> Result<(), DecodeError> {
        let found = self.fingerprint()?;
        if found != expected {
            return Err(DecodeError::WrongType {
                expected,
                expected_name,
                found,
            });
        }
        Ok(())
    }

    fn i64(&mut self) -> Result<i64, DecodeError> {
        self.array().map(i64::from_be_bytes)
    }

    fn bool(&mut self) -> Result<bool, DecodeError> {
        match self.array::<1>()? {
            [0] => Ok(false),
            [1] => Ok(true),
            [b] => Err(DecodeError::Malformed(format!("boolean byte {b:#04x}"))),
        }
    }

    pub(super) fn string(&mut self) -> Result<&'a str, DecodeError> {
        let len = u32::from_be_bytes(self.array()?) as usize;
        let Some(content_len) = len.checked_sub(1) else {
            return Err(DecodeError::Malformed(
                "string length 0 lacks the NUL".into(),
            ));
        };
        let bytes = self.take(len)?;
        let (content, nul) = bytes.split_at(content_len);
        if nul != [0] {
            return Err(DecodeError::Malformed("string does not end in NUL".into()));
        }
        std::str::from_utf8(content)
            .map_err(|e| DecodeError::Malformed(format!("string is not UTF-8: {e}")))
    }

    pub(crate) fn finish(&self) -> Result<(), DecodeError> {
        match self.remaining() {
            0 => Ok(()),
            count => Err(DecodeError::TrailingBytes { count }),
        }
    }
}

struct Writer<'a>(&'a mut Vec<u8>);

impl Writer<'_> {
    fn i64(&mut self, v: i64) {
        self.0.extend_from_slice(&v.to_be_bytes());
    }

    fn bool(&mut self, v: bool) {
        self.0.push(u8::from(v));
    }

    fn string(&mut self, s: &str) {
        write_string(self.0, s);
    }
}

/// Appends a ZCM string: its length with the NUL, its bytes, the NUL.
pub(super) fn write_string(out: &mut Vec<u8>, s: &str) {
    // Longer strings can't fit a datagram; the length field is u32 anyway.
    let len = u32::try_from(s.len() + 1).unwrap_or(u32::MAX);
    out.extend_from_slice(&len.to_be_bytes());
    out.extend_from_slice(s.as_bytes());
    out.push(0);
}

/// Writes a serde primitive as its ZCM message; refuses everything else.
struct PrimitiveSerializer<'a>(&'a mut Vec<u8>);

#[derive(Debug)]
struct NotPrimitive;

impl std::fmt::Display for NotPrimitive {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("not a ZCM primitive")
    }
}

impl std::error::Error for NotPrimitive {}

impl ser::Error for NotPrimitive {
    fn custom<T: std::fmt::Display>(_msg: T) -> Self {
        NotPrimitive
    }
}

macro_rules! primitive {
    ($method:ident, $ty:ty, $variant:ident) => {
        fn $method(self, v: $ty) -> Result<(), NotPrimitive> {
            Primitive::$variant(v.into()).encode(self.0);
            Ok(())
        }
    };
}

macro_rules! refuse {
    ($($method:ident($($arg:ty),*) -> $ret:ty;)*) => {
        $(fn $method(self, $(_: $arg),*) -> Result<$ret, NotPrimitive> { Err(NotPrimitive) })*
    };
}

impl ser::Serializer for PrimitiveSerializer<'_> {
    type Ok = ();
    type Error = NotPrimitive;
    type SerializeSeq = Impossible<(), NotPrimitive>;
    type SerializeTuple = Impossible<(), NotPrimitive>;
    type SerializeTupleStruct = Impossible<(), NotPrimitive>;
    type SerializeTupleVariant = Impossible<(), NotPrimitive>;
    type SerializeMap = Impossible<(), NotPrimitive>;
    type SerializeStruct = Impossible<(), NotPrimitive>;
    type SerializeStructVariant = Impossible<(), NotPrimitive>;

    primitive!(serialize_bool, bool, Bool);
    primitive!(serialize_u8, u8, Byte);
    primitive!(serialize_i8, i8, I8);
    primitive!(serialize_i16, i16, I16);
    primitive!(serialize_i32, i32, I32);
    primitive!(serialize_i64, i64, I64);
    primitive!(serialize_f32, f32, Float);
    primitive!(serialize_f64, f64, Double);

    fn serialize_str(self, v: &str) -> Result<(), NotPrimitive> {
        self.0.extend_from_slice(&fingerprint::STRING_MSG.0);
        Writer(self.0).string(v);
        Ok(())
    }

    refuse! {
        serialize_u16(u16) -> ();
        serialize_u32(u32) -> ();
        serialize_u64(u64) -> ();
        serialize_char(char) -> ();
        serialize_bytes(&[u8]) -> ();
        serialize_none() -> ();
        serialize_unit() -> ();
        serialize_unit_struct(&'static str) -> ();
        serialize_unit_variant(&'static str, u32, &'static str) -> ();
        serialize_seq(Option<usize>) -> Self::SerializeSeq;
        serialize_tuple(usize) -> Self::SerializeTuple;
        serialize_tuple_struct(&'static str, usize) -> Self::SerializeTupleStruct;
        serialize_tuple_variant(&'static str, u32, &'static str, usize) -> Self::SerializeTupleVariant;
        serialize_map(Option<usize>) -> Self::SerializeMap;
        serialize_struct(&'static str, usize) -> Self::SerializeStruct;
        serialize_struct_variant(&'static str, u32, &'static str, usize) -> Self::SerializeStructVariant;
    }

    fn serialize_some<T: Serialize + ?Sized>(self, _: &T) -> Result<(), NotPrimitive> {
        Err(NotPrimitive)
    }

    fn serialize_newtype_struct<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: &T,
    ) -> Result<(), NotPrimitive> {
        Err(NotPrimitive)
    }

    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: &T,
    ) -> Result<(), NotPrimitive> {
        Err(NotPrimitive)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn malformed_strings_and_counts_are_errors() {
        let fp = fingerprint::STRING_MSG.0;
        let with = |tail: &[u8]| [&fp[..], tail].concat();
        for bad in [
            with(&[0, 0, 0, 0]),
            with(&[0, 0, 0, 2, b'a', b'b']),
            with(&[0xff, 0xff, 0xff, 0xff, b'a']),
            with(&[0, 0, 0, 3, 0xc3, 0x28, 0]),
            with(&[0, 0, 0, 1, 0, 0]),
        ] {
            assert!(Primitive::decode(&bad).is_err(), "{bad:02x?}");
        }
        let mut hb = fingerprint::PULICAST_NODE.0.to_vec();
        hb.extend_from_slice(&[0, 0, 0, 1, 0]);
        hb.extend_from_slice(&[0; 8]);
        hb.extend_from_slice(&i16::MAX.to_be_bytes());
        assert!(matches!(
            decode_heartbeat(&hb),
            Err(DecodeError::Truncated { .. })
        ));
        let n = hb.len() - 2;
        hb[n..].copy_from_slice(&(-1i16).to_be_bytes());
        assert!(matches!(
            decode_heartbeat(&hb),
            Err(DecodeError::Malformed(_))
        ));
    }

    #[test]
    fn every_truncation_of_a_heartbeat_fails_cleanly() {
        let hb = Heartbeat {
            name: "n".into(),
            session_id: -1,
            channels: vec![ChannelAnnouncement {
                name: "a/b".into(),
                period_ns: 5,
                is_published: true,
                is_subscribed: true,
            }],
        };
        let mut buf = Vec::new();
        encode_heartbeat(&hb, &mut buf);
        assert_eq!(decode_heartbeat(&buf).unwrap(), hb);
        for len in 0..buf.len() {
            assert!(decode_heartbeat(&buf[..len]).is_err());
        }
        buf.push(0);
        assert_eq!(
            decode_heartbeat(&buf),
            Err(DecodeError::TrailingBytes { count: 1 })
        );
    }

    #[test]
    fn serde_primitives_map_to_zcm() {
        let mut out = Vec::new();
        assert!(encode_serde_primitive(&"hi", &mut out));
        assert_eq!(
            Primitive::decode(&out).unwrap(),
            Primitive::String("hi".into())
        );
        out.clear();
        assert!(encode_serde_primitive(&1.5f32, &mut out));
        assert_eq!(Primitive::decode(&out).unwrap(), Primitive::Float(1.5));
        out.clear();
        assert!(!encode_serde_primitive(&(1u8, 2u8), &mut out));
        assert!(!encode_serde_primitive(&7u32, &mut out));
        assert!(out.is_empty());
    }
}

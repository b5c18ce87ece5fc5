//! Typed messages: Rust primitives as ZCM, everything else as native postcard.
//!
//! ```text
//! native message:
//! +---------------------------+------------------------------+
//! | fingerprint (8 bytes)     | postcard encoding of the value |
//! | FNV-1a 64 of the schema   |                              |
//! +---------------------------+------------------------------+
//! ```
//!
//! The fingerprint hashes the type's full [`postcard_schema`] description
//! (the names of the type and of every nested type, field and variant names,
//! and the serde data model of every field), so a subscriber of another type,
//! or of an incompatible version of the same type, gets a
//! [`DecodeError::WrongType`] instead of garbage. `Meters(f64)` and
//! `Seconds(f64)` differ; renaming a field or a nested type changes it too. Types whose serde form is a single `bool`, `u8`, `i8`,
//! `i16`, `i32`, `i64`, `f32`, `f64` or string travel as the ZCM primitive
//! messages instead, so Pulicast 2.x peers read them natively.

use postcard_schema::schema::{
    DataModelType, DataModelVariant, NamedType, NamedValue, NamedVariant,
};
use postcard_schema::Schema;
use serde::de::{DeserializeOwned, IntoDeserializer};
use serde::Serialize;

use super::zcm::{self, Primitive, PrimitiveKind, Reader};
use super::{DecodeError, Fingerprint};

/// Salts the schema hash, so our fingerprints live in their own space.
const FINGERPRINT_DOMAIN: &str = "pulicast-native/1";

/// The fingerprint a value of type `T` carries on the wire.
///
/// Primitives report their ZCM fingerprint; other types the hash of their schema.
///
/// ```
/// use pulicast_proto::wire::{fingerprint_of, zcm::fingerprint};
/// assert_eq!(fingerprint_of::<String>(), fingerprint::STRING_MSG);
/// assert_ne!(fingerprint_of::<(i32, i32)>(), fingerprint_of::<(i32, u32)>());
/// ```
pub const fn fingerprint_of<T: Schema + ?Sized>() -> Fingerprint {
    match primitive_kind(T::SCHEMA) {
        Some(kind) => kind.fingerprint(),
        None => {
            let state = schema_hash::bytes(schema_hash::BASIS, FINGERPRINT_DOMAIN.as_bytes());
            Fingerprint(schema_hash::named_type(state, T::SCHEMA).to_be_bytes())
        }
    }
}

/// FNV-1a 64 over a schema, names included.
///
/// postcard-schema's own key hash leaves type names out (to let `Vec<u8>` and
/// `&[u8]` pun); a robot message's name is part of its meaning, so we walk the
/// schema ourselves. Every string is length-prefixed and every node tagged, so
/// distinct schemas can't produce the same byte stream.
mod schema_hash {
    use super::{DataModelType as T, DataModelVariant as V, NamedType, NamedValue, NamedVariant};

    pub(super) const BASIS: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;

    pub(super) const fn bytes(mut state: u64, data: &[u8]) -> u64 {
        let mut i = 0;
        while i < data.len() {
            state ^= data[i] as u64;
            state = state.wrapping_mul(PRIME);
            i += 1;
        }
        state
    }

    const fn tag(state: u64, tag: u8) -> u64 {
        bytes(state, &[tag])
    }

    const fn len(state: u64, n: usize) -> u64 {
        bytes(state, &(n as u64).to_le_bytes())
    }

    const fn text(state: u64, s: &str) -> u64 {
        bytes(len(state, s.len()), s.as_bytes())
    }

    pub(super) const fn named_type(state: u64, nt: &NamedType) -> u64 {
        model(text(state, nt.name), nt.ty)
    }

    const fn types(state: u64, nts: &[&NamedType]) -> u64 {
        let mut state = len(state, nts.len());
        let mut i = 0;
        while i < nts.len() {
            state = named_type(state, nts[i]);
            i += 1;
        }
        state
    }

    const fn values(state: u64, nvs: &[&NamedValue]) -> u64 {
        let mut state = len(state, nvs.len());
        let mut i = 0;
        while i < nvs.len() {
            state = named_type(text(state, nvs[i].name), nvs[i].ty);
            i += 1;
        }
        state
    }

    const fn variants(state: u64, vs: &[&NamedVariant]) -> u64 {
        let mut state = len(state, vs.len());
        let mut i = 0;
        while i < vs.len() {
            state = text(state, vs[i].name);
            state = match vs[i].ty {
                V::UnitVariant => tag(state, 40),
                V::NewtypeVariant(nt) => named_type(tag(state, 41), nt),
                V::TupleVariant(nts) => types(tag(state, 42), nts),
                V::StructVariant(nvs) => values(tag(state, 43), nvs),
            };
            i += 1;
        }
        state
    }

    const fn model(state: u64, ty: &T) -> u64 {
        match ty {
            T::Bool => tag(state, 1),
            T::I8 => tag(state, 2),
            T::U8 => tag(state, 3),
            T::I16 => tag(state, 4),
            T::I32 => tag(state, 5),
            T::I64 => tag(state, 6),
            T::I128 => tag(state, 7),
            T::U16 => tag(state, 8),
            T::U32 => tag(state, 9),
            T::U64 => tag(state, 10),
            T::U128 => tag(state, 11),
            T::Usize => tag(state, 12),
            T::Isize => tag(state, 13),
            T::F32 => tag(state, 14),
            T::F64 => tag(state, 15),
            T::Char => tag(state, 16),
            T::String => tag(state, 17),
            T::ByteArray => tag(state, 18),
            T::Option(nt) => named_type(tag(state, 19), nt),
            T::Unit => tag(state, 20),
            T::UnitStruct => tag(state, 21),
            T::NewtypeStruct(nt) => named_type(tag(state, 22), nt),
            T::Seq(nt) => named_type(tag(state, 23), nt),
            T::Tuple(nts) => types(tag(state, 24), nts),
            T::TupleStruct(nts) => types(tag(state, 25), nts),
            T::Map { key, val } => named_type(named_type(tag(state, 26), key), val),
            T::Struct(nvs) => values(tag(state, 27), nvs),
            T::Enum(vs) => variants(tag(state, 28), vs),
            T::Schema => tag(state, 29),
        }
    }
}

/// The description of `T` that discovery announces, so tools can decode its
/// messages without knowing the type at compile time.
pub fn type_info_of<T: Schema + ?Sized>() -> pulicast_discovery::wire::TypeInfo {
    use pulicast_discovery::wire::{TypeEncoding, TypeInfo};
    match primitive_kind(T::SCHEMA) {
        Some(kind) => TypeInfo {
            encoding: TypeEncoding::Zcm,
            name: kind.type_name().into(),
            fingerprint: kind.fingerprint().0,
            schema: Vec::new(),
        },
        None => {
            let owned = postcard_schema::schema::owned::OwnedNamedType::from(T::SCHEMA);
            TypeInfo {
                encoding: TypeEncoding::Native,
                name: readable_name(&owned),
                fingerprint: fingerprint_of::<T>().0,
                schema: postcard::to_stdvec(&owned).unwrap_or_default(),
            }
        }
    }
}

/// A type's name as a user writes it in Rust: `(f64, f64)`, `Vec<Pose>`,
/// `[u8; 4]`, `Option<String>`, `HashMap<String, i32>`; a struct or enum by
/// its own name. The schema's own name is generic for the standard types
/// (`(A, B,)`, `Vec<T>`), which tells a user nothing.
///
/// ```
/// use pulicast_proto::wire::type_info_of;
/// assert_eq!(type_info_of::<(f64, f64)>().name, "(f64, f64)");
/// assert_eq!(type_info_of::<Vec<Option<u32>>>().name, "Vec<Option<u32>>");
/// assert_eq!(type_info_of::<[i16; 3]>().name, "[i16; 3]");
/// ```
pub fn readable_name(ty: &postcard_schema::schema::owned::OwnedNamedType) -> String {
    use postcard_schema::schema::owned::OwnedDataModelType as T;
    // The name before its generic part: `HashMap` of `HashMap<K, V>`.
    let base = |fallback: &'static str| match ty.name.split_once('<') {
        Some((base, _)) if !base.is_empty() => base.to_string(),
        _ => fallback.to_string(),
    };
    let list = |items: &[postcard_schema::schema::owned::OwnedNamedType]| {
        items
            .iter()
            .map(readable_name)
            .collect::<Vec<_>>()
            .join(", ")
    };
    match &ty.ty {
        T::Bool => "bool".into(),
        T::I8 => "i8".into(),
        T::U8 => "u8".into(),
        T::I16 => "i16".into(),
        T::I32 => "i32".into(),
        T::I64 => "i64".into(),
        T::I128 => "i128".into(),
        T::U16 => "u16".into(),
        T::U32 => "u32".into(),
        T::U64 => "u64".into(),
        T::U128 => "u128".into(),
        T::Usize => "usize".into(),
        T::Isize => "isize".into(),
        T::F32 => "f32".into(),
        T::F64 => "f64".into(),
        T::Char => "char".into(),
        T::String => "String".into(),
        T::ByteArray => "Vec<u8>".into(),
        T::Unit => "()".into(),
        T::Option(inner) => format!("Option<{}>", readable_name(inner)),
        T::Seq(inner) => format!("{}<{}>", base("Vec"), readable_name(inner)),
        T::Map { key, val } => format!(
            "{}<{}, {}>",
            base("Map"),
            readable_name(key),
            readable_name(val)
        ),
        // An array's schema is a tuple of one type, named `[T; N]`.
        T::Tuple(items) if ty.name.starts_with('[') => match items.first() {
            Some(first) => format!("[{}; {}]", readable_name(first), items.len()),
            None => "[(); 0]".into(),
        },
        T::Tuple(items) if items.len() == 1 => format!("({},)", list(items)),
        T::Tuple(items) => format!("({})", list(items)),
        // User types (and the standard ones with a plain name: Duration).
        T::UnitStruct
        | T::NewtypeStruct(_)
        | T::TupleStruct(_)
        | T::Struct(_)
        | T::Enum(_)
        | T::Schema => ty.name.clone(),
    }
}

/// The ZCM primitive a schema maps to, if any.
pub(crate) const fn primitive_kind(schema: &NamedType) -> Option<PrimitiveKind> {
    Some(match schema.ty {
        DataModelType::Bool => PrimitiveKind::Bool,
        DataModelType::U8 => PrimitiveKind::Byte,
        DataModelType::I8 => PrimitiveKind::I8,
        DataModelType::I16 => PrimitiveKind::I16,
        DataModelType::I32 => PrimitiveKind::I32,
        DataModelType::I64 => PrimitiveKind::I64,
        DataModelType::F32 => PrimitiveKind::Float,
        DataModelType::F64 => PrimitiveKind::Double,
        DataModelType::String => PrimitiveKind::String,
        _ => return None,
    })
}

/// Whether a type is a run of bytes (`Vec<u8>`, `[u8]`, `&[u8]`), which
/// travels raw, as `pulicast::Channel::publish_bytes` sends it: no
/// fingerprint, no length, what 2.x peers read as `bytes`.
pub const fn is_raw_bytes(schema: &NamedType) -> bool {
    match schema.ty {
        DataModelType::ByteArray => true,
        DataModelType::Seq(inner) => matches!(inner.ty, DataModelType::U8),
        _ => false,
    }
}

/// Appends the message encoding of `value` (fingerprint and body) to `out`;
/// a run of bytes ([`is_raw_bytes`]) as it is.
///
/// ```
/// use serde::{Deserialize, Serialize};
/// use pulicast_proto::wire;
/// use postcard_schema::Schema;
///
/// #[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
/// struct Twist { linear: f64, angular: f64 }
///
/// let mut buf = Vec::new();
/// wire::encode_native(&Twist { linear: 0.3, angular: 0.0 }, &mut buf).unwrap();
/// let back: Twist = wire::decode_native(&buf).unwrap();
/// assert_eq!(back, Twist { linear: 0.3, angular: 0.0 });
/// ```
pub fn encode_native<T: Serialize + Schema + ?Sized>(
    value: &T,
    out: &mut Vec<u8>,
) -> Result<(), EncodeError> {
    if is_raw_bytes(T::SCHEMA) {
        // postcard writes a run of bytes as a varint length and the bytes:
        // keep the bytes.
        let start = out.len();
        *out = postcard::to_extend(value, std::mem::take(out)).map_err(|e| EncodeError {
            type_name: T::SCHEMA.name,
            reason: e.to_string(),
        })?;
        let prefix = out[start..].iter().take_while(|b| **b & 0x80 != 0).count() + 1;
        out.drain(start..start + prefix.min(out.len() - start));
        return Ok(());
    }
    if primitive_kind(T::SCHEMA).is_some() {
        if zcm::encode_serde_primitive(value, out) {
            return Ok(());
        }
        return Err(EncodeError {
            type_name: T::SCHEMA.name,
            reason: "it declares a primitive schema but does not serialize as one".into(),
        });
    }
    let start = out.len();
    out.extend_from_slice(&fingerprint_of::<T>().0);
    match postcard::to_extend(value, std::mem::take(out)) {
        Ok(buf) => {
            *out = buf;
            Ok(())
        }
        Err(e) => {
            out.truncate(start);
            Err(EncodeError {
                type_name: T::SCHEMA.name,
                reason: e.to_string(),
            })
        }
    }
}

/// A value that could not be encoded as a message of its type (the API
/// reports it as `pulicast::Error::Encode`).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("cannot encode a {type_name} message: {reason}")]
#[non_exhaustive]
pub struct EncodeError {
    /// The message type's name.
    pub type_name: &'static str,
    /// Why, for a person to read.
    pub reason: String,
}

/// Decodes a message payload into `T`, checking its fingerprint first.
pub fn decode_native<T: DeserializeOwned + Schema>(payload: &[u8]) -> Result<T, DecodeError> {
    let malformed = |e: &dyn std::fmt::Display| DecodeError::Malformed(e.to_string());
    if is_raw_bytes(T::SCHEMA) {
        // The whole payload, whatever it holds.
        type E = serde::de::value::Error;
        let bytes = serde::de::value::SeqDeserializer::<_, E>::new(payload.iter().copied());
        return T::deserialize(bytes).map_err(|e| malformed(&e));
    }
    if let Some(kind) = primitive_kind(T::SCHEMA) {
        type E = serde::de::value::Error;
        let result = match Primitive::decode_as(kind, payload)? {
            Primitive::Bool(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
            Primitive::Byte(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
            Primitive::I8(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
            Primitive::I16(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
            Primitive::I32(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
            Primitive::I64(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
            Primitive::Float(v) => {
                // float_msg carries a double; an f32 subscriber asked for single precision.
                T::deserialize(IntoDeserializer::<E>::into_deserializer(v as f32))
            }
            Primitive::Double(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
            Primitive::String(v) => T::deserialize(IntoDeserializer::<E>::into_deserializer(v)),
        };
        return result.map_err(|e| malformed(&e));
    }
    let mut r = Reader::new(payload);
    r.expect_fingerprint(fingerprint_of::<T>(), T::SCHEMA.name)?;
    let body = &payload[8..];
    let (value, rest) = postcard::take_from_bytes::<T>(body).map_err(|e| match e {
        postcard::Error::DeserializeUnexpectedEnd => DecodeError::Truncated {
            offset: payload.len(),
            needed: 1,
        },
        other => malformed(&other),
    })?;
    if !rest.is_empty() {
        return Err(DecodeError::TrailingBytes { count: rest.len() });
    }
    Ok(value)
}

#[cfg(test)]
mod tests {
    use serde::Deserialize;

    use super::*;

    #[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
    struct Pose {
        x: f64,
        y: f64,
        label: String,
    }

    #[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
    struct Meters(f64);

    #[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
    struct Seconds(f64);

    #[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
    struct Point {
        x: f64,
        y: f64,
        label: String,
    }

    #[test]
    fn fingerprints_tell_names_and_layouts_apart() {
        let all = [
            fingerprint_of::<Pose>(),
            fingerprint_of::<Point>(),
            fingerprint_of::<Meters>(),
            fingerprint_of::<Seconds>(),
            fingerprint_of::<(f64, f64)>(),
            fingerprint_of::<Vec<f64>>(),
            fingerprint_of::<Vec<f32>>(),
            fingerprint_of::<Option<f64>>(),
            fingerprint_of::<u32>(),
            fingerprint_of::<u64>(),
        ];
        for (i, a) in all.iter().enumerate() {
            for b in &all[i + 1..] {
                assert_ne!(a, b);
            }
        }
        // Computed at compile time, and stable across runs.
        const POSE: Fingerprint = fingerprint_of::<Pose>();
        assert_eq!(POSE, fingerprint_of::<Pose>());
    }

    #[test]
    fn native_round_trip_and_type_checks() {
        let pose = Pose {
            x: 1.0,
            y: -2.0,
            label: "base".into(),
        };
        let mut buf = Vec::new();
        encode_native(&pose, &mut buf).unwrap();
        assert_eq!(&buf[..8], &fingerprint_of::<Pose>().0);
        assert_eq!(decode_native::<Pose>(&buf).unwrap(), pose);
        assert!(matches!(
            decode_native::<Meters>(&buf),
            Err(DecodeError::WrongType { .. })
        ));
        assert!(matches!(
            decode_native::<String>(&buf),
            Err(DecodeError::WrongType { .. })
        ));
        for len in 0..buf.len() {
            assert!(decode_native::<Pose>(&buf[..len]).is_err(), "len {len}");
        }
        buf.push(0);
        assert_eq!(
            decode_native::<Pose>(&buf),
            Err(DecodeError::TrailingBytes { count: 1 })
        );
    }

    #[test]
    fn newtypes_are_native_and_primitives_are_zcm() {
        let mut buf = Vec::new();
        encode_native(&Meters(2.5), &mut buf).unwrap();
        assert_ne!(&buf[..8], &zcm::fingerprint::DOUBLE_MSG.0);
        assert_eq!(decode_native::<Meters>(&buf).unwrap(), Meters(2.5));

        buf.clear();
        encode_native(&2.5f64, &mut buf).unwrap();
        assert_eq!(&buf[..8], &zcm::fingerprint::DOUBLE_MSG.0);
        assert_eq!(decode_native::<f64>(&buf).unwrap(), 2.5);

        buf.clear();
        encode_native("text", &mut buf).unwrap();
        assert_eq!(decode_native::<String>(&buf).unwrap(), "text");
        assert!(decode_native::<i64>(&buf).is_err());

        for v in [i8::MIN, -1, 0, i8::MAX] {
            buf.clear();
            encode_native(&v, &mut buf).unwrap();
            assert_eq!(decode_native::<i8>(&buf).unwrap(), v);
        }
        buf.clear();
        encode_native(&true, &mut buf).unwrap();
        assert!(decode_native::<bool>(&buf).unwrap());
        buf.clear();
        encode_native(&7u8, &mut buf).unwrap();
        assert_eq!(decode_native::<u8>(&buf).unwrap(), 7);
        buf.clear();
        encode_native(&1.25f32, &mut buf).unwrap();
        assert_eq!(decode_native::<f32>(&buf).unwrap(), 1.25);
        buf.clear();
        encode_native(&u32::MAX, &mut buf).unwrap();
        assert_eq!(decode_native::<u32>(&buf).unwrap(), u32::MAX);
    }
}

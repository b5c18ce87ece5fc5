//! Every message has a text form: payloads decoded to JSON values for tools.
//!
//! A person exploring a fleet from a terminal sees values, not bytes, and can
//! carry what they see into code. [`decode_payload`] turns any payload into a
//! [`serde_json::Value`] and the name of its type:
//!
//! 1. native messages, from the type description discovery announces for the
//!    channel ([`TypeInfo`]), without compiling the type into the tool;
//! 2. the ZCM messages of Pulicast 2.x by their fingerprint: the primitives,
//!    and every struct the reference defines (`pulicast_node`, `ping`, ...);
//! 3. our discovery datagrams;
//! 4. anything else as its length and hex.
//!
//! Decoding never fails and never panics: what can't be decoded as the type it
//! claims falls through to the next rule, and finally to bytes.
//!
//! ```
//! use pulicast_proto::text::decode_payload;
//! use pulicast_proto::wire::zcm::Primitive;
//! let mut payload = Vec::new();
//! Primitive::String("Go LEFT!".into()).encode(&mut payload);
//! let decoded = decode_payload(&payload, None);
//! assert_eq!(decoded.type_name, "string_msg");
//! assert_eq!(decoded.value, "Go LEFT!");
//! ```

use postcard_schema::schema::owned::{
    OwnedDataModelType, OwnedDataModelVariant, OwnedNamedType, OwnedNamedValue,
};
use pulicast_discovery::wire::{Message as DiscoveryMessage, TypeEncoding, TypeInfo};
use serde_json::{json, Map, Value};

use crate::wire::zcm_types::{self, Dim, ZcmStruct, ZcmType};
use crate::wire::Fingerprint;

/// Largest type description decoded: descriptions arrive from the network,
/// and this bounds the recursion decoding one can cause.
pub const MAX_SCHEMA_BYTES: usize = 4096;

/// How deep a value may nest before decoding gives up.
const MAX_DEPTH: usize = 64;

/// A payload in text form.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// The type it was decoded as: a native type's name, a ZCM message name,
    /// `pulicast_discovery`, or `bytes`.
    pub type_name: String,
    /// The value.
    pub value: Value,
}

impl Decoded {
    fn bytes(payload: &[u8]) -> Self {
        Decoded {
            type_name: "bytes".into(),
            value: json!({ "len": payload.len(), "hex": hex(payload) }),
        }
    }
}

/// Decodes a payload for display; `hint` is the type discovery announced for
/// its channel, if any.
pub fn decode_payload(payload: &[u8], hint: Option<&TypeInfo>) -> Decoded {
    // The description is parsed only for a payload of its type.
    let fingerprint = Fingerprint::of_payload(payload).map(|f| f.0);
    let hint = hint.filter(|info| {
        info.encoding == TypeEncoding::Native && fingerprint == Some(info.fingerprint)
    });
    let schema = hint.and_then(schema_of);
    let hint = hint.zip(schema.as_ref());
    decode_typed(payload, hint).unwrap_or_else(|| Decoded::bytes(payload))
}

/// Decodes a payload as [`decode_payload`] does, with the announced type's
/// description parsed beforehand ([`schema_of`], once for many payloads);
/// `None` where `decode_payload` shows bytes: a payload of no type known
/// here, or one that does not fit its type.
pub fn decode_typed(payload: &[u8], hint: Option<(&TypeInfo, &OwnedNamedType)>) -> Option<Decoded> {
    let fingerprint = Fingerprint::of_payload(payload);
    if let Some((info, schema)) = hint {
        if info.encoding == TypeEncoding::Native
            && fingerprint.map(|f| f.0) == Some(info.fingerprint)
        {
            if let Some(value) = payload
                .get(8..)
                .and_then(|b| decode_native_value(schema, b))
            {
                return Some(Decoded {
                    type_name: info.name.clone(),
                    value,
                });
            }
        }
    }
    if let Some(def) = fingerprint.and_then(zcm_types::by_fingerprint) {
        if let Some(value) = payload.get(8..).and_then(|b| decode_zcm_struct(def, b)) {
            // The primitives are shown as their value, the way 2.x unwraps them.
            let value = match (def.members.len(), value) {
                (1, Value::Object(mut fields)) if def.name.ends_with("_msg") => {
                    fields.remove("value").unwrap_or(Value::Null)
                }
                (_, value) => value,
            };
            return Some(Decoded {
                type_name: def.name.into(),
                value,
            });
        }
    }
    if DiscoveryMessage::is_discovery(payload) {
        if let Ok(message) = DiscoveryMessage::decode(payload) {
            if let Ok(value) = serde_json::to_value(&message) {
                return Some(Decoded {
                    type_name: "pulicast_discovery".into(),
                    value,
                });
            }
        }
    }
    None
}

/// The type description carried in a [`TypeInfo`], if it decodes and
/// nests at most 64 levels deep (as deep as a value is decoded). A deeper
/// one is refused here, once, for everything that walks a description
/// recursively (decoding values, showing or serializing it): 4 KiB of
/// announcement nest two thousand levels deep, which overflows a thread's
/// stack when walked.
pub fn schema_of(info: &TypeInfo) -> Option<OwnedNamedType> {
    if info.schema.is_empty() || info.schema.len() > MAX_SCHEMA_BYTES {
        return None;
    }
    let schema: OwnedNamedType = postcard::from_bytes(&info.schema).ok()?;
    (depth_of(&schema) <= MAX_DEPTH).then_some(schema)
}

/// How deep a description nests (a primitive: 1), without recursion.
fn depth_of(t: &OwnedNamedType) -> usize {
    let mut deepest = 0;
    let mut todo = vec![(t, 1)];
    while let Some((t, depth)) = todo.pop() {
        deepest = deepest.max(depth);
        todo.extend(inner_types(t).into_iter().map(|inner| (inner, depth + 1)));
    }
    deepest
}

/// The descriptions one level inside `t`.
fn inner_types(t: &OwnedNamedType) -> Vec<&OwnedNamedType> {
    match &t.ty {
        OwnedDataModelType::Option(inner)
        | OwnedDataModelType::NewtypeStruct(inner)
        | OwnedDataModelType::Seq(inner) => vec![&**inner],
        OwnedDataModelType::Tuple(items) | OwnedDataModelType::TupleStruct(items) => {
            items.iter().collect()
        }
        OwnedDataModelType::Map { key, val } => vec![&**key, &**val],
        OwnedDataModelType::Struct(fields) => fields.iter().map(|f| &f.ty).collect(),
        OwnedDataModelType::Enum(variants) => variants
            .iter()
            .flat_map(|v| match &v.ty {
                OwnedDataModelVariant::UnitVariant => Vec::new(),
                OwnedDataModelVariant::NewtypeVariant(inner) => vec![&**inner],
                OwnedDataModelVariant::TupleVariant(items) => items.iter().collect(),
                OwnedDataModelVariant::StructVariant(fields) => {
                    fields.iter().map(|f| &f.ty).collect()
                }
            })
            .collect(),
        _ => Vec::new(),
    }
}

/// Decodes a postcard body (without fingerprint) by its type description.
/// `None` if the bytes don't fit the description exactly.
pub fn decode_native_value(schema: &OwnedNamedType, body: &[u8]) -> Option<Value> {
    let mut r = Cursor::new(body);
    let value = native(&mut r, schema, 0)?;
    (r.pos == body.len()).then_some(value)
}

/// Decodes a ZCM struct body (without fingerprint) by its definition.
pub fn decode_zcm_struct(def: &ZcmStruct, body: &[u8]) -> Option<Value> {
    let mut r = Cursor::new(body);
    let value = zcm(&mut r, def, 0)?;
    (r.pos == body.len()).then_some(value)
}

/// Most values a message may decode to that take no bytes of it (`()`,
/// an empty struct, a tuple of them). Every other value takes at least a
/// byte, so a message decodes to at most its length plus this many
/// values: without the bound, a description that is a list of tuples of
/// thousands of `()` makes a 64 KiB message billions of JSON values.
const MAX_ZERO_SIZED: usize = 1 << 16;

struct Cursor<'a> {
    buf: &'a [u8],
    pos: usize,
    /// Zero-sized values still allowed ([`MAX_ZERO_SIZED`]).
    zero_sized: usize,
}

impl<'a> Cursor<'a> {
    fn new(buf: &'a [u8]) -> Self {
        Self {
            buf,
            pos: 0,
            zero_sized: MAX_ZERO_SIZED,
        }
    }

    fn take(&mut self, n: usize) -> Option<&'a [u8]> {
        let end = self.pos.checked_add(n)?;
        let bytes = self.buf.get(self.pos..end)?;
        self.pos = end;
        Some(bytes)
    }

    fn array<const N: usize>(&mut self) -> Option<[u8; N]> {
        self.take(N)?.try_into().ok()
    }

    fn varint(&mut self) -> Option<u128> {
        let mut value: u128 = 0;
        for shift in (0..128).step_by(7) {
            let byte = *self.take(1)?.first()?;
            value |= u128::from(byte & 0x7f) << shift;
            if byte & 0x80 == 0 {
                return Some(value);
            }
        }
        None
    }

    fn zigzag(&mut self) -> Option<i128> {
        let v = self.varint()?;
        Some(((v >> 1) as i128) ^ -((v & 1) as i128))
    }

    /// A length that the remaining bytes could possibly hold.
    fn len(&mut self) -> Option<usize> {
        let n = usize::try_from(self.varint()?).ok()?;
        (n <= self.buf.len() - self.pos).then_some(n)
    }
}

fn big(v: i128) -> Value {
    i64::try_from(v)
        .map(Value::from)
        .unwrap_or_else(|_| Value::String(v.to_string()))
}

fn ubig(v: u128) -> Value {
    u64::try_from(v)
        .map(Value::from)
        .unwrap_or_else(|_| Value::String(v.to_string()))
}

fn float(v: f64) -> Value {
    serde_json::Number::from_f64(v)
        .map(Value::Number)
        .unwrap_or_else(|| Value::String(v.to_string()))
}

fn native(r: &mut Cursor<'_>, t: &OwnedNamedType, depth: usize) -> Option<Value> {
    if depth > MAX_DEPTH {
        return None;
    }
    let start = r.pos;
    let value = native_value(r, t, depth)?;
    if r.pos == start {
        r.zero_sized = r.zero_sized.checked_sub(1)?;
    }
    Some(value)
}

fn native_value(r: &mut Cursor<'_>, t: &OwnedNamedType, depth: usize) -> Option<Value> {
    let d = depth + 1;
    Some(match &t.ty {
        OwnedDataModelType::Bool => match r.take(1)?[0] {
            0 => Value::Bool(false),
            1 => Value::Bool(true),
            _ => return None,
        },
        OwnedDataModelType::I8 => Value::from(r.take(1)?[0] as i8),
        OwnedDataModelType::U8 => Value::from(r.take(1)?[0]),
        OwnedDataModelType::I16
        | OwnedDataModelType::I32
        | OwnedDataModelType::I64
        | OwnedDataModelType::I128
        | OwnedDataModelType::Isize => big(r.zigzag()?),
        OwnedDataModelType::U16
        | OwnedDataModelType::U32
        | OwnedDataModelType::U64
        | OwnedDataModelType::U128
        | OwnedDataModelType::Usize => ubig(r.varint()?),
        OwnedDataModelType::F32 => float(f64::from(f32::from_le_bytes(r.array()?))),
        OwnedDataModelType::F64 => float(f64::from_le_bytes(r.array()?)),
        OwnedDataModelType::Char | OwnedDataModelType::String => {
            let n = r.len()?;
            Value::String(std::str::from_utf8(r.take(n)?).ok()?.to_owned())
        }
        OwnedDataModelType::ByteArray => {
            let n = r.len()?;
            Value::String(hex(r.take(n)?))
        }
        OwnedDataModelType::Option(inner) => match r.take(1)?[0] {
            0 => Value::Null,
            1 => native(r, inner, d)?,
            _ => return None,
        },
        OwnedDataModelType::Unit | OwnedDataModelType::UnitStruct => Value::Null,
        OwnedDataModelType::NewtypeStruct(inner) => native(r, inner, d)?,
        OwnedDataModelType::Seq(inner) => {
            let n = r.len()?;
            let mut items = Vec::with_capacity(n.min(1024));
            for _ in 0..n {
                items.push(native(r, inner, d)?);
            }
            Value::Array(items)
        }
        OwnedDataModelType::Tuple(items) | OwnedDataModelType::TupleStruct(items) => Value::Array(
            items
                .iter()
                .map(|t| native(r, t, d))
                .collect::<Option<_>>()?,
        ),
        OwnedDataModelType::Map { key, val } => {
            let n = r.len()?;
            let mut pairs = Vec::with_capacity(n.min(1024));
            for _ in 0..n {
                pairs.push((native(r, key, d)?, native(r, val, d)?));
            }
            if pairs.iter().all(|(k, _)| k.is_string()) {
                let map: Map<String, Value> = pairs
                    .into_iter()
                    .filter_map(|(k, v)| Some((k.as_str()?.to_owned(), v)))
                    .collect();
                Value::Object(map)
            } else {
                Value::Array(pairs.into_iter().map(|(k, v)| json!([k, v])).collect())
            }
        }
        OwnedDataModelType::Struct(fields) => fields_of(r, fields, d)?,
        OwnedDataModelType::Enum(variants) => {
            let index = usize::try_from(r.varint()?).ok()?;
            let variant = variants.get(index)?;
            let content = match &variant.ty {
                OwnedDataModelVariant::UnitVariant => {
                    return Some(Value::String(variant.name.clone()))
                }
                OwnedDataModelVariant::NewtypeVariant(inner) => native(r, inner, d)?,
                OwnedDataModelVariant::TupleVariant(items) => Value::Array(
                    items
                        .iter()
                        .map(|t| native(r, t, d))
                        .collect::<Option<_>>()?,
                ),
                OwnedDataModelVariant::StructVariant(fields) => fields_of(r, fields, d)?,
            };
            json!({ variant.name.clone(): content })
        }
        OwnedDataModelType::Schema => return None,
    })
}

fn fields_of(r: &mut Cursor<'_>, fields: &[OwnedNamedValue], depth: usize) -> Option<Value> {
    let mut map = Map::new();
    for field in fields {
        map.insert(field.name.clone(), native(r, &field.ty, depth)?);
    }
    Some(Value::Object(map))
}

fn zcm(r: &mut Cursor<'_>, def: &ZcmStruct, depth: usize) -> Option<Value> {
    if depth > MAX_DEPTH {
        return None;
    }
    let mut map = Map::new();
    for member in def.members {
        let value = match member.dims {
            [] => zcm_scalar(r, member.ty, depth)?,
            [dim] => {
                let n = match dim {
                    Dim::Fixed(n) => *n,
                    Dim::Variable(by) => {
                        let n = map.get(*by)?.as_i64()?;
                        usize::try_from(n).ok()?
                    }
                };
                if n > r.buf.len() - r.pos {
                    return None;
                }
                if member.ty == ZcmType::Primitive("byte") {
                    Value::String(hex(r.take(n)?))
                } else {
                    let mut items = Vec::with_capacity(n.min(1024));
                    for _ in 0..n {
                        items.push(zcm_scalar(r, member.ty, depth)?);
                    }
                    Value::Array(items)
                }
            }
            // No reference type has more than one dimension.
            _ => return None,
        };
        map.insert(member.name.into(), value);
    }
    Some(Value::Object(map))
}

fn zcm_scalar(r: &mut Cursor<'_>, ty: ZcmType, depth: usize) -> Option<Value> {
    Some(match ty {
        ZcmType::Struct(def) => zcm(r, def, depth + 1)?,
        ZcmType::Primitive(name) => match name {
            "boolean" => match r.take(1)?[0] {
                0 => Value::Bool(false),
                1 => Value::Bool(true),
                _ => return None,
            },
            "byte" => Value::from(r.take(1)?[0]),
            "int8_t" => Value::from(r.take(1)?[0] as i8),
            "int16_t" => Value::from(i16::from_be_bytes(r.array()?)),
            "int32_t" => Value::from(i32::from_be_bytes(r.array()?)),
            "int64_t" => Value::from(i64::from_be_bytes(r.array()?)),
            "float" => float(f64::from(f32::from_be_bytes(r.array()?))),
            "double" => float(f64::from_be_bytes(r.array()?)),
            "string" => {
                let n = usize::try_from(u32::from_be_bytes(r.array()?)).ok()?;
                let bytes = r.take(n)?;
                let (text, nul) = bytes.split_at(n.checked_sub(1)?);
                if nul != [0] {
                    return None;
                }
                Value::String(String::from_utf8_lossy(text).into_owned())
            }
            _ => return None,
        },
    })
}

/// Why a JSON value does not fit a type description.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{path}: {problem}")]
pub struct ValueError {
    /// Where in the value: `.pose.x`, `[3]`, or `value` at the top.
    pub path: String,
    /// What is wrong there.
    pub problem: String,
}

/// Encodes a JSON value as a native message of the described type
/// (fingerprint included): the text form, back into bytes, so what a person
/// types reaches a typed subscriber.
pub fn encode_native_value(
    schema: &OwnedNamedType,
    fingerprint: [u8; 8],
    value: &Value,
) -> Result<Vec<u8>, ValueError> {
    let mut out = fingerprint.to_vec();
    encode_value(&mut out, schema, value, "value", 0)?;
    Ok(out)
}

fn fail<T>(path: &str, problem: impl Into<String>) -> Result<T, ValueError> {
    Err(ValueError {
        path: path.to_string(),
        problem: problem.into(),
    })
}

fn varint(out: &mut Vec<u8>, mut v: u128) {
    loop {
        let byte = (v & 0x7f) as u8;
        v >>= 7;
        if v == 0 {
            out.push(byte);
            return;
        }
        out.push(byte | 0x80);
    }
}

fn int_of(v: &Value, path: &str, min: i128, max: i128) -> Result<i128, ValueError> {
    let n = match v {
        Value::Number(n) => n
            .as_i64()
            .map(i128::from)
            .or_else(|| n.as_u64().map(i128::from))
            .or_else(|| {
                n.as_f64()
                    .filter(|f| f.fract() == 0.0 && f.abs() < 1e30)
                    .map(|f| f as i128)
            }),
        Value::String(s) => s.parse::<i128>().ok(),
        _ => None,
    };
    match n {
        Some(n) if (min..=max).contains(&n) => Ok(n),
        Some(n) => fail(path, format!("{n} is out of range {min}..={max}")),
        None => fail(path, format!("expected an integer, got {v}")),
    }
}

fn uint_of(v: &Value, path: &str, max: u128) -> Result<u128, ValueError> {
    if let Value::String(s) = v {
        if let Ok(n) = s.parse::<u128>() {
            return if n <= max {
                Ok(n)
            } else {
                fail(path, format!("{n} is above {max}"))
            };
        }
    }
    // Below zero, the range said is the type's own, not i128's.
    let n = int_of(v, path, 0, i128::try_from(max).unwrap_or(i128::MAX))?;
    let n = n as u128;
    if n <= max {
        Ok(n)
    } else {
        fail(path, format!("{n} is above {max}"))
    }
}

fn encode_value(
    out: &mut Vec<u8>,
    t: &OwnedNamedType,
    v: &Value,
    path: &str,
    depth: usize,
) -> Result<(), ValueError> {
    if depth > MAX_DEPTH {
        return fail(path, "nested too deeply");
    }
    let d = depth + 1;
    match &t.ty {
        OwnedDataModelType::Bool => match v {
            Value::Bool(b) => out.push(u8::from(*b)),
            _ => return fail(path, format!("expected true or false, got {v}")),
        },
        OwnedDataModelType::I8 => {
            out.push(int_of(v, path, i128::from(i8::MIN), i128::from(i8::MAX))? as i8 as u8)
        }
        OwnedDataModelType::U8 => out.push(uint_of(v, path, u128::from(u8::MAX))? as u8),
        OwnedDataModelType::I16
        | OwnedDataModelType::I32
        | OwnedDataModelType::I64
        | OwnedDataModelType::Isize
        | OwnedDataModelType::I128 => {
            let (min, max) = match &t.ty {
                OwnedDataModelType::I16 => (i128::from(i16::MIN), i128::from(i16::MAX)),
                OwnedDataModelType::I32 => (i128::from(i32::MIN), i128::from(i32::MAX)),
                OwnedDataModelType::I128 => (i128::MIN, i128::MAX),
                _ => (i128::from(i64::MIN), i128::from(i64::MAX)),
            };
            let n = int_of(v, path, min, max)?;
            varint(out, ((n << 1) ^ (n >> 127)) as u128);
        }
        OwnedDataModelType::U16
        | OwnedDataModelType::U32
        | OwnedDataModelType::U64
        | OwnedDataModelType::Usize
        | OwnedDataModelType::U128 => {
            let max = match &t.ty {
                OwnedDataModelType::U16 => u128::from(u16::MAX),
                OwnedDataModelType::U32 => u128::from(u32::MAX),
                OwnedDataModelType::U128 => u128::MAX,
                _ => u128::from(u64::MAX),
            };
            varint(out, uint_of(v, path, max)?);
        }
        OwnedDataModelType::F32 | OwnedDataModelType::F64 => {
            let Some(f) = v.as_f64() else {
                return fail(path, format!("expected a number, got {v}"));
            };
            if matches!(t.ty, OwnedDataModelType::F32) {
                out.extend_from_slice(&(f as f32).to_le_bytes());
            } else {
                out.extend_from_slice(&f.to_le_bytes());
            }
        }
        OwnedDataModelType::Char | OwnedDataModelType::String => {
            let Value::String(s) = v else {
                return fail(path, format!("expected a string, got {v}"));
            };
            if matches!(t.ty, OwnedDataModelType::Char) && s.chars().count() != 1 {
                return fail(path, format!("expected one character, got {s:?}"));
            }
            varint(out, s.len() as u128);
            out.extend_from_slice(s.as_bytes());
        }
        OwnedDataModelType::ByteArray => {
            let bytes = match v {
                Value::String(s) => unhex(s).ok_or_else(|| ValueError {
                    path: path.into(),
                    problem: format!("expected hex bytes, got {s:?}"),
                })?,
                Value::Array(items) => items
                    .iter()
                    .enumerate()
                    .map(|(i, x)| uint_of(x, &format!("{path}[{i}]"), 255).map(|b| b as u8))
                    .collect::<Result<_, _>>()?,
                _ => return fail(path, format!("expected hex bytes, got {v}")),
            };
            varint(out, bytes.len() as u128);
            out.extend_from_slice(&bytes);
        }
        OwnedDataModelType::Option(inner) => {
            if v.is_null() {
                out.push(0);
            } else {
                out.push(1);
                encode_value(out, inner, v, path, d)?;
            }
        }
        OwnedDataModelType::Unit | OwnedDataModelType::UnitStruct => {}
        OwnedDataModelType::NewtypeStruct(inner) => encode_value(out, inner, v, path, d)?,
        OwnedDataModelType::Seq(inner) => {
            let Value::Array(items) = v else {
                return fail(path, format!("expected an array, got {v}"));
            };
            varint(out, items.len() as u128);
            for (i, item) in items.iter().enumerate() {
                encode_value(out, inner, item, &format!("{path}[{i}]"), d)?;
            }
        }
        OwnedDataModelType::Tuple(types) | OwnedDataModelType::TupleStruct(types) => {
            let Value::Array(items) = v else {
                return fail(
                    path,
                    format!("expected an array of {}, got {v}", types.len()),
                );
            };
            if items.len() != types.len() {
                return fail(
                    path,
                    format!("expected {} items, got {}", types.len(), items.len()),
                );
            }
            for (i, (item, t)) in items.iter().zip(types).enumerate() {
                encode_value(out, t, item, &format!("{path}[{i}]"), d)?;
            }
        }
        OwnedDataModelType::Map { key, val } => {
            let pairs: Vec<(Value, &Value)> = match v {
                Value::Object(map) => map
                    .iter()
                    .map(|(k, v)| (Value::String(k.clone()), v))
                    .collect(),
                Value::Array(items) => items
                    .iter()
                    .map(|p| match p.as_array().map(Vec::as_slice) {
                        Some([k, v]) => Ok((k.clone(), v)),
                        _ => fail(path, "expected [key, value] pairs"),
                    })
                    .collect::<Result<_, _>>()?,
                _ => return fail(path, format!("expected an object, got {v}")),
            };
            varint(out, pairs.len() as u128);
            for (k, v) in pairs {
                let p = format!("{path}[{k}]");
                encode_value(out, key, &k, &p, d)?;
                encode_value(out, val, v, &p, d)?;
            }
        }
        OwnedDataModelType::Struct(fields) => encode_fields(out, fields, v, path, d)?,
        OwnedDataModelType::Enum(variants) => {
            let (name, content) = match v {
                Value::String(name) => (name.as_str(), &Value::Null),
                Value::Object(map) if map.len() == 1 => {
                    let Some((name, content)) = map.iter().next() else {
                        return fail(path, "expected one variant");
                    };
                    (name.as_str(), content)
                }
                _ => {
                    return fail(
                        path,
                        format!("expected \"Variant\" or {{\"Variant\": ...}}, got {v}"),
                    )
                }
            };
            let Some(index) = variants.iter().position(|x| x.name == name) else {
                let known: Vec<&str> = variants.iter().map(|x| x.name.as_str()).collect();
                return fail(
                    path,
                    format!("no variant {name:?}; variants: {}", known.join(", ")),
                );
            };
            varint(out, index as u128);
            let p = format!("{path}.{name}");
            match &variants[index].ty {
                OwnedDataModelVariant::UnitVariant => {}
                OwnedDataModelVariant::NewtypeVariant(inner) => {
                    encode_value(out, inner, content, &p, d)?
                }
                OwnedDataModelVariant::TupleVariant(types) => {
                    let tuple = OwnedNamedType {
                        name: name.to_string(),
                        ty: OwnedDataModelType::Tuple(types.clone()),
                    };
                    encode_value(out, &tuple, content, &p, d)?;
                }
                OwnedDataModelVariant::StructVariant(fields) => {
                    encode_fields(out, fields, content, &p, d)?
                }
            }
        }
        OwnedDataModelType::Schema => return fail(path, "schema values can't be typed in"),
    }
    Ok(())
}

fn encode_fields(
    out: &mut Vec<u8>,
    fields: &[OwnedNamedValue],
    v: &Value,
    path: &str,
    depth: usize,
) -> Result<(), ValueError> {
    let Value::Object(map) = v else {
        return fail(path, format!("expected an object, got {v}"));
    };
    if let Some(unknown) = map.keys().find(|k| !fields.iter().any(|f| &f.name == *k)) {
        let known: Vec<&str> = fields.iter().map(|f| f.name.as_str()).collect();
        return fail(
            path,
            format!("unknown field {unknown:?}; fields: {}", known.join(", ")),
        );
    }
    for field in fields {
        let p = format!("{path}.{}", field.name);
        match map.get(&field.name) {
            Some(value) => encode_value(out, &field.ty, value, &p, depth)?,
            // A missing optional field is None; anything else must be given.
            None if matches!(field.ty.ty, OwnedDataModelType::Option(_)) => out.push(0),
            None => return fail(&p, "missing"),
        }
    }
    Ok(())
}

/// Bytes from hex (an optional `0x` prefix, no separators).
pub fn unhex(s: &str) -> Option<Vec<u8>> {
    let s = s.strip_prefix("0x").unwrap_or(s);
    if s.len() % 2 != 0 {
        return None;
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok())
        .collect()
}

/// Lower-case hex of bytes.
pub fn hex(bytes: &[u8]) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut out = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        out.push(char::from(DIGITS[usize::from(b >> 4)]));
        out.push(char::from(DIGITS[usize::from(b & 0xf)]));
    }
    out
}

/// The longest prefix of `text` of at most `max` bytes that ends on a
/// character boundary: text from the network or a handler, bounded for a
/// frame or a log line.
///
/// ```
/// assert_eq!(pulicast_proto::text::cut("héllo", 2), "h");
/// assert_eq!(pulicast_proto::text::cut("hi", 8), "hi");
/// ```
pub fn cut(text: &str, max: usize) -> &str {
    let mut end = text.len().min(max);
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    &text[..end]
}

/// The JSON Schema (draft 2020-12) of a native type's messages in JSON:
/// what [`decode_native_value`] makes of them, and what
/// [`encode_native_value`] takes. A form or a viewer (Foxglove's
/// `jsonschema` channels) builds its fields from it.
///
/// Integers carry their type's bounds; 128-bit ones may also be strings
/// of digits, as they are shown beyond 64 bits. Floats are numbers (a NaN
/// or an infinity is shown as a string, and can't be sent). Byte arrays
/// are lower-case hex. A struct is an object with exactly its fields; an
/// enum's unit variant is its name, any other variant an object of one
/// key. Named types carry their name as `title`. A description nested
/// deeper than any value is decoded gets `{}` (anything) below that depth.
pub fn json_schema(t: &OwnedNamedType) -> Value {
    schema_node(t, 0)
}

/// The JSON Schema of the messages of an announced type, as
/// [`decode_payload`] shows them: a native type's by its description
/// ([`json_schema`]), a 2.x primitive's as its value, another ZCM type
/// known here as an object of its members. `None` for a native type whose
/// description does not decode, or a ZCM type not known here.
pub fn json_schema_of(info: &TypeInfo) -> Option<Value> {
    match info.encoding {
        TypeEncoding::Native => schema_of(info).map(|s| json_schema(&s)),
        TypeEncoding::Zcm => {
            let def = zcm_types::by_fingerprint(Fingerprint(info.fingerprint))?;
            let mut schema = match def.members {
                // The primitives are shown as their value (decode_payload).
                [only] if def.name.ends_with("_msg") && only.dims.is_empty() => {
                    zcm_member_schema(only.ty, 0)
                }
                _ => zcm_schema(def, 0),
            };
            titled(&mut schema, def.name);
            Some(schema)
        }
    }
}

fn titled(schema: &mut Value, name: &str) {
    if let Value::Object(map) = schema {
        map.insert("title".into(), Value::String(name.into()));
    }
}

fn int_schema(min: impl Into<Value>, max: impl Into<Value>) -> Value {
    json!({ "type": "integer", "minimum": min.into(), "maximum": max.into() })
}

fn schema_node(t: &OwnedNamedType, depth: usize) -> Value {
    if depth > MAX_DEPTH {
        return json!({});
    }
    let d = depth + 1;
    let fields = |fields: &[OwnedNamedValue]| {
        let properties: Map<String, Value> = fields
            .iter()
            .map(|f| (f.name.clone(), schema_node(&f.ty, d)))
            .collect();
        let required: Vec<Value> = fields
            .iter()
            .map(|f| Value::String(f.name.clone()))
            .collect();
        json!({
            "type": "object",
            "properties": properties,
            "required": required,
            "additionalProperties": false,
        })
    };
    let tuple = |items: &[OwnedNamedType]| {
        let prefix: Vec<Value> = items.iter().map(|t| schema_node(t, d)).collect();
        json!({
            "type": "array",
            "prefixItems": prefix,
            "minItems": items.len(),
            "maxItems": items.len(),
        })
    };
    let mut schema = match &t.ty {
        OwnedDataModelType::Bool => json!({ "type": "boolean" }),
        OwnedDataModelType::I8 => int_schema(i8::MIN, i8::MAX),
        OwnedDataModelType::U8 => int_schema(u8::MIN, u8::MAX),
        OwnedDataModelType::I16 => int_schema(i16::MIN, i16::MAX),
        OwnedDataModelType::U16 => int_schema(u16::MIN, u16::MAX),
        OwnedDataModelType::I32 => int_schema(i32::MIN, i32::MAX),
        OwnedDataModelType::U32 => int_schema(u32::MIN, u32::MAX),
        OwnedDataModelType::I64 | OwnedDataModelType::Isize => int_schema(i64::MIN, i64::MAX),
        OwnedDataModelType::U64 | OwnedDataModelType::Usize => int_schema(u64::MIN, u64::MAX),
        OwnedDataModelType::I128 => json!({
            "anyOf": [{ "type": "integer" }, { "type": "string", "pattern": "^-?[0-9]+$" }]
        }),
        OwnedDataModelType::U128 => json!({
            "anyOf": [
                { "type": "integer", "minimum": 0 },
                { "type": "string", "pattern": "^[0-9]+$" }
            ]
        }),
        OwnedDataModelType::F32 | OwnedDataModelType::F64 => json!({ "type": "number" }),
        OwnedDataModelType::Char => json!({ "type": "string", "minLength": 1, "maxLength": 1 }),
        OwnedDataModelType::String => json!({ "type": "string" }),
        OwnedDataModelType::ByteArray => {
            json!({ "type": "string", "pattern": "^([0-9a-f]{2})*$", "contentEncoding": "base16" })
        }
        OwnedDataModelType::Option(inner) => {
            json!({ "anyOf": [{ "type": "null" }, schema_node(inner, d)] })
        }
        OwnedDataModelType::Unit | OwnedDataModelType::UnitStruct => json!({ "type": "null" }),
        OwnedDataModelType::NewtypeStruct(inner) => schema_node(inner, d),
        OwnedDataModelType::Seq(inner) => {
            json!({ "type": "array", "items": schema_node(inner, d) })
        }
        OwnedDataModelType::Tuple(items) | OwnedDataModelType::TupleStruct(items) => tuple(items),
        OwnedDataModelType::Map { key, val } => match key.ty {
            // Shown as an object when every key is a string.
            OwnedDataModelType::String | OwnedDataModelType::Char => {
                json!({ "type": "object", "additionalProperties": schema_node(val, d) })
            }
            _ => json!({
                "type": "array",
                "items": {
                    "type": "array",
                    "prefixItems": [schema_node(key, d), schema_node(val, d)],
                    "minItems": 2,
                    "maxItems": 2,
                }
            }),
        },
        OwnedDataModelType::Struct(f) => fields(f),
        OwnedDataModelType::Enum(variants) => {
            let one_of: Vec<Value> = variants
                .iter()
                .map(|v| {
                    let content = match &v.ty {
                        OwnedDataModelVariant::UnitVariant => {
                            return json!({ "const": v.name.clone() });
                        }
                        OwnedDataModelVariant::NewtypeVariant(inner) => schema_node(inner, d),
                        OwnedDataModelVariant::TupleVariant(items) => tuple(items),
                        OwnedDataModelVariant::StructVariant(f) => fields(f),
                    };
                    json!({
                        "type": "object",
                        "properties": { v.name.clone(): content },
                        "required": [v.name.clone()],
                        "additionalProperties": false,
                    })
                })
                .collect();
            json!({ "oneOf": one_of })
        }
        // Never sent as a message.
        OwnedDataModelType::Schema => json!({}),
    };
    let named = matches!(
        t.ty,
        OwnedDataModelType::Struct(_)
            | OwnedDataModelType::Enum(_)
            | OwnedDataModelType::NewtypeStruct(_)
            | OwnedDataModelType::TupleStruct(_)
            | OwnedDataModelType::UnitStruct
    );
    if named {
        titled(&mut schema, &t.name);
    }
    schema
}

fn zcm_schema(def: &ZcmStruct, depth: usize) -> Value {
    if depth > MAX_DEPTH {
        return json!({});
    }
    let properties: Map<String, Value> = def
        .members
        .iter()
        .map(|m| {
            let schema = match m.dims {
                [] => zcm_member_schema(m.ty, depth),
                // Byte arrays are shown as hex, other arrays as arrays.
                _ if m.ty == ZcmType::Primitive("byte") => {
                    json!({ "type": "string", "pattern": "^([0-9a-f]{2})*$", "contentEncoding": "base16" })
                }
                [Dim::Fixed(n)] => json!({
                    "type": "array",
                    "items": zcm_member_schema(m.ty, depth),
                    "minItems": n,
                    "maxItems": n,
                }),
                _ => json!({ "type": "array", "items": zcm_member_schema(m.ty, depth) }),
            };
            (m.name.to_string(), schema)
        })
        .collect();
    let required: Vec<Value> = def
        .members
        .iter()
        .map(|m| Value::String(m.name.into()))
        .collect();
    json!({
        "type": "object",
        "properties": properties,
        "required": required,
        "additionalProperties": false,
    })
}

fn zcm_member_schema(ty: ZcmType, depth: usize) -> Value {
    match ty {
        ZcmType::Struct(def) => {
            let mut schema = zcm_schema(def, depth + 1);
            titled(&mut schema, def.name);
            schema
        }
        ZcmType::Primitive(name) => match name {
            "boolean" => json!({ "type": "boolean" }),
            "byte" => int_schema(u8::MIN, u8::MAX),
            "int8_t" => int_schema(i8::MIN, i8::MAX),
            "int16_t" => int_schema(i16::MIN, i16::MAX),
            "int32_t" => int_schema(i32::MIN, i32::MAX),
            "int64_t" => int_schema(i64::MIN, i64::MAX),
            "float" | "double" => json!({ "type": "number" }),
            "string" => json!({ "type": "string" }),
            _ => json!({}),
        },
    }
}

#[cfg(test)]
mod tests {
    use serde::{Deserialize, Serialize};

    use super::*;
    use crate::wire::zcm::{self, Primitive};
    use crate::wire::{encode_native, type_info_of};
    use postcard_schema::Schema;

    #[derive(Serialize, Deserialize, Schema)]
    enum Mode {
        Idle,
        Drive { speed: f32 },
        Turn(i16),
    }

    #[derive(Serialize, Deserialize, Schema)]
    struct Pose {
        x: f64,
        label: String,
        path: Vec<(i32, u64)>,
        mode: Mode,
        spare: Option<u8>,
        raw: Vec<u8>,
        big: u128,
        tags: std::collections::BTreeMap<String, bool>,
    }

    #[test]
    fn native_messages_decode_from_their_announced_schema() {
        let pose = Pose {
            x: 1.5,
            label: "base".into(),
            path: vec![(-1, 2), (3, u64::MAX)],
            mode: Mode::Drive { speed: 0.5 },
            spare: None,
            raw: vec![0xca, 0xfe],
            big: u128::MAX,
            tags: [("up".to_string(), true)].into(),
        };
        let mut payload = Vec::new();
        encode_native(&pose, &mut payload).unwrap();
        let info = type_info_of::<Pose>();
        let decoded = decode_payload(&payload, Some(&info));
        assert_eq!(decoded.type_name, "Pose");
        assert_eq!(
            decoded.value,
            json!({
                "x": 1.5, "label": "base", "path": [[-1, 2], [3, u64::MAX]],
                "mode": {"Drive": {"speed": 0.5}}, "spare": null, "raw": [0xca, 0xfe],
                "big": u128::MAX.to_string(), "tags": {"up": true}
            })
        );
        // Without the description it is bytes; with a wrong one too.
        assert_eq!(decode_payload(&payload, None).type_name, "bytes");
        let other = type_info_of::<Mode>();
        assert_eq!(decode_payload(&payload, Some(&other)).type_name, "bytes");
        // Every truncation falls back to bytes, never panics.
        for len in 0..payload.len() {
            assert_eq!(
                decode_payload(&payload[..len], Some(&info)).type_name,
                "bytes"
            );
        }
    }

    #[test]
    fn json_encodes_back_into_the_same_bytes() {
        let pose = Pose {
            x: -2.5,
            label: "dock".into(),
            path: vec![(7, 8)],
            mode: Mode::Turn(-3),
            spare: Some(9),
            raw: vec![1, 2],
            big: 1 << 100,
            tags: [("a".to_string(), false)].into(),
        };
        let info = type_info_of::<Pose>();
        let schema = schema_of(&info).unwrap();
        let mut expected = Vec::new();
        encode_native(&pose, &mut expected).unwrap();
        let text = decode_payload(&expected, Some(&info)).value;
        let again = encode_native_value(&schema, info.fingerprint, &text).unwrap();
        assert_eq!(again, expected);
        // Mistakes say where and what.
        let mut wrong = text.clone();
        wrong["path"][0][0] = json!("seven");
        let err = encode_native_value(&schema, info.fingerprint, &wrong).unwrap_err();
        assert_eq!(err.path, "value.path[0][0]");
        let mut wrong = text.clone();
        wrong["mode"] = json!("Fly");
        let err = encode_native_value(&schema, info.fingerprint, &wrong).unwrap_err();
        assert!(err.problem.contains("Idle, Drive, Turn"), "{err}");
        // Out of range: the range of the field's own type.
        let mut wrong = text.clone();
        wrong["path"][0][1] = json!(-1);
        let err = encode_native_value(&schema, info.fingerprint, &wrong).unwrap_err();
        assert_eq!(err.problem, "-1 is out of range 0..=18446744073709551615");
        wrong["path"][0][1] = json!(7);
        wrong["spare"] = json!(256);
        let err = encode_native_value(&schema, info.fingerprint, &wrong).unwrap_err();
        assert_eq!(
            (err.path.as_str(), err.problem.as_str()),
            ("value.spare", "256 is out of range 0..=255")
        );
        let mut wrong = text;
        wrong.as_object_mut().unwrap().remove("x");
        assert_eq!(
            encode_native_value(&schema, info.fingerprint, &wrong)
                .unwrap_err()
                .path,
            "value.x"
        );
    }

    /// A 2.x heartbeat, a ZCM struct with nested structs and an array.
    fn heartbeat() -> pulicast_discovery::compat::Heartbeat {
        pulicast_discovery::compat::Heartbeat {
            name: "rover".into(),
            session_id: 5,
            channels: vec![pulicast_discovery::compat::ChannelAnnouncement {
                name: "__nodes".into(),
                period_ns: 100,
                is_published: true,
                is_subscribed: false,
            }],
        }
    }

    /// Whether `v` conforms to `schema`, for the keywords `json_schema`
    /// uses (a checker of the test's own: no validator crate).
    fn conforms(v: &Value, schema: &Value) -> bool {
        let Some(s) = schema.as_object() else {
            return false;
        };
        if let Some(any) = s.get("anyOf").and_then(Value::as_array) {
            return any.iter().any(|x| conforms(v, x));
        }
        if let Some(one) = s.get("oneOf").and_then(Value::as_array) {
            return one.iter().filter(|x| conforms(v, x)).count() == 1;
        }
        if let Some(c) = s.get("const") {
            return v == c;
        }
        match s.get("type").and_then(Value::as_str) {
            None => true,
            Some("null") => v.is_null(),
            Some("boolean") => v.is_boolean(),
            Some("number") => v.is_number(),
            Some("string") => v.is_string(),
            Some("integer") => {
                let (Some(x), min, max) = (
                    v.as_i64().map(i128::from).or(v.as_u64().map(i128::from)),
                    s.get("minimum")
                        .and_then(|m| m.as_i64().map(i128::from).or(m.as_u64().map(i128::from))),
                    s.get("maximum")
                        .and_then(|m| m.as_i64().map(i128::from).or(m.as_u64().map(i128::from))),
                ) else {
                    return false;
                };
                min.is_none_or(|m| x >= m) && max.is_none_or(|m| x <= m)
            }
            Some("array") => {
                let Some(items) = v.as_array() else {
                    return false;
                };
                let n = items.len() as u64;
                if s.get("minItems")
                    .and_then(Value::as_u64)
                    .is_some_and(|m| n < m)
                    || s.get("maxItems")
                        .and_then(Value::as_u64)
                        .is_some_and(|m| n > m)
                {
                    return false;
                }
                let prefix = s.get("prefixItems").and_then(Value::as_array);
                items
                    .iter()
                    .enumerate()
                    .all(|(i, item)| match prefix.and_then(|p| p.get(i)) {
                        Some(p) => conforms(item, p),
                        None => s.get("items").is_none_or(|each| conforms(item, each)),
                    })
            }
            Some("object") => {
                let Some(map) = v.as_object() else {
                    return false;
                };
                let properties = s.get("properties").and_then(Value::as_object);
                let required = s.get("required").and_then(Value::as_array);
                let closed = s.get("additionalProperties") == Some(&Value::Bool(false));
                let extra = s.get("additionalProperties").filter(|x| x.is_object());
                required.is_none_or(|r| {
                    r.iter()
                        .all(|k| k.as_str().is_some_and(|k| map.contains_key(k)))
                }) && map
                    .iter()
                    .all(|(k, x)| match properties.and_then(|p| p.get(k)) {
                        Some(p) => conforms(x, p),
                        None => !closed && extra.is_none_or(|e| conforms(x, e)),
                    })
            }
            Some(_) => false,
        }
    }

    #[test]
    fn the_json_schema_describes_what_decoding_shows() {
        let pose = Pose {
            x: 1.5,
            label: "base".into(),
            path: vec![(-1, 2), (3, u64::MAX)],
            mode: Mode::Turn(-3),
            spare: Some(7),
            raw: vec![0xca, 0xfe],
            big: u128::MAX,
            tags: [("up".to_string(), true)].into(),
        };
        let mut payload = Vec::new();
        encode_native(&pose, &mut payload).unwrap();
        let info = type_info_of::<Pose>();
        let schema = json_schema_of(&info).unwrap();
        assert_eq!(schema["title"], "Pose");
        let shown = decode_payload(&payload, Some(&info)).value;
        assert!(conforms(&shown, &schema), "{shown} against {schema}");
        for mode in [
            json!("Idle"),
            json!({"Drive": {"speed": 0.25}}),
            json!({"Turn": 5}),
        ] {
            let mut v = shown.clone();
            v["mode"] = mode;
            assert!(conforms(&v, &schema), "{v}");
        }
        // What does not decode does not conform either.
        for (field, bad) in [
            ("x", json!("fast")),
            ("spare", json!(256)),
            ("path", json!([[1, 2, 3]])),
            ("mode", json!("Sideways")),
            ("mode", json!({"Turn": 40000})),
            ("tags", json!({"up": 1})),
        ] {
            let mut v = shown.clone();
            v[field] = bad;
            assert!(!conforms(&v, &schema), "{v} conforms");
            let schema_of_pose = schema_of(&info).unwrap();
            let fingerprint = info.fingerprint;
            assert!(
                encode_native_value(&schema_of_pose, fingerprint, &v).is_err(),
                "{v} encodes"
            );
        }
        let mut v = shown.clone();
        v.as_object_mut().unwrap().remove("label");
        assert!(!conforms(&v, &schema));
        v["label"] = json!("x");
        v["unknown"] = json!(1);
        assert!(!conforms(&v, &schema));
    }

    #[test]
    fn the_json_schema_of_2x_types_and_hostile_descriptions() {
        let int = json_schema_of(&TypeInfo {
            encoding: TypeEncoding::Zcm,
            name: "int64_msg".into(),
            fingerprint: zcm_types::INT64_MSG.fingerprint().0,
            schema: Vec::new(),
        })
        .unwrap();
        assert_eq!(
            (int["type"].as_str(), int["title"].as_str()),
            (Some("integer"), Some("int64_msg"))
        );
        let mut payload = Vec::new();
        Primitive::I64(-42).encode(&mut payload);
        assert!(conforms(&decode_payload(&payload, None).value, &int));
        // A 2.x struct: its members, nested structs and arrays.
        let hb = heartbeat();
        payload.clear();
        zcm::encode_heartbeat(&hb, &mut payload);
        let shown = decode_payload(&payload, None);
        let fingerprint = Fingerprint::of_payload(&payload).unwrap().0;
        let info = TypeInfo {
            encoding: TypeEncoding::Zcm,
            name: shown.type_name.clone(),
            fingerprint,
            schema: Vec::new(),
        };
        let schema = json_schema_of(&info).unwrap();
        assert!(
            conforms(&shown.value, &schema),
            "{} against {schema}",
            shown.value
        );
        assert!(schema["properties"]["channels"]["items"]["properties"]["name"].is_object());
        // Unknown ZCM types and descriptions that don't decode have none.
        let unknown = TypeInfo {
            fingerprint: [9; 8],
            ..info.clone()
        };
        assert!(json_schema_of(&unknown).is_none());
        let broken = TypeInfo {
            encoding: TypeEncoding::Native,
            schema: vec![0xff; 16],
            ..info
        };
        assert!(json_schema_of(&broken).is_none());
        // A description nested far deeper than any value is bounded, and
        // does not overflow the stack.
        let mut deep = OwnedNamedType {
            name: "leaf".into(),
            ty: OwnedDataModelType::U8,
        };
        for _ in 0..10_000 {
            deep = OwnedNamedType {
                name: "wrap".into(),
                ty: OwnedDataModelType::Option(Box::new(deep)),
            };
        }
        let schema = json_schema(&deep);
        assert!(conforms(&Value::Null, &schema));
        // Dropped iteratively: a 10,000-deep box would overflow the stack.
        let mut next = Some(deep);
        while let Some(t) = next.take() {
            if let OwnedDataModelType::Option(inner) = t.ty {
                next = Some(*inner);
            }
        }
    }

    #[test]
    fn zcm_messages_decode_by_fingerprint() {
        let mut payload = Vec::new();
        Primitive::I64(-42).encode(&mut payload);
        assert_eq!(
            decode_payload(&payload, None),
            Decoded {
                type_name: "int64_msg".into(),
                value: json!(-42)
            }
        );
        payload.clear();
        Primitive::Float(1.25).encode(&mut payload);
        assert_eq!(decode_payload(&payload, None).value, json!(1.25));
        payload.clear();
        let hb = heartbeat();
        zcm::encode_heartbeat(&hb, &mut payload);
        let decoded = decode_payload(&payload, None);
        assert_eq!(decoded.type_name, "pulicast_node");
        assert_eq!(decoded.value["name"], "rover");
        assert_eq!(decoded.value["channels"][0]["name"], "__nodes");
        assert_eq!(decoded.value["channels"][0]["publishing_period_ns"], 100);
    }

    #[test]
    fn discovery_and_unknown_payloads() {
        let leave = DiscoveryMessage::Leave(pulicast_discovery::wire::Leave {
            sender: 3,
            incarnation: 1,
        });
        let decoded = decode_payload(&leave.encode(), None);
        assert_eq!(decoded.type_name, "pulicast_discovery");
        assert_eq!(decoded.value["Leave"]["sender"], 3);
        let decoded = decode_payload(&[1, 2, 3], None);
        assert_eq!(decoded.value, json!({"len": 3, "hex": "010203"}));
    }

    #[test]
    fn hostile_schemas_are_bounded() {
        // A deeply nested description is refused, not followed into a stack overflow.
        let mut t = OwnedNamedType {
            name: "u8".into(),
            ty: OwnedDataModelType::U8,
        };
        for _ in 0..(MAX_DEPTH + 10) {
            t = OwnedNamedType {
                name: "o".into(),
                ty: OwnedDataModelType::Option(Box::new(t)),
            };
        }
        let body = vec![1u8; MAX_DEPTH + 20];
        assert!(decode_native_value(&t, &body).is_none());
        let info = TypeInfo {
            encoding: TypeEncoding::Native,
            name: "x".into(),
            fingerprint: [0; 8],
            schema: vec![0; MAX_SCHEMA_BYTES + 1],
        };
        assert!(schema_of(&info).is_none());
        // So is a description within the size that nests deeper than a
        // value may (it decoded, and overflowed a stack when walked).
        let deep = TypeInfo {
            schema: postcard::to_stdvec(&t).unwrap(),
            ..info.clone()
        };
        assert!(deep.schema.len() <= MAX_SCHEMA_BYTES);
        assert!(schema_of(&deep).is_none());
        // A sequence length beyond the bytes at hand is refused up front.
        let seq = OwnedNamedType {
            name: "v".into(),
            ty: OwnedDataModelType::Seq(Box::new(OwnedNamedType {
                name: "u8".into(),
                ty: OwnedDataModelType::U8,
            })),
        };
        assert!(decode_native_value(&seq, &[0xff, 0xff, 0xff, 0x0f]).is_none());
    }

    #[test]
    fn a_list_of_nothing_decodes_to_a_bounded_number_of_values() {
        let unit = OwnedNamedType {
            name: String::new(),
            ty: OwnedDataModelType::Unit,
        };
        // A list of tuples of 1500 `()`: 2 bytes a `()` in the description,
        // none in the message. A 60 KB message would be 90 million nulls.
        // The list, then as many bytes as it is long: the message is used
        // up exactly, so only the bound stops it.
        let bomb = OwnedNamedType {
            name: "bomb".into(),
            ty: OwnedDataModelType::Tuple(vec![
                OwnedNamedType {
                    name: String::new(),
                    ty: OwnedDataModelType::Seq(Box::new(OwnedNamedType {
                        name: String::new(),
                        ty: OwnedDataModelType::Tuple(vec![unit.clone(); 1500]),
                    })),
                },
                OwnedNamedType {
                    name: String::new(),
                    ty: OwnedDataModelType::ByteArray,
                },
            ]),
        };
        assert!(postcard::to_stdvec(&bomb).unwrap().len() <= MAX_SCHEMA_BYTES);
        let n: u32 = 60_000;
        let mut varint = Vec::new();
        let mut v = n;
        while v >= 0x80 {
            varint.push((v as u8) | 0x80);
            v >>= 7;
        }
        varint.push(v as u8);
        let mut body = varint.clone();
        body.extend(&varint);
        body.resize(body.len() + n as usize, 0);
        let started = std::time::Instant::now();
        // (Not printed if it fails: it would be gigabytes.)
        assert!(decode_native_value(&bomb, &body).is_none(), "decoded whole");
        // Refused after at most MAX_ZERO_SIZED values, not 90 million
        // (a bound on work, not a timing claim: generous on any machine).
        assert!(started.elapsed() < std::time::Duration::from_secs(5));
        // A few of them are a value like any other (a list's length must
        // fit the bytes after it: here three bytes follow).
        let byte = OwnedNamedType {
            name: "u8".into(),
            ty: OwnedDataModelType::U8,
        };
        let few = OwnedNamedType {
            name: "few".into(),
            ty: OwnedDataModelType::Tuple(vec![
                OwnedNamedType {
                    name: "units".into(),
                    ty: OwnedDataModelType::Seq(Box::new(unit)),
                },
                byte.clone(),
                byte.clone(),
                byte,
            ]),
        };
        assert_eq!(
            decode_native_value(&few, &[3, 7, 8, 9]),
            Some(json!([[null, null, null], 7, 8, 9]))
        );
    }
}

//! The owner's side of a distributed setting, sans-IO: it takes request
//! datagrams' payloads (see [`crate::wire::setting`]), checks them, keeps
//! the value and writes the confirmation to send. The node's runtime
//! subscribes and publishes; nothing here touches a socket or a clock.
//!
//! It behaves as a Pulicast 2.x `Setting` does, so `puliconf` sees no
//! difference: every request gets a confirmation, a refused one with the
//! reason and the value unchanged; a poke is answered with the value and
//! the setting's constraints as its message; unset and reset are requests
//! like any other, checked the same way.
//!
//! ```
//! use pulicast_proto::setting::{Check, Owner};
//! use pulicast_proto::wire::setting::{Request, RocAck};
//! use pulicast_proto::wire::zcm::Primitive;
//!
//! let mut speed = Owner::new(1.5f64, vec![Check::Range(0.0, 2.0)])?;
//! let mut request = Vec::new();
//! Primitive::Double(3.0).encode(&mut request);
//! let mut confirmation = Vec::new();
//! let changed = speed.handle(&request, &mut confirmation);
//! assert!(!changed);
//! assert_eq!(RocAck::decode(&confirmation)?.message, "must be in [0, 2]");
//! assert_eq!(speed.value(), Some(&1.5));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::cmp::Ordering;
use std::fmt;

use pulicast_discovery::wire::TypeInfo;
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::wire::setting::{Request, RocAck, MAX_VALUE_LEN};
use crate::wire::zcm::{Primitive, PrimitiveKind};
use crate::wire::{DecodeError, Fingerprint};
use postcard_schema::Schema;

/// A type a setting can hold: the Pulicast 2.x primitives, which travel as
/// their ZCM messages on the 2.x channels so that Python tools read them,
/// and native `serde` + `Schema` types wrapped in [`Native`], our
/// extension.
pub trait SettingValue: Clone + PartialEq + Send + Sync + 'static {
    /// The fingerprint its messages start with.
    fn fingerprint() -> Fingerprint;
    /// Its type's name (`double_msg`, `Limits`).
    fn type_name() -> String;
    /// The hidden namespace part its channels live under:
    /// [`crate::wire::setting::CONFIG`] (2.x tools see the setting) or
    /// [`crate::wire::setting::NATIVE`] (only ours do: 2.x `puliconf`
    /// fails on a type it does not know).
    fn part() -> &'static str;
    /// The type to announce in discovery on the request channel, so that
    /// tools decode and encode its values (native types).
    fn type_info() -> Option<TypeInfo>;
    /// Appends it as a whole message, fingerprint first.
    fn encode(&self, out: &mut Vec<u8>) -> Result<(), String>;
    /// Reads a whole message; an error for another type or broken bytes.
    fn decode(message: &[u8]) -> Result<Self, DecodeError>;
    /// From a start-up file's value, or why it can't be one.
    fn from_file(value: &FileValue) -> Result<Self, String>;
    /// As a person reads it, in checks' messages.
    fn text(&self) -> String;
    /// How it compares to `other`, for range checks; `None`: unordered.
    fn order(&self, other: &Self) -> Option<Ordering>;
}

/// The 2.x primitive a Rust type travels as.
trait AsPrimitive: Sized {
    const KIND: PrimitiveKind;
    fn to_primitive(&self) -> Primitive;
    fn from_primitive(p: Primitive) -> Option<Self>;
}

macro_rules! as_primitive {
    ($($ty:ty => $variant:ident),* $(,)?) => {$(
        impl AsPrimitive for $ty {
            const KIND: PrimitiveKind = PrimitiveKind::$variant;
            fn to_primitive(&self) -> Primitive {
                Primitive::$variant(self.clone())
            }
            fn from_primitive(p: Primitive) -> Option<Self> {
                match p {
                    Primitive::$variant(v) => Some(v),
                    _ => None,
                }
            }
        }
    )*};
}

as_primitive!(bool => Bool, u8 => Byte, i8 => I8, i16 => I16, i32 => I32, i64 => I64, f64 => Double, String => String);

/// `float_msg`: a double on the wire, an `f32` here, rounded to the
/// nearest (2.x tools send `0.1` as the double nearest it). A finite value
/// beyond `f32`'s range is refused, as a value of the wrong type is.
impl AsPrimitive for f32 {
    const KIND: PrimitiveKind = PrimitiveKind::Float;
    fn to_primitive(&self) -> Primitive {
        Primitive::Float(f64::from(*self))
    }
    fn from_primitive(p: Primitive) -> Option<Self> {
        match p {
            Primitive::Float(v) => {
                let narrowed = v as f32;
                (narrowed.is_finite() || !v.is_finite()).then_some(narrowed)
            }
            _ => None,
        }
    }
}

macro_rules! primitive_setting {
    ($($ty:ty),* $(,)?) => {$(
        impl SettingValue for $ty {
            fn fingerprint() -> Fingerprint {
                <$ty as AsPrimitive>::KIND.fingerprint()
            }
            fn type_name() -> String {
                <$ty as AsPrimitive>::KIND.type_name().to_string()
            }
            fn part() -> &'static str {
                crate::wire::setting::CONFIG
            }
            fn type_info() -> Option<TypeInfo> {
                None
            }
            fn encode(&self, out: &mut Vec<u8>) -> Result<(), String> {
                self.to_primitive().encode(out);
                Ok(())
            }
            fn decode(message: &[u8]) -> Result<Self, DecodeError> {
                let kind = <$ty as AsPrimitive>::KIND;
                let primitive = Primitive::decode_as(kind, message)?;
                <$ty as AsPrimitive>::from_primitive(primitive).ok_or_else(|| {
                    DecodeError::Malformed(format!("out of range for {}", kind.type_name()))
                })
            }
            fn from_file(value: &FileValue) -> Result<Self, String> {
                let kind = <$ty as AsPrimitive>::KIND;
                let refused = || format!("{value} is not a value of type {}", kind.type_name());
                let FileValue::Value(p) = value else {
                    return Err(refused());
                };
                let converted = crate::catalog::convert(kind, p.clone())?;
                <$ty as AsPrimitive>::from_primitive(converted).ok_or_else(refused)
            }
            fn text(&self) -> String {
                self.to_string()
            }
            fn order(&self, other: &Self) -> Option<Ordering> {
                self.partial_cmp(other)
            }
        }
    )*};
}

primitive_setting!(bool, u8, i8, i16, i32, i64, f32, f64, String);

/// A native value as a setting, our extension: any `serde` + `Schema`
/// type (`Native(Limits { .. })`). Its value travels postcard-encoded in
/// the confirmation, its type is announced in discovery on the request
/// channel, and its channels live under `.settings` instead of `.config`:
/// 2.x `puliconf` can't decode such a value and fails on a setting whose
/// type it does not know, so it must not see them. Our tools decode and
/// write it as JSON (TOML tables in files), from the announced type.
///
/// Range checks need an order, which a native type does not give them:
/// they refuse every value. `OneOf`, `ReadOnly` and closures work.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Native<T>(pub T);

impl<T> SettingValue for Native<T>
where
    T: Serialize
        + DeserializeOwned
        + Schema
        + Clone
        + PartialEq
        + fmt::Debug
        + Send
        + Sync
        + 'static,
{
    fn fingerprint() -> Fingerprint {
        crate::wire::fingerprint_of::<T>()
    }
    fn type_name() -> String {
        T::SCHEMA.name.to_string()
    }
    fn part() -> &'static str {
        crate::wire::setting::NATIVE
    }
    fn type_info() -> Option<TypeInfo> {
        Some(crate::wire::type_info_of::<T>())
    }
    fn encode(&self, out: &mut Vec<u8>) -> Result<(), String> {
        crate::wire::encode_native(&self.0, out).map_err(|e| e.to_string())
    }
    fn decode(message: &[u8]) -> Result<Self, DecodeError> {
        crate::wire::decode_native(message).map(Native)
    }
    fn from_file(value: &FileValue) -> Result<Self, String> {
        let json = match value {
            FileValue::Unset => {
                return Err(format!(
                    "{value} is not a value of type {}",
                    Self::type_name()
                ))
            }
            FileValue::Structured(json) => json.clone(),
            FileValue::Value(p) => crate::catalog::primitive_json(p),
        };
        serde_json::from_value(json)
            .map(Native)
            .map_err(|e| format!("{value} is not a value of type {}: {e}", Self::type_name()))
    }
    fn text(&self) -> String {
        serde_json::to_string(&self.0).unwrap_or_else(|_| format!("{:?}", self.0))
    }
    fn order(&self, _: &Self) -> Option<Ordering> {
        None
    }
}

/// A constraint on a setting's value, checked on every change, whoever
/// asks for it (a tool, the owner, a start-up file).
pub enum Check<T> {
    /// Within `[min, max]`.
    Range(T, T),
    /// At least this.
    AtLeast(T),
    /// At most this.
    AtMost(T),
    /// One of these.
    OneOf(Vec<T>),
    /// Never changed by requests (the owner still sets it).
    ReadOnly,
    /// Anything the closure accepts; it says why not.
    Custom(Validator<T>),
}

/// A closure that accepts a value, or says why not.
pub type Validator<T> = Box<dyn Fn(&T) -> Result<(), String> + Send + Sync>;

impl<T: SettingValue> Check<T> {
    /// Why `value` is refused (`None`: an unset value), or `Ok`.
    fn check(&self, value: Option<&T>) -> Result<(), String> {
        let refused = |this: &Self| Err(this.to_string());
        let Some(v) = value else {
            // Every constraint but a closure's needs a value.
            return match self {
                // A closure checks values: an unset one it can't see.
                Check::Custom(_) => Err("must have a value".into()),
                _ => refused(self),
            };
        };
        let at_least = |min: &T| matches!(v.order(min), Some(Ordering::Greater | Ordering::Equal));
        let at_most = |max: &T| matches!(v.order(max), Some(Ordering::Less | Ordering::Equal));
        let ok = match self {
            Check::Range(min, max) => at_least(min) && at_most(max),
            Check::AtLeast(min) => at_least(min),
            Check::AtMost(max) => at_most(max),
            Check::OneOf(values) => values.contains(v),
            Check::ReadOnly => false,
            Check::Custom(f) => return f(v),
        };
        if ok {
            Ok(())
        } else {
            refused(self)
        }
    }
}

impl<T: SettingValue> fmt::Display for Check<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Check::Range(min, max) => write!(f, "must be in [{}, {}]", min.text(), max.text()),
            Check::AtLeast(min) => write!(f, "must be at least {}", min.text()),
            Check::AtMost(max) => write!(f, "must be at most {}", max.text()),
            Check::OneOf(values) => {
                let values: Vec<String> = values.iter().map(SettingValue::text).collect();
                write!(f, "must be one of {}", values.join(", "))
            }
            Check::ReadOnly => write!(f, "read-only"),
            Check::Custom(_) => write!(f, "checked by its owner"),
        }
    }
}

/// A setting's description, unit and checks, read back from what its
/// owner answers a poke with ([`Owner::about`]: `"top speed; unit: m/s;
/// must be in [0, 2]"`), for a tool that shows a slider for a range or a
/// choice for one-of.
///
/// Read best-effort from text, as 2.x tools read it: parts are taken from
/// the end while they read as checks, then a unit; the rest is the
/// description (which may itself hold `"; "`). A 2.x owner's validator
/// text reads as a description with no checks, and a one-of value with
/// `", "` in it splits in two.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SettingLimits {
    /// What the setting is for (empty if the owner says nothing).
    pub description: String,
    /// Its unit (`m/s`), empty if none.
    pub unit: String,
    /// The least value allowed (`must be in [min, ..]`, `must be at least
    /// min`), for numbers.
    pub min: Option<f64>,
    /// The greatest value allowed, for numbers.
    pub max: Option<f64>,
    /// The values allowed, as the owner writes them (`must be one of`);
    /// empty if any.
    pub one_of: Vec<String>,
    /// Tools can't change it.
    pub read_only: bool,
    /// A check of the owner's code decides: a change may be refused for
    /// reasons not listed here.
    pub checked_by_owner: bool,
}

impl SettingLimits {
    /// Reads `about` (see the type's docs).
    pub fn parse(about: &str) -> Self {
        let mut limits = SettingLimits::default();
        let mut parts: Vec<&str> = about.split("; ").collect();
        while let Some(last) = parts.last() {
            if !limits.take_check(last) {
                break;
            }
            parts.pop();
        }
        if let Some(unit) = parts.last().and_then(|p| p.strip_prefix("unit: ")) {
            limits.unit = unit.to_string();
            parts.pop();
        }
        limits.description = parts.join("; ");
        limits
    }

    /// Takes in one check's text (as `Check`'s `Display` writes it); false
    /// if it is none.
    fn take_check(&mut self, text: &str) -> bool {
        let number = |t: &str| t.trim().parse::<f64>().ok().filter(|f| f.is_finite());
        if let Some(range) = text
            .strip_prefix("must be in [")
            .and_then(|r| r.strip_suffix(']'))
        {
            let Some((min, max)) = range.split_once(", ") else {
                return false;
            };
            self.min = number(min).or(self.min);
            self.max = number(max).or(self.max);
        } else if let Some(min) = text.strip_prefix("must be at least ") {
            self.min = number(min).or(self.min);
        } else if let Some(max) = text.strip_prefix("must be at most ") {
            self.max = number(max).or(self.max);
        } else if let Some(values) = text.strip_prefix("must be one of ") {
            self.one_of = values.split(", ").map(str::to_string).collect();
        } else if text == "read-only" {
            self.read_only = true;
        } else if text == "checked by its owner" {
            self.checked_by_owner = true;
        } else {
            return false;
        }
        true
    }
}

impl<T> fmt::Debug for Check<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Check::Range(..) => "Range",
            Check::AtLeast(_) => "AtLeast",
            Check::AtMost(_) => "AtMost",
            Check::OneOf(_) => "OneOf",
            Check::ReadOnly => "ReadOnly",
            Check::Custom(_) => "Custom",
        })
    }
}

/// The longest message a confirmation carries, in bytes.
pub const MAX_MESSAGE: usize = 1024;

/// Paces the confirmations a setting sends for requests that change
/// nothing (pokes, refusals, a value it already holds), so that a flood
/// of 61-byte pokes can't draw 32 KiB confirmations out of an owner, to
/// every subscriber, at its rate. A change is always confirmed at once and
/// costs nothing here: its confirmation is about the size of its request.
///
/// It is a bucket of bytes: it starts full ([`Pacer::CAPACITY`], two of
/// the largest confirmations), refills at [`Pacer::RATE`], and each
/// request heard adds twice its own bytes. Over any stretch, what the
/// paced confirmations send is at most the capacity, plus the rate, plus
/// twice what the requests sent. A confirmation that must wait is sent
/// once the bucket holds it, with the latest request's message, and
/// answers every request heard meanwhile: confirmations are multicast,
/// and each carries the current value.
///
/// ```
/// use std::time::{Duration, Instant};
/// use pulicast_proto::setting::Pacer;
/// let t = Instant::now();
/// let mut pacer = Pacer::new(t);
/// pacer.heard(t, 61);
/// assert!(pacer.take(t, 30_000)); // the first answers at once
/// assert!(pacer.take(t, 30_000));
/// pacer.heard(t, 61);
/// assert!(!pacer.take(t, 30_000)); // a flood waits
/// assert!(pacer.wait(t, 30_000) <= Duration::from_secs(1));
/// ```
#[derive(Debug, Clone)]
pub struct Pacer {
    /// Bytes that may be sent now.
    credit: f64,
    at: std::time::Instant,
}

impl Pacer {
    /// Bytes a second the bucket refills at, requests or not: the largest
    /// confirmation once a second, so that a puliconf pull (which pokes
    /// for 2 s) is answered during any flood.
    pub const RATE: f64 = 32_768.0;
    /// The most the bucket holds: two of the largest confirmations.
    pub const CAPACITY: f64 = 2.0 * (MAX_VALUE_LEN + MAX_MESSAGE + 64) as f64;

    /// A full bucket at `now`.
    pub fn new(now: std::time::Instant) -> Self {
        Self {
            credit: Self::CAPACITY,
            at: now,
        }
    }

    fn refill(&mut self, now: std::time::Instant) {
        let elapsed = now.saturating_duration_since(self.at).as_secs_f64();
        self.at = self.at.max(now);
        self.credit = (self.credit + elapsed * Self::RATE).min(Self::CAPACITY);
    }

    /// A request of `bytes` was heard at `now`: it earns twice its bytes.
    pub fn heard(&mut self, now: std::time::Instant, bytes: usize) {
        self.refill(now);
        self.credit = (self.credit + 2.0 * bytes as f64).min(Self::CAPACITY);
    }

    /// Whether a confirmation of `bytes` may be sent at `now`; if so, it
    /// is paid for.
    pub fn take(&mut self, now: std::time::Instant, bytes: usize) -> bool {
        self.refill(now);
        let cost = bytes as f64;
        if self.credit < cost.min(Self::CAPACITY) {
            return false;
        }
        self.credit -= cost;
        true
    }

    /// How long from `now` until a confirmation of `bytes` may be sent,
    /// if no request comes meanwhile.
    pub fn wait(&mut self, now: std::time::Instant, bytes: usize) -> std::time::Duration {
        self.refill(now);
        let missing = (bytes as f64).min(Self::CAPACITY) - self.credit;
        std::time::Duration::from_secs_f64((missing / Self::RATE).max(0.0))
    }
}

/// A setting's value as a puliconf file (TOML) gives it.
#[derive(Debug, Clone, PartialEq)]
pub enum FileValue {
    /// `nan`: no value.
    Unset,
    /// A value: an integer (as `int64_msg`), a float (`double_msg`), a
    /// boolean or a string, converted to the setting's type when used.
    Value(Primitive),
    /// A table or an array, as JSON: the value of a [`Native`] setting.
    Structured(serde_json::Value),
}

impl fmt::Display for FileValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FileValue::Unset => f.write_str("nan (unset)"),
            FileValue::Value(Primitive::String(s)) => write!(f, "{s:?}"),
            FileValue::Value(p) => f.write_str(&crate::catalog::primitive_text(p)),
            FileValue::Structured(json) => write!(f, "{json}"),
        }
    }
}

/// Reads a TOML value as puliconf does: `nan` is unset, integers, floats,
/// booleans and strings are values; tables and arrays are structured
/// values (for [`Native`] settings), except a 2.x structured message (a
/// table with `__msg_type__`), which is refused with the reason.
pub fn file_value(value: &toml_edit::Value) -> Result<FileValue, String> {
    use toml_edit::Value;
    Ok(match value {
        Value::Float(f) if f.value().is_nan() => FileValue::Unset,
        Value::Float(f) => FileValue::Value(Primitive::Double(*f.value())),
        Value::Integer(i) => FileValue::Value(Primitive::I64(*i.value())),
        Value::Boolean(b) => FileValue::Value(Primitive::Bool(*b.value())),
        Value::String(s) => FileValue::Value(Primitive::String(s.value().clone())),
        Value::InlineTable(t) if t.contains_key("__msg_type__") => return Err(TWO_X.into()),
        other => FileValue::Structured(toml_to_json(other)?),
    })
}

const TWO_X: &str =
    "a 2.x structured message (`__msg_type__`) is not a value pulicast settings hold";

/// A TOML value as JSON; NaN and dates have no JSON form.
pub fn toml_to_json(value: &toml_edit::Value) -> Result<serde_json::Value, String> {
    use toml_edit::Value;
    Ok(match value {
        Value::String(s) => s.value().clone().into(),
        Value::Integer(i) => (*i.value()).into(),
        Value::Float(f) => serde_json::Number::from_f64(*f.value())
            .map(serde_json::Value::Number)
            .ok_or_else(|| format!("{} has no JSON form", f.value()))?,
        Value::Boolean(b) => (*b.value()).into(),
        Value::Datetime(d) => return Err(format!("a date ({}) is no setting's value", d.value())),
        Value::Array(a) => a
            .iter()
            .map(toml_to_json)
            .collect::<Result<Vec<_>, _>>()?
            .into(),
        Value::InlineTable(t) => t
            .iter()
            .map(|(k, v)| Ok((k.to_string(), toml_to_json(v)?)))
            .collect::<Result<serde_json::Map<_, _>, String>>()?
            .into(),
    })
}

/// A JSON value as TOML (for files of [`Native`] settings); `null` has no
/// TOML form.
pub fn json_to_toml(value: &serde_json::Value) -> Option<toml_edit::Value> {
    use serde_json::Value as J;
    Some(match value {
        J::Null => return None,
        J::Bool(b) => (*b).into(),
        J::Number(n) => match n.as_i64() {
            Some(i) => i.into(),
            None => n.as_f64()?.into(),
        },
        J::String(s) => s.as_str().into(),
        J::Array(a) => {
            let mut array = toml_edit::Array::new();
            for v in a {
                array.push(json_to_toml(v)?);
            }
            array.into()
        }
        J::Object(o) => {
            let mut table = toml_edit::InlineTable::new();
            for (k, v) in o {
                table.insert(k, json_to_toml(v)?);
            }
            table.into()
        }
    })
}

/// A file entry's value: an inline value or a `[table]` section (a native
/// setting's).
pub fn item_value(item: &toml_edit::Item) -> Result<FileValue, String> {
    match item {
        toml_edit::Item::Value(v) => file_value(v),
        toml_edit::Item::Table(t) => file_value(&toml_edit::Value::InlineTable(
            t.clone().into_inline_table(),
        )),
        _ => Err("an array of tables is not a setting's value".to_string()),
    }
}

/// A file's key as a setting's fleet-wide name (a leading `/` is allowed).
pub fn setting_key(key: &str) -> String {
    key.trim_start_matches('/').to_string()
}

/// Reads a puliconf file: each key a setting's fleet-wide name, each with
/// its value or why it can't be one (a file pulled from a whole fleet may
/// hold other nodes' structured settings: only a setting made under that
/// name reports it). Fails only on text that is not TOML.
pub fn read_settings_file(
    text: &str,
) -> Result<std::collections::BTreeMap<String, Result<FileValue, String>>, String> {
    let doc: toml_edit::DocumentMut = text.parse().map_err(|e| format!("not TOML: {e}"))?;
    Ok(doc
        .iter()
        .map(|(name, item)| (setting_key(name), item_value(item)))
        .collect())
}

/// A setting as its owner keeps it.
#[derive(Debug)]
pub struct Owner<T> {
    value: Option<T>,
    default: T,
    checks: Vec<Check<T>>,
    description: String,
    unit: String,
}

impl<T: SettingValue> Owner<T> {
    /// A setting of value `default`; fails (saying why) if the default
    /// breaks a check other than [`Check::ReadOnly`].
    pub fn new(default: T, checks: Vec<Check<T>>) -> Result<Self, String> {
        let owner = Self {
            value: Some(default.clone()),
            default,
            checks,
            description: String::new(),
            unit: String::new(),
        };
        owner.refusal(owner.value.as_ref(), false)?;
        Ok(owner)
    }

    /// The value; `None` once unset.
    pub fn value(&self) -> Option<&T> {
        self.value.as_ref()
    }

    /// The value the setting started with, and a reset goes back to.
    pub fn default_value(&self) -> &T {
        &self.default
    }

    /// The constraints, as a person reads them (`""` if none): what a poke
    /// is answered with, as in 2.x.
    pub fn constraints(&self) -> String {
        let all: Vec<String> = self.checks.iter().map(ToString::to_string).collect();
        all.join("; ")
    }

    /// Starts from `value`, read from a start-up file, instead of the
    /// coded default: it becomes the default a reset goes back to. It is
    /// checked as a tool's request is, read-only included, since a file is
    /// as much an outside writer as a tool. Fails saying why, leaving the
    /// coded default.
    pub fn start_from(&mut self, value: &FileValue) -> Result<(), String> {
        let wanted = match value {
            FileValue::Unset => None,
            other => Some(T::from_file(other)?),
        };
        self.refusal(wanted.as_ref(), true)?;
        if let Some(v) = &wanted {
            self.default = v.clone();
        }
        self.value = wanted;
        Ok(())
    }

    /// Gives the setting a description and a unit (each may be empty),
    /// which tools show: they are part of [`Owner::about`].
    pub fn describe(&mut self, description: &str, unit: &str) {
        self.description = description.trim().to_string();
        self.unit = unit.trim().to_string();
    }

    /// What the setting is, for a person: description, unit and
    /// constraints, joined by `"; "` (`"top speed; unit: m/s; must be in
    /// [0, 2]"`). A poke is answered with it, as a 2.x validator answers
    /// with its text, so 2.x tools show it too.
    pub fn about(&self) -> String {
        let unit = (!self.unit.is_empty()).then(|| format!("unit: {}", self.unit));
        let parts = [
            Some(self.description.clone()),
            unit,
            Some(self.constraints()),
        ];
        let parts: Vec<String> = parts
            .into_iter()
            .flatten()
            .filter(|p| !p.is_empty())
            .collect();
        parts.join("; ")
    }

    /// Why `value` would be refused by a request (`requested`) or by the
    /// owner (who may change a read-only setting).
    fn refusal(&self, value: Option<&T>, requested: bool) -> Result<(), String> {
        // A value its confirmation can't carry would look unset to every
        // tool: refused, whoever asks.
        if let Some(v) = value {
            let mut encoded = Vec::new();
            v.encode(&mut encoded)?;
            let len = encoded.len().saturating_sub(8);
            if len > MAX_VALUE_LEN {
                return Err(format!(
                    "too long: {len} bytes encoded, a confirmation carries at most {MAX_VALUE_LEN}"
                ));
            }
        }
        // Read-only refuses changes: asking for the value it holds (a
        // reset of an untouched setting, a file pulled from the fleet) is
        // none.
        let unchanged = value == self.value.as_ref();
        for check in &self.checks {
            if matches!(check, Check::ReadOnly) && (!requested || unchanged) {
                continue;
            }
            check.check(value)?;
        }
        Ok(())
    }

    /// The owner sets the value itself (checked as a request is, except
    /// read-only); true if it changed. Send a confirmation after a change.
    pub fn set(&mut self, value: T) -> Result<bool, String> {
        self.refusal(Some(&value), false)?;
        Ok(self.replace(Some(value)))
    }

    fn replace(&mut self, value: Option<T>) -> bool {
        let changed = self.value != value;
        self.value = value;
        changed
    }

    /// Handles one request's payload: changes the value if the request is
    /// accepted, and writes the confirmation to send (always one, as 2.x
    /// does) to `out`. Returns whether the value changed.
    pub fn handle(&mut self, request: &[u8], out: &mut Vec<u8>) -> bool {
        let (changed, message) = match self.decide(request) {
            Ok(value) => (self.replace(value), String::new()),
            Err(reason) => (false, reason),
        };
        let message = if message.is_empty() && matches!(Request::decode(request), Ok(Request::Poke))
        {
            self.about()
        } else {
            message
        };
        self.confirmation(&message, out);
        changed
    }

    /// What a request asks the value to become, if it is allowed.
    fn decide(&self, request: &[u8]) -> Result<Option<T>, String> {
        let wanted = match Request::decode(request).map_err(|e| e.to_string())? {
            Request::Poke => return Ok(self.value.clone()),
            Request::Unset => None,
            Request::Reset => Some(self.default.clone()),
            Request::Value(message) => Some(T::decode(message).map_err(|e| e.to_string())?),
        };
        self.refusal(wanted.as_ref(), true)?;
        Ok(wanted)
    }

    /// Writes the confirmation of the current value with `message` (cut to
    /// [`MAX_MESSAGE`] bytes: a closure's long reason must not make the
    /// confirmation too large for clients to take).
    pub fn confirmation(&self, message: &str, out: &mut Vec<u8>) {
        let message = crate::text::cut(message, MAX_MESSAGE);
        let mut encoded = Vec::new();
        if let Some(value) = &self.value {
            // Every value held was encoded when it was checked.
            if value.encode(&mut encoded).is_err() {
                encoded.clear();
            }
        }
        let fingerprint = T::fingerprint();
        let ack = RocAck {
            message,
            fingerprint,
            value: encoded.get(8..).unwrap_or_default(),
        };
        // A primitive's encoding is far below roc_ack's limit, but a long
        // string may not be: then the confirmation says so, without value.
        if ack.encode(out).is_err() {
            let too_long = RocAck {
                message: "value too long for a confirmation",
                value: &[],
                ..ack
            };
            let _fits = too_long.encode(out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::catalog::request as catalog_request;

    fn request(p: Primitive) -> Vec<u8> {
        let mut out = Vec::new();
        p.encode(&mut out);
        out
    }

    fn answer<T: SettingValue>(owner: &mut Owner<T>, req: &[u8]) -> (bool, String, Vec<u8>) {
        let mut out = Vec::new();
        let changed = owner.handle(req, &mut out);
        let ack = RocAck::decode(&out).unwrap();
        assert_eq!(ack.fingerprint, T::fingerprint());
        (changed, ack.message.to_string(), ack.value.to_vec())
    }

    #[test]
    fn limits_read_back_what_an_owner_says_of_its_checks() {
        let mut speed = Owner::new(1.5f64, vec![Check::Range(0.0, 2.5)]).unwrap();
        speed.describe("top speed; when driving", "m/s");
        let limits = SettingLimits::parse(&speed.about());
        assert_eq!(
            limits,
            SettingLimits {
                description: "top speed; when driving".into(),
                unit: "m/s".into(),
                min: Some(0.0),
                max: Some(2.5),
                ..SettingLimits::default()
            }
        );
        let gain = Owner::new(
            3i64,
            vec![Check::AtLeast(-2), Check::AtMost(10), Check::ReadOnly],
        )
        .unwrap();
        let limits = SettingLimits::parse(&gain.about());
        assert_eq!(
            (limits.min, limits.max, limits.read_only),
            (Some(-2.0), Some(10.0), true)
        );
        assert_eq!(
            (limits.description.as_str(), limits.unit.as_str()),
            ("", "")
        );
        let mode = Owner::new(
            String::from("drive"),
            vec![
                Check::OneOf(vec!["drive".into(), "stop".into()]),
                Check::Custom(Box::new(|_: &String| Ok(()))),
            ],
        )
        .unwrap();
        let limits = SettingLimits::parse(&mode.about());
        assert_eq!(limits.one_of, ["drive", "stop"]);
        assert!(limits.checked_by_owner && limits.min.is_none());
        // A 2.x validator's text, and nothing at all: a description only.
        let limits = SettingLimits::parse("accept_range(0, 2)");
        assert_eq!(
            (limits.description.as_str(), limits.min),
            ("accept_range(0, 2)", None)
        );
        assert_eq!(SettingLimits::parse(""), SettingLimits::default());
        // A range of texts has no numbers; a malformed range is no check.
        assert_eq!(SettingLimits::parse("must be in [a, b]").min, None);
        assert_eq!(
            SettingLimits::parse("must be in [1 2]").description,
            "must be in [1 2]"
        );
    }

    #[test]
    fn requests_are_checked_and_always_confirmed() {
        let mut gain = Owner::new(3i64, vec![Check::AtLeast(0), Check::AtMost(10)]).unwrap();
        assert_eq!(
            answer(&mut gain, &request(Primitive::I64(7))),
            (true, String::new(), 7i64.to_be_bytes().to_vec())
        );
        let (changed, message, value) = answer(&mut gain, &request(Primitive::I64(11)));
        assert_eq!((changed, value), (false, 7i64.to_be_bytes().to_vec()));
        assert_eq!(message, "must be at most 10");
        // Another type: refused, with the reason, the value kept.
        let (changed, message, _) = answer(&mut gain, &request(Primitive::Double(1.0)));
        assert!(!changed && message.contains("int64_msg"), "{message}");
        // Poke: the constraints; unset: refused (a value is needed).
        let (changed, message, _) = answer(&mut gain, &catalog_request(Request::Poke));
        assert_eq!(
            (changed, message.as_str()),
            (false, "must be at least 0; must be at most 10")
        );
        let (changed, _, value) = answer(&mut gain, &catalog_request(Request::Unset));
        assert_eq!((changed, value.len()), (false, 8));
        assert_eq!(
            answer(&mut gain, &catalog_request(Request::Reset)),
            (true, String::new(), 3i64.to_be_bytes().to_vec())
        );
        // Garbage: refused, answered, nothing changed.
        let (changed, message, _) = answer(&mut gain, &[1, 2, 3]);
        assert!(!changed && !message.is_empty());
        assert_eq!(gain.value(), Some(&3));
    }

    #[test]
    fn unset_read_only_one_of_and_custom() {
        let mut mode = Owner::new("auto".to_string(), vec![]).unwrap();
        let (changed, _, value) = answer(&mut mode, &catalog_request(Request::Unset));
        assert_eq!((changed, value.len(), mode.value()), (true, 0, None));
        assert!(answer(&mut mode, &catalog_request(Request::Reset)).0);

        let mut locked = Owner::new(true, vec![Check::ReadOnly]).unwrap();
        let (changed, message, _) = answer(&mut locked, &request(Primitive::Bool(false)));
        assert_eq!((changed, message.as_str()), (false, "read-only"));
        assert_eq!(locked.set(false), Ok(true));

        let mut pick = Owner::new(1u8, vec![Check::OneOf(vec![1, 2, 4])]).unwrap();
        assert!(!answer(&mut pick, &request(Primitive::Byte(3))).0);
        assert!(answer(&mut pick, &request(Primitive::Byte(4))).0);

        let even: Check<i32> = Check::Custom(Box::new(|v: &i32| {
            if v % 2 == 0 {
                Ok(())
            } else {
                Err(format!("{v} is odd"))
            }
        }));
        let mut evens = Owner::new(2i32, vec![even]).unwrap();
        let (changed, message, _) = answer(&mut evens, &request(Primitive::I32(3)));
        assert_eq!((changed, message.as_str()), (false, "3 is odd"));
        assert_eq!(evens.set(5), Err("5 is odd".into()));

        assert!(Owner::new(20i64, vec![Check::Range(0, 10)]).is_err());
    }

    #[test]
    fn a_value_too_long_for_a_confirmation_is_refused_whoever_asks() {
        let mut text = Owner::new("short".to_string(), vec![]).unwrap();
        let long = "x".repeat(40_000);
        let (changed, message, value) =
            answer(&mut text, &request(Primitive::String(long.clone())));
        assert!(!changed);
        assert!(message.starts_with("too long: 40005 bytes"), "{message}");
        assert_eq!(value.len(), 4 + 5 + 1);
        assert!(text.set(long.clone()).is_err());
        assert!(Owner::new(long.clone(), vec![]).is_err());
        let file = FileValue::Value(Primitive::String(long));
        assert!(text.start_from(&file).is_err());
        assert_eq!(text.value().map(String::as_str), Some("short"));
    }

    #[test]
    fn file_values_read_as_puliconf_reads_them() {
        let file =
            "a = 1\nb = 2.5\nc = nan\nd = true\ne = \"x\"\nf = [1]\n\"/g/h\" = 0\n[t]\nx = 1\n";
        let values = read_settings_file(file).unwrap();
        let v = |k: &str| values[k].clone();
        assert_eq!(v("a"), Ok(FileValue::Value(Primitive::I64(1))));
        assert_eq!(v("b"), Ok(FileValue::Value(Primitive::Double(2.5))));
        assert_eq!(v("c"), Ok(FileValue::Unset));
        assert_eq!(v("d"), Ok(FileValue::Value(Primitive::Bool(true))));
        assert_eq!(v("e"), Ok(FileValue::Value(Primitive::String("x".into()))));
        assert_eq!(v("f"), Ok(FileValue::Structured(serde_json::json!([1]))));
        assert_eq!(
            v("t"),
            Ok(FileValue::Structured(serde_json::json!({"x": 1})))
        );
        let two_x = read_settings_file("p = { __msg_type__ = \"pose\", x = 1.0 }").unwrap();
        assert!(two_x["p"].as_ref().unwrap_err().contains("2.x structured"));
        assert_eq!(v("g/h"), Ok(FileValue::Value(Primitive::I64(0))));
        assert!(read_settings_file("a = = 1").is_err());
    }

    #[test]
    fn read_only_refuses_changes_not_the_value_it_holds() {
        let mut fixed = Owner::new(3i32, vec![Check::ReadOnly]).unwrap();
        let (changed, message, _) = answer(&mut fixed, &catalog_request(Request::Reset));
        assert_eq!((changed, message.as_str()), (false, ""));
        let (_, message, _) = answer(&mut fixed, &request(Primitive::I32(3)));
        assert_eq!(message, "");
        let (_, message, _) = answer(&mut fixed, &request(Primitive::I32(4)));
        assert_eq!(message, "read-only");
        fixed
            .start_from(&FileValue::Value(Primitive::I64(3)))
            .unwrap();
        assert!(fixed
            .start_from(&FileValue::Value(Primitive::I64(4)))
            .is_err());
        assert_eq!(fixed.value(), Some(&3));
    }

    #[test]
    fn long_reasons_are_cut_to_fit_a_confirmation() {
        let mut owner = Owner::new(0i32, vec![]).unwrap();
        owner
            .checks
            .push(Check::Custom(Box::new(|_: &i32| Err("é".repeat(5000)))));
        let (_, message, _) = answer(&mut owner, &request(Primitive::I32(2)));
        assert!(message.len() <= MAX_MESSAGE && message.starts_with('é'));
    }

    #[test]
    fn start_up_values_are_checked_as_requests_are() {
        let mut owner = Owner::new(1.5f64, vec![Check::Range(0.0, 2.0)]).unwrap();
        assert!(owner
            .start_from(&FileValue::Value(Primitive::Double(3.0)))
            .is_err());
        assert!(owner.start_from(&FileValue::Unset).is_err());
        assert_eq!(owner.value(), Some(&1.5));
        owner
            .start_from(&FileValue::Value(Primitive::I64(1)))
            .unwrap();
        assert_eq!((owner.value(), owner.default_value()), (Some(&1.0), &1.0));
        let mut fixed = Owner::new(1i32, vec![Check::ReadOnly]).unwrap();
        assert!(fixed
            .start_from(&FileValue::Value(Primitive::I64(2)))
            .is_err());
        let mut small = Owner::new(1u8, vec![]).unwrap();
        assert!(small
            .start_from(&FileValue::Value(Primitive::I64(300)))
            .is_err());
        let mut f = Owner::new(0.5f32, vec![]).unwrap();
        f.start_from(&FileValue::Value(Primitive::Double(0.1)))
            .unwrap();
        assert_eq!(f.value(), Some(&0.1f32));
        assert!(f
            .start_from(&FileValue::Value(Primitive::Double(1e300)))
            .is_err());
    }

    #[test]
    fn paced_confirmations_stay_within_twice_the_requests_plus_the_rate() {
        use std::time::{Duration, Instant};
        let t0 = Instant::now();
        let mut pacer = Pacer::new(t0);
        let (mut sent, mut heard, mut waiting) = (0usize, 0usize, false);
        // 10 000 pokes of 8 bytes over 2 s, each wanting 30 kB back.
        for i in 0..10_000u32 {
            let now = t0 + Duration::from_micros(200 * u64::from(i));
            pacer.heard(now, 8);
            heard += 8;
            if pacer.take(now, 30_000) {
                sent += 30_000;
                waiting = false;
            } else {
                waiting = true;
            }
        }
        let bound = 2.0 * heard as f64 + 2.0 * Pacer::RATE + Pacer::CAPACITY;
        assert!((sent as f64) <= bound, "{sent} > {bound}");
        assert!(sent >= 60_000, "the flood is still answered: {sent}");
        // What waits goes within a second once the flood stops.
        assert!(waiting);
        let end = t0 + Duration::from_secs(2);
        assert!(pacer.wait(end, 30_000) <= Duration::from_secs(1));
    }
}

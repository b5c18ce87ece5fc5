//! What `puli pub` does: turn a value typed on the command line into a
//! message, the way a program would publish it.
//!
//! Plain values go as the Pulicast 2.x primitive messages, so Python peers
//! read them. A JSON value for a channel whose native type discovery announces
//! is encoded into that type, so typed Rust subscribers receive it.

use anyhow::{anyhow, bail, Context, Result};
use pulicast::text::{encode_native_value, schema_of, unhex};
use pulicast::{Channel, TypeEncoding, TypeInfo};
use pulicast::{Primitive, PrimitiveKind};
use serde_json::Value;

/// How to read the value given on the command line.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum ValueType {
    /// The channel's announced type if it has one; otherwise a bool, an
    /// integer, a float or a string, whichever the value reads as.
    Auto,
    /// `string_msg`.
    String,
    /// `int64_msg`.
    Int,
    /// `double_msg`.
    Float,
    /// `boolean_msg` (`true`/`false`).
    Bool,
    /// Raw bytes, given as hex.
    Bytes,
    /// JSON, encoded into the channel's announced native type.
    Json,
}

/// The message to send.
#[derive(Debug, Clone, PartialEq)]
pub enum Outgoing {
    /// A ZCM primitive message.
    Primitive(Primitive),
    /// Raw bytes (a native message's bytes include its fingerprint).
    Bytes(Vec<u8>),
}

impl Outgoing {
    /// Publishes it once.
    pub fn publish(&self, channel: &Channel) -> pulicast::Result<()> {
        match self {
            Outgoing::Primitive(Primitive::String(s)) => channel.publish(s.as_str()),
            Outgoing::Primitive(Primitive::I64(v)) => channel.publish(v),
            Outgoing::Primitive(Primitive::I32(v)) => channel.publish(v),
            Outgoing::Primitive(Primitive::I16(v)) => channel.publish(v),
            Outgoing::Primitive(Primitive::I8(v)) => channel.publish(v),
            Outgoing::Primitive(Primitive::Byte(v)) => channel.publish(v),
            Outgoing::Primitive(Primitive::Double(v)) => channel.publish(v),
            Outgoing::Primitive(Primitive::Float(v)) => channel.publish(&(*v as f32)),
            Outgoing::Primitive(Primitive::Bool(v)) => channel.publish(v),
            Outgoing::Bytes(b) => channel.publish_bytes(b),
        }
    }
}

/// The type that members announce for `channel` (publishers first).
pub fn announced(channel: &Channel) -> Option<TypeInfo> {
    let name = channel.name();
    let mut members = channel.publishers();
    members.extend(channel.subscribers());
    members
        .into_iter()
        .flat_map(|m| m.channels)
        .filter(|c| c.name == name)
        .find_map(|c| c.message_type)
}

/// Builds the message for `text` read as `ty`; `announced` is the channel's
/// type from discovery.
pub fn outgoing(
    text: &str,
    ty: ValueType,
    announced: Option<&TypeInfo>,
    channel: &str,
) -> Result<Outgoing> {
    let bad = |what: &str| anyhow!("{text:?} is not {what}");
    Ok(match ty {
        ValueType::String => Outgoing::Primitive(Primitive::String(text.into())),
        ValueType::Int => Outgoing::Primitive(Primitive::I64(
            text.trim().parse().map_err(|_| bad("an integer"))?,
        )),
        ValueType::Float => Outgoing::Primitive(Primitive::Double(
            text.trim().parse().map_err(|_| bad("a number"))?,
        )),
        ValueType::Bool => Outgoing::Primitive(Primitive::Bool(
            text.trim().parse().map_err(|_| bad("true or false"))?,
        )),
        ValueType::Bytes => Outgoing::Bytes(unhex(text.trim()).ok_or_else(|| bad("hex bytes"))?),
        ValueType::Json => {
            let info = announced
                .filter(|t| t.encoding == TypeEncoding::Native)
                .ok_or_else(|| anyhow!("no member announces a native type for {channel:?}; use --type string|int|float|bool|bytes"))?;
            let schema = schema_of(info).ok_or_else(|| {
                anyhow!(
                    "the type {} announced for {channel:?} has no usable description",
                    info.name
                )
            })?;
            let value: Value =
                serde_json::from_str(text).with_context(|| format!("{text:?} is not JSON"))?;
            let bytes = encode_native_value(&schema, info.fingerprint, &value)
                .with_context(|| format!("the value does not fit {}", info.name))?;
            Outgoing::Bytes(bytes)
        }
        ValueType::Auto => match announced {
            Some(info) if info.encoding == TypeEncoding::Native => {
                return outgoing(text, ValueType::Json, announced, channel);
            }
            Some(info) => {
                let kind = PrimitiveKind::from_fingerprint(pulicast::Fingerprint(info.fingerprint))
                    .ok_or_else(|| {
                        anyhow!(
                            "{channel:?} carries {}, which puli can't type in",
                            info.name
                        )
                    })?;
                Outgoing::Primitive(primitive_of(text, kind)?)
            }
            None => Outgoing::Primitive(guess(text)),
        },
    })
}

/// Reads `text` as the given primitive message.
fn primitive_of(text: &str, kind: PrimitiveKind) -> Result<Primitive> {
    let t = text.trim();
    let bad = || anyhow!("{text:?} is not a valid {}", kind.type_name());
    Ok(match kind {
        PrimitiveKind::String => Primitive::String(text.into()),
        PrimitiveKind::Bool => Primitive::Bool(t.parse().map_err(|_| bad())?),
        PrimitiveKind::Byte => Primitive::Byte(t.parse().map_err(|_| bad())?),
        PrimitiveKind::I8 => Primitive::I8(t.parse().map_err(|_| bad())?),
        PrimitiveKind::I16 => Primitive::I16(t.parse().map_err(|_| bad())?),
        PrimitiveKind::I32 => Primitive::I32(t.parse().map_err(|_| bad())?),
        PrimitiveKind::I64 => Primitive::I64(t.parse().map_err(|_| bad())?),
        PrimitiveKind::Float => Primitive::Float(t.parse().map_err(|_| bad())?),
        PrimitiveKind::Double => Primitive::Double(t.parse().map_err(|_| bad())?),
    })
}

/// What a bare command-line value most likely means.
fn guess(text: &str) -> Primitive {
    let t = text.trim();
    if let Ok(b) = t.parse::<bool>() {
        return Primitive::Bool(b);
    }
    if let Ok(i) = t.parse::<i64>() {
        return Primitive::I64(i);
    }
    match t.parse::<f64>() {
        Ok(f) if !t.is_empty() => Primitive::Double(f),
        _ => Primitive::String(text.into()),
    }
}

/// What to publish, and how often: `puli pub`'s and `puli shell`'s `pub`.
#[derive(clap::Args, Debug, Clone)]
pub struct PubOpts {
    /// Channel name (relative to --namespace, or absolute with a leading /).
    pub channel: String,
    /// The value: text, a number, true/false, hex bytes, or JSON.
    #[arg(allow_hyphen_values = true)]
    pub value: String,
    /// How to read VALUE.
    #[arg(long = "type", value_enum, default_value_t = ValueType::Auto)]
    pub ty: ValueType,
    /// Publish this many times per second (default: once).
    #[arg(long)]
    pub rate: Option<f64>,
    /// Publish this many times (default: once, or forever with --rate).
    #[arg(long)]
    pub count: Option<u64>,
    /// How long to listen to discovery first, at most, to learn the
    /// channel's type (it goes on as soon as one is announced).
    #[arg(long, default_value_t = 0.5)]
    pub wait: f64,
}

/// Publishes as `opts` says from `node`, until the count is reached or
/// `stop` resolves; returns how many messages went out.
pub async fn run_on(
    node: &pulicast::Node,
    opts: &PubOpts,
    stop: impl std::future::Future<Output = ()>,
) -> Result<u64> {
    let channel = node.try_channel(&opts.channel)?;
    let (period, count) = plan(opts.rate, opts.count)?;
    // Discovery tells us the channel's type, if anyone announces one:
    // listen until someone does, or for `--wait` if nobody does.
    let wait = match opts.wait > 0.0 {
        true => std::time::Duration::from_secs_f64(opts.wait.min(60.0)),
        false => std::time::Duration::ZERO, // and NaN
    };
    tokio::pin!(stop);
    let announced = tokio::select! {
        found = crate::poll_for(wait, || announced(&channel)) => found,
        () = &mut stop => return Ok(0),
    };
    let message = outgoing(&opts.value, opts.ty, announced.as_ref(), channel.name())?;
    let mut sent = 0u64;
    let mut tick = period.map(tokio::time::interval);
    while count.is_none_or(|n| sent < n) {
        if let Some(tick) = tick.as_mut() {
            tokio::select! {
                // A stop beats a tick that is due at the same time.
                biased;
                () = &mut stop => break,
                _ = tick.tick() => {}
            }
        }
        message.publish(&channel)?;
        sent += 1;
    }
    Ok(sent)
}

/// Checks `--rate` and `--count` together.
pub fn plan(
    rate: Option<f64>,
    count: Option<u64>,
) -> Result<(Option<std::time::Duration>, Option<u64>)> {
    let period = match rate {
        Some(r) if !(r > 0.0 && r <= 1_000_000.0) => {
            bail!("--rate must be above 0 and at most 1000000 Hz")
        }
        Some(r) => Some(std::time::Duration::from_secs_f64(1.0 / r)),
        None => None,
    };
    // Without a rate, once; with one, until the count (or Ctrl-C).
    let count = match (period, count) {
        (None, None) => Some(1),
        (_, c) => c,
    };
    Ok((period, count))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bare_values_are_guessed_like_python_would_send_them() {
        assert_eq!(guess("42"), Primitive::I64(42));
        assert_eq!(guess("-1.5"), Primitive::Double(-1.5));
        assert_eq!(guess("true"), Primitive::Bool(true));
        assert_eq!(guess("Go LEFT!"), Primitive::String("Go LEFT!".into()));
        assert_eq!(guess(""), Primitive::String(String::new()));
    }

    #[test]
    fn explicit_types_and_clear_errors() {
        let o = |t, ty| outgoing(t, ty, None, "c");
        assert_eq!(
            o("7", ValueType::String).unwrap(),
            Outgoing::Primitive(Primitive::String("7".into()))
        );
        assert_eq!(
            o("0a0b", ValueType::Bytes).unwrap(),
            Outgoing::Bytes(vec![10, 11])
        );
        assert!(o("x", ValueType::Int)
            .unwrap_err()
            .to_string()
            .contains("not an integer"));
        assert!(o("1", ValueType::Json)
            .unwrap_err()
            .to_string()
            .contains("no member announces"));
        let announced = pulicast::type_info_of::<i16>();
        assert_eq!(
            outgoing("300", ValueType::Auto, Some(&announced), "c").unwrap(),
            Outgoing::Primitive(Primitive::I16(300))
        );
        assert!(outgoing("70000", ValueType::Auto, Some(&announced), "c").is_err());
        assert!(plan(Some(0.0), None).is_err());
        assert_eq!(plan(None, None).unwrap().1, Some(1));
    }
}

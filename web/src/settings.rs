//! The fleet's settings as the page shows them, and the changes it asks
//! for. One [`pulicast::FleetSettings`] client for the whole server: its
//! snapshot is read every [`EVERY`] (and discovery read again every
//! second), made into one frame for every client, and sent when it
//! changed. A change made anywhere (the owner itself, `puli config`,
//! another page) shows within a second.
//!
//! Bounded by the server's choice: at most [`MAX_SETTINGS`] settings in a
//! frame, names cut to [`crate::fleet::MAX_NAME`] bytes, texts (a
//! description, a refusal, a value) to [`MAX_TEXT`], [`MAX_CHOICES`]
//! choices of a one-of.

use std::sync::Arc;
use std::time::Duration;

use axum::extract::ws::Utf8Bytes;
use pulicast::{FleetSettings, Primitive, PrimitiveKind, SettingInfo};
use serde_json::{json, Value};
use tokio::sync::watch;

use crate::fleet::cut;

/// How often the settings are read again.
pub const EVERY: Duration = Duration::from_millis(250);

/// Most settings in a frame (the rest counted in `truncated`).
pub const MAX_SETTINGS: usize = 1024;

/// Longest text in a frame, in bytes.
pub const MAX_TEXT: usize = 1024;

/// Most choices of a one-of setting in a frame.
pub const MAX_CHOICES: usize = 64;

/// How long a change waits for its owner's confirmation.
pub const TIMEOUT: Duration = Duration::from_secs(3);

fn text(s: &str) -> String {
    crate::fleet::cut_to(s, MAX_TEXT)
}

/// What kind of control the value takes: `bool`, `int`, `float`,
/// `string`, `native` (JSON), or `None` while unknown.
pub(crate) fn kind(s: &SettingInfo) -> Option<&'static str> {
    if s.native_type().is_some() {
        return Some("native");
    }
    let kind = s.confirmed.as_ref().and_then(|c| c.kind()).or_else(|| {
        s.type_info
            .as_ref()
            .and_then(|t| PrimitiveKind::from_fingerprint(pulicast::Fingerprint(t.fingerprint)))
    })?;
    Some(match kind {
        PrimitiveKind::Bool => "bool",
        PrimitiveKind::Double | PrimitiveKind::Float => "float",
        PrimitiveKind::String => "string",
        PrimitiveKind::Byte
        | PrimitiveKind::I8
        | PrimitiveKind::I16
        | PrimitiveKind::I32
        | PrimitiveKind::I64 => "int",
    })
}

/// A setting's value as JSON (a native value, or a primitive), `null` when
/// unknown or too long to show (a text cut, ending in `…`).
pub(crate) fn value_of(s: &SettingInfo) -> Value {
    match value_within(s, MAX_TEXT) {
        Value::Null => match s.confirmed.as_ref().and_then(|c| c.value.as_ref()) {
            Some(Primitive::String(v)) => json!(text(v)),
            _ => Value::Null,
        },
        v => v,
    }
}

/// A setting's value as JSON, whole, or `null` when unknown or longer
/// than `limit` bytes: a value written back as it was read must be the
/// value, never a cut one.
pub(crate) fn value_within(s: &SettingInfo, limit: usize) -> Value {
    let whole = match s.value_json() {
        Some(v) => v,
        None => match s.confirmed.as_ref().and_then(|c| c.value.as_ref()) {
            Some(Primitive::Bool(b)) => json!(b),
            Some(Primitive::Byte(v)) => json!(v),
            Some(Primitive::I8(v)) => json!(v),
            Some(Primitive::I16(v)) => json!(v),
            Some(Primitive::I32(v)) => json!(v),
            Some(Primitive::I64(v)) => json!(v),
            Some(Primitive::Double(v) | Primitive::Float(v)) => json!(v),
            Some(Primitive::String(v)) => json!(v),
            None => Value::Null,
        },
    };
    match crate::decimate::fits(&whole, limit) {
        true => whole,
        false => Value::Null,
    }
}

/// One setting as the page shows it.
pub fn row(s: &SettingInfo) -> Value {
    let limits = s.limits();
    let owners: Vec<String> = s
        .owners
        .iter()
        .take(crate::fleet::MAX_ENDS)
        .map(|o| cut(&o.node))
        .collect();
    json!({
        "name": cut(&s.name),
        "kind": kind(s),
        "value": value_of(s),
        "text": s.value_text().map(|v| text(&v)),
        "type": s.type_name().map(|t| cut(&t)),
        "description": text(&limits.description),
        "unit": cut(&limits.unit),
        "min": limits.min,
        "max": limits.max,
        "one_of": limits.one_of.iter().take(MAX_CHOICES).map(|c| cut(c)).collect::<Vec<_>>(),
        "read_only": limits.read_only,
        "checked_by_owner": limits.checked_by_owner,
        "owners": owners,
        "locked": s.is_locked(),
        "stale": s.is_stale(),
        "confirmed": s.confirmed.is_some(),
        // What the owner says of the setting is no refusal, whenever it
        // was heard.
        "refusal": s
            .last_refusal
            .as_ref()
            .filter(|(_, why)| Some(why.as_str()) != s.about.as_deref())
            .map(|(_, why)| text(why)),
    })
}

/// The settings frame of `all`.
pub fn frame(all: &[SettingInfo], spent: bool) -> Value {
    let mut shown: Vec<&SettingInfo> = all.iter().collect();
    shown.sort_by(|a, b| a.name.cmp(&b.name));
    let truncated = shown.len().saturating_sub(MAX_SETTINGS);
    let rows: Vec<Value> = shown.into_iter().take(MAX_SETTINGS).map(row).collect();
    json!({ "kind": "settings", "settings": rows, "truncated": truncated, "spent": spent })
}

/// The server's settings client, and its frames: at once, then whenever
/// the settings change.
pub fn spawn(node: &pulicast::Node) -> (Arc<FleetSettings>, watch::Receiver<Utf8Bytes>) {
    let settings = Arc::new(node.fleet_settings());
    settings.refresh();
    let first = frame(&settings.snapshot(), settings.is_spent()).to_string();
    let (tx, rx) = watch::channel(Utf8Bytes::from(first));
    let polled = Arc::clone(&settings);
    let node = node.clone();
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(EVERY);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut round = 0u64;
        loop {
            tick.tick().await;
            if node.is_stopped() || tx.is_closed() {
                return;
            }
            round += 1;
            // Discovery again every second: new settings, owners gone.
            if round.is_multiple_of(4) {
                polled.refresh();
            }
            let next = frame(&polled.snapshot(), polled.is_spent()).to_string();
            tx.send_if_modified(|last| {
                let new = last.as_str() != next;
                if new {
                    *last = Utf8Bytes::from(next);
                }
                new
            });
        }
    });
    (settings, rx)
}

/// A change the page asks for.
#[derive(Debug, Clone, PartialEq)]
pub enum Change {
    /// The value as a person types it, read as the setting's type.
    Text(String),
    /// A JSON value (a native setting's, or a primitive one's).
    Json(Value),
    /// Back to the owner's default.
    Reset,
    /// No value.
    Unset,
}

/// Asks the owner of `name` for `change`; the answer for the page:
/// `{"ok": true, "text"}` with the value confirmed, or `{"ok": false,
/// "error"}` with the owner's refusal (or why nobody answered).
pub async fn apply(settings: &FleetSettings, name: &str, change: Change) -> Value {
    let done = match change {
        Change::Text(v) => settings.set_text(name, &v, TIMEOUT).await,
        Change::Json(v) => settings.set_json(name, v, TIMEOUT).await,
        Change::Reset => settings.reset(name, TIMEOUT).await,
        Change::Unset => settings.unset(name, TIMEOUT).await,
    };
    match done {
        Ok(s) => json!({ "ok": true, "text": s.value_text().map(|v| text(&v)) }),
        Err(pulicast::Error::SettingRefused { reason, .. }) => {
            json!({ "ok": false, "refused": true, "error": text(&reason) })
        }
        Err(e) => json!({ "ok": false, "error": text(&e.to_string()) }),
    }
}

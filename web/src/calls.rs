//! Service calls the page makes: a request as JSON, encoded into the type
//! the service's servers announce (as `puli call` does), its progress
//! streamed back, its reply or its fault, and a cancel. Each call is a
//! task of the client that made it, ended when the client goes.

use std::time::Duration;

use axum::extract::ws::Utf8Bytes;
use pulicast::CallEvent;
use pulicast_tools::call::{encode_request, message_json, server_types};
use serde_json::{json, Value};
use tokio::sync::{mpsc, oneshot};

use crate::fleet::cut;

/// A call's deadline when the page gives none.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(10);

/// The longest deadline a page may give.
pub const MAX_TIMEOUT: Duration = Duration::from_secs(300);

/// Longest value (a progress, a reply) sent as JSON, in bytes; a longer
/// one is sent as `{"longer_than": MAX_VALUE}`.
pub const MAX_VALUE: usize = 16 << 10;

/// A call the page asked for.
#[derive(Debug, Clone, PartialEq)]
pub struct Call {
    /// The page's name for it.
    pub id: u64,
    /// The service's full name.
    pub service: String,
    /// The server node to call, or any.
    pub target: Option<String>,
    /// The request, as JSON.
    pub request: Value,
    /// How long the call may take.
    pub timeout: Duration,
}

fn shown(value: Value) -> Value {
    match crate::decimate::fits(&value, MAX_VALUE) {
        true => value,
        false => json!({ "longer_than": MAX_VALUE }),
    }
}

/// Runs `call` on `node`, sending its events to `out` as frames
/// `{"kind": "call", "id", "event", ...}` (`started`, `progress`,
/// `reply`, `failed`, `cancelled`), until it ends or `cancel` fires.
/// Progress that finds the client's outbox full is dropped, and counted
/// in the reply's `missed_progress`.
pub async fn run(
    node: pulicast::Node,
    call: Call,
    mut cancel: oneshot::Receiver<()>,
    out: mpsc::Sender<Utf8Bytes>,
) {
    let id = call.id;
    let frame = |mut v: Value| -> Utf8Bytes {
        v["kind"] = "call".into();
        v["id"] = id.into();
        Utf8Bytes::from(v.to_string())
    };
    let failed = |error: String| frame(json!({ "event": "failed", "error": cut(&error) }));
    let Some(types) = server_types(&node, &call.service, call.target.as_deref()) else {
        let whom = call
            .target
            .as_deref()
            .map_or(String::new(), |t| format!(" at {t}"));
        let _ = out
            .send(failed(format!("no server of {}{whom}", call.service)))
            .await;
        return;
    };
    let full = match &call.target {
        Some(t) => format!("{}@{t}", call.service),
        None => call.service.clone(),
    };
    let sent = encode_request(&call.request.to_string(), types.request.as_ref(), &full)
        .and_then(|message| Ok((node.raw_client(&full)?, message)));
    let (client, message) = match sent {
        Ok(ready) => ready,
        Err(e) => {
            let _ = out.send(failed(e.to_string())).await;
            return;
        }
    };
    let mut running = match client.start(&message, call.timeout).await {
        Ok(running) => running,
        Err(e) => {
            let _ = out.send(failed(e.to_string())).await;
            return;
        }
    };
    let node_name = running.node().to_string();
    let _ = out
        .send(frame(
            json!({ "event": "started", "node": cut(&node_name) }),
        ))
        .await;
    let mut missed = 0u64;
    loop {
        tokio::select! {
            event = running.next() => {
                let last = match event {
                    Some(CallEvent::Progress(m)) => {
                        let value = shown(message_json(&m, types.progress.as_ref()));
                        if out.try_send(frame(json!({ "event": "progress", "value": value }))).is_err() {
                            missed += 1;
                        }
                        continue;
                    }
                    Some(CallEvent::Reply { message, missed_progress }) => frame(json!({
                        "event": "reply",
                        "node": cut(&node_name),
                        "value": shown(message_json(&message, types.reply.as_ref())),
                        "missed_progress": u64::from(missed_progress) + missed,
                    })),
                    Some(CallEvent::Failed { code, message, node }) => frame(json!({
                        "event": "failed",
                        "code": code,
                        "message": cut(&message),
                        "node": cut(&node),
                        "error": cut(&running.error(CallEvent::Failed { code, message: message.clone(), node: node.clone() }).to_string()),
                    })),
                    Some(other) => failed(running.error(other).to_string()),
                    None => match running.ended_with_reply() {
                        true => return,
                        false => failed(running.error(CallEvent::TimedOut).to_string()),
                    },
                };
                let _ = out.send(last).await;
                return;
            }
            _ = &mut cancel => {
                running.cancel();
                let _ = out.send(frame(json!({ "event": "cancelled" }))).await;
                return;
            }
        }
    }
}

/// Whether some live member announces `channel`: the page acts on the
/// fleet's channels only (each name a node is asked for stays in its
/// channel table).
pub fn announced(node: &pulicast::Node, channel: &str) -> bool {
    node.discovery()
        .live_members()
        .iter()
        .any(|m| m.channels.iter().any(|c| c.name == channel))
}

/// Publishes `value` on `channel` in the type its members announce (as
/// `puli pub` does: a native type from JSON, a 2.x primitive from the
/// value); why not, for the page.
pub fn publish(node: &pulicast::Node, channel: &str, value: &Value) -> Result<(), String> {
    // A service's or a setting's own channel is theirs: a message sent
    // there would pass for a reply or a confirmation.
    if pulicast::is_hidden_channel(channel) {
        return Err(format!(
            "{channel} is a hidden channel (a service's or a setting's)"
        ));
    }
    if !announced(node, channel) {
        return Err(format!("no member publishes or subscribes {channel}"));
    }
    let ty = pulicast_tools::publish::announced(&node.channel(&format!("/{channel}")));
    publish_as(node, channel, ty.as_ref(), value)
}

/// Publishes `value` on `channel` as `ty`, for a caller that checked the
/// channel is announced and not hidden and knows its type already (the
/// Foxglove server, for every message a client sends).
pub fn publish_as(
    node: &pulicast::Node,
    channel: &str,
    ty: Option<&pulicast::TypeInfo>,
    value: &Value,
) -> Result<(), String> {
    let handle = node.channel(&format!("/{channel}"));
    // A JSON string is its content, as a person means it.
    let text = match value {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    };
    let outgoing = pulicast_tools::publish::outgoing(
        &text,
        pulicast_tools::publish::ValueType::Auto,
        ty,
        channel,
    )
    .map_err(|e| format!("{e:#}"))?;
    outgoing.publish(&handle).map_err(|e| e.to_string())
}

/// The JSON Schema of what `name` takes: a service's request (`of` =
/// `service`, its servers' announced type) or a channel's message
/// (`channel`, its publishers' type, else its subscribers'), for the
/// page's forms: `{"type", "schema"}`, the schema `null` where the type
/// has none (no type announced, or one tools can't describe).
pub fn schema(node: &pulicast::Node, of: &str, name: &str) -> Value {
    let info = match of {
        "service" => server_types(node, name, None).and_then(|end| end.request),
        _ if announced(node, name) => {
            pulicast_tools::publish::announced(&node.channel(&format!("/{name}")))
        }
        _ => None,
    };
    let schema = info
        .as_ref()
        .and_then(pulicast::text::json_schema_of)
        .filter(|s| crate::decimate::fits(s, MAX_VALUE * 4));
    json!({
        "type": info.as_ref().map(|t| cut(&pulicast_tools::sniff::type_display(t))),
        "schema": schema,
    })
}

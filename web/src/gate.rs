//! The gate in front of the Foxglove server. The `foxglove` crate's
//! server takes any WebSocket that names its subprotocol: no token, no
//! check of the `Origin` (a web site open in the operator's browser could
//! drive the fleet), and each client's messages wait in a queue whose
//! drops nobody sees. So that server listens on a loopback port of its
//! own, and clients reach it through this gate, which
//!
//! - lets a WebSocket through only with the token, from the server's own
//!   hosts and origins ([`crate::guard`], as the page);
//! - passes every frame on both ways, but holds a client's message data
//!   (server frames of opcode 1, the only bulk) in a queue of
//!   [`DATA_BACKLOG`] frames per client: when the client reads slower
//!   than the fleet publishes, the oldest are dropped and counted
//!   ([`GateStats`]), so a big channel can't hold a small one back for
//!   long nor grow the server's memory; and
//! - closes a client that takes no frame at all for [`SEND_TIMEOUT`], or
//!   lets its other frames (advertisements, answers) pile past
//!   [`CONTROL_BACKLOG`].

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::extract::ws::{self, WebSocket, WebSocketUpgrade};
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use futures_util::{SinkExt, StreamExt};
use tokio::sync::Notify;
use tokio_tungstenite::tungstenite::{self as ts, client::IntoClientRequest};

use crate::guard::Guard;

/// The subprotocols of the Foxglove SDK's server.
pub const SUBPROTOCOLS: [&str; 2] = ["foxglove.sdk.v1", "foxglove.sdk.v1.1"];

/// Message data frames held for one client before the oldest is dropped.
pub const DATA_BACKLOG: usize = 256;

/// Other frames held for one client: past this, the client is closed
/// (it reads nothing at all).
pub const CONTROL_BACKLOG: usize = 4096;

/// Bytes of message data held for one client: past this the oldest go,
/// as past [`DATA_BACKLOG`] frames (a frame may be large).
pub const DATA_BYTES: usize = 8 << 20;

/// Bytes of other frames held for one client: past this it is closed.
pub const CONTROL_BYTES: usize = 16 << 20;

/// Longest a frame may wait to be taken by a client.
pub const SEND_TIMEOUT: Duration = Duration::from_secs(10);

/// How often a client is pinged (a client answers by itself).
pub const PING_EVERY: Duration = Duration::from_secs(15);

/// A client not heard from for this long (its pongs included) is closed:
/// a laptop gone to sleep does not keep its place.
pub const SILENT_FOR: Duration = Duration::from_secs(45);

/// How long frames still queued when the server's side ended may take to
/// reach the client (its last status among them).
pub const DRAIN_FOR: Duration = Duration::from_secs(2);

/// Largest message a client may send (a published message, a call).
pub const MAX_CLIENT_MESSAGE: usize = 1 << 20;

/// Most clients at once; one more is refused (503).
pub const MAX_CLIENTS: usize = 64;

/// What passed the gate.
#[derive(Debug, Default)]
pub struct GateStats {
    /// Clients connected now.
    pub clients: AtomicUsize,
    /// Message data frames sent to clients.
    pub sent: AtomicU64,
    /// Message data frames dropped because a client read too slowly.
    pub dropped: AtomicU64,
    /// Clients closed for not reading.
    pub closed_slow: AtomicU64,
}

/// The gate's routes.
#[derive(Clone)]
pub struct Gate {
    guard: Arc<Guard>,
    inner: SocketAddr,
    stats: Arc<GateStats>,
}

struct Place(Arc<GateStats>);

impl Drop for Place {
    fn drop(&mut self) {
        self.0.clients.fetch_sub(1, Ordering::SeqCst);
    }
}

impl Gate {
    /// A gate to the Foxglove server at `inner` (on loopback), behind
    /// `guard`.
    pub fn new(guard: Guard, inner: SocketAddr) -> Self {
        Self {
            guard: Arc::new(guard),
            inner,
            stats: Arc::default(),
        }
    }

    /// What passed so far.
    pub fn stats(&self) -> Arc<GateStats> {
        Arc::clone(&self.stats)
    }

    /// The router: `/`, the WebSocket, guarded.
    pub fn router(&self) -> Router {
        let routes = Router::new()
            .route("/", get(upgrade))
            .with_state(self.clone());
        crate::guard::guarded(routes, &self.guard)
    }

    /// Serves the gate on `listener` until `stop` resolves.
    pub async fn serve(
        &self,
        listener: tokio::net::TcpListener,
        stop: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> std::io::Result<()> {
        crate::http::serve(listener, self.router(), stop).await
    }
}

async fn upgrade(State(gate): State<Gate>, upgrade: WebSocketUpgrade) -> Response {
    let before = gate.stats.clients.fetch_add(1, Ordering::SeqCst);
    let place = Place(Arc::clone(&gate.stats));
    if before >= MAX_CLIENTS {
        return (StatusCode::SERVICE_UNAVAILABLE, "too many clients\n").into_response();
    }
    let upgrade = upgrade
        .protocols(SUBPROTOCOLS)
        .max_message_size(MAX_CLIENT_MESSAGE)
        .max_frame_size(MAX_CLIENT_MESSAGE);
    let Some(protocol) = upgrade.selected_protocol().cloned() else {
        return (
            StatusCode::BAD_REQUEST,
            "a Foxglove client names the subprotocol foxglove.sdk.v1\n",
        )
            .into_response();
    };
    upgrade.on_upgrade(move |socket| async move {
        pass(socket, gate, protocol).await;
        drop(place);
    })
}

/// A client's frames waiting to be sent, and whether it is done.
#[derive(Default)]
struct Outbox {
    data: VecDeque<ws::Message>,
    control: VecDeque<ws::Message>,
    /// Bytes in `data` and in `control`.
    data_bytes: usize,
    control_bytes: usize,
    closed: bool,
}

fn size(frame: &ws::Message) -> usize {
    match frame {
        ws::Message::Text(t) => t.len(),
        ws::Message::Binary(b) => b.len(),
        _ => 0,
    }
}

/// Passes frames between `client` and the inner server until either side
/// ends.
async fn pass(client: WebSocket, gate: Gate, protocol: HeaderValue) {
    let Ok(mut request) = format!("ws://{}/", gate.inner).into_client_request() else {
        return;
    };
    request
        .headers_mut()
        .insert("Sec-WebSocket-Protocol", protocol);
    let Ok((inner, _)) = tokio_tungstenite::connect_async(request).await else {
        return;
    };
    let (mut to_inner, mut from_inner) = inner.split();
    let (mut to_client, mut from_client) = client.split();
    let outbox = Arc::new(Mutex::new(Outbox::default()));
    let ready = Arc::new(Notify::new());
    let heard = Arc::new(Mutex::new(tokio::time::Instant::now()));

    // The inner server's frames, queued for the client.
    let queue = {
        let (outbox, ready, stats) = (
            Arc::clone(&outbox),
            Arc::clone(&ready),
            Arc::clone(&gate.stats),
        );
        async move {
            while let Some(Ok(frame)) = from_inner.next().await {
                let Some(frame) = to_axum(frame) else {
                    continue;
                };
                let mut out = outbox.lock().unwrap_or_else(|e| e.into_inner());
                let len = size(&frame);
                if is_data(&frame) {
                    while !out.data.is_empty()
                        && (out.data.len() >= DATA_BACKLOG || out.data_bytes + len > DATA_BYTES)
                    {
                        if let Some(old) = out.data.pop_front() {
                            out.data_bytes -= size(&old);
                        }
                        stats.dropped.fetch_add(1, Ordering::Relaxed);
                    }
                    out.data_bytes += len;
                    out.data.push_back(frame);
                } else if out.control.len() >= CONTROL_BACKLOG
                    || out.control_bytes + len > CONTROL_BYTES
                {
                    stats.closed_slow.fetch_add(1, Ordering::Relaxed);
                    out.closed = true;
                    drop(out);
                    ready.notify_one();
                    return;
                } else {
                    out.control_bytes += len;
                    out.control.push_back(frame);
                }
                drop(out);
                ready.notify_one();
            }
            outbox.lock().unwrap_or_else(|e| e.into_inner()).closed = true;
            ready.notify_one();
        }
    };
    // The queued frames, to the client: answers first, then data.
    let deliver = {
        let (outbox, ready, stats) = (
            Arc::clone(&outbox),
            Arc::clone(&ready),
            Arc::clone(&gate.stats),
        );
        let heard = Arc::clone(&heard);
        async move {
            loop {
                let next = {
                    let mut out = outbox.lock().unwrap_or_else(|e| e.into_inner());
                    let next = match out.control.pop_front() {
                        Some(f) => {
                            out.control_bytes -= size(&f);
                            Some(f)
                        }
                        None => {
                            let f = out.data.pop_front();
                            out.data_bytes -= f.as_ref().map_or(0, size);
                            f
                        }
                    };
                    next.map(|f| (f, out.closed)).ok_or(out.closed)
                };
                match next {
                    Ok((frame, _)) => {
                        let data = is_data(&frame);
                        let sent = tokio::time::timeout(SEND_TIMEOUT, to_client.send(frame)).await;
                        if !matches!(sent, Ok(Ok(()))) {
                            stats
                                .closed_slow
                                .fetch_add(u64::from(sent.is_err()), Ordering::Relaxed);
                            return;
                        }
                        if data {
                            stats.sent.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    Err(true) => {
                        let _ = to_client.close().await;
                        return;
                    }
                    Err(false) => {
                        if tokio::time::timeout(PING_EVERY, ready.notified())
                            .await
                            .is_err()
                        {
                            let silent = heard.lock().unwrap_or_else(|e| e.into_inner()).elapsed();
                            if silent >= SILENT_FOR {
                                return;
                            }
                            let ping = ws::Message::Ping(Default::default());
                            let pinged =
                                tokio::time::timeout(SEND_TIMEOUT, to_client.send(ping)).await;
                            if !matches!(pinged, Ok(Ok(()))) {
                                return;
                            }
                        }
                    }
                }
            }
        }
    };
    // The client's frames, to the inner server as they come.
    let forward = async move {
        while let Some(Ok(frame)) = from_client.next().await {
            *heard.lock().unwrap_or_else(|e| e.into_inner()) = tokio::time::Instant::now();
            let Some(frame) = to_tungstenite(frame) else {
                continue;
            };
            if to_inner.send(frame).await.is_err() {
                return;
            }
        }
        let _ = to_inner.close().await;
    };
    // The client gone, or done: the passage ends (both sockets close).
    // The server's side gone: what is queued still goes, for a moment,
    // then a close.
    tokio::pin!(deliver);
    tokio::select! {
        _ = forward => {}
        _ = &mut deliver => {}
        _ = queue => {
            let _ = tokio::time::timeout(DRAIN_FOR, &mut deliver).await;
        }
    }
}

/// Whether `frame` is message data: a binary frame of opcode 1.
fn is_data(frame: &ws::Message) -> bool {
    matches!(frame, ws::Message::Binary(b) if b.first() == Some(&1))
}

fn to_axum(frame: ts::Message) -> Option<ws::Message> {
    Some(match frame {
        ts::Message::Text(t) => ws::Message::Text(ws::Utf8Bytes::from(t.as_str())),
        ts::Message::Binary(b) => ws::Message::Binary(b),
        // Pings and closes are each side's own business.
        _ => return None,
    })
}

fn to_tungstenite(frame: ws::Message) -> Option<ts::Message> {
    Some(match frame {
        ws::Message::Text(t) => ts::Message::Text(t.as_str().into()),
        ws::Message::Binary(b) => ts::Message::Binary(b),
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_message_data_is_data() {
        assert!(is_data(&ws::Message::Binary(vec![1, 0, 0, 0, 0].into())));
        assert!(!is_data(&ws::Message::Binary(vec![2, 0].into())));
        assert!(!is_data(&ws::Message::Text(r#"{"op":"advertise"}"#.into())));
        assert!(!is_data(&ws::Message::Binary(Vec::new().into())));
    }
}

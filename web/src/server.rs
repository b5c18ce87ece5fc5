//! The routes: the page and its script and style (built into the binary),
//! and the WebSocket that carries the fleet. Every route is behind the
//! guard ([`crate::guard`]).

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use tokio::sync::watch;

use crate::guard::Guard;

/// Most browser clients at once; one more is refused (503).
pub const MAX_CLIENTS: usize = 64;

/// Longest message a client may send, in bytes: the page sends small
/// requests only.
pub const MAX_CLIENT_MESSAGE: usize = 64 << 10;

/// Longest a frame may wait to be taken by a client: one that stops
/// reading is closed after it, and its place freed.
pub const SEND_TIMEOUT: Duration = Duration::from_secs(10);

/// A client's place among the [`MAX_CLIENTS`], given back when dropped:
/// also when the upgrade fails and the socket's task never runs.
struct Place(Arc<AtomicUsize>);

impl Drop for Place {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

const INDEX: &str = include_str!("../assets/index.html");
const APP_JS: &str = include_str!("../assets/app.js");
const APP_CSS: &str = include_str!("../assets/app.css");

/// What the routes share.
#[derive(Clone)]
pub struct App {
    guard: Arc<Guard>,
    fleet: watch::Receiver<Arc<str>>,
    clients: Arc<AtomicUsize>,
}

impl App {
    /// The routes of `node`'s page, behind `guard`.
    pub fn new(node: &pulicast::Node, guard: Guard) -> Self {
        Self {
            guard: Arc::new(guard),
            fleet: crate::fleet::spawn(node.clone()),
            clients: Arc::default(),
        }
    }

    /// The clients connected now.
    pub fn clients(&self) -> usize {
        self.clients.load(Ordering::Relaxed)
    }

    /// The router: the page, its assets and the socket, all guarded.
    pub fn router(&self) -> Router {
        Router::new()
            .route("/", get(index))
            .route(
                "/app.js",
                get(|| async { asset("text/javascript; charset=utf-8", APP_JS) }),
            )
            .route(
                "/app.css",
                get(|| async { asset("text/css; charset=utf-8", APP_CSS) }),
            )
            .route("/ws", get(socket))
            .with_state(self.clone())
            .layer(axum::middleware::from_fn_with_state(
                Arc::clone(&self.guard),
                crate::guard::check,
            ))
            .layer(axum::middleware::from_fn(crate::guard::headers))
    }

    /// Serves the page on `listener` until `stop` resolves.
    pub async fn serve(
        &self,
        listener: tokio::net::TcpListener,
        stop: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> std::io::Result<()> {
        let app = self
            .router()
            .into_make_service_with_connect_info::<SocketAddr>();
        axum::serve(listener, app)
            .with_graceful_shutdown(stop)
            .await
    }
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    ([(header::CONTENT_TYPE, content_type)], body).into_response()
}

/// The page. Opened with the token in its address, it sets the cookie and
/// sends the browser on to the address without it (so the token does not
/// stay in the history or the address bar).
async fn index(State(app): State<App>, Query(query): Query<HashMap<String, String>>) -> Response {
    if query.contains_key("token") {
        return (
            StatusCode::SEE_OTHER,
            [
                (header::SET_COOKIE, app.guard.set_cookie()),
                (header::LOCATION, "/".to_string()),
            ],
        )
            .into_response();
    }
    asset("text/html; charset=utf-8", INDEX)
}

/// The fleet's socket.
async fn socket(State(app): State<App>, upgrade: WebSocketUpgrade) -> Response {
    // Counted here, so a refusal comes before the upgrade.
    let before = app.clients.fetch_add(1, Ordering::SeqCst);
    let place = Place(Arc::clone(&app.clients));
    if before >= MAX_CLIENTS {
        return (StatusCode::SERVICE_UNAVAILABLE, "too many clients\n").into_response();
    }
    upgrade
        .max_message_size(MAX_CLIENT_MESSAGE)
        // A frame's header can't make the server set aside more either.
        .max_frame_size(MAX_CLIENT_MESSAGE)
        .on_upgrade(move |socket| async move {
            serve_client(socket, app.fleet.clone()).await;
            drop(place);
        })
}

/// One client: the newest fleet frame whenever it changes; what it sends
/// must be a request the page makes (none yet but `{"op":"ping"}`), or it
/// is closed (policy violation), alone.
async fn serve_client(mut socket: WebSocket, mut fleet: watch::Receiver<Arc<str>>) {
    let first = fleet.borrow_and_update().clone();
    if !send(&mut socket, first.as_ref()).await {
        return;
    }
    loop {
        tokio::select! {
            changed = fleet.changed() => {
                if changed.is_err() {
                    return;
                }
                let frame = fleet.borrow_and_update().clone();
                if !send(&mut socket, frame.as_ref()).await {
                    return;
                }
            }
            incoming = socket.recv() => match incoming {
                Some(Ok(Message::Text(text))) if is_request(text.as_str()) => {
                    if !send(&mut socket, r#"{"kind":"pong"}"#).await {
                        return;
                    }
                }
                Some(Ok(Message::Ping(_) | Message::Pong(_))) => {}
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return,
                Some(Ok(_)) => {
                    let close = CloseFrame { code: 1008, reason: "not a request of the page".into() };
                    let _ = socket.send(Message::Close(Some(close))).await;
                    return;
                }
            },
        }
    }
}

/// Sends `text`; false if the client is gone or took longer than
/// [`SEND_TIMEOUT`] to take it.
async fn send(socket: &mut WebSocket, text: &str) -> bool {
    let sent = tokio::time::timeout(SEND_TIMEOUT, socket.send(Message::Text(text.into()))).await;
    matches!(sent, Ok(Ok(())))
}

/// Whether `text` is a request the page makes.
fn is_request(text: &str) -> bool {
    serde_json::from_str::<serde_json::Value>(text)
        .is_ok_and(|v| v.get("op").and_then(|op| op.as_str()) == Some("ping"))
}

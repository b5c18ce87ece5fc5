//! The routes: the page and its script and style (built into the binary),
//! and the WebSocket that carries the fleet. Every route is behind the
//! guard ([`crate::guard`]).

use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use tokio::sync::{broadcast, watch};

use crate::channels::{Feed, Feeds};
use crate::guard::Guard;
use crate::settings::Change;
use pulicast::FleetSettings;

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
const UPLOT_JS: &str = include_str!("../assets/vendor/uPlot.iife.min.js");
const UPLOT_CSS: &str = include_str!("../assets/vendor/uPlot.min.css");
const UPLOT_LICENSE: &str = include_str!("../assets/vendor/uPlot.LICENSE");

/// What the routes share.
#[derive(Clone)]
pub struct App {
    guard: Arc<Guard>,
    fleet: watch::Receiver<Utf8Bytes>,
    settings: Arc<FleetSettings>,
    settings_frames: watch::Receiver<Utf8Bytes>,
    feeds: Feeds,
    node: pulicast::Node,
    clients: Arc<AtomicUsize>,
}

impl App {
    /// The routes of `node`'s page, behind `guard`.
    pub fn new(node: &pulicast::Node, guard: Guard) -> Self {
        let (settings, settings_frames) = crate::settings::spawn(node);
        Self {
            settings,
            settings_frames,
            guard: Arc::new(guard),
            fleet: crate::fleet::spawn(node.clone()),
            feeds: Feeds::new(node),
            node: node.clone(),
            clients: Arc::default(),
        }
    }

    /// The clients connected now.
    pub fn clients(&self) -> usize {
        self.clients.load(Ordering::Relaxed)
    }

    /// The channels some client watches now.
    pub fn watched(&self) -> usize {
        self.feeds.watched()
    }

    /// The router: the page, its assets and the socket, all guarded.
    pub fn router(&self) -> Router {
        let routes = Router::new()
            .route("/", get(index))
            .route(
                "/app.js",
                get(|| async { asset("text/javascript; charset=utf-8", APP_JS) }),
            )
            .route(
                "/app.css",
                get(|| async { asset("text/css; charset=utf-8", APP_CSS) }),
            )
            .route(
                "/vendor/uPlot.iife.min.js",
                get(|| async { asset("text/javascript; charset=utf-8", UPLOT_JS) }),
            )
            .route(
                "/vendor/uPlot.min.css",
                get(|| async { asset("text/css; charset=utf-8", UPLOT_CSS) }),
            )
            .route(
                "/vendor/uPlot.LICENSE",
                get(|| async { asset("text/plain; charset=utf-8", UPLOT_LICENSE) }),
            )
            .route("/ws", get(socket))
            .with_state(self.clone());
        crate::guard::guarded(routes, &self.guard)
    }

    /// Serves the page on `listener` until `stop` resolves.
    pub async fn serve(
        &self,
        listener: tokio::net::TcpListener,
        stop: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> std::io::Result<()> {
        crate::http::serve(listener, self.router(), stop).await
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
            serve_client(socket, app).await;
            drop(place);
        })
}

/// Frames of a client's pending requests waiting to be sent: a call's
/// progress that finds it full is dropped (and counted in its reply).
pub const OUTBOX: usize = 256;

/// How often a client is pinged.
pub const PING_EVERY: Duration = Duration::from_secs(15);

/// A client not heard from for this long (its pongs included) is closed.
pub const SILENT_FOR: Duration = Duration::from_secs(45);

/// Most channels one client watches at once.
pub const MAX_WATCH: usize = 16;

/// Most requests of one client waiting for an answer (setting changes,
/// calls); one more is refused at once.
pub const MAX_PENDING: usize = 8;

/// What the page may ask.
#[derive(Debug, PartialEq)]
enum Request {
    Ping,
    /// Watch exactly these channels (full names) from now on.
    Watch(Vec<String>),
    /// Change a setting; the answer names `id`.
    Setting {
        id: u64,
        name: String,
        change: Change,
    },
    /// Call a service.
    Call(crate::calls::Call),
    /// Cancel the call of this id.
    Cancel(u64),
    /// Publish a JSON value on a channel.
    Publish {
        id: u64,
        channel: String,
        value: serde_json::Value,
    },
    /// The JSON Schema of a service's request or a channel's message.
    Schema {
        of: String,
        name: String,
    },
}

/// `text` as a request the page makes, or `None` (the client is then
/// closed).
fn request(text: &str) -> Option<Request> {
    let v: serde_json::Value = serde_json::from_str(text).ok()?;
    match v.get("op")?.as_str()? {
        "ping" => Some(Request::Ping),
        "watch" => {
            // More than MAX_WATCH are refused by name, in the answer; the
            // message's own bound (MAX_CLIENT_MESSAGE) bounds the list.
            let names = v.get("channels")?.as_array()?;
            let names = names
                .iter()
                .map(|n| n.as_str().map(str::to_string))
                .collect::<Option<Vec<String>>>()?;
            Some(Request::Watch(names))
        }
        op @ ("set" | "reset" | "unset") => {
            let id = v.get("id")?.as_u64()?;
            let name = v.get("name")?.as_str()?.to_string();
            let change = match op {
                "reset" => Change::Reset,
                "unset" => Change::Unset,
                _ => match (v.get("text"), v.get("json")) {
                    (Some(t), None) => Change::Text(t.as_str()?.to_string()),
                    (None, Some(j)) => Change::Json(j.clone()),
                    _ => return None,
                },
            };
            Some(Request::Setting { id, name, change })
        }
        "call" => {
            let timeout = match v.get("timeout") {
                None => crate::calls::DEFAULT_TIMEOUT,
                Some(t) => {
                    let secs = t.as_f64().filter(|s| s.is_finite() && *s > 0.0)?;
                    // Any number: one too large for a Duration is the most.
                    Duration::try_from_secs_f64(secs).map_or(crate::calls::MAX_TIMEOUT, |d| {
                        d.min(crate::calls::MAX_TIMEOUT)
                    })
                }
            };
            let target = match v.get("target") {
                None | Some(serde_json::Value::Null) => None,
                Some(t) => Some(t.as_str()?.to_string()),
            };
            Some(Request::Call(crate::calls::Call {
                id: v.get("id")?.as_u64()?,
                service: v.get("service")?.as_str()?.to_string(),
                target,
                request: v.get("request")?.clone(),
                timeout,
            }))
        }
        "cancel" => Some(Request::Cancel(v.get("id")?.as_u64()?)),
        "publish" => Some(Request::Publish {
            id: v.get("id")?.as_u64()?,
            channel: v.get("channel")?.as_str()?.to_string(),
            value: v.get("value")?.clone(),
        }),
        "schema" => {
            let of = v.get("of")?.as_str()?;
            if of != "service" && of != "channel" {
                return None;
            }
            Some(Request::Schema {
                of: of.to_string(),
                name: v.get("name")?.as_str()?.to_string(),
            })
        }
        _ => None,
    }
}

/// The channels a client watches, and the buckets it lost by falling
/// behind, by channel.
#[derive(Default)]
struct Watching {
    feeds: HashMap<String, (Arc<Feed>, broadcast::Receiver<Arc<str>>)>,
    dropped: HashMap<String, u64>,
}

impl Watching {
    /// Watches `names` (and no other): the answer for the page, which
    /// says which are watched and why any other is not.
    fn set(&mut self, feeds: &Feeds, names: Vec<String>) -> String {
        let mut refused = serde_json::Map::new();
        // By full name, as buckets name them (`/a//b` is `a/b`).
        let mut resolved = Vec::new();
        for name in names {
            match pulicast::resolve_name(&name, "") {
                Ok(full) => resolved.push(full),
                Err(e) => {
                    refused.insert(crate::fleet::cut(&name), e.to_string().into());
                }
            }
        }
        let mut names = resolved;
        names.dedup();
        if names.len() > MAX_WATCH {
            for name in names.drain(MAX_WATCH..) {
                let why = format!("a page watches at most {MAX_WATCH} channels");
                refused.insert(crate::fleet::cut(&name), why.into());
            }
        }
        self.feeds.retain(|c, _| names.contains(c));
        self.dropped.retain(|c, _| names.contains(c));
        for name in names {
            if self.feeds.contains_key(&name) {
                continue;
            }
            match feeds.get(&name) {
                Ok(feed) => {
                    let rx = feed.subscribe();
                    self.feeds.insert(name, (feed, rx));
                }
                Err(e) => {
                    refused.insert(crate::fleet::cut(&name), e.to_string().into());
                }
            }
        }
        let mut watched: Vec<&String> = self.feeds.keys().collect();
        watched.sort();
        serde_json::json!({ "kind": "watching", "channels": watched, "refused": refused })
            .to_string()
    }

    /// Every bucket that came since the last call, as one frame, or
    /// `None`.
    fn take(&mut self) -> Option<String> {
        let mut buckets: Vec<Arc<str>> = Vec::new();
        for (name, (_, rx)) in &mut self.feeds {
            loop {
                match rx.try_recv() {
                    Ok(b) => buckets.push(b),
                    Err(broadcast::error::TryRecvError::Lagged(n)) => {
                        *self.dropped.entry(name.clone()).or_default() += n;
                    }
                    Err(_) => break,
                }
            }
        }
        if buckets.is_empty() {
            return None;
        }
        // The buckets are JSON already: joined, not parsed again.
        let mut frame = String::from(r#"{"kind":"samples","buckets":["#);
        for (i, b) in buckets.iter().enumerate() {
            if i > 0 {
                frame.push(',');
            }
            frame.push_str(b);
        }
        frame.push_str(r#"],"dropped":"#);
        frame.push_str(&serde_json::to_string(&self.dropped).unwrap_or_else(|_| "{}".into()));
        frame.push('}');
        Some(frame)
    }
}

/// One client: the newest fleet frame whenever it changes, and the
/// buckets of the channels it watches, at most one frame a
/// [`crate::channels::TICK`]. What it sends must be a request the page
/// makes, or it is closed (policy violation), alone.
async fn serve_client(mut socket: WebSocket, app: App) {
    let (mut fleet, mut settings, feeds) = (app.fleet, app.settings_frames, app.feeds);
    let firsts = [
        fleet.borrow_and_update().clone(),
        settings.borrow_and_update().clone(),
    ];
    for first in firsts {
        if !send(&mut socket, first).await {
            return;
        }
    }
    // A client that went without a word (a laptop asleep, a network
    // gone) is found by pinging: the browser answers by itself.
    let mut heard = tokio::time::Instant::now();
    let mut ping = tokio::time::interval_at(heard + PING_EVERY, PING_EVERY);
    // Requests waiting for an answer (setting changes, calls), by id;
    // aborted when the client goes. Their frames come through `outbox`.
    let mut pending: tokio::task::JoinSet<u64> = tokio::task::JoinSet::new();
    let mut cancels: HashMap<u64, tokio::sync::oneshot::Sender<()>> = HashMap::new();
    let (outbox, mut answers) = tokio::sync::mpsc::channel::<Utf8Bytes>(OUTBOX);
    let mut watching = Watching::default();
    let mut tick = crate::channels::ticks(crate::channels::CLIENT_LAG);
    loop {
        tokio::select! {
            changed = fleet.changed() => {
                if changed.is_err() {
                    return;
                }
                let frame = fleet.borrow_and_update().clone();
                if !send(&mut socket, frame).await {
                    return;
                }
            }
            changed = settings.changed() => {
                if changed.is_err() {
                    return;
                }
                let frame = settings.borrow_and_update().clone();
                if !send(&mut socket, frame).await {
                    return;
                }
            }
            Some(done) = pending.join_next(), if !pending.is_empty() => {
                if let Ok(id) = done {
                    cancels.remove(&id);
                }
            }
            Some(frame) = answers.recv() => {
                if !send(&mut socket, frame).await {
                    return;
                }
            }
            _ = tick.tick(), if !watching.feeds.is_empty() => {
                if let Some(frame) = watching.take() {
                    if !send(&mut socket, frame.into()).await {
                        return;
                    }
                }
            }
            _ = ping.tick() => {
                if heard.elapsed() >= SILENT_FOR {
                    return;
                }
                let pinged = tokio::time::timeout(SEND_TIMEOUT, socket.send(Message::Ping(Default::default()))).await;
                if !matches!(pinged, Ok(Ok(()))) {
                    return;
                }
            }
            incoming = socket.recv() => match incoming {
                Some(Ok(Message::Text(text))) => {
                    heard = tokio::time::Instant::now();
                    let answer = match request(text.as_str()) {
                        Some(Request::Ping) => r#"{"kind":"pong"}"#.to_string(),
                        Some(Request::Watch(names)) => watching.set(&feeds, names),
                        Some(Request::Setting { id, .. }) if pending.len() >= MAX_PENDING => {
                            serde_json::json!({
                                "kind": "done", "id": id, "ok": false,
                                "error": format!("{MAX_PENDING} requests are waiting already"),
                            })
                            .to_string()
                        }
                        Some(Request::Setting { id, name, change }) => {
                            let fleet_settings = Arc::clone(&app.settings);
                            let out = outbox.clone();
                            pending.spawn(async move {
                                let mut answer = crate::settings::apply(&fleet_settings, &name, change).await;
                                answer["kind"] = "done".into();
                                answer["id"] = id.into();
                                answer["name"] = crate::fleet::cut(&name).into();
                                let _ = out.send(answer.to_string().into()).await;
                                id
                            });
                            continue;
                        }
                        Some(Request::Call(call)) if pending.len() >= MAX_PENDING || cancels.contains_key(&call.id) => {
                            serde_json::json!({
                                "kind": "call", "id": call.id, "event": "failed",
                                "error": format!("{MAX_PENDING} requests are waiting already, or this id is"),
                            })
                            .to_string()
                        }
                        Some(Request::Call(call)) => {
                            let (cancel, cancelled) = tokio::sync::oneshot::channel();
                            let id = call.id;
                            cancels.insert(id, cancel);
                            let run = crate::calls::run(app.node.clone(), call, cancelled, outbox.clone());
                            pending.spawn(async move {
                                run.await;
                                id
                            });
                            continue;
                        }
                        Some(Request::Publish { id, channel, value }) => {
                            let done = crate::calls::publish(&app.node, &channel, &value);
                            serde_json::json!({
                                "kind": "published", "id": id, "channel": crate::fleet::cut(&channel),
                                "ok": done.is_ok(), "error": done.err().map(|e| crate::fleet::cut(&e)),
                            })
                            .to_string()
                        }
                        Some(Request::Schema { of, name }) => {
                            let mut answer = crate::calls::schema(&app.node, &of, &name);
                            answer["kind"] = "schema".into();
                            answer["of"] = of.into();
                            answer["name"] = crate::fleet::cut(&name).into();
                            answer.to_string()
                        }
                        Some(Request::Cancel(id)) => {
                            // A call already ended has nothing to cancel.
                            if let Some(cancel) = cancels.remove(&id) {
                                let _ = cancel.send(());
                            }
                            continue;
                        }
                        None => {
                            let close = CloseFrame { code: 1008, reason: "not a request of the page".into() };
                            let _ = socket.send(Message::Close(Some(close))).await;
                            return;
                        }
                    };
                    if !send(&mut socket, answer.into()).await {
                        return;
                    }
                }
                Some(Ok(Message::Ping(_) | Message::Pong(_))) => heard = tokio::time::Instant::now(),
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => return,
                Some(Ok(Message::Binary(_))) => {
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
async fn send(socket: &mut WebSocket, text: Utf8Bytes) -> bool {
    let sent = tokio::time::timeout(SEND_TIMEOUT, socket.send(Message::Text(text))).await;
    matches!(sent, Ok(Ok(())))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_pages_requests_are_requests() {
        assert_eq!(request(r#"{"op":"ping"}"#), Some(Request::Ping));
        assert_eq!(
            request(r#"{"op":"watch","channels":["rover1/pose"]}"#),
            Some(Request::Watch(vec!["rover1/pose".into()]))
        );
        for bad in [
            "",
            "ping",
            r#"{"op":"shutdown"}"#,
            r#"{"op":"watch"}"#,
            r#"{"op":"watch","channels":"rover1/pose"}"#,
            r#"{"op":"watch","channels":[1]}"#,
            r#"{"op":"set","id":1,"name":"a"}"#,
            r#"{"op":"set","id":1,"name":"a","text":"1","json":1}"#,
            r#"{"op":"set","id":-1,"name":"a","text":"1"}"#,
            r#"{"op":"reset","name":"a"}"#,
            r#"{"op":"call","id":1,"service":"s"}"#,
            r#"{"op":"call","id":1,"service":"s","request":1,"timeout":-1}"#,
            r#"{"op":"call","id":1,"service":"s","request":1,"target":7}"#,
            r#"{"op":"cancel"}"#,
        ] {
            assert_eq!(request(bad), None, "{bad}");
        }
        assert_eq!(
            request(r#"{"op":"set","id":7,"name":"rover1/max_speed","text":"1.5"}"#),
            Some(Request::Setting {
                id: 7,
                name: "rover1/max_speed".into(),
                change: Change::Text("1.5".into())
            })
        );
        assert_eq!(
            request(r#"{"op":"unset","id":8,"name":"rover1/mode"}"#),
            Some(Request::Setting {
                id: 8,
                name: "rover1/mode".into(),
                change: Change::Unset
            })
        );
        let call = request(
            r#"{"op":"call","id":3,"service":"rover1/distance_to","request":[0,0],"timeout":1e300}"#,
        );
        assert_eq!(
            call,
            Some(Request::Call(crate::calls::Call {
                id: 3,
                service: "rover1/distance_to".into(),
                target: None,
                request: serde_json::json!([0, 0]),
                timeout: crate::calls::MAX_TIMEOUT,
            }))
        );
        assert_eq!(
            request(r#"{"op":"cancel","id":3}"#),
            Some(Request::Cancel(3))
        );
        // Too many is a request still: the answer refuses the rest.
        let many: Vec<String> = (0..=MAX_WATCH).map(|i| format!("c{i}")).collect();
        let too_many = serde_json::json!({"op": "watch", "channels": many}).to_string();
        assert_eq!(request(&too_many), Some(Request::Watch(many)));
    }
}

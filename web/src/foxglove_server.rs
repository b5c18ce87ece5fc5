//! `puli web --foxglove`: the fleet as a Foxglove WebSocket server, with
//! the `foxglove` crate. Every published channel is advertised with a JSON
//! Schema made from its announced type and its messages go as JSON (the
//! `text` conversion the tools use); services are Foxglove services
//! (request and reply as JSON); settings are Foxglove parameters (get,
//! set, subscribe); the connection graph is the fleet's; a client may
//! publish JSON into the fleet's channels.
//!
//! The crate's server listens on a loopback port of its own, behind the
//! [`crate::gate`] (token, origin, counted drops). Its callbacks run on
//! its clients' tasks and must not block: they only hand events to this
//! module's task through a bounded queue (what does not fit is dropped
//! and counted).

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use foxglove::websocket::service::{Request, Service, ServiceSchema};
use foxglove::websocket::{
    AnyClient, Capability, ChannelView, Client, ClientChannel, ConnectionGraph,
    GetParametersResponder, Parameter, ParameterHandler, ParameterValue, ServerListener,
    SetParametersResponder,
};
use foxglove::{Context, RawChannel, Schema, WebSocketServer, WebSocketServerHandle};
use pulicast::{FleetSettings, SettingInfo, TypeInfo};
use pulicast_tools::sniff::type_display;
use serde_json::Value;
use tokio::sync::mpsc;

use crate::channels::MAX_DECODED;

/// How often the fleet is read again (channels, services, graph).
pub const EVERY: Duration = Duration::from_secs(1);

/// How often settings are read again for parameter subscribers.
pub const SETTINGS_EVERY: Duration = Duration::from_millis(250);

/// Events from the server's callbacks waiting for this module's task.
pub const EVENTS: usize = 4096;

/// Message data frames the crate holds for one client (its own queue,
/// behind the gate's): oldest dropped.
pub const BACKLOG: usize = 1024;

/// Longest a service call from Foxglove may take.
pub const CALL_TIMEOUT: Duration = Duration::from_secs(30);

/// The ports of 1024 and above that the Fetch standard calls bad
/// (<https://fetch.spec.whatwg.org/#bad-port>): every browser that follows
/// it refuses to fetch from them or open a WebSocket to them. The crate's
/// server, which checks no token and no origin, listens on the first of
/// them that is free, so no web page can reach it past the gate.
pub const BROWSERS_REFUSE: [u16; 19] = [
    6665, 6666, 6667, 6668, 6669, 6679, 6697, 10080, 6566, 4190, 4045, 3659, 2049, 1719, 1720,
    1723, 5060, 5061, 6000,
];

/// Longest setting value offered as a parameter, in bytes of JSON.
pub const MAX_PARAMETER: usize = 64 << 10;

/// Most bytes of client messages waiting to be published.
pub const MAX_QUEUED_BYTES: u64 = 16 << 20;

/// Most parameter requests and service calls of all clients running at
/// once: one more is refused (the crate bounds them per connection only,
/// and a connection may come back).
pub const MAX_TASKS: usize = 128;

/// How long a parameter this server has not heard of yet is waited for.
pub const GET_WAIT: Duration = Duration::from_secs(2);

/// Most channels advertised.
pub const MAX_CHANNELS: usize = 1024;

/// Most services offered (chosen server by server beyond it).
pub const MAX_SERVICES: usize = 256;

/// What the server's callbacks hand over.
enum Event {
    Subscribe(String),
    Unsubscribe(String),
    Publish {
        client: Client,
        topic: String,
        payload: Vec<u8>,
    },
}

/// What the bridge counts.
#[derive(Debug, Default)]
pub struct BridgeStats {
    /// Messages logged to Foxglove channels.
    pub logged: AtomicU64,
    /// Callback events dropped for a full queue.
    pub events_dropped: AtomicU64,
    /// Client messages not published (not JSON, or the channel refused).
    pub publish_refused: AtomicU64,
}

struct Listener {
    events: mpsc::Sender<Event>,
    /// Bytes of client messages waiting in `events` (at most
    /// [`MAX_QUEUED_BYTES`]).
    queued: Arc<AtomicU64>,
    /// Client channels (client, channel id) to topic, for their JSON.
    advertised: Mutex<HashMap<(u32, u32), String>>,
    stats: Arc<BridgeStats>,
}

impl Listener {
    fn hand(&self, event: Event) {
        if self.events.try_send(event).is_err() {
            self.stats.events_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }
}

impl ServerListener for Listener {
    fn on_subscribe(&self, _client: Client, channel: ChannelView) {
        self.hand(Event::Subscribe(channel.topic().to_string()));
    }

    fn on_unsubscribe(&self, _client: Client, channel: ChannelView) {
        self.hand(Event::Unsubscribe(channel.topic().to_string()));
    }

    fn on_client_advertise(&self, client: Client, channel: &ClientChannel) {
        if channel.topic.len() > crate::fleet::MAX_NAME {
            client.send_status(foxglove::websocket::Status::error(format!(
                "a channel's name is at most {} bytes",
                crate::fleet::MAX_NAME
            )));
            return;
        }
        if channel.encoding != "json" {
            client.send_status(foxglove::websocket::Status::error(format!(
                "{}: only JSON is published into the fleet",
                channel.topic
            )));
            return;
        }
        let mut advertised = self.advertised.lock().unwrap_or_else(|e| e.into_inner());
        // Bounded like everything a client sends.
        if advertised.len() < 1024 {
            advertised.insert(
                (u32::from(client.id()), u32::from(channel.id)),
                channel.topic.clone(),
            );
        }
    }

    fn on_client_unadvertise(&self, client: Client, channel: &ClientChannel) {
        let mut advertised = self.advertised.lock().unwrap_or_else(|e| e.into_inner());
        advertised.remove(&(u32::from(client.id()), u32::from(channel.id)));
    }

    fn on_message_data(&self, client: Client, channel: &ClientChannel, payload: &[u8]) {
        let topic = {
            let advertised = self.advertised.lock().unwrap_or_else(|e| e.into_inner());
            advertised
                .get(&(u32::from(client.id()), u32::from(channel.id)))
                .cloned()
        };
        let Some(topic) = topic else {
            return;
        };
        // The topic goes along with each message: counted too.
        let len = (payload.len() + topic.len()) as u64;
        if self.queued.fetch_add(len, Ordering::SeqCst) + len > MAX_QUEUED_BYTES {
            self.queued.fetch_sub(len, Ordering::SeqCst);
            self.stats.events_dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        if self
            .events
            .try_send(Event::Publish {
                client,
                topic,
                payload: payload.to_vec(),
            })
            .is_err()
        {
            self.queued.fetch_sub(len, Ordering::SeqCst);
            self.stats.events_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// A setting as a Foxglove parameter.
fn parameter(s: &SettingInfo) -> Parameter {
    // Whole (a value Foxglove shows is one it may send back): one too
    // long for a parameter is none.
    let value = crate::settings::value_within(s, MAX_PARAMETER);
    match (crate::settings::kind(s), value.as_f64()) {
        // A float stays one, 1.0 included.
        (Some("float"), Some(v)) => Parameter::float64(s.name.clone(), v),
        _ => Parameter {
            name: s.name.clone(),
            r#type: None,
            // No null among Foxglove's values: an unknown one is none.
            value: serde_json::from_value::<ParameterValue>(value).ok(),
        },
    }
}

struct Parameters {
    settings: Arc<FleetSettings>,
    handle: Arc<OnceLock<WebSocketServerHandle>>,
    tasks: Arc<tokio::sync::Semaphore>,
}

impl ParameterHandler for Parameters {
    fn get(
        &self,
        client: AnyClient,
        names: Vec<String>,
        _request_id: Option<String>,
        responder: GetParametersResponder,
    ) {
        let Ok(task) = Arc::clone(&self.tasks).try_acquire_owned() else {
            client.send_error(format!("{MAX_TASKS} requests are running already"));
            responder.respond(Vec::new());
            return;
        };
        let settings = Arc::clone(&self.settings);
        // A client asks as it connects, maybe before this server has
        // heard of the setting (or its value): a name not known yet is
        // waited for a little (as `puli config get` does), all of them
        // within one deadline, not answered as missing.
        tokio::spawn(async move {
            let _task = task;
            let now = settings.snapshot();
            let found: Vec<Parameter> = match names.is_empty() {
                true if now.is_empty() => {
                    let listed = tokio::time::timeout(GET_WAIT * 2, settings.list(GET_WAIT)).await;
                    listed.unwrap_or_default().iter().map(parameter).collect()
                }
                true => now.iter().map(parameter).collect(),
                false => {
                    let mut found = Vec::new();
                    let mut unknown = Vec::new();
                    for name in names.iter().take(1024) {
                        match now
                            .iter()
                            .find(|s| &s.name == name && s.confirmed.is_some())
                        {
                            Some(s) => found.push(parameter(s)),
                            None => unknown.push(name.clone()),
                        }
                    }
                    let waited = tokio::time::timeout(GET_WAIT, async {
                        let mut got = Vec::new();
                        for name in unknown.iter().take(64) {
                            if let Ok(s) = settings.get(name, GET_WAIT).await {
                                got.push(parameter(&s));
                            }
                        }
                        got
                    })
                    .await;
                    found.extend(waited.unwrap_or_default());
                    found
                }
            };
            responder.respond(found);
        });
    }

    fn set(
        &self,
        client: AnyClient,
        parameters: Vec<Parameter>,
        _request_id: Option<String>,
        responder: SetParametersResponder,
    ) {
        let Ok(task) = Arc::clone(&self.tasks).try_acquire_owned() else {
            client.send_error(format!("{MAX_TASKS} requests are running already"));
            responder.respond(Vec::new());
            return;
        };
        let settings = Arc::clone(&self.settings);
        let handle = Arc::clone(&self.handle);
        // The owner answers in its own time: not on the client's task.
        tokio::spawn(async move {
            let _task = task;
            let mut now = Vec::new();
            for p in parameters.into_iter().take(16) {
                let wanted = p
                    .value
                    .as_ref()
                    .and_then(|v| serde_json::to_value(v).ok())
                    .unwrap_or(Value::Null);
                let answer = match wanted {
                    Value::Null => settings.unset(&p.name, crate::settings::TIMEOUT).await,
                    v => {
                        settings
                            .set_json(&p.name, v, crate::settings::TIMEOUT)
                            .await
                    }
                };
                match answer {
                    Ok(s) => now.push(parameter(&s)),
                    Err(e) => {
                        client.send_error(format!("{}: {e}", p.name));
                        // What the owner holds, not what was asked.
                        if let Some(s) = settings.snapshot().into_iter().find(|s| s.name == p.name)
                        {
                            now.push(parameter(&s));
                        }
                    }
                }
            }
            if let Some(handle) = handle.get() {
                handle.publish_parameter_values(now.clone());
            }
            responder.respond(now);
        });
    }
}

/// The Foxglove server of a node, running.
pub struct Bridge {
    handle: Arc<OnceLock<WebSocketServerHandle>>,
    port: u16,
    stats: Arc<BridgeStats>,
    /// Kept: the server holds only a weak reference to it.
    _context: Arc<Context>,
    task: tokio::task::JoinHandle<()>,
}

impl Bridge {
    /// Starts the crate's server on a free loopback port, bridged to
    /// `node`'s fleet.
    pub async fn start(node: &pulicast::Node) -> anyhow::Result<Self> {
        let context = Context::new();
        let stats = Arc::new(BridgeStats::default());
        let (events, incoming) = mpsc::channel(EVENTS);
        let queued = Arc::new(AtomicU64::new(0));
        let listener = Arc::new(Listener {
            events,
            queued: Arc::clone(&queued),
            advertised: Mutex::default(),
            stats: Arc::clone(&stats),
        });
        let settings = Arc::new(node.fleet_settings());
        settings.refresh();
        let handle = Arc::new(OnceLock::new());
        let tasks = Arc::new(tokio::sync::Semaphore::new(MAX_TASKS));
        let parameters: Arc<dyn ParameterHandler> = Arc::new(Parameters {
            settings: Arc::clone(&settings),
            handle: Arc::clone(&handle),
            tasks: Arc::clone(&tasks),
        });
        let listener: Arc<dyn ServerListener> = listener;
        // On a port browsers refuse to connect to: only the gate (and
        // programs of this machine) reach the crate's server, no web page.
        let mut tried = Vec::new();
        let mut started = None;
        for port in BROWSERS_REFUSE {
            let attempt = WebSocketServer::new()
                .name("pulicast (puli web)")
                .bind("127.0.0.1", port)
                .context(&context)
                .capabilities([
                    Capability::ClientPublish,
                    Capability::ConnectionGraph,
                    Capability::Services,
                    Capability::Parameters,
                ])
                .supported_encodings(["json"])
                .listener(Arc::clone(&listener))
                .parameter_handler(Arc::clone(&parameters))
                .message_backlog_size(BACKLOG)
                .start()
                .await;
            match attempt {
                Ok(server) => {
                    started = Some(server);
                    break;
                }
                Err(e) => tried.push(format!("{port}: {e}")),
            }
        }
        let Some(server) = started else {
            anyhow::bail!(
                "no port browsers refuse to connect to is free on 127.0.0.1 for the Foxglove server ({})",
                tried.join("; ")
            );
        };
        let port = server.port();
        let _ = handle.set(server);
        let shared = Shared {
            node: node.clone(),
            context: Arc::clone(&context),
            handle: Arc::clone(&handle),
            settings,
            queued,
            tasks,
            stats: Arc::clone(&stats),
        };
        let task = tokio::spawn(run(shared, incoming));
        Ok(Self {
            handle,
            port,
            stats,
            _context: context,
            task,
        })
    }

    /// The loopback port of the crate's server (the gate's inner side):
    /// one of [`BROWSERS_REFUSE`].
    pub fn port(&self) -> u16 {
        self.port
    }

    /// What the bridge counted.
    pub fn stats(&self) -> Arc<BridgeStats> {
        Arc::clone(&self.stats)
    }

    /// Clients connected to the crate's server now.
    pub fn clients(&self) -> usize {
        self.handle.get().map_or(0, |h| h.client_count())
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// A channel advertised to Foxglove, and its feed while subscribed.
struct Advertised {
    raw: Arc<RawChannel>,
    fingerprint: [u8; 8],
    feed: Option<tokio::task::JoinHandle<()>>,
}

/// Starts `c`'s feed when a client subscribes to it and none runs; stops
/// it when none does.
fn reconcile(node: &pulicast::Node, topic: &str, c: &mut Advertised, stats: &Arc<BridgeStats>) {
    let wanted = c.raw.has_sinks();
    match (&c.feed, wanted) {
        (None, true) => c.feed = feed(node, topic, Arc::clone(&c.raw), Arc::clone(stats)),
        (Some(f), true) if f.is_finished() => {
            c.feed = feed(node, topic, Arc::clone(&c.raw), Arc::clone(stats));
        }
        (Some(_), false) => {
            if let Some(f) = c.feed.take() {
                f.abort();
            }
        }
        _ => {}
    }
}

fn schema_bytes(info: &TypeInfo) -> Option<Vec<u8>> {
    let schema = pulicast::text::json_schema_of(info)?;
    serde_json::to_vec(&schema).ok()
}

/// What the bridge's task works with.
struct Shared {
    node: pulicast::Node,
    context: Arc<Context>,
    handle: Arc<OnceLock<WebSocketServerHandle>>,
    settings: Arc<FleetSettings>,
    queued: Arc<AtomicU64>,
    tasks: Arc<tokio::sync::Semaphore>,
    stats: Arc<BridgeStats>,
}

/// The task behind the server: follows the fleet, starts and stops feeds
/// as Foxglove subscribes, publishes what clients send.
async fn run(shared: Shared, mut incoming: mpsc::Receiver<Event>) {
    let Shared {
        node,
        context,
        handle,
        settings,
        queued,
        tasks,
        stats,
    } = shared;
    let mut channels: BTreeMap<String, Advertised> = BTreeMap::new();
    let mut services: HashMap<String, [u8; 8]> = HashMap::new();
    let mut graph_said = String::new();
    let mut fleet = tokio::time::interval(EVERY);
    let mut params = tokio::time::interval(SETTINGS_EVERY);
    let mut said_params: HashMap<String, String> = HashMap::new();
    let mut round = 0u64;
    // The channels clients may publish into (announced by some member,
    // not hidden), with the type they go out as; and when each client
    // last heard why its message to a channel was refused.
    let mut publishable: HashMap<String, Option<TypeInfo>> = HashMap::new();
    let mut told: HashMap<(u32, String), tokio::time::Instant> = HashMap::new();
    loop {
        tokio::select! {
            _ = fleet.tick() => {
                let Some(server) = handle.get() else { continue };
                let members = node.discovery().live_members();
                publishable = publishable_of(&members);
                follow_channels(&members, &context, &mut channels);
                for (topic, c) in channels.iter_mut() {
                    reconcile(&node, topic, c, &stats);
                }
                let offered = offered_services(&node);
                follow_services(&node, &offered, server, &mut services, &tasks);
                let (graph, said) = graph_of(&members, &offered);
                if said != graph_said {
                    graph_said = said;
                    let _ = server.publish_connection_graph(graph);
                }
            }
            _ = params.tick() => {
                let Some(server) = handle.get() else { continue };
                round += 1;
                if round.is_multiple_of(4) {
                    settings.refresh();
                }
                let changed: Vec<Parameter> = settings
                    .snapshot()
                    .iter()
                    .map(parameter)
                    .filter(|p| {
                        let text = serde_json::to_string(&p.value).unwrap_or_default();
                        said_params.insert(p.name.clone(), text.clone()).as_deref() != Some(text.as_str())
                    })
                    .collect();
                if !changed.is_empty() {
                    server.publish_parameter_values(changed);
                }
            }
            event = incoming.recv() => match event {
                None => return,
                // Whatever the event says, the crate's own count decides:
                // a lost event can't leave a feed running or missing.
                Some(Event::Subscribe(topic) | Event::Unsubscribe(topic)) => {
                    if let Some(c) = channels.get_mut(&topic) {
                        reconcile(&node, &topic, c, &stats);
                    }
                }
                Some(Event::Publish { client, topic, payload }) => {
                    queued.fetch_sub((payload.len() + topic.len()) as u64, Ordering::SeqCst);
                    let published = match publishable.get(&topic) {
                        None => Err(format!(
                            "no member publishes or subscribes {topic} (a service's or a setting's \
                             own channel is never published into)"
                        )),
                        Some(ty) => serde_json::from_slice::<Value>(&payload)
                            .map_err(|e| format!("not JSON: {e}"))
                            .and_then(|v| crate::calls::publish_as(&node, &topic, ty.as_ref(), &v)),
                    };
                    if let Err(why) = published {
                        stats.publish_refused.fetch_add(1, Ordering::Relaxed);
                        tell_refused(&mut told, &client, &topic, &why);
                    }
                }
            },
        }
    }
}

/// Advertises each published channel (not hidden) with its type's
/// schema; closes those whose publishers are gone, or whose type changed
/// (advertised again with the new one).
fn follow_channels(
    members: &[pulicast::MemberView],
    context: &Arc<Context>,
    channels: &mut BTreeMap<String, Advertised>,
) {
    let mut published: BTreeMap<String, Option<TypeInfo>> = BTreeMap::new();
    for m in members {
        for c in m.channels.iter().filter(|c| c.publishes) {
            if pulicast::is_hidden_channel(&c.name) {
                continue;
            }
            let slot = published.entry(c.name.clone()).or_default();
            if slot.is_none() {
                *slot = c.message_type.clone();
            }
        }
    }
    // Beyond the bound, which are offered is chosen member by member: a
    // member announcing thousands can't push out the others'.
    if published.len() > MAX_CHANNELS {
        let owners = crate::fleet::channel_owners(members)
            .into_iter()
            .map(|o| {
                o.into_iter()
                    .filter(|n| published.contains_key(*n))
                    .collect()
            })
            .collect();
        let offered: std::collections::HashSet<&str> =
            crate::fair::choose(owners, MAX_CHANNELS, usize::MAX, |_| 0)
                .into_iter()
                .collect();
        published.retain(|name, _| offered.contains(name.as_str()));
    }
    channels.retain(|name, c| {
        let same = published
            .get(name)
            .is_some_and(|t| t.as_ref().map_or([0; 8], |t| t.fingerprint) == c.fingerprint);
        if !same {
            if let Some(f) = c.feed.take() {
                f.abort();
            }
            c.raw.close();
        }
        same
    });
    for (name, info) in published {
        if channels.contains_key(&name) {
            continue;
        }
        let schema = info
            .as_ref()
            .and_then(|t| Some(Schema::new(type_display(t), "jsonschema", schema_bytes(t)?)));
        let built = context
            .channel_builder(name.clone())
            .message_encoding("json")
            .schema(schema)
            .build_raw();
        if let Ok(raw) = built {
            channels.insert(
                name,
                Advertised {
                    raw,
                    fingerprint: info.as_ref().map_or([0; 8], |t| t.fingerprint),
                    feed: None,
                },
            );
        }
    }
}

/// The channels some member announces (not hidden), each with the type a
/// client's message goes out as: its publishers', else its subscribers'
/// (as `puli pub` and the page read it).
fn publishable_of(members: &[pulicast::MemberView]) -> HashMap<String, Option<TypeInfo>> {
    let mut by_publishers: HashMap<String, Option<TypeInfo>> = HashMap::new();
    let mut by_subscribers: HashMap<String, Option<TypeInfo>> = HashMap::new();
    for m in members {
        for c in &m.channels {
            if pulicast::is_hidden_channel(&c.name) {
                continue;
            }
            // Not bounded here: no larger than discovery's own table,
            // and a bound would let many channels announced first make
            // others unpublishable.
            let map = match c.publishes {
                true => &mut by_publishers,
                false => &mut by_subscribers,
            };
            let slot = map.entry(c.name.clone()).or_default();
            if slot.is_none() {
                *slot = c.message_type.clone();
            }
        }
    }
    for (name, ty) in by_subscribers {
        let slot = by_publishers.entry(name).or_default();
        if slot.is_none() {
            *slot = ty;
        }
    }
    by_publishers
}

/// Most (client, channel) pairs remembered for [`tell_refused`].
const MAX_TOLD: usize = 4096;

/// How often a client hears why its messages to one channel are refused.
const TELL_EVERY: Duration = Duration::from_secs(5);

/// Tells `client` why its message to `topic` was refused: the first time,
/// then at most every [`TELL_EVERY`] (a client publishing at 100 Hz
/// into a refused channel is told, not flooded).
fn tell_refused(
    told: &mut HashMap<(u32, String), tokio::time::Instant>,
    client: &Client,
    topic: &str,
    why: &str,
) {
    let now = tokio::time::Instant::now();
    let key = (u32::from(client.id()), topic.to_string());
    if told.get(&key).is_some_and(|at| now - *at < TELL_EVERY) {
        return;
    }
    if told.len() >= MAX_TOLD {
        told.retain(|_, at| now - *at < TELL_EVERY);
    }
    // Still full: thousands of refused channels within seconds are a
    // flood; its senders are told nothing more until the table clears
    // (each refusal is still counted).
    if told.len() >= MAX_TOLD {
        return;
    }
    told.insert(key, now);
    client.send_status(
        foxglove::websocket::Status::warning(crate::fleet::cut_to(
            &format!("not published into {topic}: {why}"),
            crate::settings::MAX_TEXT,
        ))
        .with_id(format!("publish:{}", crate::fleet::cut(topic))),
    );
}

/// Sends each message of `topic` to `raw` as JSON while Foxglove
/// subscribes.
fn feed(
    node: &pulicast::Node,
    topic: &str,
    raw: Arc<RawChannel>,
    stats: Arc<BridgeStats>,
) -> Option<tokio::task::JoinHandle<()>> {
    let channel = node.channel(&format!("/{topic}"));
    let mut sub = channel.watch_raw().ok()?;
    Some(tokio::spawn(async move {
        let mut batch = Vec::new();
        let mut known = None;
        let mut looked: Option<tokio::time::Instant> = None;
        while sub.recv_many(&mut batch, 256).await > 0 {
            if looked.is_none_or(|at| at.elapsed() >= Duration::from_secs(2)) {
                known = crate::channels::known(&channel);
                looked = Some(tokio::time::Instant::now());
            }
            for m in batch.drain(..) {
                let value = match m.value.len() {
                    len @ (MAX_DECODED..) => serde_json::json!({ "bytes": len }),
                    _ => crate::channels::decode(&m.value, known.as_ref()),
                };
                if let Ok(bytes) = serde_json::to_vec(&value) {
                    raw.log(&bytes);
                    stats.logged.fetch_add(1, Ordering::Relaxed);
                }
            }
            tokio::task::yield_now().await;
        }
    }))
}

/// The services served now; beyond [`MAX_SERVICES`], those chosen
/// server by server (`crate::fair`).
fn offered_services(node: &pulicast::Node) -> Vec<pulicast::ServiceInfo> {
    let mut all = node.discovery().services();
    all.retain(|s| !s.servers.is_empty());
    let chosen: std::collections::HashSet<String> = crate::fair::choose(
        crate::fleet::service_owners(&all),
        MAX_SERVICES,
        usize::MAX,
        |_| 0,
    )
    .into_iter()
    .map(str::to_string)
    .collect();
    all.retain(|s| chosen.contains(&s.name));
    all
}

/// Offers each served service (its servers' types) as a Foxglove
/// service; takes back those gone.
fn follow_services(
    node: &pulicast::Node,
    offered: &[pulicast::ServiceInfo],
    server: &WebSocketServerHandle,
    services: &mut HashMap<String, [u8; 8]>,
    tasks: &Arc<tokio::sync::Semaphore>,
) {
    let now: HashMap<String, pulicast::ServiceEnd> = offered
        .iter()
        .filter_map(|s| {
            let end = s.server_types()?.clone();
            Some((s.name.clone(), end))
        })
        .collect();
    // Request and reply types: either changed, the schemas are offered again.
    let key = |end: &pulicast::ServiceEnd| {
        let fp = |t: &Option<TypeInfo>| t.as_ref().map_or([0; 8], |t| t.fingerprint);
        let (req, rep) = (fp(&end.request), fp(&end.reply));
        let mut key = [0u8; 8];
        for (i, k) in key.iter_mut().enumerate() {
            *k = req[i] ^ rep[i].rotate_left(1);
        }
        key
    };
    let gone: Vec<String> = services
        .iter()
        .filter(|(name, fp)| now.get(*name).is_none_or(|end| key(end) != **fp))
        .map(|(name, _)| name.clone())
        .collect();
    if !gone.is_empty() {
        server.remove_services(&gone);
        for name in gone {
            services.remove(&name);
        }
    }
    for (name, end) in now {
        if services.contains_key(&name) {
            continue;
        }
        let mut schema = ServiceSchema::new(name.clone());
        if let Some(t) = &end.request {
            if let Some(bytes) = schema_bytes(t) {
                schema =
                    schema.with_request("json", Schema::new(type_display(t), "jsonschema", bytes));
            }
        }
        if let Some(t) = &end.reply {
            if let Some(bytes) = schema_bytes(t) {
                schema =
                    schema.with_response("json", Schema::new(type_display(t), "jsonschema", bytes));
            }
        }
        let caller = node.clone();
        let service = name.clone();
        let tasks = Arc::clone(tasks);
        let built =
            Service::builder(name.clone(), schema).async_handler_fn(move |request: Request| {
                let (node, service) = (caller.clone(), service.clone());
                let task = Arc::clone(&tasks).try_acquire_owned();
                async move {
                    let _task =
                        task.map_err(|_| format!("{MAX_TASKS} requests are running already"))?;
                    call(&node, &service, request.payload()).await
                }
            });
        if server.add_services([built]).is_ok() {
            services.insert(name, key(&end));
        }
    }
}

/// One call from Foxglove: the request as JSON, the reply as JSON (its
/// progress is not Foxglove's to see); a fault as the error text.
async fn call(node: &pulicast::Node, service: &str, payload: &[u8]) -> Result<Vec<u8>, String> {
    let request: Value = serde_json::from_slice(payload).map_err(|e| format!("not JSON: {e}"))?;
    let types = pulicast_tools::call::server_types(node, service, None)
        .ok_or_else(|| format!("no server of {service}"))?;
    let message =
        pulicast_tools::call::encode_request(&request.to_string(), types.request.as_ref(), service)
            .map_err(|e| format!("{e:#}"))?;
    let client = node.raw_client(service).map_err(|e| e.to_string())?;
    let mut running = client
        .start(&message, CALL_TIMEOUT)
        .await
        .map_err(|e| e.to_string())?;
    while let Some(event) = running.next().await {
        match event {
            pulicast::CallEvent::Progress(_) => continue,
            pulicast::CallEvent::Reply { message, .. } => {
                let value = pulicast_tools::call::message_json(&message, types.reply.as_ref());
                return serde_json::to_vec(&value).map_err(|e| e.to_string());
            }
            other => return Err(running.error(other).to_string()),
        }
    }
    Err(running.error(pulicast::CallEvent::TimedOut).to_string())
}

/// The fleet's connection graph: who publishes and subscribes each
/// channel, who serves each service (by node name); and a text of it, to
/// tell a change.
fn graph_of(
    members: &[pulicast::MemberView],
    offered: &[pulicast::ServiceInfo],
) -> (ConnectionGraph, String) {
    let mut published: BTreeMap<String, Vec<String>> = BTreeMap::new();
    let mut subscribed: BTreeMap<String, Vec<String>> = BTreeMap::new();
    // Beyond the bound, which channels are drawn is chosen member by
    // member, and which services server by server.
    let shown: std::collections::HashSet<&str> = crate::fair::choose(
        crate::fleet::channel_owners(members),
        MAX_CHANNELS,
        usize::MAX,
        |_| 0,
    )
    .into_iter()
    .collect();
    for m in members {
        for c in &m.channels {
            if !shown.contains(c.name.as_str()) {
                continue;
            }
            if c.publishes {
                published
                    .entry(c.name.clone())
                    .or_default()
                    .push(m.name.clone());
            }
            if c.subscribes {
                subscribed
                    .entry(c.name.clone())
                    .or_default()
                    .push(m.name.clone());
            }
        }
    }
    let served: BTreeMap<String, Vec<String>> = offered
        .iter()
        .map(|s| {
            (
                s.name.clone(),
                s.servers.iter().map(|e| e.node.clone()).collect::<Vec<_>>(),
            )
        })
        .filter(|(_, servers)| !servers.is_empty())
        .collect();
    let said = format!("{published:?}{subscribed:?}{served:?}");
    let mut graph = ConnectionGraph::new();
    for (topic, nodes) in published {
        graph.set_published_topic(topic, nodes);
    }
    for (topic, nodes) in subscribed {
        graph.set_subscribed_topic(topic, nodes);
    }
    for (service, servers) in served {
        graph.set_advertised_service(service, servers);
    }
    (graph, said)
}

//! What `puli-sniffer` does: watch the fleet through discovery, subscribe to
//! channels raw, decode every message to text, measure rates and bandwidth.
//! The binary is argument parsing on top of this.

use std::collections::{BTreeMap, HashMap};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use parking_lot::Mutex;
use pulicast::text::decode_payload;
use pulicast::{MemberView, Node, TypeEncoding, TypeInfo};
use serde_json::{json, Value};

use crate::flags::NetArgs;

/// The name the sniffer's own node goes by.
pub const NODE_NAME: &str = "puli-sniffer";

/// Starts the sniffer's node. It announces itself like any node (so the
/// fleet knows who watches) but never publishes data.
pub async fn start(net: &NetArgs) -> Result<Node> {
    net.node(NODE_NAME)?
        .start()
        .await
        .with_context(|| format!("starting a node on port {}", net.port))
}

/// Notes for stderr on what the keys given (or missing) hid from the
/// sniffer: sealed traffic it has no key for, sealed traffic that did not
/// open under the key given for its namespace (another key), unsealed
/// traffic refused because a key was given, and a key whose namespace no
/// member uses. Without them a wrong `--key` would look like an empty fleet.
pub fn key_notes(node: &Node) -> Vec<String> {
    let mut notes = Vec::new();
    let sealed = node.stats().dropped(pulicast::DropReason::NoKey);
    if sealed > 0 {
        notes.push(format!(
            "note: {sealed} sealed datagrams this tool has no key for were dropped; what they carry is not shown: pass --key NAMESPACE=KEY or set PULICAST_KEYS"
        ));
    }
    let members = node.discovery().live_members();
    let own = node.session_id();
    for used in node.key_uses() {
        let ns = if used.namespace.is_empty() {
            "/"
        } else {
            used.namespace.as_str()
        };
        // What others sent decides: a stray datagram next to traffic that
        // opens says nothing about the key.
        match (used.not_opened, used.opened) {
            (0, _) => {}
            (n, 0) => notes.push(format!(
                "note: {n} sealed datagrams in namespace {ns} did not open under the key given for it: the fleet seals {ns} with another key"
            )),
            (n, _) => notes.push(format!(
                "note: {n} sealed datagrams in namespace {ns} did not open under its key (another key, or tampered with); {} did",
                used.opened
            )),
        }
        match (used.unsealed, used.opened) {
            (0, _) => {}
            (n, 0) => notes.push(format!(
                "note: {n} datagrams in namespace {ns} were not sealed, and were dropped because a key was given for it: the fleet does not seal {ns}; leave out its --key"
            )),
            (n, _) => notes.push(format!(
                "note: {n} unsealed datagrams in namespace {ns} were dropped because a key was given for it; {} sealed ones opened",
                used.opened
            )),
        }
        let in_use = members
            .iter()
            .filter(|m| m.session != Some(own))
            .flat_map(|m| m.channels.iter())
            .any(|c| {
                !crate::is_internal(&c.name) && pulicast::in_namespace(&used.namespace, &c.name)
            });
        if !in_use && used.opened == 0 && used.not_opened == 0 && used.unsealed == 0 {
            notes.push(format!(
                "note: no member of the fleet has a channel in namespace {ns}, which a key was given for"
            ));
        }
    }
    notes
}

/// A member as the `nodes` command prints it.
pub fn node_json(m: &MemberView) -> Value {
    let names = |pred: fn(&pulicast::ChannelInfo) -> bool| -> Vec<&str> {
        m.channels
            .iter()
            .filter(|c| pred(c))
            .map(|c| c.name.as_str())
            .collect()
    };
    json!({
        "session": m.session.map(|s| s.to_string()),
        "key": m.key,
        "name": m.name,
        "namespace": m.namespace,
        "config": m.config,
        "host": m.host,
        "address": m.address.to_string(),
        "data_address": m.data_address.map(|a| a.to_string()),
        "state": format!("{:?}", m.state).to_lowercase(),
        "incarnation": m.incarnation,
        "compat": m.compat,
        "contested_by": m.contested_by.map(|a| a.to_string()),
        "remote": m.remote.as_ref().map(|r| json!({"bridge": r.bridge, "site": r.site})),
        "start_time_unix_ms": m.start_time.and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map(|d| d.as_millis() as u64),
        "publishes": names(|c| c.publishes),
        "subscribes": names(|c| c.subscribes),
        "channels": m.channels.iter().map(|c| json!({
            "name": c.name,
            "publishes": c.publishes,
            "subscribes": c.subscribes,
            "period_ns": c.period_ns,
            "type": c.message_type.as_ref().map(|t| t.name.clone()),
        })).collect::<Vec<_>>(),
    })
}

/// Most (channel, sender) meters a [`ChannelWatch`] keeps.
pub const MAX_SOURCES: usize = 1024;

/// Most channels a [`ChannelWatch`] subscribes to by default: each costs a
/// subscription, a task and meters, and anyone can announce channels.
pub const MAX_WATCHED: usize = 4096;

/// Most bytes of a channel's last payload a [`ChannelWatch`] keeps (enough
/// to show a value; a larger payload is kept cut to this), so the last
/// values of every watched channel hold at most 64 MiB.
pub const LAST_BYTES: usize = 16 << 10;

/// How long a channel must go without a message, at least, before its
/// rate shows 0.
pub const QUIET: Duration = Duration::from_secs(2);

/// Message counts and timing of one channel, as observed.
#[derive(Debug, Clone, Default)]
pub struct RateMeter {
    /// Messages seen.
    pub count: u64,
    /// Payload bytes seen.
    pub bytes: u64,
    /// Messages the leads say were lost.
    pub lost: u64,
    /// When metering began.
    since: Option<Instant>,
    last: Option<Instant>,
    // Interval statistics (Welford), seconds.
    intervals: u64,
    mean: f64,
    m2: f64,
    min: f64,
    max: f64,
}

impl RateMeter {
    /// Records a message of `len` bytes with `lead` at `now`.
    pub fn record(&mut self, now: Instant, len: usize, lead: i64) {
        self.count += 1;
        self.bytes += len as u64;
        self.lost += u64::try_from(lead - 1).unwrap_or(0);
        if let Some(last) = self.last {
            let dt = now.saturating_duration_since(last).as_secs_f64();
            self.intervals += 1;
            let delta = dt - self.mean;
            self.mean += delta / self.intervals as f64;
            self.m2 += delta * (dt - self.mean);
            self.min = if self.intervals == 1 {
                dt
            } else {
                self.min.min(dt)
            };
            self.max = self.max.max(dt);
        }
        self.last = Some(now);
    }

    /// The rate at `now`, if at least two messages were seen: their mean
    /// rate while they keep coming. A channel that went quiet decays: once
    /// the wait for the next message is longer than the mean interval, the
    /// rate is at most one per wait, and after five intervals (and at
    /// least [`QUIET`]) without a message it is 0.
    pub fn rate_hz(&self, now: Instant) -> Option<f64> {
        if self.intervals == 0 || self.mean <= 0.0 {
            return None;
        }
        let waited = self.last.map_or(0.0, |last| {
            now.saturating_duration_since(last).as_secs_f64()
        });
        Some(if waited > (5.0 * self.mean).max(QUIET.as_secs_f64()) {
            0.0
        } else {
            1.0 / self.mean.max(waited)
        })
    }

    /// A meter that starts counting at `now`.
    pub fn new(now: Instant) -> Self {
        Self {
            since: Some(now),
            ..Self::default()
        }
    }

    /// Bytes per second since metering began (or over `window` for a meter
    /// made with `default()`).
    pub fn bandwidth(&self, window: Duration) -> f64 {
        let window = self.since.map_or(window, |s| s.elapsed());
        self.bytes as f64 / window.as_secs_f64().max(1e-9)
    }

    /// Loss from sequence gaps, as a share of what was sent.
    pub fn loss(&self) -> f64 {
        let sent = self.count + self.lost;
        if sent == 0 {
            0.0
        } else {
            self.lost as f64 / sent as f64
        }
    }

    /// Interval statistics in seconds: mean, min, max, standard deviation.
    pub fn intervals(&self) -> Option<(f64, f64, f64, f64)> {
        (self.intervals > 0).then(|| {
            let sd = if self.intervals > 1 {
                (self.m2 / (self.intervals - 1) as f64).sqrt()
            } else {
                0.0
            };
            (self.mean, self.min, self.max, sd)
        })
    }
}

/// Subscribes raw to channels as discovery reveals them and meters them.
pub struct ChannelWatch {
    node: Node,
    meters: Arc<Mutex<BTreeMap<String, RateMeter>>>,
    /// The same, per channel and sender (at most [`MAX_SOURCES`]).
    sources: Arc<Mutex<BTreeMap<(String, SocketAddr), RateMeter>>>,
    last: Option<Arc<Mutex<HashMap<String, pulicast::Bytes>>>>,
    tasks: HashMap<String, tokio::task::JoinHandle<()>>,
    started: Instant,
    limit: usize,
    unwatched: usize,
    unwatchable: usize,
    /// When [`ChannelWatch::watch_announced`] last read the fleet.
    counted: Option<Instant>,
    /// Watch without announcing a subscription ([`ChannelWatch::quiet`]).
    quiet: bool,
}

impl ChannelWatch {
    /// Watches nothing yet.
    pub fn new(node: &Node) -> Self {
        Self {
            node: node.clone(),
            meters: Arc::default(),
            sources: Arc::default(),
            last: None,
            tasks: HashMap::new(),
            started: Instant::now(),
            limit: MAX_WATCHED,
            unwatched: 0,
            unwatchable: 0,
            counted: None,
            quiet: false,
        }
    }

    /// Watches without taking part ([`pulicast::Channel::watch_raw`]):
    /// discovery does not announce this node as a subscriber of what it
    /// meters, so a server that meters the whole fleet (`puli web`) does
    /// not show up in every channel's subscribers, nor as a server of
    /// every service.
    pub fn quiet(mut self) -> Self {
        self.quiet = true;
        self
    }

    /// Watches at most `channels` channels instead of [`MAX_WATCHED`].
    pub fn with_limit(mut self, channels: usize) -> Self {
        self.limit = channels;
        self
    }

    /// How many announced channels were not watched at the last
    /// [`ChannelWatch::watch_announced`], for the limit.
    pub fn unwatched(&self) -> usize {
        self.unwatched
    }

    /// Also keeps the last payload of every watched channel in `last`.
    pub fn keep_last(&mut self, last: Arc<Mutex<HashMap<String, pulicast::Bytes>>>) {
        self.last = Some(last);
    }

    /// Starts metering `channel` (a resolved name), once; false if it is
    /// not watched because the limit is reached.
    pub fn watch(&mut self, channel: &str) -> Result<bool> {
        if self.tasks.contains_key(channel) {
            return Ok(true);
        }
        if self.tasks.len() >= self.limit {
            return Ok(false);
        }
        let handle = self.node.channel(&format!("/{channel}"));
        let mut sub = match self.quiet {
            true => handle.watch_raw()?,
            false => handle.subscribe_raw()?,
        };
        let meters = Arc::clone(&self.meters);
        let sources = Arc::clone(&self.sources);
        let name = channel.to_string();
        meters
            .lock()
            .insert(name.clone(), RateMeter::new(Instant::now()));
        let last = self.last.clone();
        let task = tokio::spawn(async move {
            while let Some(m) = sub.recv().await {
                let now = Instant::now();
                meters
                    .lock()
                    .entry(name.clone())
                    .or_default()
                    .record(now, m.value.len(), m.lead);
                let mut sources = sources.lock();
                let key = (name.clone(), m.source);
                // Anyone can send from new addresses: past the bound, the
                // channel's meter still counts them.
                if sources.len() < MAX_SOURCES || sources.contains_key(&key) {
                    sources
                        .entry(key)
                        .or_insert_with(|| RateMeter::new(now))
                        .record(now, m.value.len(), m.lead);
                }
                drop(sources);
                if let Some(last) = &last {
                    // A copy when cut, so the whole message is not kept alive.
                    let value = if m.value.len() > LAST_BYTES {
                        pulicast::Bytes::copy_from_slice(&m.value[..LAST_BYTES])
                    } else {
                        m.value
                    };
                    last.lock().insert(name.clone(), value);
                }
            }
        });
        self.tasks.insert(channel.to_string(), task);
        Ok(true)
    }

    /// Watches every channel some live member announces, up to the limit
    /// ([`ChannelWatch::unwatched`] says how many are left out). A name
    /// that is no channel name (anyone may announce one) is skipped and
    /// counted ([`ChannelWatch::unwatchable`]): one bad name never stops
    /// the others being watched.
    pub fn watch_announced(&mut self) {
        // Full, it only counts what it leaves out: not more than every 2 s,
        // for a fleet of a stranger's thousands of names.
        let full = self.tasks.len() >= self.limit;
        if full
            && self
                .counted
                .is_some_and(|at| at.elapsed() < Duration::from_secs(2))
        {
            return;
        }
        self.counted = Some(Instant::now());
        let members = self.node.discovery().live_members();
        let mut left_out = std::collections::HashSet::new();
        let mut unwatchable = std::collections::HashSet::new();
        for channel in members.iter().flat_map(|m| &m.channels) {
            let name = channel.name.as_str();
            match self.watch(name) {
                Ok(true) => {}
                Ok(false) => {
                    left_out.insert(name);
                }
                Err(_) => {
                    unwatchable.insert(name);
                }
            }
        }
        self.unwatched = left_out.len();
        self.unwatchable = unwatchable.len();
    }

    /// How many announced names could not be watched at the last
    /// [`ChannelWatch::watch_announced`]: no channel names.
    pub fn unwatchable(&self) -> usize {
        self.unwatchable
    }

    /// The meters so far.
    pub fn meters(&self) -> BTreeMap<String, RateMeter> {
        self.meters.lock().clone()
    }

    /// The meters of `channel`'s senders, by address.
    pub fn source_meters(&self, channel: &str) -> Vec<(SocketAddr, RateMeter)> {
        self.sources
            .lock()
            .iter()
            .filter(|((c, _), _)| c == channel)
            .map(|((_, source), meter)| (*source, meter.clone()))
            .collect()
    }

    /// Time since watching began.
    pub fn elapsed(&self) -> Duration {
        self.started.elapsed()
    }
}

impl Drop for ChannelWatch {
    fn drop(&mut self) {
        for task in self.tasks.values() {
            task.abort();
        }
    }
}

/// One channel as the `channels` command prints it.
#[derive(Debug, Clone, Default)]
pub struct ChannelRow {
    /// Resolved name.
    pub name: String,
    /// Names of the live members publishing.
    pub publishers: Vec<String>,
    /// Names of the live members subscribing.
    pub subscribers: Vec<String>,
    /// Message type, as its publishers announce it (as its subscribers do
    /// when no publisher announces one).
    pub type_name: Option<String>,
    /// When members disagree on the type: what each publishes or
    /// subscribes as, e.g. `odometer publishes Odometry; controller
    /// subscribes as Twist`. Messages of the wrong type are dropped by the
    /// subscribers that expect another.
    pub type_conflict: Option<String>,
    /// Measured rate, or the announced one.
    pub rate_hz: f64,
    /// Measured bandwidth, bytes per second.
    pub bandwidth: f64,
    /// Loss from sequence gaps.
    pub loss: f64,
}

impl ChannelRow {
    /// The JSON object for `--json`.
    pub fn json(&self) -> Value {
        json!({
            "name": self.name,
            "publishers": self.publishers,
            "subscribers": self.subscribers,
            "type": self.type_name,
            "type_conflict": self.type_conflict,
            "rate_hz": self.rate_hz,
            "bandwidth_bytes_per_s": self.bandwidth,
            "loss": self.loss,
        })
    }
}

/// Channels by name, from the members' announcements and the meters.
pub fn channel_rows(
    members: &[MemberView],
    meters: &BTreeMap<String, RateMeter>,
    window: Duration,
) -> Vec<ChannelRow> {
    let mut rows: BTreeMap<String, ChannelRow> = BTreeMap::new();
    // Per channel, who announced which type (by fingerprint), and how.
    let mut types: BTreeMap<String, Vec<(String, bool, TypeInfo)>> = BTreeMap::new();
    for m in members.iter().filter(|m| m.is_live()) {
        for c in &m.channels {
            let row = rows.entry(c.name.clone()).or_insert_with(|| ChannelRow {
                name: c.name.clone(),
                ..ChannelRow::default()
            });
            if c.publishes {
                row.publishers.push(m.name.clone());
                if row.rate_hz == 0.0 && c.period_ns > 0 {
                    row.rate_hz = 1e9 / c.period_ns as f64;
                }
            }
            if c.subscribes {
                row.subscribers.push(m.name.clone());
            }
            if let Some(t) = &c.message_type {
                types.entry(c.name.clone()).or_default().push((
                    m.name.clone(),
                    c.publishes,
                    t.clone(),
                ));
            }
        }
    }
    for (channel, announced) in types {
        let Some(row) = rows.get_mut(&channel) else {
            continue;
        };
        let published = announced.iter().find(|(_, publishes, _)| *publishes);
        row.type_name = published
            .or(announced.first())
            .map(|(_, _, t)| type_display(t));
        let first = &announced[0].2.fingerprint;
        if announced.iter().any(|(_, _, t)| t.fingerprint != *first) {
            let said: Vec<String> = announced
                .iter()
                .map(|(member, publishes, t)| match publishes {
                    true => format!("{member} publishes {}", type_display(t)),
                    false => format!("{member} subscribes as {}", type_display(t)),
                })
                .collect();
            row.type_conflict = Some(said.join("; "));
        }
    }
    let now = Instant::now();
    for (name, meter) in meters {
        let row = rows.entry(name.clone()).or_insert_with(|| ChannelRow {
            name: name.clone(),
            ..ChannelRow::default()
        });
        if let Some(rate) = meter.rate_hz(now) {
            row.rate_hz = rate;
        }
        row.bandwidth = meter.bandwidth(window);
        row.loss = meter.loss();
    }
    rows.into_values().collect()
}

/// The native type announced for `channel`, to decode its messages.
pub fn announced_type(node: &Node, channel: &str) -> Option<TypeInfo> {
    crate::publish::announced(&node.channel(&format!("/{channel}")))
        .filter(|t| t.encoding == TypeEncoding::Native)
}

/// A payload of `channel` as a short text: decoded with `hint` (or its
/// fingerprint); a service channel's frames as what they are (`request to
/// planner, 24 B`), not as bytes.
pub fn value_text(channel: &str, payload: &[u8], hint: Option<&TypeInfo>) -> String {
    use pulicast_proto::wire::service::{service_of, Frame};
    if service_of(channel).is_some() {
        return match Frame::decode(payload) {
            Ok(Frame::Request {
                target, message, ..
            }) => match target {
                "" => format!("request ({} B)", message.len()),
                to => format!("request to {} ({} B)", crate::one_line(to), message.len()),
            },
            Ok(Frame::Progress { seq, message, .. }) => {
                format!("progress {seq} ({} B)", message.len())
            }
            Ok(Frame::Reply { message, .. }) => format!("reply ({} B)", message.len()),
            Ok(Frame::Failure {
                code,
                message,
                node,
                ..
            }) => crate::one_line(&format!("failure {code} from {node}: {message}")).into_owned(),
            Ok(Frame::Cancel { .. }) => "cancel".to_string(),
            Ok(Frame::Busy { .. }) => "busy".to_string(),
            Ok(Frame::Running { .. }) => "running".to_string(),
            Err(_) => format!("not a service frame ({} B)", payload.len()),
        };
    }
    crate::one_line(&decode_payload(payload, hint).value.to_string()).into_owned()
}

/// One received message as `echo` prints it.
pub fn echo_json(
    channel: &str,
    message: &pulicast::Message<pulicast::Bytes>,
    hint: Option<&TypeInfo>,
) -> Value {
    let decoded = decode_payload(&message.value, hint);
    json!({
        "channel": channel,
        "source": message.source.to_string(),
        "seq": message.seq,
        "lead": message.lead,
        "type": decoded.type_name,
        "len": message.value.len(),
        "value": decoded.value,
    })
}

/// The text line for one received message.
pub fn echo_line(
    channel: &str,
    message: &pulicast::Message<pulicast::Bytes>,
    hint: Option<&TypeInfo>,
) -> String {
    let decoded = decode_payload(&message.value, hint);
    format!(
        "{channel} #{} lead {} from {} {}: {}",
        message.seq, message.lead, message.source, decoded.type_name, decoded.value
    )
}

/// A type as a user writes it: a 2.x primitive message by the Rust type
/// that travels as it (`f64` for `double_msg`), a native type by its name
/// (which our nodes announce as Rust writes it: `(f64, f64)`).
pub fn type_display(t: &TypeInfo) -> String {
    let primitive = match t.encoding {
        TypeEncoding::Zcm => {
            pulicast::PrimitiveKind::from_fingerprint(pulicast::Fingerprint(t.fingerprint))
        }
        TypeEncoding::Native => None,
    };
    match primitive {
        Some(kind) => kind.rust_name().to_string(),
        None => crate::one_line(&t.name).into_owned(),
    }
}

/// A type for `--json`: its name as a user writes it, its name on the
/// wire, its encoding and fingerprint, and a native type's schema as JSON
/// (the postcard-schema description its publishers announce), not bytes.
pub fn type_json(t: &TypeInfo) -> Value {
    // Decoded as the decoders read it: bounded in size and depth.
    let schema = match t.encoding {
        TypeEncoding::Native => {
            pulicast::text::schema_of(t).and_then(|s| serde_json::to_value(s).ok())
        }
        TypeEncoding::Zcm => None,
    };
    let fingerprint: String = t.fingerprint.iter().map(|b| format!("{b:02x}")).collect();
    json!({
        "name": type_display(t),
        "wire_name": t.name,
        "encoding": format!("{:?}", t.encoding).to_lowercase(),
        "fingerprint": fingerprint,
        "schema": schema,
    })
}

/// The services for `--json`: as [`pulicast::ServiceInfo`], each type by
/// [`type_json`].
pub fn services_json(services: &[pulicast::ServiceInfo]) -> Value {
    let ty = |t: &Option<TypeInfo>| t.as_ref().map(type_json);
    let ends = |ends: &[pulicast::ServiceEnd]| -> Vec<Value> {
        ends.iter()
            .map(|e| {
                json!({
                    "node": e.node,
                    "key": e.key,
                    "request": ty(&e.request),
                    "reply": ty(&e.reply),
                    "progress": ty(&e.progress),
                    "sealed": e.sealed,
                })
            })
            .collect()
    };
    services
        .iter()
        .map(|s| {
            json!({
                "name": s.name,
                "servers": ends(&s.servers),
                "clients": ends(&s.clients),
            })
        })
        .collect()
}

/// The services as a table: name, servers, clients, and the types its
/// servers announce (`Request -> Reply`, progress in brackets, `sealed`).
pub fn services_table(services: &[pulicast::ServiceInfo]) -> String {
    let type_name = |t: &Option<TypeInfo>| t.as_ref().map_or("?".to_string(), type_display);
    let mut out = format!(
        "{:<28} {:<28} {:<20} TYPES\n",
        "SERVICE", "SERVERS", "CLIENTS"
    );
    for s in services {
        let nodes = |ends: &[pulicast::ServiceEnd]| {
            let names: Vec<String> = ends
                .iter()
                .map(|e| crate::one_line(&e.node).into_owned())
                .collect();
            match names.is_empty() {
                true => "-".to_string(),
                false => names.join(","),
            }
        };
        let types = match s.server_types() {
            Some(end) => {
                let mut t = format!("{} -> {}", type_name(&end.request), type_name(&end.reply));
                if end.progress.is_some() {
                    t += &format!(" [progress {}]", type_name(&end.progress));
                }
                if end.sealed {
                    t += " sealed";
                }
                t
            }
            None => "(no server)".to_string(),
        };
        out += &format!(
            "{:<28} {:<28} {:<20} {types}\n",
            crate::one_line(&s.name),
            nodes(&s.servers),
            nodes(&s.clients)
        );
    }
    out
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn types_are_shown_as_a_user_writes_them() {
        let shown = |t: TypeInfo| type_display(&t);
        assert_eq!(shown(pulicast::type_info_of::<(f64, f64)>()), "(f64, f64)");
        assert_eq!(shown(pulicast::type_info_of::<f64>()), "f64");
        assert_eq!(shown(pulicast::type_info_of::<String>()), "String");
        assert_eq!(
            shown(pulicast::type_info_of::<Vec<(u8, i32)>>()),
            "Vec<(u8, i32)>"
        );
        let json = type_json(&pulicast::type_info_of::<(f64, f64)>());
        assert_eq!(json["name"], "(f64, f64)");
        assert_eq!(json["encoding"], "native");
        assert!(json["schema"].is_object(), "{json}");
        assert_eq!(json["fingerprint"].as_str().map(str::len), Some(16));
    }

    #[test]
    fn a_schema_nested_as_deep_as_its_bytes_allow_is_shown_without_overflow() {
        // Option<Option<...u8>>: one tag and an empty name per level.
        let mut schema = Vec::new();
        let levels = pulicast::text::MAX_SCHEMA_BYTES / 2 - 2;
        for _ in 0..levels {
            schema.extend([0u8, 18]);
        }
        schema.extend([0u8, 2]);
        let t = TypeInfo {
            encoding: TypeEncoding::Native,
            name: "deep".into(),
            fingerprint: [0; 8],
            schema,
        };
        let json = std::thread::Builder::new()
            .stack_size(2 << 20)
            .spawn(move || type_json(&t).to_string())
            .unwrap()
            .join()
            .unwrap();
        assert!(json.contains("\"deep\""), "{json}");
        assert!(json.contains("\"schema\":null"), "{json}");
    }

    #[test]
    fn a_rate_decays_to_zero_when_messages_stop() {
        let t0 = Instant::now();
        let mut meter = RateMeter::new(t0);
        assert_eq!(meter.rate_hz(t0), None);
        for i in 0..=10 {
            meter.record(t0 + Duration::from_millis(100 * i), 8, 1);
        }
        let last = t0 + Duration::from_secs(1);
        let at = |ms: u64| meter.rate_hz(last + Duration::from_millis(ms)).unwrap();
        // While messages keep coming: the mean rate.
        assert!((at(50) - 10.0).abs() < 1e-6);
        // Overdue: at most one per wait.
        assert!((at(500) - 2.0).abs() < 1e-6);
        assert!((at(1_000) - 1.0).abs() < 1e-6);
        // Quiet for longer than QUIET: nothing arrives.
        assert_eq!(at(2_001), 0.0);
        assert_eq!(at(10_000), 0.0);
    }
}

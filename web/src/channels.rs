//! Channels the page watches: one feed per channel, shared by every
//! client that watches it. A feed watches the channel without taking
//! part ([`pulicast::Channel::watch_raw`]: discovery announces no
//! subscriber), decodes each message once (the `text` conversion the
//! tools use), decimates ([`crate::decimate`]) and every [`TICK`] hands
//! the bucket to its clients through a bounded broadcast. A client that
//! falls behind loses the oldest buckets, counted; a feed no client
//! holds stops.

use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use pulicast::text;
use serde_json::{json, Value};
use tokio::sync::broadcast;

use crate::decimate::Decimator;

/// A bucket's length: at most this many frames a second reach a client
/// per channel (30), whatever the channel's rate.
pub const TICK: Duration = Duration::from_millis(33);

/// How long after the feeds end their buckets the clients take them: the
/// feeds' and the clients' ticks keep one phase (see [`ticks`]), so a
/// bucket waits this long for its client, not up to a whole tick.
pub const CLIENT_LAG: Duration = Duration::from_millis(4);

/// Ticks every [`TICK`], at `offset` past the multiples of [`TICK`] since
/// the server's start: every feed ends its bucket at the same moments,
/// and every client takes them [`CLIENT_LAG`] later. A tick missed is
/// skipped, not made up, so the phase holds.
pub fn ticks(offset: Duration) -> tokio::time::Interval {
    static EPOCH: std::sync::OnceLock<tokio::time::Instant> = std::sync::OnceLock::new();
    let epoch = *EPOCH.get_or_init(tokio::time::Instant::now);
    let now = tokio::time::Instant::now();
    let since = now.saturating_duration_since(epoch).as_nanos();
    let tick = TICK.as_nanos();
    let next = epoch
        + Duration::from_nanos(u64::try_from((since / tick + 1) * tick).unwrap_or(0))
        + offset;
    let mut interval = tokio::time::interval_at(next, TICK);
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    interval
}

/// Buckets a client may fall behind by before it loses the oldest (about
/// two seconds).
pub const BACKLOG: usize = 64;

/// Payloads larger than this are counted, not decoded (a camera frame is
/// no plot).
pub const MAX_DECODED: usize = 64 << 10;

/// Most messages of a channel decoded in one bucket, and most bytes: the
/// rest are counted, not decoded (a 10 kHz channel is plotted from its
/// first 64 messages of each 33 ms), so one channel's rate can't hold
/// the server's threads.
pub const DECODE_MESSAGES: usize = 64;

/// See [`DECODE_MESSAGES`].
pub const DECODE_BYTES: usize = 256 << 10;

/// Most channels watched at once by the whole server.
pub const MAX_FEEDS: usize = 256;

/// How often a feed that knows no type for its channel looks again.
const TYPE_EVERY: Duration = Duration::from_millis(200);

/// How often a feed that knows its channel's type looks again (a
/// publisher gone, another come).
const TYPE_AGAIN: Duration = Duration::from_secs(2);

/// One channel's decoded, decimated messages.
pub struct Feed {
    tx: broadcast::Sender<Arc<str>>,
    task: tokio::task::JoinHandle<()>,
}

impl Feed {
    /// A receiver of the buckets from now on.
    pub fn subscribe(&self) -> broadcast::Receiver<Arc<str>> {
        self.tx.subscribe()
    }
}

impl Drop for Feed {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// Why a channel can't be watched.
#[derive(Debug, thiserror::Error)]
pub enum FeedError {
    /// Not a channel name, or the node can't watch it.
    #[error("{0}")]
    Channel(#[from] pulicast::Error),
    /// The server already watches [`MAX_FEEDS`] channels.
    #[error("the server watches {MAX_FEEDS} channels already")]
    Full,
    /// No live member announces the channel.
    #[error("no member publishes or subscribes it")]
    NotAnnounced,
}

/// The feeds of one node, by channel.
#[derive(Clone)]
pub struct Feeds {
    node: pulicast::Node,
    feeds: Arc<Mutex<HashMap<String, Weak<Feed>>>>,
    /// Feed tasks running now (each holds a [`Running`]).
    running: Arc<AtomicUsize>,
}

/// A feed task's mark in [`Feeds::running`], taken back when the task
/// ends or is aborted.
struct Running(Arc<AtomicUsize>);

impl Drop for Running {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

impl Feeds {
    /// No feed yet.
    pub fn new(node: &pulicast::Node) -> Self {
        Self {
            node: node.clone(),
            feeds: Arc::default(),
            running: Arc::default(),
        }
    }

    /// The feed of `channel` (a full name, `rover1/pose`), started if no
    /// client watches it yet.
    pub fn get(&self, channel: &str) -> Result<Arc<Feed>, FeedError> {
        let mut feeds = self.feeds.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(feed) = feeds.get(channel).and_then(Weak::upgrade) {
            return Ok(feed);
        }
        feeds.retain(|_, f| f.strong_count() > 0);
        if feeds.len() >= MAX_FEEDS {
            return Err(FeedError::Full);
        }
        // Only what the fleet announces: each name a node is asked for
        // stays in its channel table, so a page's requests must not be
        // able to grow it with names of their own.
        if !crate::calls::announced(&self.node, channel) {
            return Err(FeedError::NotAnnounced);
        }
        let handle = self.node.channel(&format!("/{channel}"));
        let sub = handle.watch_raw()?;
        let (tx, _) = broadcast::channel(BACKLOG);
        self.running.fetch_add(1, Ordering::SeqCst);
        let running = Running(Arc::clone(&self.running));
        let task = tokio::spawn(run(handle, sub, tx.clone(), running));
        let feed = Arc::new(Feed { tx, task });
        feeds.insert(channel.to_string(), Arc::downgrade(&feed));
        Ok(feed)
    }

    /// The channels watched now: feed tasks running.
    pub fn watched(&self) -> usize {
        self.running.load(Ordering::SeqCst)
    }
}

fn now_ms() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1000.0)
}

/// The channel's announced type, with a native type's description parsed
/// once (not for every message).
pub(crate) type Known = (
    pulicast::TypeInfo,
    Option<pulicast::postcard_schema::schema::owned::OwnedNamedType>,
);

/// The type the channel's publishers announce (its subscribers' only
/// when no publisher announces one: anyone may subscribe under any type).
pub(crate) fn known(channel: &pulicast::Channel) -> Option<Known> {
    let info = pulicast_tools::publish::announced(channel)?;
    let schema = text::schema_of(&info);
    Some((info, schema))
}

/// `payload` as JSON, read as the channel's `known` type where it fits.
pub(crate) fn decode(payload: &[u8], known: Option<&Known>) -> Value {
    // A payload that does not fit the announced type is read without it
    // (its own fingerprint may name a primitive or a 2.x type): the
    // description is not parsed again for each message.
    let decoded = match known {
        Some((info, Some(schema))) => text::decode_typed(payload, Some((info, schema))),
        _ => None,
    };
    decoded
        .unwrap_or_else(|| text::decode_payload(payload, None))
        .value
}

async fn run(
    channel: pulicast::Channel,
    mut sub: pulicast::Subscription<pulicast::Bytes>,
    tx: broadcast::Sender<Arc<str>>,
    _running: Running,
) {
    let name = channel.name().to_string();
    let mut decimator = Decimator::new();
    let mut tick = ticks(Duration::ZERO);
    let mut known = known(&channel);
    let mut looked = tokio::time::Instant::now();
    let mut batch = Vec::new();
    // What this bucket has decoded so far.
    let (mut decoded, mut decoded_bytes) = (0usize, 0usize);
    loop {
        tokio::select! {
            n = sub.recv_many(&mut batch, 256) => {
                if n == 0 {
                    return;
                }
                let again = match known {
                    None => TYPE_EVERY,
                    Some(_) => TYPE_AGAIN,
                };
                if looked.elapsed() >= again {
                    known = self::known(&channel);
                    looked = tokio::time::Instant::now();
                }
                let t = now_ms();
                for m in batch.drain(..) {
                    let len = m.value.len();
                    if len >= MAX_DECODED {
                        decimator.push_opaque(t, json!({ "bytes": len }));
                    } else if decoded < DECODE_MESSAGES && decoded_bytes < DECODE_BYTES {
                        decoded += 1;
                        decoded_bytes += len;
                        decimator.push(t, decode(&m.value, known.as_ref()));
                    } else {
                        decimator.skip(t);
                    }
                }
                // Other tasks' turn between batches.
                tokio::task::yield_now().await;
            }
            _ = tick.tick() => {
                (decoded, decoded_bytes) = (0, 0);
                if let Some(mut bucket) = decimator.take() {
                    bucket["channel"] = json!(name);
                    if let Some((info, _)) = &known {
                        bucket["type"] = json!(crate::fleet::cut(&pulicast_tools::sniff::type_display(info)));
                    }
                    // No receiver now is no error: one may come.
                    let _ = tx.send(Arc::from(bucket.to_string()));
                }
            }
        }
    }
}

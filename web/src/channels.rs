//! Channels the page watches: one feed per channel, shared by every
//! client that watches it. A feed watches the channel without taking
//! part ([`pulicast::Channel::watch_raw`]: discovery announces no
//! subscriber), decodes each message once (the `text` conversion the
//! tools use), decimates ([`crate::decimate`]) and every [`TICK`] hands
//! the bucket to its clients through a bounded broadcast. A client that
//! falls behind loses the oldest buckets, counted; a feed no client
//! holds stops.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use pulicast::text;
use serde_json::{json, Value};
use tokio::sync::broadcast;

use crate::decimate::Decimator;

/// A bucket's length: at most this many frames a second reach a client
/// per channel (30), whatever the channel's rate.
pub const TICK: Duration = Duration::from_millis(33);

/// Buckets a client may fall behind by before it loses the oldest (about
/// two seconds).
pub const BACKLOG: usize = 64;

/// Payloads larger than this are counted, not decoded (a camera frame is
/// no plot).
pub const MAX_DECODED: usize = 64 << 10;

/// Most channels watched at once by the whole server.
pub const MAX_FEEDS: usize = 256;

/// How often a feed that knows no type for its channel looks again.
const TYPE_EVERY: Duration = Duration::from_millis(200);

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
}

/// The feeds of one node, by channel.
#[derive(Clone)]
pub struct Feeds {
    node: pulicast::Node,
    feeds: Arc<Mutex<HashMap<String, Weak<Feed>>>>,
}

impl Feeds {
    /// No feed yet.
    pub fn new(node: &pulicast::Node) -> Self {
        Self {
            node: node.clone(),
            feeds: Arc::default(),
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
        let handle = self.node.channel(&format!("/{channel}"));
        let sub = handle.watch_raw()?;
        let (tx, _) = broadcast::channel(BACKLOG);
        let task = tokio::spawn(run(handle, sub, tx.clone()));
        let feed = Arc::new(Feed { tx, task });
        feeds.insert(channel.to_string(), Arc::downgrade(&feed));
        Ok(feed)
    }

    /// The channels watched now.
    pub fn watched(&self) -> usize {
        let feeds = self.feeds.lock().unwrap_or_else(|e| e.into_inner());
        feeds.values().filter(|f| f.strong_count() > 0).count()
    }
}

fn now_ms() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1000.0)
}

/// The channel's announced type, with a native type's description parsed
/// once (not for every message).
type Known = (
    pulicast::TypeInfo,
    Option<pulicast::postcard_schema::schema::owned::OwnedNamedType>,
);

fn known(channel: &pulicast::Channel) -> Option<Known> {
    let info = pulicast_tools::publish::announced(channel)?;
    let schema = text::schema_of(&info);
    Some((info, schema))
}

fn decode(payload: &[u8], known: Option<&Known>) -> Value {
    let decoded = match known {
        Some((info, Some(schema))) => text::decode_typed(payload, Some((info, schema)))
            .unwrap_or_else(|| text::decode_payload(payload, Some(info))),
        Some((info, None)) => text::decode_payload(payload, Some(info)),
        None => text::decode_payload(payload, None),
    };
    decoded.value
}

async fn run(
    channel: pulicast::Channel,
    mut sub: pulicast::Subscription<pulicast::Bytes>,
    tx: broadcast::Sender<Arc<str>>,
) {
    let name = channel.name().to_string();
    let mut decimator = Decimator::new();
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut known = known(&channel);
    let mut looked = tokio::time::Instant::now();
    let mut batch = Vec::new();
    loop {
        tokio::select! {
            n = sub.recv_many(&mut batch, 256) => {
                if n == 0 {
                    return;
                }
                if known.is_none() && looked.elapsed() >= TYPE_EVERY {
                    known = self::known(&channel);
                    looked = tokio::time::Instant::now();
                }
                let t = now_ms();
                for m in batch.drain(..) {
                    match m.value.len() {
                        len @ (MAX_DECODED..) => decimator.push_opaque(t, json!({ "bytes": len })),
                        _ => decimator.push(t, decode(&m.value, known.as_ref())),
                    }
                }
            }
            _ = tick.tick() => {
                if let Some(mut bucket) = decimator.take() {
                    bucket["channel"] = json!(name);
                    if let Some((info, _)) = &known {
                        bucket["type"] = json!(pulicast_tools::sniff::type_display(info));
                    }
                    // No receiver now is no error: one may come.
                    let _ = tx.send(Arc::from(bucket.to_string()));
                }
            }
        }
    }
}

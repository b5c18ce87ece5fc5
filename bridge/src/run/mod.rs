//! The bridge at work: a pulicast node, a Zenoh session, and the tasks
//! that move messages and member tables between them. What to move is
//! decided by [`crate::plan`]; this module only applies it.
//!
//! This file holds the handle ([`Bridge`]), the state the tasks and Zenoh's
//! callbacks share, and the counters. The rooms: `control` (the task
//! that steps the plan), `sites` (the other sites' tables), `export` and
//! `import` (channels out and in), `calls` (services between sites).

mod calls;
mod control;
mod export;
mod import;
mod sites;

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use parking_lot::{Mutex, RwLock};
use pulicast::{Node, RawClient};
use serde::Serialize;
use tokio::sync::Notify;
use tokio::task::JoinHandle;
use zenoh::query::Query;
use zenoh::sample::{Locality, Sample, SampleKind};
use zenoh::Session;

use self::calls::take_call;
use self::control::{control, Declared, Leftovers};
use self::sites::{take_table, MAX_SITES};
use crate::call::CallCancel;
use crate::options::{Checked, Options};
use crate::plan::Sources;
use crate::sample::Refused;
use crate::table::SiteTable;

/// Counters of one bridge.
#[derive(Debug, Default)]
struct Counters {
    out_messages: AtomicU64,
    out_bytes: AtomicU64,
    out_rate_limited: AtomicU64,
    out_not_local: AtomicU64,
    out_failed: AtomicU64,
    out_over_names: AtomicU64,
    in_messages: AtomicU64,
    in_bytes: AtomicU64,
    in_refused: [AtomicU64; Refused::LABELS.len()],
    in_lost: AtomicU64,
    in_failed: AtomicU64,
    tables_refused: AtomicU64,
    calls_out: AtomicU64,
    calls_in: AtomicU64,
    calls_refused: AtomicU64,
}

/// A snapshot of a bridge's counters.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
#[non_exhaustive]
pub struct BridgeStats {
    /// Whether it is its site's active bridge.
    pub active: bool,
    /// Channels going out.
    pub exports: usize,
    /// Channels coming in.
    pub imports: usize,
    /// Channels that would go out but are left out for the bounds
    /// (`--max-exports`, `--max-per-member`).
    pub exports_left_out: usize,
    /// Channels that would come in but are left out for the bounds.
    pub imports_left_out: usize,
    /// Distinct names imported since the bridge started, listed ones (a
    /// publisher is listed by another site) and the others: bounded by
    /// `--max-import-names`.
    pub import_names: [usize; 2],
    /// Of `imports_left_out`, those never imported before and left out
    /// because `import_names` reached its bound.
    pub imports_refused: usize,
    /// Other sites whose tables it holds.
    pub sites: usize,
    /// Members of other sites it relays here.
    pub relayed: usize,
    /// Messages put on Zenoh.
    pub out_messages: u64,
    /// Their payload bytes.
    pub out_bytes: u64,
    /// Messages not sent: over their channel's rate limit.
    pub out_rate_limited: u64,
    /// Messages not sent: not from a member of this site (another bridge's
    /// import, or an unknown sender).
    pub out_not_local: u64,
    /// Puts that failed.
    pub out_failed: u64,
    /// Messages not sent: their name was never exported before and
    /// `--max-export-names` distinct names were (see `export_names`).
    pub out_over_names: u64,
    /// Distinct names exported (given a Zenoh publisher) since the bridge
    /// started.
    pub export_names: usize,
    /// Messages published here from Zenoh.
    pub in_messages: u64,
    /// Their payload bytes.
    pub in_bytes: u64,
    /// Samples refused, by reason (see [`Refused`]).
    pub in_refused: BTreeMap<&'static str, u64>,
    /// Messages that the Zenoh hop lost, from the sequence numbers of
    /// samples that carry them.
    pub in_lost: u64,
    /// Publishes here that failed.
    pub in_failed: u64,
    /// Site tables refused (malformed, too large, too many).
    pub tables_refused: u64,
    /// Calls of this site passed on to servers of other sites.
    pub calls_out: u64,
    /// Calls of other sites run on servers of this site.
    pub calls_in: u64,
    /// Calls from other sites refused (malformed, for a server this site
    /// does not offer, too many at once), and answers from other sites
    /// that could not be passed on.
    pub calls_refused: u64,
    /// Calls of other sites running here now.
    pub calls_running: usize,
    /// Services of other sites this bridge answers for here.
    pub services: usize,
}

/// What the Zenoh callbacks tell the control task: the latest word per
/// bridge, so nothing queues up behind a slow step and nothing is lost.
#[derive(Default)]
struct Inbox {
    /// Token changes, the latest per bridge: present or gone.
    tokens: HashMap<i64, bool>,
    /// The newest table per bridge, with its memory cost.
    tables: HashMap<i64, (SiteTable, usize)>,
    /// Memory of the tables waiting here.
    bytes: usize,
}

/// State shared by the control task, the callbacks and the handle.
struct Shared {
    node: Node,
    session: Session,
    me: i64,
    checked: Checked,
    counters: Counters,
    /// Data addresses whose messages may go out.
    sources: RwLock<Sources>,
    /// This site's bridges: samples they exported are refused coming in.
    local_bridges: RwLock<HashSet<i64>>,
    /// The current table's bytes, for queries; empty while standing by.
    table: RwLock<Vec<u8>>,
    status: Mutex<BridgeStats>,
    /// The names ever given a Zenoh publisher, at most
    /// `--max-export-names`: Zenoh keeps state for each for good.
    export_names: Mutex<HashSet<String>>,
    drop_log: Mutex<HashMap<&'static str, Instant>>,
    inbox: Mutex<Inbox>,
    /// Wakes the control task: the inbox has news.
    news: Notify,
    stop: Notify,
    /// The runtime the bridge started on: Zenoh's callbacks start tasks
    /// here.
    runtime: tokio::runtime::Handle,
    /// The servers of other sites answered for here: service, node, and
    /// the bridge of its site.
    serving: RwLock<BTreeMap<String, BTreeMap<String, i64>>>,
    /// Numbers the calls passed on, for their cancels.
    next_call: AtomicU64,
    /// Calls of other sites running here, by calling bridge and number.
    calls: Mutex<HashMap<(i64, u64), Arc<Notify>>>,
    /// Clients of this site's services, by `service@node`.
    clients: Mutex<HashMap<String, RawClient>>,
}

impl Shared {
    /// Counts a refused sample, and logs it at most once a second per
    /// reason.
    fn refuse(&self, why: Refused, key: &str) {
        self.counters.in_refused[why.index()].fetch_add(1, Relaxed);
        let mut log = self.drop_log.lock();
        let now = Instant::now();
        let due = log
            .get(why.label())
            .is_none_or(|last| now.duration_since(*last) >= Duration::from_secs(1));
        if due {
            log.insert(why.label(), now);
            tracing::warn!(key = %printable(key), reason = why.label(), ?why, "dropped a sample from Zenoh");
        }
    }
}

/// Text from the network, with control characters escaped for logs.
fn printable(text: &str) -> String {
    text.chars().flat_map(char::escape_debug).collect()
}

/// A running bridge. Dropping it stops it.
pub struct Bridge {
    shared: Arc<Shared>,
    /// The control task; what it leaves is taken down after the stop.
    control: Option<JoinHandle<Leftovers>>,
}

impl std::fmt::Debug for Bridge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bridge")
            .field("me", &self.shared.me)
            .finish()
    }
}

impl Bridge {
    /// Starts a bridge: its node on this site, its Zenoh session, and the
    /// task that keeps both in step. Must run inside a tokio runtime.
    pub async fn start(options: &Options) -> Result<Bridge> {
        let checked = options.check()?;
        let config = options.zenoh_config()?;
        let mut builder = Node::new(options.name.clone())
            .port(options.port)
            .ttl(options.ttl);
        if let Some(interface) = options.interface {
            builder = builder.interface(interface);
        }
        for peer in &options.peer {
            builder = builder.peer(*peer);
        }
        for key in &options.keys {
            let (namespace, key) = key.parse().map_err(|e| anyhow!("--key: {e}"))?;
            builder = builder.key(namespace, key);
        }
        if options.encrypt {
            builder = builder.encrypt(true);
        }
        let node = builder.start().await?;
        let session = zenoh::open(config)
            .await
            .map_err(|e| anyhow!("opening the Zenoh session: {e}"))?;
        Self::start_with(node, session, checked).await
    }

    /// Starts a bridge on a node and a Zenoh session made by the caller
    /// (tests, and embedding the bridge in a process of one's own).
    pub async fn start_with(node: Node, session: Session, checked: Checked) -> Result<Bridge> {
        let me = node.compat_session_id();
        // Bridges of this prefix on this site find each other by this.
        let marker = node.try_channel(&checked.keys.marker_channel())?;
        let marker_sub = marker.subscribe_raw()?;
        let shared = Arc::new(Shared {
            node,
            session,
            me,
            checked,
            counters: Counters::default(),
            sources: RwLock::new(Sources::default()),
            local_bridges: RwLock::new(HashSet::new()),
            table: RwLock::new(Vec::new()),
            status: Mutex::new(BridgeStats::default()),
            export_names: Mutex::new(HashSet::new()),
            drop_log: Mutex::new(HashMap::new()),
            inbox: Mutex::new(Inbox::default()),
            news: Notify::new(),
            stop: Notify::new(),
            runtime: tokio::runtime::Handle::current(),
            serving: RwLock::new(BTreeMap::new()),
            // Not guessable from outside: a cancel names a call by it.
            next_call: AtomicU64::new(pulicast::Uuid::new_v4().as_u64_pair().0),
            calls: Mutex::new(HashMap::new()),
            clients: Mutex::new(HashMap::new()),
        });
        // Announced as this prefix's bridge: a marker published and
        // subscribed (a node that only subscribes it is no bridge).
        marker.publish_bytes(&[])?;
        let keys = &shared.checked.keys;
        // Tables and tokens: Zenoh calls back on its own threads; the
        // control task does the work.
        let weak = Arc::downgrade(&shared);
        let tables = shared
            .session
            .declare_subscriber(keys.site_tables())
            .allowed_origin(Locality::Remote)
            .callback(move |sample: Sample| {
                if let Some(shared) = weak.upgrade() {
                    take_table(&shared, &sample);
                }
            })
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let weak = Arc::downgrade(&shared);
        let tokens = shared
            .session
            .liveliness()
            .declare_subscriber(keys.bridge_tokens())
            .history(true)
            .callback(move |sample: Sample| {
                let Some(shared) = weak.upgrade() else { return };
                let map = &shared.checked.keys;
                if let Some(bridge) = map.bridge_of_token(sample.key_expr().as_str()) {
                    if bridge == shared.me {
                        return;
                    }
                    let live = sample.kind() == SampleKind::Put;
                    let mut inbox = shared.inbox.lock();
                    // Bounded: a token beyond the sites followed is
                    // refused (its going is always taken).
                    if !live || inbox.tokens.len() < MAX_SITES || inbox.tokens.contains_key(&bridge)
                    {
                        inbox.tokens.insert(bridge, live);
                    } else {
                        shared.counters.tables_refused.fetch_add(1, Relaxed);
                    }
                    drop(inbox);
                    shared.news.notify_one();
                }
            })
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let weak = Arc::downgrade(&shared);
        let queryable = shared
            .session
            .declare_queryable(keys.site_table(me))
            .allowed_origin(Locality::Remote)
            .callback(move |query| {
                let Some(shared) = weak.upgrade() else { return };
                let table = shared.table.read().clone();
                if table.is_empty() {
                    return;
                }
                let key = query.key_expr().clone();
                // Replies are sent from a task: the callback must not block.
                shared.runtime.spawn(async move {
                    if let Err(e) = query.reply(key, table).await {
                        tracing::debug!("table reply not sent: {e}");
                    }
                });
            })
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let weak = Arc::downgrade(&shared);
        let calls = shared
            .session
            .declare_queryable(keys.calls(me))
            .allowed_origin(Locality::Remote)
            .callback(move |query: Query| {
                if let Some(shared) = weak.upgrade() {
                    take_call(&shared, query);
                }
            })
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let weak = Arc::downgrade(&shared);
        let cancels = shared
            .session
            .declare_subscriber(keys.cancels(me))
            .allowed_origin(Locality::Remote)
            .callback(move |sample: Sample| {
                let Some(shared) = weak.upgrade() else { return };
                match CallCancel::decode(&sample.payload().to_bytes()) {
                    Ok(cancel) => {
                        if let Some(running) = shared.calls.lock().get(&(cancel.bridge, cancel.id))
                        {
                            running.notify_one();
                        }
                    }
                    Err(e) => {
                        shared.counters.calls_refused.fetch_add(1, Relaxed);
                        tracing::debug!("{e}");
                    }
                }
            })
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let control = tokio::spawn(control(
            shared.clone(),
            Declared {
                _calls: calls,
                _cancels: cancels,
                _tables: tables,
                _tokens: tokens,
                _queryable: queryable,
                _marker: (marker, marker_sub),
            },
        ));
        Ok(Bridge {
            shared,
            control: Some(control),
        })
    }

    /// The bridge's node on its site.
    pub fn node(&self) -> &Node {
        &self.shared.node
    }

    /// The bridge's Zenoh session.
    pub fn session(&self) -> &Session {
        &self.shared.session
    }

    /// The counters, and what the bridge is doing now.
    pub fn stats(&self) -> BridgeStats {
        stats_of(&self.shared)
    }

    /// Stops the bridge: its members leave the other sites, the channels it
    /// imported stop here, and its node leaves this site.
    pub async fn stop(mut self) {
        self.shared.stop.notify_one();
        let mut leftovers = Leftovers::default();
        if let Some(control) = self.control.take() {
            leftovers = control.await.unwrap_or_default();
        }
        self.shared.node.stop();
        if let Err(e) = self.shared.session.close().await {
            tracing::debug!("closing the Zenoh session: {e}");
        }
        drop(leftovers);
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        if let Some(control) = self.control.take() {
            control.abort();
            self.shared.node.stop();
        }
    }
}

fn stats_of(shared: &Shared) -> BridgeStats {
    let c = &shared.counters;
    let mut stats = shared.status.lock().clone();
    stats.out_messages = c.out_messages.load(Relaxed);
    stats.out_bytes = c.out_bytes.load(Relaxed);
    stats.out_rate_limited = c.out_rate_limited.load(Relaxed);
    stats.out_not_local = c.out_not_local.load(Relaxed);
    stats.out_failed = c.out_failed.load(Relaxed);
    stats.out_over_names = c.out_over_names.load(Relaxed);
    stats.export_names = shared.export_names.lock().len();
    stats.in_messages = c.in_messages.load(Relaxed);
    stats.in_bytes = c.in_bytes.load(Relaxed);
    stats.in_refused = Refused::LABELS
        .iter()
        .zip(&c.in_refused)
        .map(|(label, n)| (*label, n.load(Relaxed)))
        .collect();
    stats.in_lost = c.in_lost.load(Relaxed);
    stats.in_failed = c.in_failed.load(Relaxed);
    stats.tables_refused = c.tables_refused.load(Relaxed);
    stats.calls_out = c.calls_out.load(Relaxed);
    stats.calls_in = c.calls_in.load(Relaxed);
    stats.calls_refused = c.calls_refused.load(Relaxed);
    stats.calls_running = shared.calls.lock().len();
    stats
}

/// When a channel last carried a message (nanoseconds after `born`, plus
/// one; 0: never), written on its path without a lock.
struct LastUsed {
    born: Instant,
    at: AtomicU64,
}

impl LastUsed {
    fn new() -> Self {
        Self {
            born: Instant::now(),
            at: AtomicU64::new(0),
        }
    }

    fn now(&self) {
        let nanos = u64::try_from(self.born.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.at.store(nanos.saturating_add(1), Relaxed);
    }

    fn get(&self) -> Option<Instant> {
        match self.at.load(Relaxed) {
            0 => None,
            n => Some(self.born + Duration::from_nanos(n - 1)),
        }
    }
}

/// Says once that channels are left out of a direction (`exported`,
/// `imported`), and again after all fit once more.
fn say_left_out(what: &str, left_out: usize, said: &mut bool) {
    if left_out > 0 && !*said {
        tracing::warn!(
            left_out,
            "more channels to be {what} than the bridge's bounds take (--max-exports, \
             --max-imports, --max-per-member): channels that carry messages keep their \
             places, the others take turns"
        );
    }
    *said = left_out > 0;
}

//! The bridge at work: a pulicast node, a Zenoh session, and the tasks
//! that move messages and member tables between them. What to move is
//! decided by [`crate::plan`]; this module only applies it.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex, RwLock, Weak};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use pulicast::{
    CallContext, CallEvent, Channel, Fault, MemberState, Node, RawClient, RelayedMember,
};
use serde::Serialize;
use tokio::sync::Notify;
use tokio::task::JoinHandle;
use zenoh::liveliness::LivelinessToken;
use zenoh::qos::CongestionControl;
use zenoh::query::{ConsolidationMode, Query};
use zenoh::sample::{Locality, Sample, SampleKind};
use zenoh::Session;

use crate::call::{CallAnswer, CallCancel, CallRequest};
use crate::filter::{Limit, RateGate};
use crate::options::{Checked, Options};
use crate::pace::Pacer;
use crate::plan::{self, Import, Plan, Sources};
use crate::sample::{self, Losses, Origin, Refused};
use crate::slots::Slots;
use crate::table::{SiteTable, MAX_TABLE_BYTES};

/// How often the plan is recomputed when nothing wakes the bridge.
const TICK: Duration = Duration::from_millis(200);

/// The channels of one member a step reads at least, however many members
/// share `--max-channels`.
const MIN_SHARE: usize = 16;

/// The shortest time between two steps, however much news comes.
const MIN_STEP: Duration = Duration::from_millis(100);

/// How often an active bridge puts its table even if nothing changed, for
/// a site that missed a put.
const TABLE_REFRESH: Duration = Duration::from_secs(5);

/// Most other sites (bridge tokens) followed, and the memory their tables
/// may hold together (as [`table_cost`] counts it).
const MAX_SITES: usize = 256;
const MAX_SITES_BYTES: usize = 64 << 20;

/// How long a bridge watches its site before it may become active: long
/// enough for gossip to show the other bridges there.
const SETTLE: Duration = Duration::from_millis(1500);

/// How long a bridge seen on this site counts as this site's after it is
/// gone: its token and samples may outlive it on Zenoh for a lease.
const SEEN_FOR: Duration = Duration::from_secs(60);

/// Calls one bridge runs at once for the servers of its site (for all
/// other sites together); more are answered `UNREACHABLE` (busy).
const MAX_CALLS: usize = 1024;

/// Calls one relay server (one service) passes on at once.
const RELAY_CONCURRENCY: usize = 256;

/// Clients kept for the services of this site that other sites call.
const MAX_CLIENTS: usize = 1024;

/// The longest a call between sites runs (a server's own bound,
/// `pulicast::ServiceLimits::longest`, by default).
const LONGEST_CALL: Duration = Duration::from_secs(300);

/// Most progress messages one call passes on.
const MAX_PROGRESS: u32 = 65_536;

/// Bytes a service frame adds to its message (kind, call id, counts): an
/// answer larger than pulicast's largest message less this can't be sent.
const FRAME_OVERHEAD: usize = 64;

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
        let mut log = self
            .drop_log
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
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
            let (namespace, key) = key.key()?;
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
                    let mut inbox = lock(&shared.inbox);
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
                let table = read(&shared.table).clone();
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
                        if let Some(running) = lock(&shared.calls).get(&(cancel.bridge, cancel.id))
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
    let mut stats = lock(&shared.status).clone();
    stats.out_messages = c.out_messages.load(Relaxed);
    stats.out_bytes = c.out_bytes.load(Relaxed);
    stats.out_rate_limited = c.out_rate_limited.load(Relaxed);
    stats.out_not_local = c.out_not_local.load(Relaxed);
    stats.out_failed = c.out_failed.load(Relaxed);
    stats.out_over_names = c.out_over_names.load(Relaxed);
    stats.export_names = lock(&shared.export_names).len();
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
    stats.calls_running = lock(&shared.calls).len();
    stats
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn read<T>(m: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    m.read().unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn write<T>(m: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    m.write().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A table from Zenoh: decoded here (bounded), kept in the inbox (the
/// newest per bridge, bounded in memory) for the control task.
fn take_table(shared: &Shared, sample: &Sample) {
    if sample.kind() != SampleKind::Put {
        return;
    }
    let refused = |why: &dyn std::fmt::Display| {
        shared.counters.tables_refused.fetch_add(1, Relaxed);
        tracing::warn!("dropped a site table from Zenoh: {why}");
    };
    let table = match SiteTable::decode(&sample.payload().to_bytes()) {
        Ok(t) => t,
        Err(e) => return refused(&e),
    };
    if table.bridge == shared.me {
        return;
    }
    // Filed under the bridge whose key it came on, and no other.
    if sample.key_expr().as_str() != shared.checked.keys.site_table(table.bridge) {
        return refused(&"a table under another bridge's key");
    }
    let cost = table_cost(&table);
    let mut inbox = lock(&shared.inbox);
    let old = inbox.tables.get(&table.bridge).map_or(0, |(_, c)| *c);
    let fits = inbox.tables.contains_key(&table.bridge) || inbox.tables.len() < MAX_SITES;
    if !fits || inbox.bytes - old + cost > MAX_SITES_BYTES {
        drop(inbox);
        return refused(&"the tables waiting are at their bound");
    }
    inbox.bytes = inbox.bytes - old + cost;
    inbox.tables.insert(table.bridge, (table, cost));
    drop(inbox);
    shared.news.notify_one();
}

/// What a table holds in memory, about: its members' states as discovery
/// counts them, and its names.
fn table_cost(table: &SiteTable) -> usize {
    std::mem::size_of::<SiteTable>()
        + table.site.capacity()
        + table.bridge_name.capacity()
        + table
            .members
            .iter()
            .map(|m| m.info.memory_cost())
            .sum::<usize>()
}

/// Declarations that live as long as the control task.
struct Declared {
    _calls: zenoh::query::Queryable<()>,
    _cancels: zenoh::pubsub::Subscriber<()>,
    _tables: zenoh::pubsub::Subscriber<()>,
    _tokens: zenoh::pubsub::Subscriber<()>,
    _queryable: zenoh::query::Queryable<()>,
    _marker: (Channel, pulicast::Subscription<pulicast::Bytes>),
}

/// What the control task has set up.
struct Applied {
    plan: Plan,
    started: Instant,
    /// Held while active: the subscription that says so on this site.
    active_marker: Option<pulicast::Subscription<pulicast::Bytes>>,
    /// Bridges seen on this site, and when last.
    seen_bridges: HashMap<i64, Instant>,
    /// Whether this site's table was over its bound last time (said once).
    table_too_large: bool,
    /// Servers answering here for other sites' servers, by service.
    relay_servers: HashMap<String, pulicast::Server>,
    exports: HashMap<String, Exported>,
    imports: HashMap<String, Imported>,
    /// Which of the plan's exports and imports are carried (bounded).
    export_slots: Slots,
    import_slots: Slots,
    /// Whether channels left out were said, per direction.
    exports_left_out_said: bool,
    imports_left_out_said: bool,
    /// Whether names left out for `--max-import-names` were said (once:
    /// the bound holds until the bridge restarts).
    import_names_said: bool,
    token: Option<LivelinessToken>,
    table_version: u64,
    table_put: Option<Instant>,
    /// What was last handed to `Discovery::relay`.
    relayed: Vec<RelayedMember>,
    /// Members no longer relayed, sent as dead for a while so they fail at
    /// once here instead of when their last entry ages out.
    ended: HashMap<i64, (RelayedMember, Instant)>,
}

/// How long a member that stopped being relayed is sent as dead: the relay
/// entries' lifetime, so every node hears it before the entry would have
/// aged out anyway.
const ENDED_FOR: Duration = Duration::from_secs(3);

/// One exported channel's task, and when it last put a message.
struct Exported {
    task: JoinHandle<()>,
    used: Arc<LastUsed>,
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

struct Imported {
    /// Taken first when the import ends, so no callback adds to the batch
    /// that the flusher's end sends.
    subscriber: Option<zenoh::pubsub::Subscriber<()>>,
    /// Sends the channel's pending batch (see [`flush_imports`]).
    flusher: JoinHandle<()>,
    spec: Import,
    state: Arc<ImportState>,
}

impl Drop for Imported {
    fn drop(&mut self) {
        drop(self.subscriber.take());
        self.flusher.abort();
        let _ = self.state.channel.flush();
    }
}

/// One imported channel, as its Zenoh callback sees it.
struct ImportState {
    channel: Channel,
    /// The channel's key: a sample under it needs no further look.
    key: String,
    fingerprints: RwLock<Vec<[u8; 8]>>,
    gate: Mutex<RateGate>,
    losses: Mutex<Losses>,
    /// Whether a message leaves alone or batched.
    pacer: Pacer,
    /// Asks the flusher to send the batch.
    flush: Notify,
    /// The pacer's clock starts here.
    born: Instant,
    /// When a sample was last published here.
    used: LastUsed,
}

impl ImportState {
    fn now(&self) -> u64 {
        u64::try_from(self.born.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }
}

/// The longest an imported message waits in a batch if its flusher is
/// late; normally it leaves as soon as the flusher runs.
const IMPORT_BATCH_DELAY: Duration = Duration::from_millis(1);

/// The other sites, as Zenoh tells them: tables are kept only for bridges
/// whose token is present.
#[derive(Default)]
struct Sites {
    live: HashSet<i64>,
    tables: BTreeMap<i64, SiteTable>,
    /// Memory the tables hold, as [`table_cost`] counts it.
    bytes: usize,
}

impl Sites {
    /// Takes what the callbacks left in the inbox; true if anything changed.
    fn take(&mut self, shared: &Arc<Shared>) -> bool {
        let inbox = std::mem::take(&mut *lock(&shared.inbox));
        let mut changed = false;
        for (bridge, live) in inbox.tokens {
            changed = true;
            if live {
                // Bounded: a bridge beyond the sites followed is refused,
                // and its table never asked for.
                if !self.live.contains(&bridge) && self.live.len() >= MAX_SITES {
                    shared.counters.tables_refused.fetch_add(1, Relaxed);
                    tracing::debug!("a bridge beyond the {MAX_SITES} sites followed is ignored");
                    continue;
                }
                // A token (back): its table is asked afresh, whatever
                // version was held before.
                self.live.insert(bridge);
                self.drop_table(bridge);
                ask_table(shared, bridge);
            } else {
                self.live.remove(&bridge);
                self.drop_table(bridge);
                // Its calls here have nobody to answer to.
                for ((caller, _), running) in lock(&shared.calls).iter() {
                    if *caller == bridge {
                        running.notify_one();
                    }
                }
            }
        }
        for (bridge, (table, cost)) in inbox.tables {
            let newer = self
                .tables
                .get(&bridge)
                .is_none_or(|held| table.version > held.version);
            if !self.live.contains(&bridge) || !newer {
                continue;
            }
            let held = self.tables.get(&bridge).map_or(0, table_cost);
            if self.bytes - held + cost > MAX_SITES_BYTES {
                shared.counters.tables_refused.fetch_add(1, Relaxed);
                tracing::debug!("a site table over the memory the tables may hold is dropped");
                continue;
            }
            self.bytes = self.bytes - held + cost;
            self.tables.insert(bridge, table);
            changed = true;
        }
        changed
    }

    fn drop_table(&mut self, bridge: i64) {
        if let Some(table) = self.tables.remove(&bridge) {
            self.bytes -= table_cost(&table);
        }
    }
}

async fn control(shared: Arc<Shared>, _declared: Declared) -> Leftovers {
    let mut applied = Applied {
        plan: Plan::default(),
        started: Instant::now(),
        active_marker: None,
        seen_bridges: HashMap::new(),
        table_too_large: false,
        relay_servers: HashMap::new(),
        exports: HashMap::new(),
        imports: HashMap::new(),
        export_slots: Slots::new(shared.checked.exports),
        import_slots: Slots::new(shared.checked.imports),
        exports_left_out_said: false,
        imports_left_out_said: false,
        import_names_said: false,
        token: None,
        table_version: 0,
        table_put: None,
        relayed: Vec::new(),
        ended: HashMap::new(),
    };
    let mut sites = Sites::default();
    let mut discovery = shared.node.discovery().events();
    let mut last_step = tokio::time::Instant::now();
    loop {
        tokio::select! {
            _ = shared.stop.notified() => break,
            _ = tokio::time::sleep(TICK) => {}
            _ = shared.news.notified() => {}
            event = discovery.recv() => if event.is_none() {
                // The node stopped.
                break;
            },
        }
        // A step reads the whole fleet: a flood of discovery events (a
        // stranger's thousand fake nodes) makes one step per
        // `MIN_STEP`, not one per event.
        let due = last_step + MIN_STEP;
        if tokio::time::Instant::now() < due {
            tokio::select! {
                _ = shared.stop.notified() => break,
                _ = tokio::time::sleep_until(due) => {}
            }
        }
        while discovery.try_recv().is_some() {}
        last_step = tokio::time::Instant::now();
        sites.take(&shared);
        // A step under a stranger's flood can take a while (hundreds of new
        // exports, each joining a group): a stop ends it where it is, as
        // what it left half done is taken down below anyway.
        tokio::select! {
            _ = shared.stop.notified() => break,
            _ = step(&shared, &sites, &mut applied) => {}
        }
    }
    // Leaving: the other sites see this bridge's token go and fail its
    // members at once; imported channels stop here.
    applied.token.take();
    // What the imports hold is sent now; their Zenoh subscribers go with
    // the session (undeclared one by one, thousands of them took seconds).
    let imports = std::mem::take(&mut applied.imports);
    for import in imports.values() {
        import.flusher.abort();
        let _ = import.state.channel.flush();
    }
    applied.relay_servers.clear();
    if let Err(e) = shared.node.discovery().relay(Vec::new()) {
        tracing::debug!("relay list not cleared: {e}");
    }
    Leftovers {
        imports,
        exports: std::mem::take(&mut applied.exports),
    }
}

/// What the control task leaves to take down once the node has stopped
/// and the Zenoh session is closed: thousands of exports and imports
/// (under a stranger's flood) each leaving its group or undeclaring its
/// subscriber one by one took seconds; after the stop, they cost nothing.
#[derive(Default)]
struct Leftovers {
    imports: HashMap<String, Imported>,
    exports: HashMap<String, Exported>,
}

impl Drop for Leftovers {
    fn drop(&mut self) {
        self.imports.clear();
        for export in self.exports.values() {
            export.task.abort();
        }
    }
}

/// Asks a bridge whose token appeared for its table.
fn ask_table(shared: &Arc<Shared>, bridge: i64) {
    let key = shared.checked.keys.site_table(bridge);
    let weak = Arc::downgrade(shared);
    tokio::spawn(async move {
        let Some(shared) = weak.upgrade() else { return };
        let replies = match shared
            .session
            .get(key)
            .allowed_destination(Locality::Remote)
            .timeout(Duration::from_secs(5))
            .await
        {
            Ok(r) => r,
            Err(e) => return tracing::debug!("asking for a site table: {e}"),
        };
        drop(shared);
        while let Ok(reply) = replies.recv_async().await {
            let Some(shared) = weak.upgrade() else { return };
            if let Ok(sample) = reply.result() {
                take_table(&shared, sample);
            }
        }
    });
}

/// Recomputes the plan and applies what changed.
async fn step(shared: &Arc<Shared>, sites: &Sites, applied: &mut Applied) {
    // Each member's share of the channels a step reads: at most
    // `--max-per-member`, and no more than `--max-channels` in all, so that
    // thousands of strangers' members cost a step no more than that.
    // Members that carry messages through this bridge are read first, each
    // up to its share of the whole; the others share what is left. A real
    // node of hundreds of channels is then read whole however many
    // strangers' members announce names they never send on.
    let discovery = shared.node.discovery();
    let c = &shared.checked;
    let share_of = |budget: usize, members: usize| {
        c.exports
            .per_member
            .min((budget / members.max(1)).max(MIN_SHARE))
    };
    let exports = &applied.exports;
    let carrying = applied.export_slots.carrying(
        |name| exports.get(name).and_then(|e| e.used.get()),
        Instant::now(),
    );
    let members = discovery.members_within(0);
    let carrying_count = members.iter().filter(|m| carrying.contains(&m.key)).count();
    let mut local = Vec::new();
    let mut left = c.max_channels;
    let mut share = 0;
    if carrying_count > 0 {
        share = share_of(c.max_channels, carrying_count);
        local = discovery.members_picked(share, |key| carrying.contains(&key));
        let read: usize = local.iter().map(|m| m.channels.len()).sum();
        left = left.saturating_sub(read);
    }
    let others = share_of(left, members.len() - carrying_count);
    local.extend(discovery.members_picked(others, |key| !carrying.contains(&key)));
    let share = share.max(others);
    let remote = &sites.tables;
    let now = Instant::now();
    applied
        .seen_bridges
        .retain(|_, at| now.duration_since(*at) < SEEN_FOR);
    for bridge in &applied.plan.local_bridges {
        applied.seen_bridges.insert(*bridge, now);
    }
    let seen: HashSet<i64> = applied.seen_bridges.keys().copied().collect();
    let data_port = shared
        .node
        .discovery()
        .local()
        .data_address
        .map_or(0, |a| a.port());
    let plan = plan::plan(plan::Inputs {
        me: shared.me,
        local: &local,
        remote,
        keys: &c.keys,
        out: &c.out,
        inn: &c.inn,
        data_port,
        active: applied.plan.active,
        settled: applied.started.elapsed() >= SETTLE,
        seen_bridges: &seen,
        per_member: share,
    });
    let ended_expired = applied
        .ended
        .values()
        .any(|(_, at)| at.elapsed() >= ENDED_FOR);
    let more = applied.export_slots.more_waiting() || applied.import_slots.more_waiting();
    if plan == applied.plan && !table_due(applied) && !ended_expired && !more {
        return;
    }
    if plan.active != applied.plan.active {
        tracing::info!(
            active = plan.active,
            "this bridge {} its site",
            if plan.active {
                "now carries"
            } else {
                "stands by for"
            }
        );
        applied.active_marker = match plan.active {
            true => shared
                .node
                .try_channel(&shared.checked.keys.active_channel())
                .and_then(|c| c.subscribe_raw())
                .map_err(|e| tracing::warn!("the active marker: {e}"))
                .ok(),
            false => None,
        };
    }
    *write(&shared.sources) = plan.sources.clone();
    *write(&shared.local_bridges) = plan.local_bridges.clone();
    if plan.unmappable != applied.plan.unmappable {
        for (name, why) in &plan.unmappable {
            tracing::warn!(channel = %printable(name), "not bridged: {why}");
        }
    }
    apply_exports(shared, &plan, applied);
    apply_imports(shared, &plan, applied).await;
    let relayed = relay_list(&plan, applied);
    if relayed != applied.relayed {
        if let Err(e) = shared.node.discovery().relay(relayed.clone()) {
            tracing::warn!("relaying other sites' members: {e}");
        }
        applied.relayed = relayed;
    }
    apply_services(shared, &plan, applied);
    apply_table(shared, &plan, applied).await;
    {
        let mut status = lock(&shared.status);
        status.active = plan.active;
        status.exports = applied.exports.len();
        status.imports = applied.imports.len();
        status.exports_left_out = applied.export_slots.left_out();
        status.imports_left_out = applied.import_slots.left_out();
        status.import_names = applied.import_slots.names_tried();
        status.imports_refused = applied.import_slots.refused();
        status.sites = sites.live.len();
        status.relayed = plan.relayed.len();
        status.services = plan.services.len();
    }
    applied.plan = plan;
}

/// The plan's relayed members, plus those it no longer has, as dead (for
/// [`ENDED_FOR`]).
fn relay_list(plan: &Plan, applied: &mut Applied) -> Vec<RelayedMember> {
    let now = Instant::now();
    let current: HashSet<i64> = plan.relayed.iter().map(|m| m.info.key()).collect();
    for old in &applied.relayed {
        let key = old.info.key();
        if !current.contains(&key) && old.state != MemberState::Dead {
            let mut dead = old.clone();
            dead.state = MemberState::Dead;
            applied.ended.insert(key, (dead, now));
        }
    }
    applied
        .ended
        .retain(|key, (_, at)| !current.contains(key) && now.duration_since(*at) < ENDED_FOR);
    let mut list = plan.relayed.clone();
    list.extend(applied.ended.values().map(|(m, _)| m.clone()));
    list
}

fn table_due(applied: &Applied) -> bool {
    applied.plan.active
        && applied
            .table_put
            .is_none_or(|at| at.elapsed() >= TABLE_REFRESH)
}

/// Declares the token and puts the table while active; withdraws both
/// when standing by.
async fn apply_table(shared: &Arc<Shared>, plan: &Plan, applied: &mut Applied) {
    let keys = &shared.checked.keys;
    if !plan.active {
        applied.token = None;
        write(&shared.table).clear();
        return;
    }
    let changed = plan.table != applied.plan.table || applied.table_put.is_none();
    if changed {
        applied.table_version += 1;
    }
    let table = SiteTable {
        bridge: shared.me,
        bridge_name: shared.node.name().to_owned(),
        site: shared.checked.site.clone(),
        version: applied.table_version,
        members: plan.table.clone(),
    };
    let bytes = table.encode();
    let too_large = bytes.len() > MAX_TABLE_BYTES;
    if too_large != std::mem::replace(&mut applied.table_too_large, too_large) && too_large {
        tracing::warn!(
            bytes = bytes.len(),
            "this site's table is over its bound; other sites keep the last one"
        );
    }
    if too_large {
        return;
    }
    *write(&shared.table) = bytes.clone();
    match shared
        .session
        .put(keys.site_table(shared.me), bytes)
        .congestion_control(CongestionControl::Block)
        .await
    {
        Ok(()) => applied.table_put = Some(Instant::now()),
        Err(e) => tracing::debug!("site table not put: {e}"),
    }
    // The token goes up after the table is there to be asked for.
    if applied.token.is_none() {
        match shared
            .session
            .liveliness()
            .declare_token(keys.bridge_token(shared.me))
            .await
        {
            Ok(token) => applied.token = Some(token),
            Err(e) => tracing::warn!("liveliness token not declared: {e}"),
        }
    }
}

/// Answers here for the servers of other sites: one relay server per
/// service, taking the calls whose target is one of them.
fn apply_services(shared: &Arc<Shared>, plan: &Plan, applied: &mut Applied) {
    *write(&shared.serving) = plan.services.clone();
    applied
        .relay_servers
        .retain(|service, _| plan.services.contains_key(service));
    for service in plan.services.keys() {
        if applied.relay_servers.contains_key(service) {
            continue;
        }
        match relay_server(shared, service) {
            Ok(server) => {
                applied.relay_servers.insert(service.clone(), server);
            }
            Err(e) => tracing::warn!(service = %printable(service), "not answered for here: {e}"),
        }
    }
}

fn relay_server(shared: &Arc<Shared>, service: &str) -> pulicast::Result<pulicast::Server> {
    let weak = Arc::downgrade(shared);
    let name = service.to_owned();
    let answers_for = move |target: &str| {
        weak.upgrade().is_some_and(|shared| {
            read(&shared.serving)
                .get(&name)
                .is_some_and(|nodes| nodes.contains_key(target))
        })
    };
    let weak = Arc::downgrade(shared);
    let name = service.to_owned();
    shared
        .node
        .make_namespace("/")
        .server(service)
        .concurrency(RELAY_CONCURRENCY)
        .serve_for(answers_for, move |message, context| {
            let weak = weak.clone();
            let name = name.clone();
            async move {
                match weak.upgrade() {
                    Some(shared) => pass_on(&shared, &name, message, context).await,
                    None => Err(Fault::new(Fault::UNREACHABLE, "the bridge stopped")),
                }
            }
        })
}

/// Tells the server's site that a call passed on was cancelled, unless it
/// ended first.
struct CancelOnDrop {
    session: Session,
    key: String,
    cancel: CallCancel,
    armed: bool,
}

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        if !self.armed {
            return;
        }
        let session = self.session.clone();
        let key = std::mem::take(&mut self.key);
        let bytes = self.cancel.encode();
        if let Ok(runtime) = tokio::runtime::Handle::try_current() {
            runtime.spawn(async move {
                // Not dropped under congestion: a lost cancel keeps a
                // call running to its deadline.
                let _ = session
                    .put(key, bytes)
                    .congestion_control(CongestionControl::Block)
                    .await;
            });
        }
    }
}

/// Passes a call of this site on to the bridge of the server's site, and
/// its progress and answer back.
async fn pass_on(
    shared: &Arc<Shared>,
    service: &str,
    message: pulicast::Bytes,
    context: CallContext<()>,
) -> Result<Vec<u8>, Fault> {
    let unreachable = |why: String| Fault::new(Fault::UNREACHABLE, why);
    let target = context.target().to_owned();
    let bridge = read(&shared.serving)
        .get(service)
        .and_then(|nodes| nodes.get(&target))
        .copied()
        .ok_or_else(|| {
            unreachable(format!(
                "{target} is no longer reachable through this bridge"
            ))
        })?;
    let left = context.deadline().map_or(Duration::from_secs(300), |d| {
        d.saturating_duration_since(Instant::now())
    });
    let id = shared.next_call.fetch_add(1, Relaxed);
    let request = CallRequest {
        bridge: shared.me,
        id,
        service: service.to_owned(),
        target,
        deadline_ms: u32::try_from(left.as_millis()).unwrap_or(u32::MAX).max(1),
        message: message.to_vec(),
    };
    let keys = &shared.checked.keys;
    shared.counters.calls_out.fetch_add(1, Relaxed);
    let replies = shared
        .session
        .get(keys.calls(bridge))
        .payload(request.encode())
        .consolidation(ConsolidationMode::None)
        .allowed_destination(Locality::Remote)
        .timeout(left + Duration::from_millis(500))
        .await
        .map_err(|e| unreachable(format!("the server's site: {e}")))?;
    let mut cancel = CancelOnDrop {
        session: shared.session.clone(),
        key: keys.cancels(bridge),
        cancel: CallCancel {
            bridge: shared.me,
            id,
        },
        armed: true,
    };
    let fits = |m: &[u8]| m.len() + FRAME_OVERHEAD <= pulicast::MAX_MESSAGE;
    let mut progress = 0u32;
    while let Ok(reply) = replies.recv_async().await {
        let Ok(sample) = reply.result() else { continue };
        match CallAnswer::decode(&sample.payload().to_bytes()) {
            Ok(CallAnswer::Progress(m)) if fits(&m) && progress < MAX_PROGRESS => {
                progress += 1;
                let _ = context.progress_encoded(&m);
            }
            Ok(CallAnswer::Progress(_)) => {
                shared.counters.calls_refused.fetch_add(1, Relaxed);
            }
            Ok(CallAnswer::Reply(m)) if fits(&m) => {
                cancel.armed = false;
                return Ok(m);
            }
            Ok(CallAnswer::Reply(_)) => {
                shared.counters.calls_refused.fetch_add(1, Relaxed);
                return Err(unreachable(
                    "the server's reply is too large to pass on".into(),
                ));
            }
            Ok(CallAnswer::Failure { code, message }) => {
                cancel.armed = false;
                return Err(Fault::new(code, message));
            }
            Err(e) => {
                shared.counters.calls_refused.fetch_add(1, Relaxed);
                tracing::debug!("{e}");
            }
        }
    }
    cancel.armed = false;
    Err(unreachable("no answer from the server's site".into()))
}

/// A call from another site for a server of this one: run in a task.
fn take_call(shared: &Arc<Shared>, query: Query) {
    let request = match query.payload().map(|p| CallRequest::decode(&p.to_bytes())) {
        Some(Ok(r)) => r,
        Some(Err(e)) => {
            shared.counters.calls_refused.fetch_add(1, Relaxed);
            return tracing::warn!("{e}");
        }
        None => {
            shared.counters.calls_refused.fetch_add(1, Relaxed);
            return;
        }
    };
    let cancel = Arc::new(Notify::new());
    let admitted = {
        let mut calls = lock(&shared.calls);
        let key = (request.bridge, request.id);
        (calls.len() < MAX_CALLS && !calls.contains_key(&key))
            .then(|| calls.insert(key, Arc::clone(&cancel)))
            .is_some()
    };
    let shared = Arc::clone(shared);
    shared.runtime.clone().spawn(async move {
        let reply_key = query.key_expr().clone();
        let answer = |a: CallAnswer| {
            let bytes = a.encode();
            let key = reply_key.clone();
            let query = &query;
            async move {
                if let Err(e) = query.reply(key, bytes).await {
                    tracing::debug!("call answer not sent: {e}");
                }
            }
        };
        if !admitted {
            shared.counters.calls_refused.fetch_add(1, Relaxed);
            return answer(CallAnswer::Failure {
                code: Fault::UNREACHABLE,
                message: "the bridge of the server's site runs as many calls as it may".into(),
            })
            .await;
        }
        shared.counters.calls_in.fetch_add(1, Relaxed);
        let outcome = run_call(&shared, &request, &cancel, &answer).await;
        lock(&shared.calls).remove(&(request.bridge, request.id));
        if let Some(last) = outcome {
            answer(last).await;
        }
    });
}

/// Runs a call from another site on this site's server; progress goes
/// through `answer`, the final answer is returned (`None` if cancelled).
async fn run_call<F, Fut>(
    shared: &Shared,
    request: &CallRequest,
    cancel: &Notify,
    answer: &F,
) -> Option<CallAnswer>
where
    F: Fn(CallAnswer) -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    let unreachable = |message: String| CallAnswer::Failure {
        code: Fault::UNREACHABLE,
        message,
    };
    // Only what this site offers: a live member of its own that serves
    // the service, and a request channel its out-filter passes. Anything
    // else is answered at once, before it costs a client.
    let channel = pulicast::ServiceInfo::request_channel_of(&request.service);
    // The request channel's subscribers, not the whole fleet: a stranger's
    // members of thousands of names cost a call nothing.
    let offered = shared.checked.out.passes(&channel)
        && shared
            .node
            .try_channel(&format!("/{channel}"))
            .map(|c| c.subscribers())
            .unwrap_or_default()
            .iter()
            .any(|m| m.remote.is_none() && m.name == request.target && m.serves(&channel));
    if !offered {
        shared.counters.calls_refused.fetch_add(1, Relaxed);
        return Some(unreachable(format!(
            "{} serves no {} on this site",
            request.target, request.service
        )));
    }
    let name = format!("{}@{}", request.service, request.target);
    let client = {
        let mut clients = lock(&shared.clients);
        match clients.get(&name) {
            Some(c) => c.clone(),
            None => match shared.node.make_namespace("/").raw_client(&name) {
                Ok(c) => {
                    // Names are of this site's own servers; past the
                    // bound, clients are made per call.
                    if clients.len() < MAX_CLIENTS {
                        clients.insert(name.clone(), c.clone());
                    }
                    c
                }
                Err(e) => return Some(unreachable(e.to_string())),
            },
        }
    };
    // 0 (no deadline) and anything longer: the longest a call runs.
    let within = match Duration::from_millis(u64::from(request.deadline_ms)) {
        d if d.is_zero() || d > LONGEST_CALL => LONGEST_CALL,
        d => d,
    };
    let mut call = tokio::select! {
        started = client.start(&request.message, within) => match started {
            Ok(call) => call,
            Err(e) => return Some(unreachable(e.to_string())),
        },
        () = cancel.notified() => return None,
    };
    loop {
        tokio::select! {
            () = cancel.notified() => {
                call.cancel();
                return None;
            }
            event = call.next() => match event {
                Some(CallEvent::Progress(m)) => answer(CallAnswer::Progress(m)).await,
                Some(CallEvent::Reply { message, .. }) => return Some(CallAnswer::Reply(message)),
                Some(CallEvent::Failed { code, message, .. }) => {
                    // SERVER_GONE is a caller's own conclusion, never sent:
                    // over there it reads as out of reach.
                    let code = if code == Fault::SERVER_GONE { Fault::UNREACHABLE } else { code };
                    return Some(CallAnswer::Failure { code, message });
                }
                Some(CallEvent::Busy) => return Some(unreachable("the server is busy".into())),
                Some(CallEvent::TimedOut) | None => {
                    return Some(CallAnswer::Failure {
                        code: Fault::DEADLINE,
                        message: "no reply by the call's deadline".into(),
                    });
                }
            }
        }
    }
}

fn apply_exports(shared: &Arc<Shared>, plan: &Plan, applied: &mut Applied) {
    let wanted: HashMap<&str, i64> = plan
        .exports
        .iter()
        .map(|(name, e)| (name.as_str(), e.member))
        .collect();
    let exports = &applied.exports;
    let choice = applied.export_slots.choose(
        &wanted,
        |name| exports.get(name).and_then(|e| e.used.get()),
        Instant::now(),
    );
    for name in &choice.stop {
        if let Some(export) = applied.exports.remove(name) {
            export.task.abort();
        }
    }
    // An export whose task ended (its subscription failed) starts again.
    let ended: Vec<String> = applied
        .exports
        .iter()
        .filter(|(_, e)| e.task.is_finished())
        .map(|(name, _)| name.clone())
        .collect();
    for name in choice.start.into_iter().chain(ended) {
        let used = Arc::new(LastUsed::new());
        let task = tokio::spawn(export(shared.clone(), name.clone(), used.clone()));
        applied.exports.insert(name, Exported { task, used });
    }
    let left_out = applied.export_slots.left_out();
    say_left_out("exported", left_out, &mut applied.exports_left_out_said);
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

/// Whether `name` may have a Zenoh publisher: it had one before, or
/// fewer than `--max-export-names` names did. Said once when one may not.
fn admit_export_name(shared: &Shared, name: &str) -> bool {
    let mut names = lock(&shared.export_names);
    if names.contains(name) {
        return true;
    }
    let max = shared.checked.max_export_names;
    if names.len() < max {
        names.insert(name.to_owned());
        return true;
    }
    drop(names);
    if shared.counters.out_over_names.load(Relaxed) == 0 {
        tracing::warn!(
            channel = %printable(name),
            max,
            "this bridge exported as many distinct names as --max-export-names allows: \
             messages on names never exported before are dropped until it restarts (Zenoh \
             keeps state for every key ever published); names exported before still go out"
        );
    }
    false
}

/// Moves one channel's messages from this site to Zenoh.
async fn export(shared: Arc<Shared>, name: String, used: Arc<LastUsed>) {
    let keys = &shared.checked.keys;
    let Ok(key) = keys.key_of(&name) else { return };
    let limit = Limit::find(&shared.checked.limits, &name);
    let mut gate = RateGate::new(limit.and_then(|l| l.max_rate));
    let priority = limit.map(|l| l.priority).unwrap_or_default();
    // Watched, not subscribed: a bridge that subscribed `X.r` while it
    // publishes `X` (a setting of another site's node) would be taken here
    // for the setting's owner. Nothing needs the bridge's subscription: the
    // members that publish the channel are what it exports for.
    let mut sub = match shared
        .node
        .try_channel(&format!("/{name}"))
        .and_then(|c| c.watch_raw())
    {
        Ok(s) => s,
        Err(e) => return tracing::warn!(channel = %printable(&name), "not exported: {e}"),
    };
    // Grown with the first messages, not before: thousands of exports that
    // never carry one (a stranger's names) cost no batch each.
    let mut batch = Vec::new();
    // The Zenoh publisher is declared with the first message: a name
    // announced and never used costs Zenoh nothing, here or elsewhere.
    if sub.recv_many(&mut batch, 64).await == 0 {
        return;
    }
    if !admit_export_name(&shared, &name) {
        // Kept as an export that carries nothing, so that its place goes
        // to another channel in time and the task is not started again
        // at every step.
        let c = &shared.counters;
        loop {
            c.out_over_names.fetch_add(batch.len() as u64, Relaxed);
            batch.clear();
            if sub.recv_many(&mut batch, 64).await == 0 {
                return;
            }
        }
    }
    let publisher = match shared
        .session
        .declare_publisher(key)
        .priority(priority.zenoh())
        .congestion_control(CongestionControl::Drop)
        .await
    {
        Ok(p) => p,
        Err(e) => return tracing::warn!(channel = %printable(&name), "not exported: {e}"),
    };
    let c = &shared.counters;
    let mut members = Vec::with_capacity(64);
    loop {
        if batch.is_empty() && sub.recv_many(&mut batch, 64).await == 0 {
            return;
        }
        // The publishers of the messages at hand, under one lock.
        members.clear();
        {
            let sources = read(&shared.sources);
            members.extend(batch.iter().map(|m| sources.of(m.source, &name)));
        }
        for (m, member) in batch.drain(..).zip(members.iter()) {
            let Some(member) = *member else {
                c.out_not_local.fetch_add(1, Relaxed);
                continue;
            };
            if !gate.admit_now() {
                c.out_rate_limited.fetch_add(1, Relaxed);
                continue;
            }
            let origin = Origin {
                bridge: shared.me,
                publisher: member,
                seq: m.seq,
            };
            let len = m.value.len() as u64;
            match publisher
                .put(m.value)
                .attachment(origin.encode().to_vec())
                .await
            {
                Ok(()) => {
                    c.out_messages.fetch_add(1, Relaxed);
                    c.out_bytes.fetch_add(len, Relaxed);
                    used.now();
                }
                Err(e) => {
                    c.out_failed.fetch_add(1, Relaxed);
                    tracing::debug!("put failed: {e}");
                }
            }
        }
    }
}

async fn apply_imports(shared: &Arc<Shared>, plan: &Plan, applied: &mut Applied) {
    let wanted: HashMap<&str, i64> = plan
        .imports
        .iter()
        .map(|(name, i)| (name.as_str(), i.member))
        .collect();
    let imports = &applied.imports;
    let choice = applied.import_slots.choose_listed(
        &wanted,
        |name| imports.get(name).and_then(|i| i.state.used.get()),
        |name| plan.imports.get(name).is_some_and(|i| i.listed),
        Instant::now(),
    );
    for name in &choice.stop {
        applied.imports.remove(name);
    }
    for (name, spec) in &plan.imports {
        if let Some(imported) = applied.imports.get_mut(name) {
            if imported.spec != *spec {
                *write(&imported.state.fingerprints) = spec.fingerprints.clone();
                if let Some(t) = &spec.message_type {
                    let _ = imported.state.channel.declare_type(t.clone());
                }
                imported.spec = spec.clone();
            }
        }
    }
    for name in &choice.start {
        let Some(spec) = plan.imports.get(name) else {
            continue;
        };
        match import(shared, name, spec).await {
            Ok(imported) => {
                applied.imports.insert(name.clone(), imported);
            }
            Err(e) => tracing::warn!(channel = %printable(name), "not imported: {e}"),
        }
    }
    let left_out = applied.import_slots.left_out();
    say_left_out("imported", left_out, &mut applied.imports_left_out_said);
    let refused = applied.import_slots.refused();
    if refused > 0 && !applied.import_names_said {
        applied.import_names_said = true;
        let [listed, others] = applied.import_slots.names_tried();
        tracing::warn!(
            refused,
            listed,
            others,
            "this bridge imported as many distinct names as --max-import-names allows: names \
             never imported before are left out until it restarts (Zenoh keeps state for every \
             key ever subscribed); names imported before still come and go"
        );
    }
}

/// Starts taking one channel's samples from Zenoh.
async fn import(shared: &Arc<Shared>, name: &str, spec: &Import) -> Result<Imported> {
    let key = shared
        .checked
        .keys
        .key_of(name)
        .map_err(|e| anyhow!("{e}"))?;
    let channel = shared.node.try_channel(&format!("/{name}"))?;
    if let Some(t) = &spec.message_type {
        channel.declare_type(t.clone())?;
    }
    channel.enable_batching(IMPORT_BATCH_DELAY)?;
    let limit = Limit::find(&shared.checked.limits, name);
    let state = Arc::new(ImportState {
        channel,
        key: key.clone(),
        fingerprints: RwLock::new(spec.fingerprints.clone()),
        gate: Mutex::new(RateGate::new(limit.and_then(|l| l.max_rate))),
        losses: Mutex::new(Losses::default()),
        pacer: Pacer::default(),
        flush: Notify::new(),
        born: Instant::now(),
        used: LastUsed::new(),
    });
    let weak = Arc::downgrade(shared);
    let st = state.clone();
    let subscriber = shared
        .session
        .declare_subscriber(key)
        // This bridge's own exports never come back to it.
        .allowed_origin(Locality::Remote)
        .callback(move |sample: Sample| {
            if let Some(shared) = weak.upgrade() {
                on_sample(&shared, &st, &sample);
            }
        })
        .await
        .map_err(|e| anyhow!("{e}"))?;
    // Started once the subscriber is in place: an import that failed leaves
    // no task behind (a sample that came first has left its wake-up).
    let flusher = shared
        .runtime
        .spawn(flush_imports(Arc::downgrade(shared), state.clone()));
    Ok(Imported {
        subscriber: Some(subscriber),
        flusher,
        spec: spec.clone(),
        state,
    })
}

/// A sample of an imported channel: checked, then published here.
fn on_sample(shared: &Shared, state: &ImportState, sample: &Sample) {
    if sample.kind() != SampleKind::Put {
        // A Zenoh delete is no message.
        return;
    }
    let key = sample.key_expr().as_str();
    // The subscription is on the channel's own key: another key reaches it
    // only through a put on a wildcard key (`<prefix>/**`), which names no
    // channel and must not spill into every channel it matches.
    if key != state.key {
        return shared.refuse(Refused::BadChannel, key);
    }
    let payload = sample.payload().to_bytes();
    let attachment = sample.attachment().map(|a| a.to_bytes());
    let checked = {
        let bridges = read(&shared.local_bridges);
        let fingerprints = read(&state.fingerprints);
        sample::check(
            &payload,
            attachment.as_deref(),
            |b| bridges.contains(&b),
            &fingerprints,
        )
    };
    let origin = match checked {
        Ok(origin) => origin,
        Err(why) => return shared.refuse(why, key),
    };
    if let Some(origin) = origin {
        // A publisher this site hears itself: its messages are here
        // already (another site bridged them out of here).
        if read(&shared.sources).members.contains(&origin.publisher) {
            return shared.refuse(Refused::Loop, key);
        }
        match lock(&state.losses).note(&origin) {
            Some(lost) => {
                shared.counters.in_lost.fetch_add(u64::from(lost), Relaxed);
            }
            None => return shared.refuse(Refused::Duplicate, key),
        }
    }
    if !lock(&state.gate).admit_now() {
        return shared.refuse(Refused::RateLimited, key);
    }
    let c = &shared.counters;
    let now = state.now();
    let alone = state.pacer.alone(now);
    let published = match alone {
        true => state.channel.publish_bytes_now(&payload),
        false => state.channel.publish_bytes(&payload),
    };
    match published {
        Ok(()) => {
            c.in_messages.fetch_add(1, Relaxed);
            c.in_bytes.fetch_add(payload.len() as u64, Relaxed);
            state.used.now();
            if alone {
                state.pacer.sent(now);
            } else if state.pacer.batched() {
                state.flush.notify_one();
            }
        }
        Err(e) => {
            c.in_failed.fetch_add(1, Relaxed);
            tracing::debug!("publishing an imported message failed: {e}");
        }
    }
}

/// Sends an imported channel's batch when messages joined it (see
/// [`crate::pace`]).
async fn flush_imports(shared: Weak<Shared>, state: Arc<ImportState>) {
    loop {
        state.flush.notified().await;
        state.pacer.flushing();
        let sent = state.channel.flush();
        state.pacer.sent(state.now());
        if let Err(e) = sent {
            let Some(shared) = shared.upgrade() else {
                return;
            };
            shared.counters.in_failed.fetch_add(1, Relaxed);
            tracing::debug!("sending imported messages failed: {e}");
        }
    }
}

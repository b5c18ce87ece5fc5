//! The control task: one step at a time, it reads the fleet and the other
//! sites, recomputes the plan ([`crate::plan`]) and applies what changed
//! (exports, imports, relayed members, services, this site's table).
//! Everything that changes what the bridge carries happens here, in one
//! task, so the parts never race each other.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use pulicast::{Channel, MemberState, RelayedMember};
use zenoh::liveliness::LivelinessToken;
use zenoh::qos::CongestionControl;

use super::calls::apply_services;
use super::export::{apply_exports, Exported};
use super::import::{apply_imports, Imported};
use super::sites::Sites;
use super::{printable, Shared};
use crate::plan::{self, Plan};
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

/// How long a bridge watches its site before it may become active: long
/// enough for gossip to show the other bridges there.
const SETTLE: Duration = Duration::from_millis(1500);

/// How long a bridge seen on this site counts as this site's after it is
/// gone: its token and samples may outlive it on Zenoh for a lease.
const SEEN_FOR: Duration = Duration::from_secs(60);

/// Declarations that live as long as the control task.
pub(super) struct Declared {
    pub(super) _calls: zenoh::query::Queryable<()>,
    pub(super) _cancels: zenoh::pubsub::Subscriber<()>,
    pub(super) _tables: zenoh::pubsub::Subscriber<()>,
    pub(super) _tokens: zenoh::pubsub::Subscriber<()>,
    pub(super) _queryable: zenoh::query::Queryable<()>,
    pub(super) _marker: (Channel, pulicast::Subscription<pulicast::Bytes>),
}

/// What the control task has set up.
pub(super) struct Applied {
    pub(super) plan: Plan,
    pub(super) started: Instant,
    /// Held while active: the subscription that says so on this site.
    pub(super) active_marker: Option<pulicast::Subscription<pulicast::Bytes>>,
    /// Bridges seen on this site, and when last.
    pub(super) seen_bridges: HashMap<i64, Instant>,
    /// Whether this site's table was over its bound last time (said once).
    pub(super) table_too_large: bool,
    /// Servers answering here for other sites' servers, by service.
    pub(super) relay_servers: HashMap<String, pulicast::Server>,
    pub(super) exports: HashMap<String, Exported>,
    pub(super) imports: HashMap<String, Imported>,
    /// Which of the plan's exports and imports are carried (bounded).
    pub(super) export_slots: Slots,
    pub(super) import_slots: Slots,
    /// Whether channels left out were said, per direction.
    pub(super) exports_left_out_said: bool,
    pub(super) imports_left_out_said: bool,
    /// Whether names left out for `--max-import-names` were said (once:
    /// the bound holds until the bridge restarts).
    pub(super) import_names_said: bool,
    pub(super) token: Option<LivelinessToken>,
    pub(super) table_version: u64,
    pub(super) table_put: Option<Instant>,
    /// What was last handed to `Discovery::relay`.
    pub(super) relayed: Vec<RelayedMember>,
    /// Members no longer relayed, sent as dead for a while so they fail at
    /// once here instead of when their last entry ages out.
    pub(super) ended: HashMap<i64, (RelayedMember, Instant)>,
}

/// How long a member that stopped being relayed is sent as dead: the relay
/// entries' lifetime, so every node hears it before the entry would have
/// aged out anyway.
const ENDED_FOR: Duration = Duration::from_secs(3);

pub(super) async fn control(shared: Arc<Shared>, _declared: Declared) -> Leftovers {
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
        import.flush_now();
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
pub(super) struct Leftovers {
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
    *shared.sources.write() = plan.sources.clone();
    *shared.local_bridges.write() = plan.local_bridges.clone();
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
        let mut status = shared.status.lock();
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
        shared.table.write().clear();
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
    *shared.table.write() = bytes.clone();
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

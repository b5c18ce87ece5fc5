//! The other sites as Zenoh shows them: their bridges' tokens and tables,
//! taken from the callbacks' inbox and held within their bounds. Apart
//! from the control step because the tables are what a stranger on
//! another site can grow.

use std::collections::{BTreeMap, HashSet};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

use zenoh::sample::{Locality, Sample, SampleKind};

use super::Shared;
use crate::table::SiteTable;

/// Most other sites (bridge tokens) followed, and the memory their tables
/// may hold together (as [`table_cost`] counts it).
pub(super) const MAX_SITES: usize = 256;
const MAX_SITES_BYTES: usize = 64 << 20;

/// A table from Zenoh: decoded here (bounded), kept in the inbox (the
/// newest per bridge, bounded in memory) for the control task.
pub(super) fn take_table(shared: &Shared, sample: &Sample) {
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
    let mut inbox = shared.inbox.lock();
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

/// The other sites, as Zenoh tells them: tables are kept only for bridges
/// whose token is present.
#[derive(Default)]
pub(super) struct Sites {
    pub(super) live: HashSet<i64>,
    pub(super) tables: BTreeMap<i64, SiteTable>,
    /// Memory the tables hold, as [`table_cost`] counts it.
    pub(super) bytes: usize,
}

impl Sites {
    /// Takes what the callbacks left in the inbox; true if anything changed.
    pub(super) fn take(&mut self, shared: &Arc<Shared>) -> bool {
        let inbox = std::mem::take(&mut *shared.inbox.lock());
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
                for ((caller, _), running) in shared.calls.lock().iter() {
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

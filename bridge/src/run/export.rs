//! Channels going out: one task per exported channel watches it here and
//! puts its messages on Zenoh, within the channel's rate limit and the
//! bridge's bound on distinct names.

use std::collections::HashMap;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Instant;

use tokio::task::JoinHandle;
use zenoh::qos::CongestionControl;

use super::control::Applied;
use super::{printable, say_left_out, LastUsed, Shared};
use crate::filter::{Limit, RateGate};
use crate::plan::Plan;
use crate::sample::Origin;

/// One exported channel's task, and when it last put a message.
pub(super) struct Exported {
    pub(super) task: JoinHandle<()>,
    pub(super) used: Arc<LastUsed>,
}

pub(super) fn apply_exports(shared: &Arc<Shared>, plan: &Plan, applied: &mut Applied) {
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

/// Whether `name` may have a Zenoh publisher: it had one before, or
/// fewer than `--max-export-names` names did. Said once when one may not.
fn admit_export_name(shared: &Shared, name: &str) -> bool {
    let mut names = shared.export_names.lock();
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
            let sources = shared.sources.read();
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

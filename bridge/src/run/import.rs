//! Channels coming in: one Zenoh subscriber per imported channel, whose
//! callback checks each sample (its key, origin, fingerprint, loops,
//! duplicates, rate) and publishes it here, alone or batched as the pacer
//! says.

use std::collections::HashMap;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::{Arc, Weak};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use parking_lot::{Mutex, RwLock};
use pulicast::Channel;
use tokio::sync::Notify;
use tokio::task::JoinHandle;
use zenoh::sample::{Locality, Sample, SampleKind};

use super::control::Applied;
use super::{printable, say_left_out, LastUsed, Shared};
use crate::filter::{Limit, RateGate};
use crate::pace::Pacer;
use crate::plan::{Import, Plan};
use crate::sample::{self, Losses, Refused};

pub(super) struct Imported {
    /// Taken first when the import ends, so no callback adds to the batch
    /// that the flusher's end sends.
    subscriber: Option<zenoh::pubsub::Subscriber<()>>,
    /// Sends the channel's pending batch (see [`flush_imports`]).
    flusher: JoinHandle<()>,
    spec: Import,
    state: Arc<ImportState>,
}

impl Imported {
    /// Sends what the channel holds and stops its flusher, leaving the
    /// Zenoh subscriber to go with the session (a stop's quick way out).
    pub(super) fn flush_now(&self) {
        self.flusher.abort();
        let _ = self.state.channel.flush();
    }
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

pub(super) async fn apply_imports(shared: &Arc<Shared>, plan: &Plan, applied: &mut Applied) {
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
                *imported.state.fingerprints.write() = spec.fingerprints.clone();
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
        let bridges = shared.local_bridges.read();
        let fingerprints = state.fingerprints.read();
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
        if shared.sources.read().members.contains(&origin.publisher) {
            return shared.refuse(Refused::Loop, key);
        }
        match state.losses.lock().note(&origin) {
            Some(lost) => {
                shared.counters.in_lost.fetch_add(u64::from(lost), Relaxed);
            }
            None => return shared.refuse(Refused::Duplicate, key),
        }
    }
    if !state.gate.lock().admit_now() {
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

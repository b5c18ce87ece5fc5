//! The settings client driven: the sans-IO [`Catalog`] fed from discovery
//! and from the owners' confirmations, settings poked until they answer,
//! requests sent again until confirmed, and the waits between. The API's
//! `FleetSettings` holds one of these and nothing that reads a clock or a
//! socket.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::Notify;

use super::{ChannelState, Handler, Inner};
use crate::error::{Error, Result};
use crate::proto::catalog::{
    self, Catalog, Member, SettingInfo, Unaskable, Verdict, Wanted, DEFAULT_MAX_SETTINGS,
};
use crate::proto::receiver::RawMessage;
use crate::stats::Counters;
use crate::sync::lock;
use crate::wire::setting::{name_of_any_confirmation, REQUEST_SUFFIX};

/// How often a setting without an answer is poked, and how many times.
const POKE_PERIOD: Duration = Duration::from_millis(200);
const QUICK_POKES: u32 = 10;
/// How often a setting that answered none of those is poked after.
const SLOW_POKE_PERIOD: Duration = Duration::from_secs(2);
/// Request channels one client publishes on at most: each stays in the
/// node's channel table (its sequence numbers must go on), so a fleet
/// announcing ever new settings must not grow it without end.
const MAX_REQUEST_CHANNELS: usize = 2 * DEFAULT_MAX_SETTINGS;
/// How soon a request without an answer is first sent again (as
/// puliconf), doubling up to [`MAX_RESEND_PERIOD`].
const RESEND_PERIOD: Duration = Duration::from_millis(100);
const MAX_RESEND_PERIOD: Duration = Duration::from_secs(1);
/// How often discovery is read again while waiting.
const TICK: Duration = Duration::from_millis(50);

/// What the confirmations' handlers share with the driver.
struct Heard {
    catalog: Mutex<Catalog>,
    heard: Notify,
    /// Whether a confirmation nobody answers for was logged.
    unowned_logged: AtomicBool,
}

/// One confirmation channel followed: a quiet-less subscription (the
/// owner must see a subscriber to its confirmations, as 2.x `puliconf`
/// is one) that ends when dropped.
struct Followed {
    inner: Arc<Inner>,
    channel: Arc<ChannelState>,
    handler: Arc<Handler>,
    id: u64,
}

impl Drop for Followed {
    fn drop(&mut self) {
        // Before the receiver lets go of it: a confirmation already in an
        // outbox must not reach the catalog of a setting no longer followed.
        self.handler.end();
        self.inner.unsubscribe(&self.channel, self.id, false);
    }
}

/// A settings client of one node.
pub(crate) struct SettingsDriver {
    inner: Arc<Inner>,
    shared: Arc<Heard>,
    followed: Mutex<HashMap<String, Followed>>,
    /// Per confirmation channel: when it was last poked, how many times.
    pokes: Mutex<HashMap<String, (Instant, u32)>>,
    /// Request channels this client has published on.
    requested: Mutex<HashSet<String>>,
    full_logged: AtomicBool,
    requests_full_logged: AtomicBool,
}

impl SettingsDriver {
    pub(crate) fn new(inner: Arc<Inner>) -> Self {
        Self {
            inner,
            shared: Arc::new(Heard {
                catalog: Mutex::new(Catalog::default()),
                heard: Notify::new(),
                unowned_logged: AtomicBool::new(false),
            }),
            followed: Mutex::new(HashMap::new()),
            pokes: Mutex::new(HashMap::new()),
            requested: Mutex::new(HashSet::new()),
            full_logged: AtomicBool::new(false),
            requests_full_logged: AtomicBool::new(false),
        }
    }

    /// Reads discovery again: follows the confirmations of settings found
    /// since, drops those of settings gone, and pokes settings still
    /// without an answer (ten times 200 ms apart, then every 2 s). Returns
    /// how many settings were found for the first time.
    pub(crate) fn refresh(&self) -> usize {
        // Settings' channels only (confirmations and their requests): a
        // stranger's thousands of other names cost a refresh nothing.
        let settings = |c: &str| {
            let confirmation = c.strip_suffix(REQUEST_SUFFIX).unwrap_or(c);
            name_of_any_confirmation(confirmation).is_some()
        };
        let members = self.inner.fleet_members_on(&settings);
        let (found, left_out, tracked, unanswered) = {
            let mut catalog = lock(&self.shared.catalog);
            let found = catalog.update(members.iter().map(|m| Member {
                key: m.key,
                node: &m.name,
                live: m.is_live(),
                channels: &m.channels,
                address: m.address,
                data_address: m.data_address,
            }));
            let tracked: HashSet<String> = catalog.channels().map(str::to_string).collect();
            (found, catalog.left_out(), tracked, catalog.unanswered())
        };
        if left_out > 0 && !self.full_logged.swap(true, Ordering::Relaxed) {
            tracing::warn!(
                left_out,
                "the fleet announces more settings than a client follows ({DEFAULT_MAX_SETTINGS}); \
                 some are not listed"
            );
        }
        {
            let mut followed = lock(&self.followed);
            followed.retain(|channel, _| tracked.contains(channel));
            lock(&self.pokes).retain(|channel, _| tracked.contains(channel));
            for channel in &found {
                match self.follow(channel) {
                    Ok(f) => {
                        followed.insert(channel.clone(), f);
                    }
                    Err(e) => tracing::warn!(channel, "can't follow a setting: {e}"),
                }
            }
        }
        let now = Instant::now();
        for (channel, request) in unanswered {
            let due = {
                let mut pokes = lock(&self.pokes);
                let (last, count) = pokes.entry(channel.clone()).or_insert((now, 0));
                let period = if *count < QUICK_POKES {
                    POKE_PERIOD
                } else {
                    SLOW_POKE_PERIOD
                };
                let due = *count == 0 || now.duration_since(*last) >= period;
                if due {
                    *last = now;
                    *count = count.saturating_add(1);
                }
                due
            };
            if due {
                let poke = lock(&self.shared.catalog).poke(&channel, now);
                self.send(&request, &poke);
            }
        }
        found.len()
    }

    /// Subscribes confirmation channel `channel` (a name discovery
    /// announced: checked like any name a user gives).
    fn follow(&self, channel: &str) -> Result<Followed> {
        let channel = self
            .inner
            .channel_state(&crate::name::resolve_name(channel, "")?);
        let shared = Arc::clone(&self.shared);
        let name = Arc::clone(channel.name());
        let handler = Arc::new(Handler::new(move |m: RawMessage, counters: &Counters| {
            let (heard, unowned) = {
                let mut catalog = lock(&shared.catalog);
                let before = catalog.unowned();
                let heard = catalog
                    .hear(&name, &m.payload, m.source, Instant::now())
                    .map(|s| s.is_some());
                (heard, catalog.unowned() > before)
            };
            if unowned && !shared.unowned_logged.swap(true, Ordering::Relaxed) {
                tracing::warn!(
                    channel = %name,
                    source = %m.source,
                    "a confirmation from where no owner of the setting sends was not taken \
                     (a stranger's, or a claim not announced yet); logged once"
                );
            }
            match heard {
                Ok(true) => {
                    shared.heard.notify_waiters();
                    true
                }
                Ok(false) => true,
                Err(e) => {
                    counters.drop_decode(&e, Some(&name), m.source);
                    false
                }
            }
        }));
        let id =
            self.inner
                .subscribe_handler(&channel, false, None, Arc::clone(&handler), false)?;
        Ok(Followed {
            inner: Arc::clone(&self.inner),
            channel,
            handler,
            id,
        })
    }

    /// Sends `payload` on request channel `request`; false if this client
    /// has published on too many request channels to take another.
    fn send(&self, request: &str, payload: &[u8]) -> bool {
        {
            let mut used = lock(&self.requested);
            if !used.contains(request) {
                if used.len() >= MAX_REQUEST_CHANNELS {
                    if !self.requests_full_logged.swap(true, Ordering::Relaxed) {
                        tracing::warn!(
                            "this client has asked {MAX_REQUEST_CHANNELS} settings; make a new \
                             FleetSettings to ask others"
                        );
                    }
                    return false;
                }
                used.insert(request.to_string());
            }
        }
        let sent = crate::name::resolve_name(request, "").and_then(|name| {
            let channel = self.inner.channel_state(&name);
            self.inner.publish_payload(&channel, payload)
        });
        if let Err(e) = sent {
            tracing::debug!(request, "request not sent: {e}");
        }
        true
    }

    /// Whether this client has asked as many settings as one client may.
    pub(crate) fn is_spent(&self) -> bool {
        lock(&self.requested).len() >= MAX_REQUEST_CHANNELS
    }

    /// The settings known now, by name.
    pub(crate) fn snapshot(&self) -> Vec<SettingInfo> {
        lock(&self.shared.catalog).settings()
    }

    /// Waits until no new setting has appeared for `quiet` and every
    /// setting found has answered a poke or been poked ten times.
    pub(crate) async fn list(&self, quiet: Duration) -> Vec<SettingInfo> {
        let mut calm_since = Instant::now();
        loop {
            if self.refresh() > 0 {
                calm_since = Instant::now();
            }
            let unanswered = lock(&self.shared.catalog).unanswered();
            let pending = unanswered.iter().any(|(channel, _)| {
                lock(&self.pokes)
                    .get(channel)
                    .is_none_or(|(_, n)| *n < QUICK_POKES)
            });
            if calm_since.elapsed() >= quiet && !pending {
                return self.snapshot();
            }
            self.pause().await;
        }
    }

    /// Waits for a confirmation or a tick.
    async fn pause(&self) {
        let heard = self.shared.heard.notified();
        let _ = tokio::time::timeout(TICK, heard).await;
    }

    /// The setting `name` as confirmed by its owner, waiting up to
    /// `deadline` for discovery to find it and the owner to answer.
    pub(crate) async fn confirmed(&self, name: &str, deadline: Instant) -> Result<SettingInfo> {
        let name = setting_name(name)?;
        let name = name.as_str();
        loop {
            self.refresh();
            let known = lock(&self.shared.catalog).get(name).cloned();
            if let Some(s) = &known {
                // A stale value is no answer: its owner may come back.
                if s.confirmed.is_some() && !s.is_stale() {
                    return Ok(s.clone());
                }
            }
            if known.is_none() && self.owned_here(name) {
                return Err(unavailable(
                    name,
                    "this node owns it, and a node's fleet settings list only other nodes' \
                     settings: change it through its Setting"
                        .to_string(),
                ));
            }
            if Instant::now() >= deadline {
                let reason = match known {
                    None => "no node owns it (or none was found in time)".to_string(),
                    Some(s) if s.is_stale() => "its owner is gone".to_string(),
                    Some(_) => "its owner did not answer".to_string(),
                };
                return Err(unavailable(name, reason));
            }
            self.pause().await;
        }
    }

    /// Whether this node itself owns setting `name` (it publishes the
    /// setting's confirmation channel).
    fn owned_here(&self, name: &str) -> bool {
        self.inner
            .local_view()
            .channels
            .iter()
            .any(|c| c.publishes && name_of_any_confirmation(&c.name).as_deref() == Some(name))
    }

    /// Asks the owner of `name` for `wanted` and waits up to `timeout` for
    /// its confirmation, sending the request again (less and less often)
    /// until it comes.
    pub(crate) async fn request(
        &self,
        name: &str,
        wanted: Wanted,
        timeout: Duration,
    ) -> Result<SettingInfo> {
        let deadline = Instant::now() + timeout;
        let name = setting_name(name)?;
        let name = name.as_str();
        // A lock needs every claimant known: 2.x ones are listed only once
        // this node had a fair chance to hear them.
        while self.inner.age() < self.inner.fair_chance() && Instant::now() < deadline {
            self.pause().await;
        }
        let setting = self.confirmed(name, deadline).await?;
        if setting.is_locked() {
            let owners: Vec<&str> = setting.owners.iter().map(|o| o.node.as_str()).collect();
            return Err(unavailable(
                name,
                format!("locked: owned by {}", owners.join(" and ")),
            ));
        }
        let (payload, target) = catalog::request_for(&setting, &wanted).map_err(|e| match e {
            Unaskable::NotOfType(r) => refused(name, r),
            Unaskable::Unwritable(r) => unavailable(name, r),
        })?;
        let sent_at = setting.heard;
        let mut next_send = Instant::now();
        let mut resend = RESEND_PERIOD;
        loop {
            if Instant::now() >= next_send {
                // Sent again until answered (a request may be lost), less
                // and less often; asking again for the same is harmless.
                if !self.send(&setting.request_channel(), &payload) {
                    return Err(unavailable(
                        name,
                        "this client asks too many settings".into(),
                    ));
                }
                next_send = Instant::now() + resend;
                resend = (resend * 2).min(MAX_RESEND_PERIOD);
            }
            let now = lock(&self.shared.catalog).get(name).cloned();
            let Some(now) = now else {
                return Err(unavailable(name, "no node owns it any more".into()));
            };
            match catalog::judge(&now, &target, sent_at) {
                Verdict::Granted => return Ok(now),
                Verdict::Refused(why) => return Err(refused(name, why)),
                Verdict::Waiting => {}
            }
            if Instant::now() >= deadline {
                // Confirmations came, none showing what was asked: the
                // owner kept another value without saying why.
                return Err(match now.heard > sent_at {
                    true => refused(name, catalog::kept(&now)),
                    false => unavailable(
                        name,
                        format!("no confirmation from its owner within {timeout:?}"),
                    ),
                });
            }
            self.pause().await;
        }
    }
}

/// `name` as the catalog names settings (`rover1//max_speed` and
/// `/rover1/max_speed` are `rover1/max_speed`); a name no setting can
/// have fails at once rather than after the wait.
fn setting_name(name: &str) -> Result<String> {
    crate::name::resolve_name(name, "")
}

fn unavailable(name: &str, reason: String) -> Error {
    Error::SettingUnavailable {
        name: name.trim_start_matches('/').to_string(),
        reason,
    }
}

fn refused(name: &str, reason: String) -> Error {
    Error::SettingRefused {
        name: name.trim_start_matches('/').to_string(),
        reason,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_client_that_asked_its_share_of_settings_says_it_is_spent() {
        let node = crate::Node::new("spent")
            .port(crate::unused_port().unwrap())
            .interface(std::net::Ipv4Addr::LOCALHOST)
            // Nothing but this client's requests: it is all that is tested.
            .discovery(false)
            .compat_heartbeat(false)
            .keys_from_env(false)
            .start_blocking()
            .unwrap();
        let settings = SettingsDriver::new(Arc::clone(node.inner()));
        for i in 0..MAX_REQUEST_CHANNELS - 1 {
            lock(&settings.requested).insert(format!("ask/{i}"));
        }
        assert!(!settings.is_spent());
        // The last request channel it may use: still sent.
        assert!(settings.send("ask/last", b"poke"));
        assert!(settings.is_spent());
        // A new one is refused; one already used is not.
        assert!(!settings.send("ask/another", b"poke"));
        assert!(settings.send("ask/7", b"poke"));
        node.stop();
    }
}

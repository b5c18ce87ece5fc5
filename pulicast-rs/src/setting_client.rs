//! The client side of distributed settings: any node lists the fleet's
//! settings, reads them and asks their owners for changes. The bookkeeping
//! is the sans-IO [`Catalog`]; this adds subscriptions, pokes and time.

use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use tokio::sync::Notify;

use crate::channel::Namespace;
use crate::error::{Error, Result};
use crate::proto::catalog::{
    self, Catalog, Member, SettingInfo, Unaskable, Verdict, Wanted, DEFAULT_MAX_SETTINGS,
};
use crate::subscription::{CallbackSubscription, Message};
use crate::sync::lock;
use crate::wire::zcm::Primitive;

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

struct State {
    catalog: Mutex<Catalog>,
    heard: Notify,
    /// Whether a confirmation nobody answers for was logged.
    unowned_logged: AtomicBool,
}

/// What this node sees of the fleet's settings, and how it changes them:
/// made by [`crate::Node::fleet_settings`]. Settings are named as in the
/// fleet (`rover1/max_speed`); those this node owns itself are not listed
/// (it holds their [`crate::Setting`]).
///
/// Every method waits on discovery and on the owners' answers, so all are
/// async; each ends by its deadline. Bad input (a confirmation that is no
/// `roc_ack`, a huge one) is dropped and logged, and changes nothing.
///
/// ```no_run
/// # async fn f(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::Primitive;
/// use std::time::Duration;
/// let settings = node.fleet_settings();
/// for s in settings.list(Duration::from_secs(2)).await {
///     println!("{} = {:?} ({:?})", s.name, s.value_text(), s.about);
/// }
/// let wait = Duration::from_secs(3);
/// settings.set("rover1/max_speed", Primitive::Double(1.0), wait).await?;
/// settings.set_text("rover1/mode", "manual", wait).await?;
/// settings.reset("rover1/max_speed", wait).await?;
/// # Ok(()) }
/// ```
pub struct FleetSettings {
    root: Namespace,
    state: Arc<State>,
    subscriptions: Mutex<HashMap<String, CallbackSubscription>>,
    /// Per confirmation channel: when it was last poked, how many times.
    pokes: Mutex<HashMap<String, (Instant, u32)>>,
    /// Request channels this client has published on.
    requested: Mutex<HashSet<String>>,
    full_logged: AtomicBool,
    requests_full_logged: AtomicBool,
}

impl std::fmt::Debug for FleetSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FleetSettings").finish_non_exhaustive()
    }
}

impl FleetSettings {
    pub(crate) fn new(root: Namespace) -> Self {
        Self {
            root,
            state: Arc::new(State {
                catalog: Mutex::new(Catalog::default()),
                heard: Notify::new(),
                unowned_logged: AtomicBool::new(false),
            }),
            subscriptions: Mutex::new(HashMap::new()),
            pokes: Mutex::new(HashMap::new()),
            requested: Mutex::new(HashSet::new()),
            full_logged: AtomicBool::new(false),
            requests_full_logged: AtomicBool::new(false),
        }
    }

    /// Reads discovery again: subscribes the confirmations of settings
    /// found since, drops those of settings gone, and pokes settings still
    /// without an answer (ten times 200 ms apart, then every 2 s). Returns
    /// how many settings were found for the first time.
    ///
    /// The waiting methods call it as they go; call it to keep
    /// [`FleetSettings::snapshot`] current.
    pub fn refresh(&self) -> usize {
        // Settings' channels only (confirmations and their requests): a
        // stranger's thousands of other names cost a refresh nothing.
        let settings = |c: &str| {
            let confirmation = c
                .strip_suffix(crate::wire::setting::REQUEST_SUFFIX)
                .unwrap_or(c);
            crate::wire::setting::name_of_any_confirmation(confirmation).is_some()
        };
        let members = self.root.inner().fleet_members_on(&settings);
        let (found, left_out, tracked, unanswered) = {
            let mut catalog = lock(&self.state.catalog);
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
            let mut subs = lock(&self.subscriptions);
            subs.retain(|channel, _| tracked.contains(channel));
            lock(&self.pokes).retain(|channel, _| tracked.contains(channel));
            for channel in &found {
                match self.subscribe(channel) {
                    Ok(sub) => {
                        subs.insert(channel.clone(), sub);
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
                let poke = lock(&self.state.catalog).poke(&channel, now);
                self.send(&request, &poke);
            }
        }
        found.len()
    }

    fn subscribe(&self, channel: &str) -> Result<CallbackSubscription> {
        let state = Arc::clone(&self.state);
        let inner = Arc::clone(self.root.inner());
        let name = channel.to_string();
        self.root
            .try_channel(channel)?
            .subscribe_raw_with(move |m: Message<Bytes>| {
                let (heard, unowned) = {
                    let mut catalog = lock(&state.catalog);
                    let before = catalog.unowned();
                    let heard = catalog
                        .hear(&name, &m.value, m.source, Instant::now())
                        .map(|s| s.is_some());
                    (heard, catalog.unowned() > before)
                };
                if unowned && !state.unowned_logged.swap(true, Ordering::Relaxed) {
                    tracing::warn!(
                        channel = %name,
                        source = %m.source,
                        "a confirmation from where no owner of the setting sends was not taken \
                         (a stranger's, or a claim not announced yet); logged once"
                    );
                }
                match heard {
                    Ok(true) => state.heard.notify_waiters(),
                    Ok(false) => {}
                    Err(e) => inner.counters().drop_decode(&e, Some(&name), m.source),
                }
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
        let sent = self
            .root
            .try_channel(request)
            .and_then(|c| c.publish_bytes(payload));
        if let Err(e) = sent {
            tracing::debug!(request, "request not sent: {e}");
        }
        true
    }

    /// Whether this client has asked as many settings as one client may
    /// (twice the settings it follows at once): settings found since are
    /// listed but never asked, so their values stay unknown and changing
    /// them times out. A fleet whose settings come and go under ever new
    /// names spends a long-lived client. The bound is what keeps the
    /// node's channel table bounded (each request channel stays in it),
    /// so a new client on the same node would grow the table again: tell
    /// the user, as `puli shell` does, or start a new node.
    pub fn is_spent(&self) -> bool {
        lock(&self.requested).len() >= MAX_REQUEST_CHANNELS
    }

    /// The settings known now, by name, without waiting.
    pub fn snapshot(&self) -> Vec<SettingInfo> {
        lock(&self.state.catalog).settings()
    }

    /// Waits until no new setting has appeared for `quiet` and every
    /// setting found has answered a poke or been poked ten times, then
    /// returns them all. 2.x `puliconf` waits 2 s the same way. A fleet
    /// whose settings keep appearing keeps it waiting: bound it with a
    /// timeout (`tokio::time::timeout`), as `puli config` does.
    pub async fn list(&self, quiet: Duration) -> Vec<SettingInfo> {
        let mut calm_since = Instant::now();
        loop {
            if self.refresh() > 0 {
                calm_since = Instant::now();
            }
            let unanswered = lock(&self.state.catalog).unanswered();
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
        let heard = self.state.heard.notified();
        let _ = tokio::time::timeout(TICK, heard).await;
    }

    /// The setting `name` as confirmed by its owner, waiting up to
    /// `timeout` for discovery to find it and the owner to answer.
    pub async fn get(&self, name: &str, timeout: Duration) -> Result<SettingInfo> {
        let deadline = Instant::now() + timeout;
        self.confirmed(name, deadline).await
    }

    async fn confirmed(&self, name: &str, deadline: Instant) -> Result<SettingInfo> {
        let name = setting_name(name)?;
        let name = name.as_str();
        loop {
            self.refresh();
            let known = lock(&self.state.catalog).get(name).cloned();
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
        self.root.inner().local_view().channels.iter().any(|c| {
            c.publishes
                && crate::wire::setting::name_of_any_confirmation(&c.name).as_deref() == Some(name)
        })
    }

    /// Asks the owner of `name` to take `value` (converted to the
    /// setting's type where nothing is lost: an integer to a float or a
    /// smaller integer that holds it), and waits up to `timeout` for its
    /// confirmation. Returns the setting as confirmed; the owner's refusal
    /// is [`Error::SettingRefused`] with its reason.
    pub async fn set(
        &self,
        name: &str,
        value: Primitive,
        timeout: Duration,
    ) -> Result<SettingInfo> {
        self.request(name, Wanted::Value(value), timeout).await
    }

    /// Like [`FleetSettings::set`], with the value as a person types it,
    /// read as the setting's type (`1.5`, `true`, `manual`).
    pub async fn set_text(&self, name: &str, text: &str, timeout: Duration) -> Result<SettingInfo> {
        self.request(name, Wanted::Text(text.to_string()), timeout)
            .await
    }

    /// Like [`FleetSettings::set`], with a JSON value: a native setting's
    /// (our extension; encoded from the type its owner announces), or a
    /// primitive one's.
    pub async fn set_json(
        &self,
        name: &str,
        value: serde_json::Value,
        timeout: Duration,
    ) -> Result<SettingInfo> {
        self.request(name, Wanted::Json(value), timeout).await
    }

    /// Asks the owner of `name` to unset it (no value).
    pub async fn unset(&self, name: &str, timeout: Duration) -> Result<SettingInfo> {
        self.request(name, Wanted::Unset, timeout).await
    }

    /// Asks the owner of `name` to go back to its default.
    pub async fn reset(&self, name: &str, timeout: Duration) -> Result<SettingInfo> {
        self.request(name, Wanted::Reset, timeout).await
    }

    async fn request(&self, name: &str, wanted: Wanted, timeout: Duration) -> Result<SettingInfo> {
        let deadline = Instant::now() + timeout;
        let name = setting_name(name)?;
        let name = name.as_str();
        // A lock needs every claimant known: 2.x ones are listed only once
        // this node had a fair chance to hear them.
        let inner = Arc::clone(self.root.inner());
        while inner.age() < inner.fair_chance() && Instant::now() < deadline {
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
            let now = lock(&self.state.catalog).get(name).cloned();
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
        let settings = node.fleet_settings();
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

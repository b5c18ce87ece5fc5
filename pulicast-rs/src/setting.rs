//! Distributed settings owned by this node: values that any tool in the
//! fleet can read and change at run time, checked by their owner, on the
//! Pulicast 2.x puliconf wire (see [`crate::wire::setting`]).

use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use crate::channel::{Channel, Namespace};
use crate::error::{Error, Result};
use crate::proto::catalog::{Catalog, Member};
use crate::proto::setting::{Check, Owner, Pacer, SettingValue};
use crate::runtime::Inner;
use crate::subscription::{CallbackSubscription, Message};
use crate::sync::lock;
use crate::wire::setting as wire;
use crate::wire::setting::Request;
use bytes::Bytes;

/// What is told of a change: the new value (`None` once unset).
type Watcher<T> = Box<dyn FnMut(Option<&T>) + Send>;

/// The confirmations of requests that changed nothing, paced (see
/// [`Pacer`]); locked only under the owner's lock.
struct Pacing {
    pacer: Pacer,
    /// The confirmation waiting for the bucket: the latest, answering
    /// every request heard since the last one sent.
    pending: Option<Vec<u8>>,
    /// Whether a task is waiting to send `pending`.
    scheduled: bool,
    /// Confirmations folded into a later one, for the log.
    coalesced: u64,
}

/// Who else claims this setting, judged as a client's catalog judges it
/// (see [`crate::proto::catalog`]): while another live owner answered for
/// it, the owner refuses every change, as the tools refuse to ask.
struct Rivals {
    inner: Weak<Inner>,
    /// Only this setting's channels, from discovery and from the
    /// confirmations other owners send.
    catalog: Catalog,
    /// When discovery was last read (at most every [`RIVALS_EVERY`]).
    checked: Option<Instant>,
    /// This node's key: it claims the setting too, so that the catalog
    /// keeps it and a rival's early confirmation waits for its claim.
    own: i64,
}

/// How often an owner reads discovery for rivals, at most (on requests).
const RIVALS_EVERY: Duration = Duration::from_millis(250);

impl Rivals {
    /// The live owners other than this node that answered for `name`
    /// (its confirmation channel `channel`), with discovery read again if
    /// it is older than [`RIVALS_EVERY`].
    fn answered(&mut self, name: &str, channel: &str, now: Instant) -> Vec<String> {
        self.refresh(channel, now);
        self.catalog
            .get(name)
            .map(|s| {
                s.owners
                    .iter()
                    .filter(|o| o.key != self.own && o.live && o.answered)
                    .map(|o| o.node.clone())
                    .collect()
            })
            .unwrap_or_default()
    }

    /// Reads discovery again if it is older than [`RIVALS_EVERY`].
    fn refresh(&mut self, channel: &str, now: Instant) {
        let due = self
            .checked
            .is_none_or(|at| now.saturating_duration_since(at) >= RIVALS_EVERY);
        if due {
            self.checked = Some(now);
            if let Some(inner) = self.inner.upgrade() {
                let request = format!("{channel}{}", crate::wire::setting::REQUEST_SUFFIX);
                let mut members = inner.fleet_members_on(&|c| c == channel || c == request);
                members.push(inner.local_view());
                let claims: Vec<_> = members
                    .iter()
                    .map(|m| {
                        let ours = m
                            .channels
                            .iter()
                            .filter(|c| c.name == channel || c.name == request)
                            .cloned()
                            .collect::<Vec<_>>();
                        (m, ours)
                    })
                    .filter(|(_, ours)| !ours.is_empty())
                    .collect();
                self.catalog.update(claims.iter().map(|(m, ours)| Member {
                    key: m.key,
                    node: &m.name,
                    live: m.is_live(),
                    channels: ours,
                    address: m.address,
                    data_address: m.data_address,
                }));
            }
        }
    }
}

struct Shared<T> {
    owner: Mutex<Owner<T>>,
    pacing: Mutex<Pacing>,
    rivals: Mutex<Rivals>,
    confirmations: Channel,
    watchers: Mutex<Vec<Watcher<T>>>,
    /// The latest value, for [`Setting::get`] (read without the owner's lock) and [`Setting::changes`].
    latest: tokio::sync::watch::Sender<Option<T>>,
    name: String,
}

impl<T: SettingValue> Shared<T> {
    /// Sends the confirmation of the current value.
    fn confirm(&self, owner: &Owner<T>, message: &str) -> Result<()> {
        let mut out = Vec::new();
        owner.confirmation(message, &mut out);
        // It carries the current value: one waiting would carry an older.
        lock(&self.pacing).pending = None;
        self.confirmations.publish_bytes(&out)
    }

    /// Handles one request heard (under the owner's lock, so that
    /// confirmations leave in the order of the changes): a change is
    /// confirmed at once; any other answer is paced, and one that must
    /// wait replaces the one waiting.
    fn answer(self: &Arc<Self>, owner: &mut Owner<T>, request: &[u8]) -> bool {
        let now = Instant::now();
        let mut out = Vec::new();
        let poke = matches!(Request::decode(request), Ok(Request::Poke));
        let rivals = match poke {
            true => Vec::new(),
            false => lock(&self.rivals).answered(&self.name, self.confirmations.name(), now),
        };
        let changed = if rivals.is_empty() {
            let changed = owner.handle(request, &mut out);
            if changed {
                // Before the confirmation leaves: whoever hears it reads
                // the new value with `get`.
                self.latest.send_replace(owner.value().cloned());
            }
            changed
        } else {
            let why = format!("locked: also owned by {}", rivals.join(" and "));
            owner.confirmation(&why, &mut out);
            false
        };
        let mut pacing = lock(&self.pacing);
        pacing.pacer.heard(now, request.len());
        if changed || (pacing.pending.is_none() && pacing.pacer.take(now, out.len())) {
            pacing.pending = None;
            drop(pacing);
            self.publish(&out);
            return changed;
        }
        if pacing.pending.replace(out).is_some() {
            pacing.coalesced += 1;
            if pacing.coalesced.is_power_of_two() {
                tracing::warn!(
                    setting = %self.name,
                    coalesced = pacing.coalesced,
                    "requests that change nothing come faster than their confirmations may \
                     go (a flood?): confirmations are folded into one"
                );
            }
        }
        if !pacing.scheduled {
            let Ok(runtime) = tokio::runtime::Handle::try_current() else {
                return changed;
            };
            pacing.scheduled = true;
            let len = pacing.pending.as_ref().map_or(0, Vec::len);
            let wait = pacing.pacer.wait(now, len);
            runtime.spawn(send_pending(Arc::downgrade(self), wait));
        }
        changed
    }

    fn publish(&self, confirmation: &[u8]) {
        if let Err(e) = self.confirmations.publish_bytes(confirmation) {
            tracing::debug!(setting = %self.name, "confirmation not sent: {e}");
        }
    }

    /// Tells the watchers; called after the owner's lock is let go (a
    /// watcher may read the setting), with `latest` already set under it.
    fn changed(&self, value: Option<&T>) {
        // Called with the list unlocked, so a watcher may add another.
        let mut watchers = std::mem::take(&mut *lock(&self.watchers));
        for watcher in &mut watchers {
            watcher(value);
        }
        let mut kept = lock(&self.watchers);
        let added = std::mem::replace(&mut *kept, watchers);
        kept.extend(added);
    }
}

/// Sends the confirmation waiting in `shared`'s pacing once the bucket
/// holds it, after `wait` at first; ends with the setting.
async fn send_pending<T: SettingValue>(shared: Weak<Shared<T>>, mut wait: std::time::Duration) {
    loop {
        tokio::time::sleep(wait).await;
        let Some(shared) = shared.upgrade() else {
            return;
        };
        // The owner's lock first, as everywhere: a change meanwhile sent
        // the current value and dropped what waited.
        let _owner = lock(&shared.owner);
        let mut pacing = lock(&shared.pacing);
        let now = Instant::now();
        let Some(len) = pacing.pending.as_ref().map(Vec::len) else {
            pacing.scheduled = false;
            return;
        };
        if pacing.pacer.take(now, len) {
            if let Some(out) = pacing.pending.take() {
                shared.publish(&out);
            }
            pacing.scheduled = false;
            return;
        }
        wait = pacing.pacer.wait(now, len);
    }
}

/// A distributed setting this node owns: made by [`Namespace::setting`] or
/// [`Namespace::setting_checked`]; dropping it removes it from the fleet.
///
/// Tools (`puliconf` of Pulicast 2.x included) find it as the channels
/// `NS/.config/NAME` (published: confirmations) and `NS/.config/NAME.r`
/// (subscribed: requests of change), read it by poking it, and change it by
/// sending a value; every request is checked and confirmed, a refused one
/// with the reason.
///
/// ```
/// use pulicast::Check;
/// # let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("rover_controller")
///     .namespace("rover1")
///     .interface(std::net::Ipv4Addr::LOCALHOST)
/// #   .port(port)
///     .start_blocking()?;
/// let speed = node.setting_checked("max_speed", 1.5f64, vec![Check::Range(0.0, 2.0)])?;
/// assert_eq!(speed.name(), "rover1/max_speed");
/// assert_eq!(speed.get(), Some(1.5));
/// assert!(speed.set(3.0).is_err()); // the owner's own changes are checked too
/// speed.set(1.0)?;
/// assert_eq!(speed.get(), Some(1.0));
/// # Ok::<(), pulicast::Error>(())
/// ```
pub struct Setting<T> {
    shared: Arc<Shared<T>>,
    _requests: CallbackSubscription,
    /// Other owners' confirmations, for [`Rivals`].
    _rivals: CallbackSubscription,
}

impl<T> std::fmt::Debug for Setting<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Setting")
            .field("name", &self.shared.name)
            .finish()
    }
}

impl<T: SettingValue> Setting<T> {
    fn new(ns: &Namespace, name: &str, default: T, checks: Vec<Check<T>>) -> Result<Self> {
        SettingBuilder {
            ns: ns.clone(),
            name: name.to_string(),
            default,
            checks,
            description: String::new(),
            unit: String::new(),
        }
        .build()
    }

    fn build(b: SettingBuilder<T>) -> Result<Self> {
        let SettingBuilder {
            ns,
            name,
            default,
            checks,
            description,
            unit,
        } = b;
        let ns = &ns;
        let name = name.as_str();
        let confirmation = wire::confirmation_channel_in(T::part(), ns.path(), name);
        // Checked as any channel name (and so the setting's name with it).
        let root = ns.make_namespace("/");
        let confirmations = root.try_channel(&confirmation)?;
        let requests = root.try_channel(&(confirmation.clone() + wire::REQUEST_SUFFIX))?;
        if let Some(ty) = T::type_info() {
            // Tools read and write a native value from its announced type.
            requests.declare_type(ty)?;
        }
        let full_name = wire::name_of_any_confirmation(confirmations.name()).ok_or_else(|| {
            Error::InvalidName {
                name: name.to_string(),
                reason: crate::NameError::Reserved,
            }
        })?;
        let mut owner = Owner::new(default, checks).map_err(|reason| Error::SettingRefused {
            name: full_name.clone(),
            reason,
        })?;
        owner.describe(&description, &unit);
        if let Some((value, file)) = ns.inner().start_value(&full_name) {
            let started = value.as_ref().map_err(String::clone).and_then(|value| {
                owner
                    .start_from(value)
                    .map_err(|reason| format!("start-up value {value}: {reason}"))
            });
            started.map_err(|reason| Error::SettingRefused {
                name: full_name.clone(),
                reason: format!("{file}: {reason}"),
            })?;
        }
        let (latest, _) = tokio::sync::watch::channel(owner.value().cloned());
        let shared = Arc::new(Shared {
            owner: Mutex::new(owner),
            pacing: Mutex::new(Pacing {
                pacer: Pacer::new(Instant::now()),
                pending: None,
                scheduled: false,
                coalesced: 0,
            }),
            rivals: Mutex::new(Rivals {
                inner: Arc::downgrade(ns.inner()),
                catalog: Catalog::new(1),
                checked: None,
                own: ns.inner().compat_session_id(),
            }),
            confirmations,
            watchers: Mutex::new(Vec::new()),
            latest,
            name: full_name,
        });
        let handling = Arc::clone(&shared);
        let requests = requests.subscribe_raw_with(move |m: Message<Bytes>| {
            let mut owner = lock(&handling.owner);
            // Sent and recorded under the lock, so confirmations leave in
            // the order of the changes, whoever makes them.
            let changed = handling.answer(&mut owner, &m.value);
            let value = owner.value().cloned();
            drop(owner);
            if changed {
                handling.changed(value.as_ref());
            }
        })?;
        {
            // Made: the first confirmation, which is how tools find it.
            let owner = lock(&shared.owner);
            shared.confirm(&owner, &owner.about())?;
        }
        let hearing = Arc::clone(&shared);
        let rivals = shared
            .confirmations
            .watch_raw_with(move |m: Message<Bytes>| {
                let mut rivals = lock(&hearing.rivals);
                let channel = hearing.confirmations.name();
                let now = Instant::now();
                rivals.refresh(channel, now);
                // Bad bytes are no rival's answer; the clients count them.
                let _ = rivals.catalog.hear(channel, &m.value, m.source, now);
            })?;
        Ok(Self {
            shared,
            _requests: requests,
            _rivals: rivals,
        })
    }

    /// The fleet-wide name (`rover1/max_speed`).
    pub fn name(&self) -> &str {
        &self.shared.name
    }

    /// What tools are told it is: description, unit and checks, as
    /// [`SettingInfo::about`](crate::SettingInfo::about) shows it to them.
    pub fn about(&self) -> String {
        lock(&self.shared.owner).about()
    }

    /// The value; `None` if a tool unset it. Read without the setting's
    /// lock (from the last change told), so a check may read the setting
    /// it checks: it sees the value before the change.
    pub fn get(&self) -> Option<T> {
        self.shared.latest.borrow().clone()
    }

    /// Sets the value from the owner's side: checked (read-only aside),
    /// confirmed to the fleet; true if it changed.
    pub fn set(&self, value: T) -> Result<bool> {
        let mut owner = lock(&self.shared.owner);
        let changed = owner.set(value).map_err(|reason| Error::SettingRefused {
            name: self.shared.name.clone(),
            reason,
        })?;
        if changed {
            let value = owner.value().cloned();
            self.shared.latest.send_replace(value.clone());
            self.shared.confirm(&owner, "")?;
            drop(owner);
            self.shared.changed(value.as_ref());
        }
        Ok(changed)
    }

    /// The setting's changes, to await in async code: each
    /// [`SettingChanges::changed`] returns the value after the next change
    /// (the latest, if several came meanwhile).
    pub fn changes(&self) -> SettingChanges<T> {
        let mut rx = self.shared.latest.subscribe();
        rx.mark_unchanged();
        SettingChanges(rx)
    }

    /// Calls `watcher` with the new value after each change (by a tool or
    /// by [`Setting::set`]), on the thread that made it: keep it short, as
    /// a subscription's handler.
    pub fn on_change(&self, watcher: impl FnMut(Option<&T>) + Send + 'static) {
        lock(&self.shared.watchers).push(Box::new(watcher));
    }
}

/// The changes of one [`Setting`], from [`Setting::changes`].
///
/// ```
/// # #[tokio::main(flavor = "current_thread")]
/// # async fn main() -> pulicast::Result<()> {
/// # let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("rover_controller")
///     .interface(std::net::Ipv4Addr::LOCALHOST)
/// #   .port(port)
///     .start()
///     .await?;
/// let speed = node.setting("max_speed", 1.5f64)?;
/// let mut changes = speed.changes(); // from now on
/// speed.set(1.0)?; // a tool's request is seen the same way
/// assert_eq!(changes.changed().await, Some(Some(1.0)));
/// // In a task of its own: `while let Some(value) = changes.changed().await { ... }`,
/// // which ends once the setting is dropped.
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub struct SettingChanges<T>(tokio::sync::watch::Receiver<Option<T>>);

impl<T: Clone> SettingChanges<T> {
    /// Waits for the next change and returns the value after it (`None`
    /// inside: unset); `None` once the setting is gone.
    pub async fn changed(&mut self) -> Option<Option<T>> {
        self.0.changed().await.ok()?;
        Some(self.0.borrow_and_update().clone())
    }
}

/// A setting being declared, with more than a default and checks: made by
/// [`Namespace::setting_builder`], finished by [`SettingBuilder::build`].
///
/// ```
/// use pulicast::Check;
/// # let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("rover_controller")
///     .namespace("rover1")
///     .interface(std::net::Ipv4Addr::LOCALHOST)
/// #   .port(port)
///     .start_blocking()?;
/// let speed = node
///     .setting_builder("max_speed", 1.5f64)
///     .describe("top speed of the base")
///     .unit("m/s")
///     .check(Check::Range(0.0, 2.0))
///     .build()?;
/// assert_eq!(speed.about(), "top speed of the base; unit: m/s; must be in [0, 2]");
/// # Ok::<(), pulicast::Error>(())
/// ```
#[must_use = "a setting exists once built"]
pub struct SettingBuilder<T> {
    ns: Namespace,
    name: String,
    default: T,
    checks: Vec<Check<T>>,
    description: String,
    unit: String,
}

impl<T> std::fmt::Debug for SettingBuilder<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SettingBuilder")
            .field("name", &self.name)
            .field("checks", &self.checks)
            .finish_non_exhaustive()
    }
}

impl<T: SettingValue> SettingBuilder<T> {
    /// Adds a check every change must pass (the default too).
    pub fn check(mut self, check: Check<T>) -> Self {
        self.checks.push(check);
        self
    }

    /// What the setting does, in a line, for tools to show.
    pub fn describe(mut self, description: impl Into<String>) -> Self {
        self.description = description.into();
        self
    }

    /// The unit of its value (`m/s`), for tools to show.
    pub fn unit(mut self, unit: impl Into<String>) -> Self {
        self.unit = unit.into();
        self
    }

    /// Makes the setting: [`Error::SettingRefused`] if its default fails
    /// its checks, [`Error::InvalidName`] for a bad name.
    pub fn build(self) -> Result<Setting<T>> {
        Setting::build(self)
    }
}

impl Namespace {
    /// Starts declaring setting `name` with `default`, to give it checks,
    /// a description and a unit (see [`SettingBuilder`]).
    pub fn setting_builder<T: SettingValue>(&self, name: &str, default: T) -> SettingBuilder<T> {
        SettingBuilder {
            ns: self.clone(),
            name: name.to_string(),
            default,
            checks: Vec::new(),
            description: String::new(),
            unit: String::new(),
        }
    }

    /// A distributed setting `name` in this namespace, owned by this node,
    /// starting at `default` (see [`Setting`]).
    pub fn setting<T: SettingValue>(&self, name: &str, default: T) -> Result<Setting<T>> {
        Setting::new(self, name, default, Vec::new())
    }

    /// Like [`Namespace::setting`], with checks every change must pass
    /// (the default too: one that fails is [`Error::SettingRefused`]).
    pub fn setting_checked<T: SettingValue>(
        &self,
        name: &str,
        default: T,
        checks: Vec<Check<T>>,
    ) -> Result<Setting<T>> {
        Setting::new(self, name, default, checks)
    }
}

//! The client side of distributed settings: any node lists the fleet's
//! settings, reads them and asks their owners for changes. The bookkeeping
//! is the sans-IO catalog; the driver in `runtime::asking` adds
//! subscriptions, pokes and time. This is the handle users hold.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::error::Result;
use crate::proto::catalog::{SettingInfo, Wanted};
use crate::runtime::asking::SettingsDriver;
use crate::runtime::Inner;
use crate::wire::zcm::Primitive;

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
    driver: SettingsDriver,
}

impl std::fmt::Debug for FleetSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FleetSettings").finish_non_exhaustive()
    }
}

impl FleetSettings {
    pub(crate) fn new(inner: Arc<Inner>) -> Self {
        Self {
            driver: SettingsDriver::new(inner),
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
        self.driver.refresh()
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
        self.driver.is_spent()
    }

    /// The settings known now, by name, without waiting.
    pub fn snapshot(&self) -> Vec<SettingInfo> {
        self.driver.snapshot()
    }

    /// Waits until no new setting has appeared for `quiet` and every
    /// setting found has answered a poke or been poked ten times, then
    /// returns them all. 2.x `puliconf` waits 2 s the same way. A fleet
    /// whose settings keep appearing keeps it waiting: bound it with a
    /// timeout (`tokio::time::timeout`), as `puli config` does.
    pub async fn list(&self, quiet: Duration) -> Vec<SettingInfo> {
        self.driver.list(quiet).await
    }

    /// The setting `name` as confirmed by its owner, waiting up to
    /// `timeout` for discovery to find it and the owner to answer.
    pub async fn get(&self, name: &str, timeout: Duration) -> Result<SettingInfo> {
        self.driver.confirmed(name, Instant::now() + timeout).await
    }

    /// Asks the owner of `name` to take `value` (converted to the
    /// setting's type where nothing is lost: an integer to a float or a
    /// smaller integer that holds it), and waits up to `timeout` for its
    /// confirmation. Returns the setting as confirmed; the owner's refusal
    /// is [`Error::SettingRefused`](crate::Error::SettingRefused) with its reason.
    pub async fn set(
        &self,
        name: &str,
        value: Primitive,
        timeout: Duration,
    ) -> Result<SettingInfo> {
        self.driver
            .request(name, Wanted::Value(value), timeout)
            .await
    }

    /// Like [`FleetSettings::set`], with the value as a person types it,
    /// read as the setting's type (`1.5`, `true`, `manual`).
    pub async fn set_text(&self, name: &str, text: &str, timeout: Duration) -> Result<SettingInfo> {
        self.driver
            .request(name, Wanted::Text(text.to_string()), timeout)
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
        self.driver
            .request(name, Wanted::Json(value), timeout)
            .await
    }

    /// Asks the owner of `name` to unset it (no value).
    pub async fn unset(&self, name: &str, timeout: Duration) -> Result<SettingInfo> {
        self.driver.request(name, Wanted::Unset, timeout).await
    }

    /// Asks the owner of `name` to go back to its default.
    pub async fn reset(&self, name: &str, timeout: Duration) -> Result<SettingInfo> {
        self.driver.request(name, Wanted::Reset, timeout).await
    }
}

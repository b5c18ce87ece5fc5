//! # pulicast: publish/subscribe for robot fleets, peer to peer
//!
//! Nodes publish and subscribe on **channels** named by hierarchical paths
//! (`rover1/left_arm/pose`) over UDP multicast. There is no broker and no name
//! server: every channel maps to a multicast group, every node announces itself
//! on `__nodes`, and nodes on one host or one link find each other by
//! themselves. The wire format is Pulicast 2.x, so pulicast nodes and the
//! Python reference implementation (`pulicast==2.0.1`) talk to each other.
//!
//! ## Concepts
//!
//! - A [`Node`] is one participant, with a name (for people) and a random
//!   session id (for machines). It owns the sockets and background tasks.
//! - A [`Namespace`] is a place in the channel hierarchy. A node *is* a
//!   namespace (its default one), and [`Namespace::ns`] and
//!   [`Namespace::make_namespace`] reach others. Components take a `&Namespace`
//!   so they can be relocated; see [`resolve_name`] for the rules.
//! - A [`Channel`] publishes typed values ([`Channel::publish`]) or bytes, and
//!   makes [`Subscription`]s that yield [`Message`]s with the value, the source
//!   address, the sequence number and the **lead** (1 = in order, > 1 = losses,
//!   <= 0 = late; see [`Lead`]).
//! - Messages: Rust primitives and strings travel as the 2.x ZCM primitive
//!   messages; other types derive `serde` and [`Schema`] and travel as postcard
//!   behind a fingerprint of their schema ([`Fingerprint`], [`type_info_of`]);
//!   [`text`] shows any of them as JSON by the type its channel announces.
//!
//! ## Quick start
//!
//! ```
//! use std::net::Ipv4Addr;
//! use serde::{Deserialize, Serialize};
//! use pulicast::{Node, Schema};
//!
//! #[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
//! struct Twist { linear: f64, angular: f64 }
//!
//! # #[tokio::main(flavor = "current_thread")]
//! # async fn main() -> pulicast::Result<()> {
//! # let port = pulicast::unused_port()?;
//! let node = Node::new("rover_controller")
//!     .namespace("rover1")
//!     .interface(Ipv4Addr::LOCALHOST) // stay on this host
//!     .port(port)
//!     .start()
//!     .await?;
//! let arm = node.ns("left_arm");
//! let mut twists = arm.channel("ctrl").subscribe::<Twist>()?; // rover1/left_arm/ctrl
//!
//! arm.channel("ctrl").publish(&Twist { linear: 0.3, angular: 0.0 })?;
//! let message = twists.recv().await.expect("node is running");
//! assert_eq!(message.value, Twist { linear: 0.3, angular: 0.0 });
//! assert_eq!(message.lead, 1);
//! # Ok(()) }
//! ```
//!
//! Programs without async code start the node with
//! [`NodeBuilder::start_blocking`] and receive with
//! [`Subscription::recv_blocking`] or [`Subscription::recv_timeout`].
//!
//! ## Bad input
//!
//! Malformed datagrams and payloads of the wrong type never reach your code
//! and never disturb other messages: they are counted per [`DropReason`] in
//! [`Node::stats`] and logged through `tracing`, at most once a second per
//! reason.
//!
//! ## Where to go next
//!
//! | to | start at |
//! |---|---|
//! | start a node, name its channels | [`Node`], [`NodeBuilder`], [`Namespace`], [`resolve_name`] |
//! | publish and receive | [`Channel`], [`Subscription`], [`Message`], [`CallbackSubscription`], [`QueuePolicy`] |
//! | say what a message is | [`Schema`] (derive it), [`type_info_of`], [`Primitive`], [`text`] (payloads as JSON) |
//! | see the fleet | [`Discovery`], [`MemberView`], [`DiscoveryEvent`], [`ServiceInfo`] |
//! | call and serve | [`Client`], [`OngoingCall`], [`Server`], [`ServerBuilder`], [`ServiceTypes`], [`CallContext`], [`Fault`], [`RawClient`] |
//! | settings | [`Setting`], [`SettingBuilder`], [`FleetSettings`], [`SettingsFile`] |
//! | keys (sealed channels) | [`Key`], [`KeyArg`], [`NodeBuilder::key`], [`Node::key_uses`] |
//! | know what went wrong | [`Error`], [`Stats`], [`DropReason`], [`ReassemblyLimits`], [`ServiceLimits`] |

#![deny(unreachable_pub)]

// The protocol core, under the names the driver has always used for it.
use pulicast_proto as proto;
use pulicast_proto::wire;

mod batching;
mod channel;
mod discovery;
mod error;
mod name;
mod nearest;
mod node;
mod port;
mod queue;
mod runtime;
mod security;
mod service;
mod setting;
mod setting_client;
mod stats;
mod subscription;
mod sync;
pub mod text;
mod transport;

pub use bytes::Bytes;
pub use channel::{Channel, Namespace};
pub use discovery::{Discovery, DiscoveryEvents, DISCOVERY_CHANNEL};
pub use error::{Error, Result};
pub use name::{resolve_name, GROUP_BASE, MAX_NAME_LEN};
pub use node::{
    Node, NodeBuilder, CONFIG_ENV, DEFAULT_FRAGMENT_RATE, DEFAULT_HEARTBEAT_PERIOD, DEFAULT_PORT,
    DEFAULT_QUEUE_CAPACITY, DEFAULT_RECEIVE_BUFFER, DEFAULT_RECEIVE_SPIN, DEFAULT_TTL,
    MAX_CONFIG_LEN, MAX_RECEIVE_SPIN, MIN_FRAGMENT_RATE,
};
pub use port::unused_port;
pub use proto::sender::MAX_BATCH_DELAY;
// The `Schema` trait is postcard-schema's; the `Schema` derive is ours
// (pulicast-derive), which works without postcard-schema among the user's
// dependencies. An explicit import shadows a glob's name in its namespace
// only, so the trait comes through the glob and the derive replaces
// postcard-schema's.
/// Derives [`Schema`](trait@Schema) for a message type: its description,
/// announced in discovery so tools decode it, and its fingerprint, which
/// a subscriber checks every message against. Needs `serde` beside it;
/// no dependency on `postcard-schema`.
///
/// ```
/// use pulicast::Schema;
/// use serde::{Deserialize, Serialize};
///
/// #[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
/// struct Pose { x: f64, y: f64, heading: f32 }
///
/// #[derive(Serialize, Deserialize, Schema)]
/// enum Mode { Manual, Docking { bay: u8 } }
///
/// // Another field, another type: the fingerprints differ, so a subscriber
/// // of the old Pose drops the new one (counted as wrong_type) instead of
/// // misreading it.
/// #[derive(Serialize, Deserialize, Schema)]
/// #[serde(rename = "Pose")]
/// struct PoseV2 { x: f64, y: f64, heading: f32, z: f64 }
/// assert_ne!(pulicast::type_info_of::<Pose>().fingerprint,
///            pulicast::type_info_of::<PoseV2>().fingerprint);
/// ```
pub use pulicast_derive::Schema;
pub use schema_trait::*;
mod schema_trait {
    pub use postcard_schema::Schema;
}

/// The schema crate behind [`Schema`]: its `NamedType` and `OwnedNamedType`
/// appear in [`text::is_raw_bytes`] and [`text::schema_of`].
pub use postcard_schema;

/// Paths the `Schema` derive expands to; not an API.
#[doc(hidden)]
pub mod __private {
    pub use postcard_schema;
}

// So that `::pulicast::...`, which the derive emits, also resolves inside
// this crate.
extern crate self as pulicast;

/// The examples of `docs/services.md`, compiled as doc tests.
#[cfg(doctest)]
#[doc = include_str!("../../docs/services.md")]
pub struct ServicesDoc;
pub use nearest::{NearestEvent, NearestPublisher, NearestSubscription, NEAREST_QUIET_AFTER};
pub use pulicast_discovery::compat::NODES_CHANNEL;
pub use pulicast_discovery::relay::MAX_SITE_LEN;
pub use queue::QueuePolicy;
pub use security::{DEFAULT_SEALED_MAX_AGE, ENCRYPT_ENV, KEYS_ENV};
pub use service::{
    services_of, Answer, CallContext, Client, Fault, OngoingCall, RawCall, RawClient, Server,
    ServerBuilder, ServiceEnd, ServiceInfo, ServiceTypes, DEFAULT_DEADLINE,
};
pub use setting::{Setting, SettingBuilder, SettingChanges};
pub use setting_client::FleetSettings;
pub use stats::Stats;
pub use subscription::{CallbackSubscription, Message, Subscription};
pub use uuid::Uuid;
pub use wire::fragment::MAX_MESSAGE;

// Items defined in the core crates (`pulicast-proto`, `pulicast-discovery`)
// get their examples here, one name per re-export: rustdoc shows a
// re-export's docs first on the item's page in this crate, and an example
// written in the core crate would name `pulicast_proto`, which users of this
// crate can't. A doc comment on a grouped `use` would go to every name in it.

/// A member of the fleet as [`Discovery`] lists it: who it is, where it
/// runs, in what state, with its channels.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// for m in node.discovery().live_members() {
///     let origin = match (&m.remote, m.compat) {
///         (Some(remote), _) => format!("site {}", remote.site), // through a bridge
///         (None, true) => "Pulicast 2.x".to_string(),           // known from heartbeats only
///         (None, false) => format!("{} on {}", m.namespace, m.host),
///     };
///     println!("{} ({origin}): {:?} at {}", m.name, m.state, m.address);
/// }
/// // Is anyone listening before commands go out?
/// let listened = node.discovery().live_members().iter().any(|m| m.subscribes("rover1/cmd"));
/// # let _ = listened;
/// # }
/// ```
pub use discovery::MemberView;

/// How a member of another site is present on this one, through a bridge
/// (`puli-bridge`): [`MemberView::remote`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use std::collections::BTreeMap;
/// let members = node.discovery().live_members();
/// // Members by site; those heard directly are this site's.
/// let mut sites: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
/// for m in &members {
///     let site = m.remote.as_ref().map_or("here", |r| r.site.as_str());
///     sites.entry(site).or_default().push(&m.name);
/// }
/// // The bridge is a member of this site, named by its key.
/// for remote in members.iter().filter_map(|m| m.remote.as_ref()) {
///     let bridge = members.iter().find(|b| b.key == remote.bridge).map(|b| &b.name);
///     println!("{} through {bridge:?}", remote.site);
/// }
/// # }
/// ```
pub use discovery::Remote;

/// A change in the fleet, as [`DiscoveryEvents`] delivers it.
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) {
/// use pulicast::DiscoveryEvent;
/// let mut events = node.discovery().events();
/// while let Some(event) = events.recv().await {
///     match event {
///         DiscoveryEvent::Joined(m) => println!("+ {} on {}", m.name, m.host),
///         DiscoveryEvent::Left { name, .. } => println!("- {name}"),
///         DiscoveryEvent::Failed { name, .. } => println!("- {name} (went silent)"),
///         DiscoveryEvent::ChannelAppeared { member, channel, .. } => {
///             println!("{member}: + {}", channel.name)
///         }
///         _ => {} // non_exhaustive: suspicions, recoveries, and what comes later
///     }
/// }
/// # }
/// ```
pub use discovery::DiscoveryEvent;

/// Why a channel or namespace name was refused: the reason inside
/// [`Error::InvalidName`].
///
/// ```
/// use pulicast::{resolve_name, Error, NameError};
/// let refused = |name: &str| match resolve_name(name, "rover1") {
///     Err(Error::InvalidName { reason, .. }) => Some(reason),
///     _ => None,
/// };
/// assert_eq!(refused("left_arm/pose"), None);
/// assert_eq!(refused(".."), Some(NameError::Empty)); // the root is no channel
/// assert_eq!(refused("pose/ü"), Some(NameError::NonAscii)); // 2.x peers read ASCII only
/// assert_eq!(refused(&"x".repeat(250)), Some(NameError::TooLong { len: 257 }));
/// ```
pub use error::NameError;

/// The multicast group a channel's messages travel on, as Pulicast 2.x
/// computes it: what a firewall or a switch must let through.
///
/// ```
/// use std::net::Ipv4Addr;
/// use pulicast::{group_for, resolve_name};
/// let channel = resolve_name("ctrl", "rover1")?; // groups are of full names
/// assert_eq!(group_for(&channel), Ipv4Addr::new(239, 56, 146, 15));
/// # Ok::<(), pulicast::Error>(())
/// ```
pub use name::group_for;

/// Whether a resolved channel name lies in a resolved namespace: by whole
/// parts, not by text.
///
/// ```
/// use pulicast::in_namespace;
/// assert!(in_namespace("rover1", "rover1/pose"));
/// assert!(!in_namespace("rover1", "rover10/pose")); // another rover
/// assert!(in_namespace("", "anything"));            // the root holds every channel
/// ```
pub use name::in_namespace;

/// Whether a channel is one that listings hide, as Pulicast 2.x tools do.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use pulicast::is_hidden_channel;
/// // Channels as a person wants them listed: settings' and services'
/// // channels (`rover1/.config/...`) and `__nodes` left out.
/// for m in node.discovery().live_members() {
///     let shown: Vec<&str> = m.channels.iter()
///         .map(|c| c.name.as_str())
///         .filter(|name| !is_hidden_channel(name))
///         .collect();
///     println!("{}: {}", m.name, shown.join(", "));
/// }
/// # }
/// ```
pub use name::is_hidden_channel;

/// What a [`RawCall`] tells its caller: progress messages in order, then
/// one event that ends the call.
///
/// ```
/// use pulicast::CallEvent;
/// // What a tool that shows raw calls prints for each event.
/// fn shown(event: &CallEvent) -> String {
///     match event {
///         CallEvent::Progress(bytes) => format!("progress ({} bytes)", bytes.len()),
///         CallEvent::Reply { missed_progress: 0, .. } => "done".into(),
///         CallEvent::Reply { missed_progress, .. } => format!("done, {missed_progress} progress lost"),
///         CallEvent::Failed { code, message, node } => format!("{node} failed ({code}): {message}"),
///         CallEvent::Busy => "busy: try again later".into(),
///         CallEvent::TimedOut => "no answer in time".into(),
///     }
/// }
/// assert!(!CallEvent::Progress(vec![1]).is_final()); // more follows
/// assert_eq!(shown(&CallEvent::Busy), "busy: try again later");
/// ```
pub use proto::call::Event as CallEvent;

/// A setting's last confirmation from its owner: [`SettingInfo::confirmed`].
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::Primitive;
/// let wait = std::time::Duration::from_secs(3);
/// let gain = node.fleet_settings().get("rover1/gain", wait).await?;
/// if let Some(confirmed) = &gain.confirmed {
///     match &confirmed.value {
///         Some(Primitive::Double(gain)) => println!("gain {gain}"),
///         Some(other) => println!("gain of another type: {other:?}"),
///         None if !confirmed.is_set() => println!("unset"),
///         None => println!("{} bytes of a native type", confirmed.encoded.len()),
///     }
///     if !confirmed.message.is_empty() {
///         println!("its owner says: {}", confirmed.message); // a refusal, a warning
///     }
/// }
/// # Ok(()) }
/// ```
pub use proto::catalog::Confirmed;

/// A member that owns a setting, or claims to: [`SettingInfo::owners`].
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) {
/// for setting in node.fleet_settings().list(std::time::Duration::from_secs(2)).await {
///     // An owner counts once a confirmation came from it; anyone can claim.
///     let owners: Vec<&str> = setting.owners.iter()
///         .filter(|o| o.live && o.answered)
///         .map(|o| o.node.as_str())
///         .collect();
///     let claims: Vec<&str> = setting.unanswered_claims().map(|o| o.node.as_str()).collect();
///     println!("{}: owned by {owners:?}, claimed by {claims:?}", setting.name);
/// }
/// # }
/// ```
pub use proto::catalog::OwnerRef;

/// One setting of the fleet, as [`FleetSettings`] reads it.
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// let wait = std::time::Duration::from_secs(3);
/// let speed = node.fleet_settings().get("rover1/max_speed", wait).await?;
/// println!(
///     "{} = {} ({}; {})",
///     speed.name,
///     speed.value_text().unwrap_or_default(),         // "1.5", "unset", JSON
///     speed.type_name().unwrap_or_default(),          // "double_msg", a native type's name
///     speed.about.as_deref().unwrap_or("no checks"),  // its description, unit and checks
/// );
/// if speed.is_locked() {
///     eprintln!("two owners answer for {}: nobody should write to it", speed.name);
/// }
/// # Ok(()) }
/// ```
pub use proto::catalog::SettingInfo;

/// A setting's description, unit and checks as a tool reads them back
/// ([`SettingInfo::limits`]): a range for a slider, the values of a
/// one-of for a choice. Read best-effort from the owner's text.
///
/// ```
/// let limits = pulicast::SettingLimits::parse("top speed; unit: m/s; must be in [0, 2]");
/// assert_eq!((limits.min, limits.max, limits.unit.as_str()), (Some(0.0), Some(2.0), "m/s"));
/// assert_eq!(limits.description, "top speed");
/// ```
pub use proto::setting::SettingLimits;

/// Bounds on the memory of messages still being reassembled from
/// fragments: [`NodeBuilder::reassembly_limits`].
///
/// ```
/// use std::time::Duration;
/// use pulicast::{ReassemblyLimits, MAX_MESSAGE};
/// let defaults = ReassemblyLimits::default();
/// // The largest message gets the timeout plus its size at 8 MiB/s.
/// assert_eq!(defaults.deadline_for(MAX_MESSAGE), defaults.timeout + Duration::from_secs(8));
/// // A node on a link that loses fragments: give up sooner, hold less.
/// let lossy = ReassemblyLimits { timeout: Duration::from_millis(500), ..defaults };
/// let node = pulicast::Node::new("viewer").reassembly_limits(lossy); // then start it
/// # drop(node);
/// ```
pub use proto::fragment::ReassemblyLimits;

/// How one namespace's keys fared with what the node received:
/// [`Node::key_uses`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// // After a while on the fleet: does it seal with the keys this node holds?
/// for used in node.key_uses() {
///     let namespace = if used.namespace.is_empty() { "/" } else { used.namespace.as_str() };
///     if used.opened == 0 && used.not_opened > 0 {
///         eprintln!("{namespace}: sealed with another key than ours");
///     } else if used.opened == 0 && used.unsealed > 0 {
///         eprintln!("{namespace}: the fleet does not seal it; its messages are refused");
///     }
/// }
/// # }
/// ```
pub use proto::receiver::KeyUse;

/// A pre-shared key that seals the channels of a namespace: given to
/// [`NodeBuilder::key`], read from `PULICAST_KEYS` ([`KEYS_ENV`]).
///
/// ```
/// use pulicast::{parse_key, Key, KeyError};
/// let key = Key::from_hex(&"5e".repeat(32))?;         // 64 hex digits
/// assert_eq!(format!("{key:?}"), "Key(<redacted>)"); // never printed or logged
/// assert_eq!(Key::from_hex("0123").unwrap_err(), KeyError::Format);
/// let _same = Key::from_bytes([0x5e; 32]);
/// let (namespace, _key) = parse_key(&format!("rover1={}", "5e".repeat(32)))?;
/// assert_eq!(namespace, "rover1");
/// // A node given it (`NodeBuilder::key`) seals `rover1/...` with it.
/// # Ok::<(), KeyError>(())
/// ```
pub use proto::secure::Key;

/// A `--key NAMESPACE=KEY` flag of a command-line tool, which can be
/// logged without showing the key.
///
/// ```
/// use pulicast::KeyArg;
/// let arg = KeyArg::from(format!("rover1={}", "ab".repeat(32))); // as clap gives it
/// assert!(!format!("{arg:?}").contains("abab"));
/// let (namespace, key) = arg.parse()?;
/// assert_eq!(namespace, "rover1");
/// let node = pulicast::Node::new("tool").key(namespace, key); // then start it
/// # drop(node);
/// let bad = KeyArg::from("rover1=0123".to_string()).parse().unwrap_err();
/// assert!(!bad.to_string().contains("0123")); // safe to show the user
/// # Ok::<(), pulicast::KeyError>(())
/// ```
pub use proto::secure::KeyArg;

/// Why a key or a key list could not be read. Its text never repeats key
/// material, so it can be shown and logged.
///
/// ```
/// use pulicast::{parse_keys, KeyError};
/// let good = "ab".repeat(32);
/// assert_eq!(parse_keys(&format!("rover1={good} rover2")).err(), Some(KeyError::Entry { entry: 2 }));
/// let short = parse_keys("rover1=0123abcd").unwrap_err();
/// assert!(matches!(short, KeyError::Key { entry: 1, .. }));
/// assert!(!short.to_string().contains("0123abcd"));
/// assert!(matches!(parse_keys("/=@/no/such/file"), Err(KeyError::File { .. })));
/// ```
pub use proto::secure::KeyError;

/// Reads one `NAMESPACE=KEY`: see [`Key`].
pub use proto::secure::parse_key;

/// Reads a key list as `PULICAST_KEYS` ([`KEYS_ENV`]) holds it.
///
/// ```
/// use pulicast::parse_keys;
/// let text = format!("/={},rover1={}", "aa".repeat(32), "bb".repeat(32));
/// let mut node = pulicast::Node::new("rover").keys_from_env(false);
/// for (namespace, key) in parse_keys(&text)? {
///     node = node.key(namespace, key); // `/` is the root: every other channel
/// }
/// # drop(node);
/// assert!(parse_keys("rover1=0123").is_err());
/// # Ok::<(), pulicast::KeyError>(())
/// ```
pub use proto::secure::parse_keys;

/// A server's bounds: [`ServerBuilder::limits`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use std::time::Duration;
/// use pulicast::{Fault, ServiceLimits};
/// // A planner runs two long calls at most, and one caller can't take both.
/// let limits = ServiceLimits {
///     concurrency: 2,
///     share: 1,
///     longest: Duration::from_secs(60),
///     ..ServiceLimits::default()
/// };
/// let _plan = node.server("plan").limits(limits).serve_blocking(|goal: (f64, f64)| {
///     Ok::<u32, Fault>((goal.0.abs() + goal.1.abs()) as u32)
/// })?;
/// # Ok(()) }
/// ```
pub use proto::service::ServiceLimits;

/// A constraint on a setting's value, checked on every change whoever asks
/// for it: [`Namespace::setting_checked`], [`SettingBuilder::check`].
///
/// ```
/// use pulicast::Check;
/// # let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("rover_controller")
///     .interface(std::net::Ipv4Addr::LOCALHOST)
/// #   .port(port)
///     .start_blocking()?;
/// let modes = vec!["manual".to_string(), "dock".to_string()];
/// let mode = node.setting_checked("mode", "manual".to_string(), vec![Check::OneOf(modes)])?;
/// let even = Check::Custom(Box::new(|n: &i64| match n % 2 {
///     0 => Ok(()),
///     _ => Err("must be even".to_string()), // the reason tools are told
/// }));
/// let wheels = node.setting_checked("wheels", 4i64, vec![Check::AtLeast(2), even])?;
/// assert!(mode.set("warp".to_string()).is_err());
/// assert!(wheels.set(3).is_err());
/// # Ok::<(), pulicast::Error>(())
/// ```
pub use proto::setting::Check;

/// A setting's value as a settings file gives it: [`SettingsFile::entries`],
/// [`SettingInfo::holds`].
///
/// ```
/// use pulicast::{FileValue, Primitive, SettingsFile};
/// let text = "\"rover1/max_speed\" = 1.5\n\"rover1/gain\" = nan\n\"rover1/limits\" = { speed = 1.0 }\n";
/// let file: SettingsFile = text.parse().expect("TOML");
/// for entry in file.entries() {
///     match entry.value {
///         Ok(FileValue::Value(Primitive::Double(v))) => println!("{}: {v}", entry.name),
///         Ok(FileValue::Value(other)) => println!("{}: {other:?}", entry.name),
///         Ok(FileValue::Unset) => println!("{}: no value", entry.name),
///         Ok(FileValue::Structured(json)) => println!("{}: {json}", entry.name), // native
///         Err(why) => eprintln!("{}: {why}", entry.name),
///     }
/// }
/// ```
pub use proto::setting::FileValue;

/// A native value as a setting: any `serde` + [`Schema`] type.
///
/// ```
/// use pulicast::{Native, Schema};
/// #[derive(serde::Serialize, serde::Deserialize, Schema, Clone, PartialEq, Debug)]
/// struct Limits { speed: f64, turn: f64 }
///
/// # let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("rover_controller")
///     .namespace("rover1")
///     .interface(std::net::Ipv4Addr::LOCALHOST)
/// #   .port(port)
///     .start_blocking()?;
/// let limits = node.setting("limits", Native(Limits { speed: 1.5, turn: 0.5 }))?;
/// // Tools write it as JSON (`FleetSettings::set_json`) from its announced type.
/// let Some(Native(now)) = limits.get() else { unreachable!("it has a default") };
/// assert_eq!(now.speed, 1.5);
/// # Ok::<(), pulicast::Error>(())
/// ```
pub use proto::setting::Native;

/// A type a setting can hold: `bool`, `u8`, `i8`, `i16`, `i32`, `i64`,
/// `f32`, `f64` and `String` (as the 2.x primitives, so `puliconf` reads
/// them), and [`Native`] values.
///
/// ```
/// use pulicast::{Namespace, Setting, SettingValue};
/// // A component that takes its tunables wherever it is placed.
/// fn tunable<T: SettingValue>(ns: &Namespace, name: &str, default: T) -> pulicast::Result<Setting<T>> {
///     ns.setting_builder(name, default).describe("tuned at run time").build()
/// }
/// assert_eq!(f64::type_name(), "double_msg"); // what tools see it as
/// # let _ = tunable::<f64>;
/// ```
pub use proto::setting::SettingValue;

/// A settings file in `puliconf`'s format: what `puli config pull` writes
/// and `push` reads, and what [`NodeBuilder::settings_file`] starts from.
///
/// ```
/// use pulicast::{FileValue, Primitive, SettingsFile};
/// let text = r#"
/// "rover1/max_speed" = 1.5 # m/s
/// "/rover1/mode" = "drive"
/// "rover1/gain" = nan
/// "#;
/// let file: SettingsFile = text.parse().unwrap();
/// let entries = file.entries();
/// assert_eq!(entries[0].name, "rover1/max_speed");
/// assert_eq!(entries[0].value, Ok(FileValue::Value(Primitive::Double(1.5))));
/// assert_eq!(entries[1].name, "rover1/mode"); // the leading `/` dropped
/// assert_eq!(entries[2].value, Ok(FileValue::Unset));
/// assert!("a = = 1".parse::<SettingsFile>().is_err());
/// ```
pub use proto::settings_file::SettingsFile;

/// A message type as discovery announces it, enough for a tool to decode
/// its messages: made by [`type_info_of`], carried by
/// [`ChannelInfo::message_type`].
///
/// ```
/// use pulicast::{type_info_of, PrimitiveKind, Schema, TypeEncoding};
/// #[derive(serde::Serialize, serde::Deserialize, Schema)]
/// struct Twist { linear: f64, angular: f64 }
///
/// let twist = type_info_of::<Twist>();
/// assert_eq!((twist.encoding, twist.name.as_str()), (TypeEncoding::Native, "Twist"));
/// assert!(pulicast::text::schema_of(&twist).is_some()); // its description travels along
/// let speed = type_info_of::<f64>(); // a 2.x primitive: its ZCM message
/// assert_eq!((speed.encoding, speed.name.as_str()), (TypeEncoding::Zcm, "double_msg"));
/// assert_eq!(speed.fingerprint, PrimitiveKind::Double.fingerprint().0);
/// ```
pub use pulicast_discovery::wire::TypeInfo;

/// Why received data was dropped: what [`Stats::dropped`] counts by.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use pulicast::DropReason;
/// // Drops that point at a wrong key or an attacker rather than a lossy link.
/// let security = [
///     DropReason::Unauthenticated,
///     DropReason::NoKey,
///     DropReason::Forged,
///     DropReason::Replayed,
/// ];
/// let stats = node.stats();
/// for reason in security.into_iter().filter(|r| stats.dropped(*r) > 0) {
///     eprintln!("{}: {}", reason.label(), stats.dropped(reason)); // the label logs use
/// }
/// # }
/// ```
pub use wire::DropReason;

/// Why bytes could not be decoded, each kind counted under its
/// [`DropReason`]; [`Error::Decode`] carries it.
///
/// ```
/// use pulicast::{DecodeError, DropReason, Primitive, PrimitiveKind};
/// let mut payload = Vec::new();
/// Primitive::Double(0.8).encode(&mut payload);
/// match Primitive::decode_as(PrimitiveKind::I64, &payload) {
///     Err(DecodeError::WrongType { expected_name, found, .. }) => {
///         println!("wanted {expected_name}, got a message of {found}")
///     }
///     other => panic!("a double is no int64: {other:?}"),
/// }
/// let cut = Primitive::decode(&payload[..10]).unwrap_err(); // lost its tail
/// assert_eq!(cut.reason(), DropReason::TruncatedPayload);
/// ```
pub use wire::DecodeError;

/// The 8 bytes a message starts with that name its type.
///
/// ```
/// use pulicast::{type_info_of, Fingerprint, Primitive, PrimitiveKind};
/// let mut payload = Vec::new();
/// Primitive::I64(7).encode(&mut payload); // as `publish(&7i64)` sends it
/// let found = Fingerprint::of_payload(&payload).expect("at least 8 bytes");
/// assert_eq!(found, PrimitiveKind::I64.fingerprint());
/// assert_eq!(found.to_string(), "5bb95bc420d5ff91"); // as the 2.x tools print it
/// // A subscriber of `String` would drop this message as the wrong type:
/// assert_ne!(Fingerprint(type_info_of::<String>().fingerprint), found);
/// ```
pub use wire::Fingerprint;

/// What discovery announces for a channel of `T`.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use pulicast::{type_info_of, Schema};
/// #[derive(serde::Serialize, serde::Deserialize, Schema)]
/// struct Twist { linear: f64, angular: f64 }
///
/// // Before publishing: does every subscriber expect what this node sends?
/// let mine = type_info_of::<Twist>();
/// for m in node.discovery().live_members() {
///     for c in m.channels.iter().filter(|c| c.name == "rover1/cmd" && c.subscribes) {
///         if c.message_type.as_ref().is_some_and(|t| t.fingerprint != mine.fingerprint) {
///             eprintln!("{} expects another type on {}", m.name, c.name);
///         }
///     }
/// }
/// # }
/// ```
pub use wire::type_info_of;

/// A single-value message of Pulicast 2.x, whatever its type: what
/// [`FleetSettings::set`] takes and a setting's confirmation holds.
///
/// ```
/// use pulicast::{Primitive, PrimitiveKind};
/// let mut payload = Vec::new();
/// Primitive::Double(0.8).encode(&mut payload); // as `publish(&0.8f64)` sends it
/// assert_eq!(Primitive::decode(&payload), Ok(Primitive::Double(0.8)));
/// assert_eq!(Primitive::String("dock".into()).kind(), PrimitiveKind::String);
/// // A payload that must be one type: another is refused, not converted.
/// assert!(Primitive::decode_as(PrimitiveKind::Float, &payload).is_err());
/// ```
pub use wire::zcm::Primitive;

/// Which 2.x primitive message: its fingerprint, its ZCM name, its Rust
/// type.
///
/// ```
/// use pulicast::{Fingerprint, Primitive, PrimitiveKind};
/// let mut payload = Vec::new();
/// Primitive::Bool(true).encode(&mut payload);
/// // Which primitive a payload is, from its first 8 bytes:
/// let kind = Fingerprint::of_payload(&payload).and_then(PrimitiveKind::from_fingerprint);
/// assert_eq!(kind, Some(PrimitiveKind::Bool));
/// for kind in PrimitiveKind::ALL {
///     println!("{} is Rust's {}", kind.type_name(), kind.rust_name()); // boolean_msg is Rust's bool
/// }
/// ```
pub use wire::zcm::PrimitiveKind;

/// The sdbm hash of a name, as Pulicast 2.x computes it: the low 23 bits
/// of a channel's give its multicast group ([`group_for`]).
///
/// ```
/// use pulicast::{group_for, sdbm, GROUP_BASE};
/// let offset = (sdbm("rover1/ctrl") & ((1 << 23) - 1)) as u32;
/// assert_eq!(u32::from(group_for("rover1/ctrl")), u32::from(GROUP_BASE) + offset);
/// ```
pub use name::sdbm;

/// How far a message is ahead of the last one heard from its publisher on
/// its channel ([`Message::lead`]): `1` is the next message in order, more
/// than `1` means `lead - 1` messages were lost (or are still on their
/// way), `0` or less a late or repeated one. Sequence numbers wrap at
/// 2^32 and read on; a publisher that restarts is a new source, so it
/// starts afresh. One forged datagram far ahead costs one apparent gap,
/// not every later message of the real publisher.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::Lead;
/// let mut lost = 0;
/// let mut scans = node.channel("laser/scan").subscribe_raw()?;
/// while let Some(scan) = scans.recv_blocking() {
///     let lead: Lead = scan.lead;
///     if lead > 1 {
///         lost += lead - 1; // a gap: the datagrams between never came
///     } else if lead <= 0 {
///         continue; // late or twice: a newer scan was handled already
///     }
///     println!("{} bytes, {lost} lost so far", scan.value.len());
/// }
/// # Ok(()) }
/// ```
pub use proto::Lead;

/// A 2.x node's channel as its heartbeat announces it: [`Peer::channels`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// for peer in node.peers() {
///     for c in peer.channels.iter().filter(|c| c.is_published) {
///         // 2.x announces a period, not a type: its channels carry no TypeInfo.
///         println!("{} publishes {} every {} ns", peer.name, c.name, c.period_ns);
///     }
/// }
/// # }
/// ```
pub use pulicast_discovery::compat::ChannelAnnouncement;

/// A Pulicast 2.x node known from its heartbeats on `__nodes`:
/// [`Node::peers`]. (Gossip members and 2.x peers together are
/// [`Discovery::members`].)
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use std::time::Instant;
/// for peer in node.peers() {
///     let left = peer.deadline().saturating_duration_since(Instant::now());
///     let publishes: Vec<&str> = peer.publishes().collect();
///     println!("{} at {}: {publishes:?}, counted gone in {left:?} unless heard",
///              peer.name, peer.address);
/// }
/// # }
/// ```
pub use pulicast_discovery::compat::Peer;

/// What this node's gossip discovery has done, from its start:
/// [`Discovery::stats`] (`None` when discovery is off).
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// if let Some(g) = node.discovery().stats() {
///     println!("gossip: {} datagrams in, {} out", g.datagrams_in, g.datagrams_out);
///     // Refused traffic: what a stranger or a broken peer sent.
///     if g.malformed + g.suspicious > 0 {
///         eprintln!("{} malformed, {} suspicious", g.malformed, g.suspicious);
///     }
///     if g.rejected + g.states_refused > 0 {
///         eprintln!("the fleet outgrew this node's discovery bounds");
///     }
/// }
/// # }
/// ```
pub use pulicast_discovery::gossip::GossipStats;

/// What this node did with members that bridges relay from other sites:
/// [`Discovery::relay_stats`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// if let Some(r) = node.discovery().relay_stats() {
///     println!("{} relayed entries taken, {} expired", r.accepted, r.expired);
///     if r.refused_full > 0 {
///         eprintln!("{} relayed members did not fit", r.refused_full);
///     }
/// }
/// # }
/// ```
pub use pulicast_discovery::relay::RelayStats;

/// A channel as a member announces it: whether it publishes or subscribes
/// it, how often it publishes, and its type ([`MemberView::channels`],
/// [`DiscoveryEvent::ChannelAppeared`]).
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// for m in node.discovery().live_members() {
///     for c in m.channels.iter().filter(|c| c.publishes) {
///         let rate = match c.period_ns { 0 => 0.0, ns => 1e9 / ns as f64 };
///         let ty = c.message_type.as_ref().map_or("raw bytes", |t| t.name.as_str());
///         println!("{} publishes {} ({ty}) at {rate:.1} Hz", m.name, c.name);
///     }
/// }
/// # }
/// ```
pub use pulicast_discovery::wire::ChannelInfo;

/// A member's announcement as gossip carries it: who it is and its
/// channels. [`MemberView`] is what this node makes of it; a bridge relays
/// it to other sites as a [`RelayedMember`].
///
/// ```
/// use pulicast::{ChannelInfo, MemberInfo, MemberView};
/// let info = MemberInfo {
///     session: [7; 16],
///     name: "lidar".into(),
///     namespace: "rover1".into(),
///     host: "rover1-nuc".into(),
///     pid: 4242,
///     start_time_ms: 0,
///     data_port: 40_000,
///     channels: vec![ChannelInfo {
///         name: "rover1/scan".into(),
///         publishes: true,
///         subscribes: false,
///         period_ns: 100_000_000,
///         message_type: None,
///     }],
///     config: String::new(),
///     extensions: Vec::new(),
/// };
/// // What it costs to keep (discovery's tables are bounded by this).
/// assert!(info.memory_cost() > std::mem::size_of::<MemberInfo>());
/// let view = MemberView::from_info(&info, "10.0.0.7:4000".parse().unwrap());
/// assert!(view.publishes("rover1/scan"));
/// assert_eq!(view.key, info.key()); // the session's first 8 bytes
/// ```
pub use pulicast_discovery::wire::MemberInfo;

/// A property of a member beyond [`MemberInfo`]'s fixed fields: a kind
/// and its bytes (docs/discovery.md, "Extensions"). A bridge building a
/// [`MemberInfo`] from a [`MemberView`] passes on the kinds the view
/// keeps, such as its receive buffer.
///
/// ```
/// use pulicast::Extension;
/// let announced = Extension::receive_buffer(8 << 20);
/// assert_eq!(announced.data, (8u32 << 20).to_le_bytes());
/// ```
pub use pulicast_discovery::wire::Extension;

/// What gossip believes of a member: [`MemberView::state`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use pulicast::MemberState;
/// for m in node.discovery().members() {
///     let note = match m.state {
///         MemberState::Alive => "up",
///         MemberState::Suspect => "silent: failed unless it answers",
///         MemberState::Dead => "failed",
///         MemberState::Left => "stopped",
///     };
///     println!("{}: {note}", m.name);
/// }
/// # }
/// ```
pub use pulicast_discovery::wire::MemberState;

/// A member of another site, as a bridge hands it to this site's
/// discovery ([`Discovery::relay`]): the member's announcement, its site
/// and what that site believes of it.
///
/// ```no_run
/// # fn demo(here: pulicast::Node, there: Vec<pulicast::MemberInfo>) -> pulicast::Result<()> {
/// use pulicast::{MemberState, RelayedMember};
/// // A bridge's step: the members it hears on site "depot", relayed here.
/// let relayed = there
///     .into_iter()
///     .map(|info| RelayedMember { info, site: "depot".into(), state: MemberState::Alive, incarnation: 0 })
///     .collect();
/// here.discovery().relay(relayed)?; // replaces what was relayed before
/// # Ok(()) }
/// ```
pub use pulicast_discovery::wire::RelayedMember;

/// How a type's messages are encoded: [`TypeInfo::encoding`].
///
/// ```
/// use pulicast::{type_info_of, TypeEncoding};
/// // 2.x primitives travel as ZCM messages, so Python peers read them;
/// // anything else as a fingerprint and postcard.
/// assert_eq!(type_info_of::<i32>().encoding, TypeEncoding::Zcm);
/// assert_eq!(type_info_of::<Vec<f32>>().encoding, TypeEncoding::Native);
/// ```
pub use pulicast_discovery::wire::TypeEncoding;

/// What a server did with the requests it got, from its start:
/// [`Server::counts`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// let server = node.serve_blocking("add", |(a, b): (i64, i64)| Ok(a + b))?;
/// // ... later, on a status page:
/// let c = server.counts();
/// println!("{}: {} run, {} busy ({} over a caller's share)", server.service(), c.run, c.busy, c.over_share);
/// // Retransmissions answered from the cache instead of running again:
/// println!("{} resent, {} lost", c.resent, c.lost);
/// # Ok(()) }
/// ```
pub use proto::service::ServiceCounts;

/// A setting's own check, for [`Check::Custom`]: `Ok` takes the value,
/// `Err` refuses it with the reason the asker is told.
///
/// ```
/// use pulicast::{Check, Validator};
/// let heading: Validator<f64> = Box::new(|deg| match (0.0..360.0).contains(deg) {
///     true => Ok(()),
///     false => Err(format!("{deg} is no heading (0 to 360)")),
/// });
/// let check = Check::Custom(heading);
/// # let _ = check;
/// ```
pub use proto::setting::Validator;

/// One setting of a [`SettingsFile`], by name: [`SettingsFile::entries`].
///
/// ```
/// use pulicast::{SettingsFile, SettingsFileEntry};
/// let file: SettingsFile = "\"rover1/max_speed\" = 1.5\n\"rover1/limits\" = [1, 2]\n".parse().unwrap();
/// for SettingsFileEntry { name, value } in file.entries() {
///     match value {
///         Ok(v) => println!("{name} = {v:?}"),
///         Err(why) => eprintln!("{name}: {why}"), // the rest of the file still applies
///     }
/// }
/// ```
pub use proto::settings_file::SettingsFileEntry;

/// A setting a [`SettingsFile`] could not hold, and why:
/// [`SettingsFile::pull`], [`SettingsFile::differing`].
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) {
/// use std::time::Duration;
/// use pulicast::SettingsFile;
/// let fleet = node.fleet_settings().list(Duration::from_secs(2)).await;
/// let (file, skipped) = SettingsFile::pull(&fleet);
/// for s in &skipped {
///     eprintln!("not saved: {}: {}", s.name, s.reason); // no value known yet, say
/// }
/// std::fs::write("fleet.toml", file.to_string()).unwrap();
/// # }
/// ```
pub use proto::settings_file::SkippedSetting;

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
//! | call and serve | [`Client`], [`OngoingCall`], [`Server`], [`ServerBuilder`], [`CallContext`], [`Fault`], [`RawClient`] |
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
pub use discovery::{
    Discovery, DiscoveryEvent, DiscoveryEvents, MemberView, Remote, DISCOVERY_CHANNEL,
};
pub use error::{Error, NameError, Result};
pub use name::{
    group_for, in_namespace, is_hidden_channel, resolve_name, sdbm, GROUP_BASE, MAX_NAME_LEN,
};
pub use node::{
    Node, NodeBuilder, DEFAULT_HEARTBEAT_PERIOD, DEFAULT_PORT, DEFAULT_QUEUE_CAPACITY,
    DEFAULT_RECEIVE_BUFFER, DEFAULT_RECEIVE_SPIN, DEFAULT_TTL, MAX_RECEIVE_SPIN,
};
pub use port::unused_port;
pub use proto::sender::MAX_BATCH_DELAY;
// The `Schema` trait is postcard-schema's; the `Schema` derive is ours
// (pulicast-derive), which works without postcard-schema among the user's
// dependencies. An explicit import shadows a glob's name in its namespace
// only, so the trait comes through the glob and the derive replaces
// postcard-schema's.
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
pub use proto::call::Event as CallEvent;
pub use proto::catalog::{Confirmed, OwnerRef, SettingInfo};
pub use proto::fragment::ReassemblyLimits;
pub use proto::receiver::KeyUse;
pub use proto::secure::{parse_key, parse_keys, Key, KeyArg, KeyError};
pub use proto::service::{ServiceCounts, ServiceLimits};
pub use proto::setting::{Check, FileValue, Native, SettingValue, Validator};
pub use proto::settings_file::{SettingsFile, SettingsFileEntry, SkippedSetting};
pub use proto::Lead;
pub use pulicast_discovery::compat::{ChannelAnnouncement, Heartbeat, Peer, NODES_CHANNEL};
pub use pulicast_discovery::gossip::GossipStats;
pub use pulicast_discovery::relay::{RelayStats, MAX_SITE_LEN};
pub use pulicast_discovery::wire::{
    ChannelInfo, MemberInfo, MemberState, RelayedMember, TypeEncoding, TypeInfo,
};
pub use queue::QueuePolicy;
pub use security::{DEFAULT_SEALED_MAX_AGE, ENCRYPT_ENV, KEYS_ENV};
pub use service::{
    services_of, Answer, CallContext, Client, Fault, OngoingCall, RawCall, RawClient, Server,
    ServerBuilder, ServiceEnd, ServiceInfo, DEFAULT_DEADLINE,
};
pub use setting::{Setting, SettingBuilder, SettingChanges};
pub use setting_client::FleetSettings;
pub use stats::Stats;
pub use subscription::{CallbackSubscription, Message, Subscription};
pub use uuid::Uuid;
pub use wire::fragment::MAX_MESSAGE;
pub use wire::zcm::{Primitive, PrimitiveKind};
pub use wire::{type_info_of, DecodeError, DropReason, EncodeError, Fingerprint};

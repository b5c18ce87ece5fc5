//! The Pulicast protocol as pure logic: no sockets, no tasks, no clock
//! reads. Time comes in as arguments (`now: Instant`, `unix_ms: u64`),
//! datagrams come in as byte buffers and go out through a `send` closure
//! the caller owns, so every state machine here runs the same in a node,
//! in a deterministic simulation and under a fuzzer.
//!
//! This is the core of [`pulicast`](https://example.invalid/pulicast-rs):
//! the `pulicast` crate drives these state machines with tokio and
//! sockets, and is what applications use. Depend on this crate directly
//! only to speak the wire yourself (a fuzzer, a simulation, a tool that
//! forges or inspects datagrams).
//!
//! # Layers
//!
//! Each layer uses only the ones above it:
//!
//! - [`wire`]: the encodings, byte for byte: the Pulicast 2.x packet, ZCM
//!   types and fingerprints, native (postcard) messages, fragments,
//!   batches, sealed datagrams, service and setting frames.
//! - [`name`]: channel names, namespaces and their multicast groups.
//! - [`text`]: payloads as JSON, for tools, by the type a channel announces.
//! - The state machines: [`Receiver`] (one socket's datagrams in, messages
//!   and drops out), [`ChannelTx`] (one channel's messages in, datagrams
//!   out), [`fragment`] reassembly, [`secure`] sealing and opening,
//!   [`LeadTracker`] (sequence numbers to gaps), [`call`] and [`service`]
//!   (a service call and a server's admission), [`setting`] and
//!   [`catalog`] (distributed settings), [`settings_file`] (puliconf
//!   files), [`heartbeat`] (the 2.x heartbeat).
//! - [`view`]: the fleet as a node shows it, made from what discovery
//!   holds.
//!
//! # Call order
//!
//! A driver owns the sockets, the clock and the timers, and calls:
//!
//! 1. `handle_*` when something happens: [`Receiver::handle_datagram`]
//!    for each datagram read (then [`Receiver::repay`] with the buffer it
//!    lent for the next fragment), [`ChannelTx::publish`] for each message
//!    to send (it calls `send` for each datagram, in order).
//! 2. `poll_*` until `None`, right after: [`Receiver::poll_gossip`] and
//!    [`Receiver::poll_drop`] for what the datagram produced, and the
//!    subscribers' queues for messages.
//! 3. `poll_timeout` for when to call `handle_timeout` next (a batch to
//!    flush, fragments to give up on); a driver sleeps until the earliest.
//!
//! Nothing here blocks, allocates without bound or panics on what the
//! network sends: every table the network can grow has a limit in bytes
//! ([`fragment::ReassemblyLimits`], [`service::ServiceLimits`], [`catalog`]'s bounds), and
//! bad input is dropped and counted ([`wire::DropReason`]).

#![deny(unreachable_pub)]

pub mod error;
pub mod name;
pub mod text;
pub mod wire;

pub mod call;
pub mod catalog;
pub mod fragment;
pub mod heartbeat;
mod lead;
pub mod nearest;
pub mod pace;
pub mod receiver;
pub mod secure;
pub mod sender;
pub mod service;
pub mod setting;
pub mod settings_file;
pub mod view;

pub use error::{Error, NameError, Result};
pub use lead::{Lead, LeadTracker};
pub use receiver::Receiver;
pub use sender::ChannelTx;

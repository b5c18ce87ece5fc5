//! Protocol state that is pure logic: no sockets, no clock: lead tracking,
//! the fragmentation of large messages, the batching of small ones, the
//! sealing of datagrams for authenticated channels, and the [`Receiver`]
//! that puts them together into a node's receive path.

/// Batches of messages: the format lives in [`crate::wire::batch`].
pub use crate::wire::batch;
pub mod call;
pub mod catalog;
pub mod fragment;
pub mod heartbeat;
mod lead;
pub mod receiver;
pub mod secure;
pub mod sender;
pub mod service;
pub mod setting;

pub use lead::{Lead, LeadTracker};
pub use receiver::Receiver;
pub use sender::ChannelTx;

//! Protocol state that is pure logic: no sockets, no clock: lead tracking,
//! the fragmentation of large messages, the batching of small ones, and the
//! sealing of datagrams for authenticated channels.

pub mod batch;
pub mod fragment;
mod lead;
pub mod secure;

pub use lead::{Lead, LeadTracker};

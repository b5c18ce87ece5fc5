//! Protocol state that is pure logic: no sockets, no clock: lead tracking,
//! the fragmentation of large messages and the batching of small ones.

pub mod batch;
pub mod fragment;
mod lead;

pub use lead::{Lead, LeadTracker};

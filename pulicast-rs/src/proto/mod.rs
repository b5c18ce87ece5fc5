//! Protocol state that is pure logic: no sockets, no clock: lead tracking
//! and the fragmentation of large messages.

pub mod fragment;
mod lead;

pub use lead::{Lead, LeadTracker};

//! Protocol state that is pure logic: no sockets, no clock.

mod lead;

pub use lead::{Lead, LeadTracker};

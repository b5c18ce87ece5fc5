//! `puli-bridge`: a pulicast fleet across sites that multicast does not
//! join (Wi-Fi that drops it, other subnets, VPNs, the internet), over
//! [Zenoh](https://zenoh.io).
//!
//! One bridge runs per site. It is an ordinary pulicast node on its site
//! and a Zenoh peer (or client of a Zenoh router) on the link between
//! sites. It carries:
//!
//! - **channels**: every local channel a local member publishes goes out as
//!   Zenoh samples under `<prefix>/<channel>`; every channel a local member
//!   subscribes is taken from Zenoh and published here (see [`plan`] for the
//!   rules, [`keys`] for the key mapping and [`sample`] for what a sample
//!   carries);
//! - **discovery**: each site's members, in a table ([`table`]) valid while
//!   its bridge's liveliness token is, relayed on the other sites with
//!   `pulicast::Discovery::relay`, so they are listed there, marked remote;
//! - **service calls** to servers of other sites, as Zenoh queries
//!   ([`call`]); settings cross as the channels they are.
//!
//! What it carries is bounded: exports and imports by [`slots`], each
//! member's channels in its site's table by the same per-member bound.
//!
//! The protocol logic ([`keys`], [`filter`], [`sample`], [`table`],
//! [`call`], [`plan`], [`pace`], [`slots`]) has no sockets, no Zenoh session and no clock; [`run`] drives it.
//! `docs/bridge.md` is the user's guide.

pub mod bench;
pub mod call;
pub mod filter;
pub mod keys;
pub mod options;
pub mod pace;
pub mod plan;
pub mod run;
pub mod sample;
pub mod slots;
pub mod table;

pub use options::Options;
pub use run::{Bridge, BridgeStats};

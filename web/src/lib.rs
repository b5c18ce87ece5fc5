//! `puli web`: the fleet in a browser. One binary serves one page on
//! loopback, behind a random token printed at start (as Jupyter does), to
//! a browser of the same machine: the fleet's members, live, over a
//! WebSocket. Everything it knows comes from `pulicast`'s public API, as
//! for any other user (docs/web.md).
//!
//! The page never treats what comes from the network as HTML: names of
//! nodes and channels are set as text, and the server's
//! `Content-Security-Policy` lets no inline script run.
//!
//! With `--foxglove`, the same binary serves the fleet to Foxglove (and
//! Lichtblick) too: [`foxglove_server`] behind [`gate`].

pub mod bench;
pub mod calls;
pub mod channels;
pub mod decimate;
pub mod fair;
pub mod fleet;
pub mod foxglove_server;
pub mod gate;
pub mod guard;
pub mod http;
pub mod server;
pub mod settings;

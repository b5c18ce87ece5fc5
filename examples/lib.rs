//! Shared pieces of the examples: message types and command-line flags.
//!
//! The examples stay on this host by default (`--interface 127.0.0.1`, TTL 0),
//! so they can run anywhere without touching a real network.

use std::net::Ipv4Addr;

use pulicast::{Node, NodeBuilder, Schema};
use serde::{Deserialize, Serialize};

/// Where a rover is, in metres and radians.
#[derive(Serialize, Deserialize, Schema, Debug, Clone, Copy, PartialEq, Default)]
pub struct Pose {
    /// East, metres.
    pub x: f64,
    /// North, metres.
    pub y: f64,
    /// Heading, radians counter-clockwise from east.
    pub heading: f64,
}

/// A velocity command.
#[derive(Serialize, Deserialize, Schema, Debug, Clone, Copy, PartialEq, Default)]
pub struct Twist {
    /// Forward speed, m/s.
    pub linear: f64,
    /// Turn rate, rad/s.
    pub angular: f64,
}

/// Flags every example takes.
#[derive(clap::Args, Debug, Clone)]
pub struct NetFlags {
    /// UDP port shared by all nodes of the fleet.
    #[arg(long, default_value_t = pulicast::DEFAULT_PORT)]
    pub port: u16,
    /// Interface to send and join on; the default keeps traffic on this host.
    #[arg(long, default_value_t = Ipv4Addr::LOCALHOST)]
    pub interface: Ipv4Addr,
}

impl NetFlags {
    /// A node builder with these flags applied.
    pub fn node(&self, name: &str) -> NodeBuilder {
        Node::new(name).port(self.port).interface(self.interface)
    }
}

/// Logs to stderr, filtered by `RUST_LOG` (default: warnings).
pub fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .init();
}

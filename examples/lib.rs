//! Shared pieces of the examples: message types and command-line flags.
//!
//! The examples stay on this host: TTL 0, where a node sends on loopback and
//! every node of the host hears it (Pulicast 2.x nodes included).
//! `--interface 127.0.0.1` keeps even group joins on loopback.

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
    /// Interface to send and join on (default: the node's, which at TTL 0
    /// sends on loopback).
    #[arg(long)]
    pub interface: Option<Ipv4Addr>,
}

impl NetFlags {
    /// A node builder with these flags applied.
    pub fn node(&self, name: &str) -> NodeBuilder {
        let node = Node::new(name).port(self.port);
        match self.interface {
            Some(interface) => node.interface(interface),
            None => node,
        }
    }

    /// The flags again, for a child process.
    pub fn to_args(&self) -> Vec<String> {
        let mut args = vec!["--port".to_string(), self.port.to_string()];
        if let Some(interface) = self.interface {
            args.extend(["--interface".to_string(), interface.to_string()]);
        }
        args
    }

    /// Where the nodes send, for people.
    pub fn describe(&self) -> String {
        match self.interface {
            Some(interface) => interface.to_string(),
            None => "loopback (the default at TTL 0)".to_string(),
        }
    }
}

/// Logs to stderr, filtered by `RUST_LOG` (default: warnings).
pub fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        // Colour codes only where a person reads them, not in a log file.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
}

//! Options every tool takes, flattened into each command.

use std::net::{Ipv4Addr, SocketAddr, ToSocketAddrs};
use std::time::Duration;

use pulicast::{Node, NodeBuilder};

/// Where the fleet is: port, interface, namespace and seed peers.
#[derive(clap::Args, Debug, Clone)]
pub struct NetArgs {
    /// UDP port of the fleet.
    #[arg(long, global = true, default_value_t = pulicast::DEFAULT_PORT)]
    pub port: u16,
    /// Interface to join and send on (default: the kernel's choice, plus
    /// loopback). 127.0.0.1 keeps everything on this host.
    #[arg(long, global = true)]
    pub interface: Option<Ipv4Addr>,
    /// Namespace that relative channel names resolve against.
    #[arg(long, global = true, default_value = "")]
    pub namespace: String,
    /// A seed peer (`host:port` of a node's discovery socket), for links
    /// where multicast does not pass. May be repeated.
    #[arg(long = "peer", global = true, value_parser = parse_peer)]
    pub peers: Vec<SocketAddr>,
    /// Multicast TTL: 0 stays on this host, 1 reaches the local link.
    #[arg(long, global = true, default_value_t = pulicast::DEFAULT_TTL)]
    pub ttl: u32,
}

impl NetArgs {
    /// A node builder for a tool called `name`.
    pub fn node(&self, name: &str) -> NodeBuilder {
        let mut builder = Node::new(name)
            .port(self.port)
            .ttl(self.ttl)
            .namespace(self.namespace.clone())
            .heartbeat_period(Duration::from_millis(100));
        if let Some(iface) = self.interface {
            builder = builder.interface(iface);
        }
        for peer in &self.peers {
            builder = builder.peer(*peer);
        }
        builder
    }
}

/// Parses `host:port`, resolving the host name.
pub fn parse_peer(text: &str) -> Result<SocketAddr, String> {
    let mut addrs = text
        .to_socket_addrs()
        .map_err(|e| format!("{text:?} is not host:port ({e})"))?;
    addrs
        .find(SocketAddr::is_ipv4)
        .ok_or_else(|| format!("{text:?} has no IPv4 address"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peers_parse_with_and_without_names() {
        assert_eq!(parse_peer("127.0.0.1:7777").unwrap().port(), 7777);
        assert_eq!(parse_peer("localhost:7").unwrap().port(), 7);
        assert!(parse_peer("nonsense").is_err());
        assert!(parse_peer("1.2.3.4").is_err());
    }
}

//! Options every tool takes, flattened into each command.

use std::net::{Ipv4Addr, SocketAddr, ToSocketAddrs};
use std::time::Duration;

use pulicast::{KeyArg, Node, NodeBuilder};

/// Where the fleet is: port, interface, namespace and seed peers.
#[derive(clap::Args, Debug, Clone)]
pub struct NetArgs {
    /// UDP port of the fleet.
    #[arg(long, global = true, default_value_t = pulicast::DEFAULT_PORT)]
    pub port: u16,
    /// Interface to join and send on, plus loopback (default at TTL 0: send
    /// on loopback, join on loopback and the routes' interface).
    /// 127.0.0.1 keeps even joins on this host.
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
    /// A pre-shared key of a namespace's channels: NAMESPACE=KEY, the key
    /// as 64 hex digits or as @FILE holding them; `/` is the whole fleet,
    /// discovery included. May be repeated. PULICAST_KEYS takes the same
    /// list and, like @FILE, keeps keys out of the process list.
    #[arg(long = "key", global = true, value_name = "NAMESPACE=KEY")]
    pub keys: Vec<KeyArg>,
    /// Encrypt the payloads of channels with a key, not only authenticate
    /// them (also PULICAST_ENCRYPT=1).
    #[arg(long, global = true)]
    pub encrypt: bool,
    /// The configuration to run in (`alice`, a simulation run): nearest
    /// providers are searched in it first, then among those of none. Also
    /// PULICAST_CONFIG; none by default.
    #[arg(long, global = true)]
    pub config: Option<String>,
}

impl NetArgs {
    /// A node builder for a tool called `name`; fails on a bad `--key`.
    pub fn node(&self, name: &str) -> pulicast::Result<NodeBuilder> {
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
        if let Some(config) = &self.config {
            builder = builder.config(config.clone());
        }
        for arg in &self.keys {
            let (namespace, key) = arg.parse().map_err(|e| pulicast::Error::InvalidConfig {
                setting: "--key",
                reason: e.to_string(),
            })?;
            builder = builder.key(namespace, key);
        }
        Ok(builder.encrypt(self.encrypt))
    }
}

/// A duration given in seconds on the command line.
pub fn seconds(flag: &str, secs: f64) -> anyhow::Result<Duration> {
    if !(0.0..=86_400.0).contains(&secs) {
        anyhow::bail!("{flag} must be between 0 and 86400 seconds");
    }
    Ok(Duration::from_secs_f64(secs))
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

    #[test]
    fn keys_parse_one_at_a_time_without_echoing_key_material() {
        let net = |key: String| {
            let cli = <Cli as clap::Parser>::try_parse_from(["t", "--key", &key]).unwrap();
            assert!(!format!("{:?}", cli.net).contains("abab"));
            cli.net.node("t").map(|_| ())
        };
        assert!(net(format!("rover1={}", "ab".repeat(32))).is_ok());
        assert!(net(format!("a={0},b={0}", "ab".repeat(32))).is_err());
        let short = "cd".repeat(31);
        let err = net(format!("rover1={short}")).unwrap_err().to_string();
        assert!(!err.contains(&short) && err.contains("rover1") && err.contains("--key"));
    }

    #[derive(clap::Parser)]
    struct Cli {
        #[command(flatten)]
        net: NetArgs,
    }
}

//! The bridge's settings: its command line, and the Zenoh configuration
//! made of it.

use std::net::{Ipv4Addr, SocketAddr};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, Context, Result};

use crate::filter::{Filter, Limit, Pattern};
use crate::keys::KeyMap;

/// How the bridge joins Zenoh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Mode {
    /// A Zenoh peer: connects to and accepts other bridges directly.
    #[default]
    Peer,
    /// A client of a Zenoh router (`--connect` names the router).
    Client,
}

/// Everything `puli-bridge` is told on its command line.
#[derive(Debug, Clone, clap::Parser)]
#[command(
    name = "puli-bridge",
    version,
    about = "Carries a pulicast fleet's channels and discovery between sites over Zenoh"
)]
pub struct Options {
    /// Zenoh key prefix of this fleet: channel `rover1/pose` is the key
    /// `PREFIX/rover1/pose`, so several fleets share one Zenoh network.
    #[arg(long, default_value = "pulicast")]
    pub prefix: String,
    /// This site's name, shown with its members on other sites (default:
    /// the host name).
    #[arg(long)]
    pub site: Option<String>,
    /// The bridge's node name on its site.
    #[arg(long, default_value = "puli-bridge")]
    pub name: String,
    /// Zenoh peer, or client of a router.
    #[arg(long, value_enum, default_value_t = Mode::Peer)]
    pub mode: Mode,
    /// Zenoh endpoints to connect to (`tcp/10.0.0.2:7447`), repeatable.
    #[arg(long)]
    pub connect: Vec<String>,
    /// Zenoh endpoints to listen on (`tcp/0.0.0.0:7447`), repeatable.
    #[arg(long)]
    pub listen: Vec<String>,
    /// This bridge's TLS certificate (PEM) for `tls/` and `quic/` links: it
    /// shows it when it listens, and when it connects with `--mtls`. The
    /// TLS options apply to `tls/` and `quic/` endpoints only.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The private key (PEM) of `--tls-cert`.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// The certificate authority (PEM) this bridge trusts: when it connects,
    /// the listener's certificate must be signed by it or by one of the
    /// public web roots Zenoh also trusts (and name the address); with
    /// `--mtls`, a listener takes only peers whose certificate it signed.
    #[arg(long, value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,
    /// Mutual TLS: a bridge that listens accepts only peers whose
    /// certificate `--tls-ca` signed, and one that connects shows its own.
    /// Every `--listen` endpoint must then be `tls/` or `quic/`.
    #[arg(long, requires = "tls_ca", requires = "tls_cert")]
    pub mtls: bool,
    /// Find Zenoh peers by multicast scouting too (off: the point of a
    /// bridge is links where multicast does not pass).
    #[arg(long)]
    pub scout: bool,
    /// Zenoh link lease: a link silent this long is closed, and the sites
    /// behind it fail here.
    #[arg(long, default_value = "3s", value_parser = humantime::parse_duration)]
    pub lease: Duration,
    /// A Zenoh configuration file (JSON5) to start from; the options above
    /// override what they name.
    #[arg(long)]
    pub zenoh_config: Option<PathBuf>,
    /// The pulicast port of this site.
    #[arg(long, default_value_t = pulicast::DEFAULT_PORT)]
    pub port: u16,
    /// Multicast TTL on this site: 0 keeps it on this host, 1 reaches the
    /// site's link.
    #[arg(long, default_value_t = 0)]
    pub ttl: u32,
    /// The interface to use for multicast on this site.
    #[arg(long)]
    pub interface: Option<Ipv4Addr>,
    /// Seed peers of this site's discovery (`host:port`), repeatable.
    #[arg(long)]
    pub peer: Vec<SocketAddr>,
    /// A pre-shared key of a namespace, as for any node: NAMESPACE=KEY
    /// (64 hex digits, or @FILE holding them); `/` is the whole fleet,
    /// discovery included. The bridge opens what the key seals on one site
    /// and seals it again on the other. Repeatable; PULICAST_KEYS takes the
    /// same list and keeps keys out of the process list.
    #[arg(long = "key", value_name = "NAMESPACE=KEY")]
    pub keys: Vec<pulicast::KeyArg>,
    /// Encrypt the payloads of sealed channels, not only authenticate them
    /// (also PULICAST_ENCRYPT=1).
    #[arg(long)]
    pub encrypt: bool,
    /// Channels that go out: glob (`rover1/**`) or `re:REGEX`; none: all.
    #[arg(long)]
    pub allow_out: Vec<String>,
    /// Channels that never go out.
    #[arg(long)]
    pub deny_out: Vec<String>,
    /// Channels that come in; none: all.
    #[arg(long)]
    pub allow_in: Vec<String>,
    /// Channels that never come in.
    #[arg(long)]
    pub deny_in: Vec<String>,
    /// A rate limit and priority for the channels matching a pattern, both
    /// ways: `PATTERN=RATE[,priority=NAME]` (RATE in messages a second; the
    /// first limit that matches applies), repeatable.
    #[arg(long)]
    pub limit: Vec<String>,
    /// The most channels exported at once; past it, channels that carry
    /// messages keep their slots and those that carry none give way.
    #[arg(long, default_value_t = 4096)]
    pub max_exports: usize,
    /// The most channels imported at once (as `--max-exports`). Channels
    /// that no other site lists a publisher of (a plain Zenoh application
    /// may publish them) take only places left free, a quarter at most.
    #[arg(long, default_value_t = 4096)]
    pub max_imports: usize,
    /// The most distinct channel names imported since the bridge started
    /// (by default twice `--max-imports`), and an eighth of that more for
    /// channels no other site lists a publisher of (as many as may be
    /// imported at once). Past it, names never imported
    /// before are left out until the bridge restarts; names imported
    /// before still come and go. Zenoh keeps about 2 KB for every key a
    /// subscriber was ever declared on (zenoh issues #1518 and #2393), the
    /// node under the bridge a channel for every name it published: this
    /// bounds both.
    #[arg(long)]
    pub max_import_names: Option<usize>,
    /// The most distinct channel names exported since the bridge started
    /// (by default twice `--max-exports`), counted when a name's first
    /// message goes out (its Zenoh publisher is declared then). Past it,
    /// messages on names never exported before are dropped and counted
    /// until the bridge restarts, for the reason `--max-import-names`
    /// gives.
    #[arg(long)]
    pub max_export_names: Option<usize>,
    /// The most channels of one member exported, imported and listed in
    /// this site's table.
    #[arg(long, default_value_t = 1024)]
    pub max_per_member: usize,
    /// The most channels of this site's members the bridge reads at once,
    /// shared among them (each at most `--max-per-member`): what a stranger
    /// announcing thousands of members costs it. By default
    /// `--max-exports` plus `--max-imports`, the most it carries.
    #[arg(long)]
    pub max_channels: Option<usize>,
    /// How often to log the bridge's counters (0: never).
    #[arg(long, default_value = "10s", value_parser = humantime::parse_duration)]
    pub report: Duration,
    /// Something else than bridging.
    #[command(subcommand)]
    pub command: Option<Sub>,
}

/// What `puli-bridge` does instead of bridging.
#[derive(Debug, Clone, clap::Subcommand)]
pub enum Sub {
    /// Measures a channel through two bridges on loopback, next to plain
    /// Zenoh (also `puli bench bridge`).
    Bench(crate::bench::BenchArgs),
    /// A role of the benchmark (started by it).
    #[command(hide = true)]
    BenchRole(crate::bench::RoleArgs),
}

impl Default for Options {
    fn default() -> Self {
        <Options as clap::Parser>::parse_from(["puli-bridge"])
    }
}

/// The options checked and parsed.
#[derive(Debug, Clone)]
pub struct Checked {
    /// The key map.
    pub keys: KeyMap,
    /// Which channels go out.
    pub out: Filter,
    /// Which channels come in.
    pub inn: Filter,
    /// Limits by pattern.
    pub limits: Vec<Limit>,
    /// The site's name.
    pub site: String,
    /// Bounds on exports.
    pub exports: crate::slots::Limits,
    /// Bounds on imports.
    pub imports: crate::slots::Limits,
    /// The most channels of this site's members read at once.
    pub max_channels: usize,
    /// The most distinct names given a Zenoh publisher since the start.
    pub max_export_names: usize,
}

impl Options {
    /// Checks the options: the prefix, the patterns and the limits.
    pub fn check(&self) -> Result<Checked> {
        let keys =
            KeyMap::new(&self.prefix).map_err(|e| anyhow!("--prefix {:?}: {e}", self.prefix))?;
        let patterns = |texts: &[String]| -> Result<Vec<Pattern>> {
            texts
                .iter()
                .map(|t| Pattern::parse(t).map_err(|e| anyhow!(e)))
                .collect()
        };
        let limits = self
            .limit
            .iter()
            .map(|t| Limit::parse(t).map_err(|e| anyhow!("--limit: {e}")))
            .collect::<Result<Vec<_>>>()?;
        for key in &self.keys {
            key.parse().map_err(|e| anyhow!("--key: {e}"))?;
        }
        if self.lease < Duration::from_millis(100) {
            return Err(anyhow!("--lease must be at least 100ms"));
        }
        self.check_tls()?;
        let site = self.site.clone().unwrap_or_else(|| {
            std::env::var("HOSTNAME")
                .ok()
                .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
                .map(|h| h.trim().to_owned())
                .filter(|h| !h.is_empty())
                .unwrap_or_else(|| "site".to_owned())
        });
        Ok(Checked {
            keys,
            out: Filter {
                allow: patterns(&self.allow_out)?,
                deny: patterns(&self.deny_out)?,
            },
            inn: Filter {
                allow: patterns(&self.allow_in)?,
                deny: patterns(&self.deny_in)?,
            },
            limits,
            site,
            exports: crate::slots::Limits {
                total: self.max_exports,
                per_member: self.max_per_member,
                ..Default::default()
            },
            imports: crate::slots::Limits {
                total: self.max_imports,
                per_member: self.max_per_member,
                unlisted: self.max_imports / 4,
                names: {
                    let names = self
                        .max_import_names
                        .unwrap_or(self.max_imports.saturating_mul(2));
                    [names, names / 8]
                },
                ..Default::default()
            },
            max_export_names: self
                .max_export_names
                .unwrap_or(self.max_exports.saturating_mul(2)),
            max_channels: self
                .max_channels
                .unwrap_or(self.max_exports.saturating_add(self.max_imports)),
        })
    }

    /// The TLS options make sense with the endpoints: they must apply to
    /// one, and with `--mtls` no listener may let peers in without a
    /// certificate.
    fn check_tls(&self) -> Result<()> {
        let encrypted = |e: &String| e.starts_with("tls/") || e.starts_with("quic/");
        let tls_options = self.tls_cert.is_some() || self.tls_ca.is_some() || self.mtls;
        let any_encrypted = self.listen.iter().chain(&self.connect).any(encrypted);
        if tls_options && !any_encrypted && self.zenoh_config.is_none() {
            return Err(anyhow!(
                "the TLS options apply to tls/ and quic/ endpoints only, and none is given"
            ));
        }
        if let Some(plain) = self.listen.iter().find(|e| self.mtls && !encrypted(e)) {
            return Err(anyhow!(
                "--mtls with --listen {plain}: peers without a certificate would get in there; listen on tls/ or quic/ only"
            ));
        }
        Ok(())
    }

    /// The Zenoh configuration.
    pub fn zenoh_config(&self) -> Result<zenoh::Config> {
        let mut config = match &self.zenoh_config {
            Some(path) => zenoh::Config::from_file(path)
                .map_err(|e| anyhow!("{e}"))
                .with_context(|| format!("--zenoh-config {}", path.display()))?,
            None => zenoh::Config::default(),
        };
        let mut set = |key: &str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| anyhow!("zenoh configuration {key} = {value}: {e}"))
        };
        let mode = match self.mode {
            Mode::Peer => "peer",
            Mode::Client => "client",
        };
        set("mode", format!("{mode:?}"))?;
        if !self.connect.is_empty() {
            set("connect/endpoints", serde_json::to_string(&self.connect)?)?;
        }
        // Without --listen (and no configuration file saying otherwise) a
        // bridge listens nowhere: Zenoh's peers would listen on every
        // interface by default, a way in that nobody asked for.
        if !self.listen.is_empty() || self.zenoh_config.is_none() {
            set("listen/endpoints", serde_json::to_string(&self.listen)?)?;
        }
        set("scouting/multicast/enabled", self.scout.to_string())?;
        let path = |p: &PathBuf| -> Result<String> {
            // Zenoh reads the files when a link opens; a missing one is
            // better said now.
            std::fs::metadata(p).with_context(|| format!("TLS file {}", p.display()))?;
            Ok(serde_json::to_string(&p.display().to_string())?)
        };
        if let (Some(cert), Some(key)) = (&self.tls_cert, &self.tls_key) {
            set("transport/link/tls/listen_certificate", path(cert)?)?;
            set("transport/link/tls/listen_private_key", path(key)?)?;
            if self.mtls {
                set("transport/link/tls/connect_certificate", path(cert)?)?;
                set("transport/link/tls/connect_private_key", path(key)?)?;
            }
        }
        if let Some(ca) = &self.tls_ca {
            set("transport/link/tls/root_ca_certificate", path(ca)?)?;
        }
        if self.mtls {
            set("transport/link/tls/enable_mtls", "true".into())?;
        }
        set(
            "transport/link/tx/lease",
            self.lease.as_millis().to_string(),
        )?;
        Ok(config)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[test]
    fn options_make_a_zenoh_configuration_and_bad_ones_are_refused() {
        let opts = Options::parse_from([
            "puli-bridge",
            "--connect",
            "tcp/127.0.0.1:7447",
            "--listen",
            "tcp/127.0.0.1:0",
            "--lease",
            "2s",
            "--allow-out",
            "rover1/**",
            "--limit",
            "rover1/camera/**=5",
        ]);
        let checked = opts.check().unwrap();
        assert!(checked.out.passes("rover1/pose"));
        assert!(!checked.out.passes("rover2/pose"));
        assert!(checked.inn.passes("rover2/pose"));
        let config = opts.zenoh_config().unwrap();
        let text = format!("{config}");
        assert!(text.contains("7447"), "{text}");
        assert!(text.contains("2000"), "{text}");
        for bad in [
            vec!["--prefix", "a/*"],
            vec!["--allow-in", "re:("],
            vec!["--limit", "x=fast"],
            vec!["--lease", "1ms"],
        ] {
            let opts = Options::parse_from(std::iter::once("puli-bridge").chain(bad.clone()));
            assert!(opts.check().is_err(), "{bad:?}");
        }
        let opts = Options::parse_from(["puli-bridge", "--connect", "nonsense"]);
        assert!(opts.zenoh_config().is_err());
        // Without --listen, nothing listens (not Zenoh's default).
        let opts = Options::parse_from(["puli-bridge", "--connect", "tcp/127.0.0.1:7447"]);
        let config = opts.zenoh_config().unwrap();
        let listen = config.get_json("listen/endpoints").unwrap();
        assert!(!listen.contains('/'), "no endpoint: {listen}");
        let default = zenoh::Config::default()
            .get_json("listen/endpoints")
            .unwrap();
        assert!(
            default.contains("tcp/"),
            "Zenoh's default listens: {default}"
        );
    }

    #[test]
    fn tls_options_must_meet_an_encrypted_endpoint_and_mtls_listens_on_nothing_plain() {
        let check = |args: &[&str]| {
            Options::parse_from(std::iter::once("puli-bridge").chain(args.iter().copied()))
                .check()
                .map(drop)
        };
        let ca = ["--tls-ca", "ca.pem"];
        assert!(check(&[&ca[..], &["--connect", "tcp/10.0.0.2:7447"]].concat()).is_err());
        assert!(check(&[&ca[..], &["--connect", "tls/10.0.0.2:7447"]].concat()).is_ok());
        assert!(check(&[&ca[..], &["--connect", "quic/10.0.0.2:7447"]].concat()).is_ok());
        let mtls = [
            "--tls-ca",
            "ca.pem",
            "--tls-cert",
            "a.pem",
            "--tls-key",
            "a.key",
            "--mtls",
        ];
        assert!(check(&[&mtls[..], &["--listen", "tls/0.0.0.0:7447"]].concat()).is_ok());
        let both = [
            "--listen",
            "tls/0.0.0.0:7447",
            "--listen",
            "tcp/0.0.0.0:7448",
        ];
        assert!(check(&[&mtls[..], &both[..]].concat()).is_err());
    }
}

//! A pulicast node driven from the command line, for tests that need one in a
//! separate process. It mirrors `tests/python/peer.py`, so the same test can
//! run against either implementation.
//!
//! ```text
//! pulicast-test-peer publish   --port P --name N --channel CH --kind K --value V [--count N] [--period S] [--linger S]
//! pulicast-test-peer subscribe --port P --name N --channel CH --kind K [--count N] [--timeout S] [--ordered]
//! pulicast-test-peer nodes     --port P --name N [--for S]
//! pulicast-test-peer watch     --port P --name N [--for S] [--publish CH]
//! pulicast-test-peer tally     --port P --name N --channel CH [--for S]
//! ```
//!
//! Every command also takes `--interface IP` (default 127.0.0.1; 0.0.0.0 for
//! the node's own default, only inside a test's network namespace), `--ttl N`,
//! `--discovery-port P` and `--peer IP:PORT` (repeatable). `watch` prints one
//! JSON object per discovery event (`t_ms` since start, `event`, `name`, `key`)
//! and, at the end, `{"members": [...]}` with the live members' names.
//!
//! Kinds: str, int (i64), float (f64), bool, bytes (hex). Every command writes
//! `READY {json}` to stderr once its node (and subscription) is up. `subscribe`
//! prints one JSON object per message: `value`, `lead`, `seq`, `source`.
//! `tally` subscribes to i64 messages twice, plainly and ordered, for a
//! while, then prints one object: `plain` and `ordered` as `[seq, lead,
//! value]` triples, the node's drop counters (`dropped`) and `rss_kb`.

use std::net::Ipv4Addr;
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand, ValueEnum};
use pulicast::{Node, Subscription};
use serde_json::{json, Value};

#[derive(Parser)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Args)]
struct Common {
    #[arg(long)]
    port: u16,
    #[arg(long)]
    name: String,
    #[arg(long, default_value_t = 0.1)]
    heartbeat: f64,
    #[arg(long, default_value_t = Ipv4Addr::LOCALHOST)]
    interface: Ipv4Addr,
    #[arg(long, default_value_t = 0)]
    ttl: u32,
    #[arg(long, default_value_t = 0)]
    discovery_port: u16,
    /// A seed peer, `host:port`.
    #[arg(long, value_parser = parse_peer)]
    peer: Vec<std::net::SocketAddr>,
    /// Keys, `NAMESPACE=HEX` (as in PULICAST_KEYS).
    #[arg(long)]
    key: Vec<String>,
    /// Encrypt sealed channels.
    #[arg(long)]
    encrypt: bool,
}

fn parse_peer(text: &str) -> Result<std::net::SocketAddr, String> {
    use std::net::ToSocketAddrs;
    text.to_socket_addrs()
        .map_err(|e| format!("{text}: {e}"))?
        .find(std::net::SocketAddr::is_ipv4)
        .ok_or_else(|| format!("{text}: no IPv4 address"))
}

#[derive(Clone, Copy, ValueEnum)]
enum Kind {
    Str,
    Int,
    Float,
    Bool,
    Bytes,
}

#[derive(Subcommand)]
enum Command {
    Publish {
        #[command(flatten)]
        common: Common,
        #[arg(long)]
        channel: String,
        #[arg(long, value_enum)]
        kind: Kind,
        /// `{i}` is replaced by the message index.
        #[arg(long)]
        value: String,
        #[arg(long, default_value_t = 1)]
        count: u32,
        #[arg(long, default_value_t = 0.05)]
        period: f64,
        #[arg(long, default_value_t = 0.0)]
        delay: f64,
        #[arg(long, default_value_t = 0.0)]
        linger: f64,
        /// Count failed publishes and go on, instead of stopping at the first.
        #[arg(long)]
        keep_going: bool,
    },
    Subscribe {
        #[command(flatten)]
        common: Common,
        #[arg(long)]
        channel: String,
        #[arg(long, value_enum)]
        kind: Kind,
        #[arg(long, default_value_t = 1)]
        count: u32,
        #[arg(long, default_value_t = 10.0)]
        timeout: f64,
        #[arg(long)]
        ordered: bool,
    },
    Nodes {
        #[command(flatten)]
        common: Common,
        #[arg(long = "for", default_value_t = 1.0)]
        for_secs: f64,
    },
    Tally {
        #[command(flatten)]
        common: Common,
        #[arg(long)]
        channel: String,
        #[arg(long = "for", default_value_t = 1.0)]
        for_secs: f64,
    },
    Watch {
        #[command(flatten)]
        common: Common,
        #[arg(long = "for", default_value_t = 1.0)]
        for_secs: f64,
        /// Publish an i64 on this channel every 100 ms while watching.
        #[arg(long)]
        publish: Option<String>,
    },
}

async fn start(common: &Common) -> pulicast::Result<Node> {
    let mut builder = Node::new(&common.name).port(common.port);
    // 0.0.0.0: the node's default (no interface given).
    if !common.interface.is_unspecified() {
        builder = builder.interface(common.interface);
    }
    let mut builder = builder
        .ttl(common.ttl)
        .discovery_port(common.discovery_port)
        .heartbeat_period(Duration::from_secs_f64(common.heartbeat));
    for peer in &common.peer {
        builder = builder.peer(*peer);
    }
    for text in &common.key {
        let keys = pulicast_proto::secure::parse_keys(text).map_err(|e| {
            pulicast::Error::InvalidConfig {
                setting: "--key",
                reason: e.to_string(),
            }
        })?;
        for (namespace, key) in keys {
            builder = builder.key(namespace, key);
        }
    }
    let node = builder.encrypt(common.encrypt).start().await?;
    Ok(node)
}

fn ready(node: &Node, cmd: &str) {
    eprintln!(
        "READY {}",
        json!({"cmd": cmd, "name": node.name(), "session_id": node.compat_session_id()})
    );
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Result<Vec<u8>, String> {
    if s.len() % 2 != 0 {
        return Err(format!("odd-length hex {s:?}"));
    }
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).map_err(|e| format!("hex {s:?}: {e}")))
        .collect()
}

async fn publish(node: &Node, channel: &str, kind: Kind, text: &str) -> Result<(), String> {
    let ch = node.channel(channel);
    let sent = match kind {
        Kind::Str => ch.publish(text),
        Kind::Int => ch.publish(&text.parse::<i64>().map_err(|e| e.to_string())?),
        Kind::Float => ch.publish(&text.parse::<f64>().map_err(|e| e.to_string())?),
        Kind::Bool => ch.publish(&text.parse::<bool>().map_err(|e| e.to_string())?),
        Kind::Bytes => ch.publish_bytes(&unhex(text)?),
    };
    sent.map_err(|e| e.to_string())
}

async fn next_json<T>(sub: &mut Subscription<T>, to_json: impl Fn(T) -> Value) -> Option<Value> {
    let m = sub.recv().await?;
    Some(
        json!({"value": to_json(m.value), "lead": m.lead, "seq": m.seq, "source": m.source.to_string()}),
    )
}

async fn subscribe(
    node: &Node,
    channel: &str,
    kind: Kind,
    ordered: bool,
    count: u32,
) -> Result<(), String> {
    macro_rules! run {
        ($ty:ty, $to_json:expr) => {{
            let ch = node.channel(channel);
            let mut sub: Subscription<$ty> = if ordered {
                ch.subscribe_ordered()
            } else {
                ch.subscribe()
            }
            .map_err(|e| e.to_string())?;
            ready(node, "subscribe");
            for _ in 0..count {
                let Some(line) = next_json(&mut sub, $to_json).await else {
                    break;
                };
                println!("{line}");
            }
        }};
    }
    match kind {
        Kind::Str => run!(String, |v| json!(v)),
        Kind::Int => run!(i64, |v| json!(v)),
        Kind::Float => run!(f64, |v| json!(v)),
        Kind::Bool => run!(bool, |v| json!(v)),
        Kind::Bytes => {
            let mut sub = node
                .channel(channel)
                .subscribe_raw()
                .map_err(|e| e.to_string())?;
            ready(node, "subscribe");
            for _ in 0..count {
                let Some(line) = next_json(&mut sub, |v| json!(hex(&v))).await else {
                    break;
                };
                println!("{line}");
            }
        }
    }
    Ok(())
}

async fn run(cli: Cli) -> Result<(), String> {
    match cli.command {
        Command::Publish {
            common,
            channel,
            kind,
            value,
            count,
            period,
            delay,
            linger,
            keep_going,
        } => {
            let node = start(&common).await.map_err(|e| e.to_string())?;
            ready(&node, "publish");
            tokio::time::sleep(Duration::from_secs_f64(delay)).await;
            let mut failed = 0u32;
            for i in 0..count {
                let sent =
                    publish(&node, &channel, kind, &value.replace("{i}", &i.to_string())).await;
                match sent {
                    Err(_) if keep_going => failed += 1,
                    other => other?,
                }
                tokio::time::sleep(Duration::from_secs_f64(period)).await;
            }
            println!(
                "{}",
                json!({"published": count, "failed": failed, "session_id": node.compat_session_id()})
            );
            tokio::time::sleep(Duration::from_secs_f64(linger)).await;
        }
        Command::Subscribe {
            common,
            channel,
            kind,
            count,
            timeout,
            ordered,
        } => {
            let node = start(&common).await.map_err(|e| e.to_string())?;
            let within = Duration::from_secs_f64(timeout);
            tokio::time::timeout(within, subscribe(&node, &channel, kind, ordered, count))
                .await
                .map_err(|_| format!("timeout: fewer than {count} messages"))??;
        }
        Command::Nodes { common, for_secs } => {
            let node = start(&common).await.map_err(|e| e.to_string())?;
            ready(&node, "nodes");
            tokio::time::sleep(Duration::from_secs_f64(for_secs)).await;
            let nodes: Vec<Value> = node
                .peers()
                .iter()
                .map(|p| {
                    json!({
                        "name": p.name,
                        "session_id": p.session_id,
                        "source": p.address.to_string(),
                        "publishes": p.publishes().collect::<Vec<_>>(),
                        "subscribes": p.subscribes().collect::<Vec<_>>(),
                    })
                })
                .collect();
            println!("{}", Value::Array(nodes));
        }
        Command::Tally {
            common,
            channel,
            for_secs,
        } => {
            let node = start(&common).await.map_err(|e| e.to_string())?;
            let ch = node.channel(&channel);
            let mut plain = ch.subscribe::<i64>().map_err(|e| e.to_string())?;
            let mut ordered = ch.subscribe_ordered::<i64>().map_err(|e| e.to_string())?;
            ready(&node, "tally");
            let until = tokio::time::Instant::now() + Duration::from_secs_f64(for_secs);
            let (mut got_plain, mut got_ordered) = (Vec::new(), Vec::new());
            loop {
                tokio::select! {
                    _ = tokio::time::sleep_until(until) => break,
                    Some(m) = plain.recv() => got_plain.push(json!([m.seq, m.lead, m.value])),
                    Some(m) = ordered.recv() => got_ordered.push(json!([m.seq, m.lead, m.value])),
                }
            }
            let rss_kb = std::fs::read_to_string("/proc/self/status")
                .ok()
                .and_then(|s| {
                    let line = s.lines().find(|l| l.starts_with("VmRSS:"))?.to_string();
                    line.split_whitespace().nth(1)?.parse::<u64>().ok()
                })
                .unwrap_or(0);
            println!(
                "{}",
                json!({
                    "plain": got_plain,
                    "ordered": got_ordered,
                    "dropped": node.stats().dropped_total(),
                    "rss_kb": rss_kb,
                })
            );
        }
        Command::Watch {
            common,
            for_secs,
            publish,
        } => {
            let node = start(&common).await.map_err(|e| e.to_string())?;
            let mut events = node.discovery().events();
            ready(&node, "watch");
            let started = std::time::Instant::now();
            let until = tokio::time::Instant::now() + Duration::from_secs_f64(for_secs);
            let mut tick = tokio::time::interval(Duration::from_millis(100));
            let mut count = 0i64;
            loop {
                tokio::select! {
                    _ = tokio::time::sleep_until(until) => break,
                    _ = tick.tick() => {
                        if let Some(channel) = &publish {
                            node.channel(channel).publish(&count).map_err(|e| e.to_string())?;
                            count += 1;
                        }
                    }
                    event = events.recv() => {
                        let Some(event) = event else { break };
                        println!("{}", event_json(started.elapsed(), &event));
                    }
                }
            }
            let mut members: Vec<String> = node
                .discovery()
                .live_members()
                .into_iter()
                .map(|m| m.name)
                .collect();
            members.sort();
            // Events up to (and just after) the snapshot, so that a member
            // missing from it shows why.
            tokio::time::sleep(Duration::from_millis(50)).await;
            while let Some(event) = events.try_recv() {
                println!("{}", event_json(started.elapsed(), &event));
            }
            println!("{}", json!({ "members": members }));
        }
    }
    Ok(())
}

fn event_json(elapsed: Duration, event: &pulicast::DiscoveryEvent) -> Value {
    use pulicast::DiscoveryEvent as E;
    let t_ms = elapsed.as_secs_f64() * 1000.0;
    let (kind, key, name, extra) = match event {
        E::Joined(m) => ("joined", m.key, m.name.clone(), json!(m.compat)),
        E::Left { key, name } => ("left", *key, name.clone(), Value::Null),
        E::Failed { key, name } => ("failed", *key, name.clone(), Value::Null),
        E::Suspected { key, name } => ("suspected", *key, name.clone(), Value::Null),
        E::Recovered { key, name } => ("recovered", *key, name.clone(), Value::Null),
        E::ChannelAppeared {
            key,
            member,
            channel,
        } => (
            "channel_appeared",
            *key,
            member.clone(),
            json!(channel.name),
        ),
        E::ChannelDisappeared {
            key,
            member,
            channel,
        } => (
            "channel_disappeared",
            *key,
            member.clone(),
            json!(channel.name),
        ),
        E::Suspicious { key, what } => ("suspicious", *key, String::new(), json!(what)),
        _ => ("other", 0, String::new(), Value::Null),
    };
    json!({"t_ms": t_ms, "event": kind, "key": key, "name": name, "detail": extra})
}

#[tokio::main(flavor = "current_thread")]
async fn main() -> ExitCode {
    // Warnings and up to stderr, where tests read them (RUST_LOG overrides).
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(false)
        .init();
    match run(Cli::parse()).await {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("pulicast-test-peer: {e}");
            ExitCode::FAILURE
        }
    }
}

//! `puli-sniffer`: see the fleet. Observes, never publishes data (the
//! dashboard's settings view pokes settings: a read that changes nothing).
//!
//! ```text
//! puli-sniffer                      (the live dashboard)
//! puli-sniffer nodes [--for SECS] [--json]
//! puli-sniffer channels [--for SECS] [--json] [--all]
//! puli-sniffer echo CHANNEL [--count N] [--for SECS] [--json]
//! puli-sniffer hz CHANNEL [--for SECS]
//! puli-sniffer bw [CHANNEL] [--for SECS]
//! ```

use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Result;
use clap::{Parser, Subcommand};
use pulicast::resolve_name;
use pulicast_tools::flags::NetArgs;
use pulicast_tools::sniff::{self, ChannelWatch};
use serde_json::Value;

/// How long `echo` and `hz` listen for a publisher before saying that none
/// is known (what arrives meanwhile is kept).
const PUBLISHER_WAIT: Duration = Duration::from_secs(2);

/// How much longer `echo` listens for the type a publisher announces, when
/// the publisher was heard before its type.
const TYPE_WAIT: Duration = Duration::from_secs(1);

#[derive(Parser)]
#[command(
    name = "puli-sniffer",
    version,
    about = "See a pulicast fleet: its nodes, channels, messages, rates and bandwidth",
    long_about = "See a pulicast fleet: its nodes, channels, messages (decoded to text), rates, \
                  bandwidth and settings. Observes only: it announces itself like any node and \
                  publishes no data; the dashboard's settings view pokes settings (a read \
                  request that changes nothing) to learn their values."
)]
struct Cli {
    #[command(flatten)]
    net: NetArgs,
    /// Without a command: the live dashboard (plain tables every second when
    /// stdout is not a terminal).
    #[command(subcommand)]
    command: Option<Command>,
    /// With the dashboard: quit after this many seconds.
    #[arg(long = "for")]
    for_secs: Option<f64>,
}

#[derive(Subcommand)]
enum Command {
    /// The nodes discovery saw: name, session, host, state, channels.
    Nodes {
        /// How long to listen before printing.
        #[arg(long = "for", default_value_t = 1.0)]
        for_secs: f64,
        /// One JSON array instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// The channels: publishers, subscribers, type, rate, bandwidth, loss.
    Channels {
        /// How long to listen (and measure rates) before printing.
        #[arg(long = "for", default_value_t = 2.0)]
        for_secs: f64,
        /// One JSON array instead of a table.
        #[arg(long)]
        json: bool,
        /// Hidden channels too (settings' `.config/...`, any part starting
        /// with `.`), which are left out otherwise, as in Pulicast 2.x.
        #[arg(long)]
        all: bool,
    },
    /// The services: who serves and who calls each, with the request,
    /// reply and progress types.
    Services {
        /// How long to listen before printing.
        #[arg(long = "for", default_value_t = 1.0)]
        for_secs: f64,
        /// One JSON array instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Print the messages of one channel, decoded to text.
    Echo {
        /// Channel name (relative to --namespace, or absolute with a leading /).
        channel: String,
        /// Stop after this many messages.
        #[arg(long)]
        count: Option<u64>,
        /// Stop after this many seconds.
        #[arg(long = "for")]
        for_secs: Option<f64>,
        /// One JSON object per line.
        #[arg(long)]
        json: bool,
    },
    /// Message rate of one channel: mean, min/max interval, jitter.
    Hz {
        /// Channel name.
        channel: String,
        /// Stop after this many seconds (default: run until interrupted).
        #[arg(long = "for")]
        for_secs: Option<f64>,
    },
    /// Print a shell completion script (bash, zsh, fish, elvish, powershell).
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
    /// Bandwidth of one channel, or of all (discovery included).
    Bw {
        /// Channel name; all channels when left out.
        channel: Option<String>,
        /// Stop after this many seconds (default: run until interrupted).
        #[arg(long = "for")]
        for_secs: Option<f64>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("puli-sniffer: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(cli)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("puli-sniffer: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn secs(s: f64) -> Result<Duration> {
    pulicast_tools::flags::seconds("--for", s)
}

async fn run(cli: Cli) -> Result<()> {
    if let Some(Command::Completions { shell }) = cli.command {
        let mut command = <Cli as clap::CommandFactory>::command();
        clap_complete::generate(shell, &mut command, "puli-sniffer", &mut std::io::stdout());
        return Ok(());
    }
    let node = sniff::start(&cli.net).await?;
    let resolve =
        |channel: &str| -> Result<String> { Ok(resolve_name(channel, &cli.net.namespace)?) };
    let Some(command) = cli.command else {
        pulicast_tools::dashboard::run(&node, cli.net.port, cli.for_secs).await?;
        node.stop();
        return Ok(());
    };
    match command {
        Command::Nodes { for_secs, json } => {
            tokio::time::sleep(secs(for_secs)?).await;
            let mut members = node.discovery().members();
            members.sort_by(|a, b| (&a.name, a.key).cmp(&(&b.name, b.key)));
            if json {
                let all: Vec<Value> = members.iter().map(sniff::node_json).collect();
                pulicast_tools::outln!("{}", Value::Array(all));
            } else {
                pulicast_tools::outln!(
                    "{:<20} {:<20} {:<8} {:<22} {:>4} {:>4}  HOST",
                    "NAME",
                    "SESSION",
                    "STATE",
                    "ADDRESS",
                    "PUB",
                    "SUB"
                );
                for m in &members {
                    let session = m
                        .session
                        .map(|s| s.to_string()[..18].to_string())
                        .unwrap_or_else(|| format!("2.x {:x}", m.key));
                    let state = format!("{:?}", m.state).to_lowercase();
                    let pubs = m.channels.iter().filter(|c| c.publishes).count();
                    let subs = m.channels.iter().filter(|c| c.subscribes).count();
                    let contested = m
                        .contested_by
                        .map(|a| format!("  (session also announced from {a}: one is an impostor)"))
                        .unwrap_or_default();
                    pulicast_tools::outln!(
                        "{:<20} {:<20} {:<8} {:<22} {:>4} {:>4}  {}{}",
                        m.name,
                        session,
                        state,
                        m.address,
                        pubs,
                        subs,
                        m.host,
                        contested
                    );
                }
            }
            for note in sniff::key_notes(&node) {
                eprintln!("{note}");
            }
        }
        Command::Services { for_secs, json } => {
            tokio::time::sleep(secs(for_secs)?).await;
            let services = node.discovery().services();
            if json {
                pulicast_tools::outln!("{}", serde_json::to_value(&services)?);
            } else {
                print_text_table(&sniff::services_table(&services));
            }
        }
        Command::Channels {
            for_secs,
            json,
            all,
        } => {
            let window = secs(for_secs)?;
            let mut watch = ChannelWatch::new(&node);
            let deadline = Instant::now() + window;
            while Instant::now() < deadline {
                watch.watch_announced()?;
                tokio::time::sleep(
                    Duration::from_millis(100)
                        .min(deadline.saturating_duration_since(Instant::now())),
                )
                .await;
            }
            if watch.unwatched() > 0 {
                eprintln!(
                    "note: {} announced channels not measured: a sniffer watches at most {}",
                    watch.unwatched(),
                    sniff::MAX_WATCHED
                );
            }
            let mut rows = sniff::channel_rows(
                &node.discovery().members(),
                &watch.meters(),
                watch.elapsed(),
            );
            if !all {
                rows.retain(|r| !pulicast::is_hidden_channel(&r.name));
            }
            if json {
                pulicast_tools::outln!(
                    "{}",
                    Value::Array(rows.iter().map(sniff::ChannelRow::json).collect())
                );
            } else {
                pulicast_tools::outln!(
                    "{:<32} {:>9} {:>11} {:>6}  {:<16} PUBLISHERS / SUBSCRIBERS",
                    "CHANNEL",
                    "RATE Hz",
                    "BW B/s",
                    "LOSS",
                    "TYPE"
                );
                for r in &rows {
                    pulicast_tools::outln!(
                        "{:<32} {:>9.1} {:>11.0} {:>5.1}%  {:<16} {} / {}",
                        r.name,
                        r.rate_hz,
                        r.bandwidth,
                        r.loss * 100.0,
                        match r.type_conflict {
                            Some(_) => format!("!{}", r.type_name.as_deref().unwrap_or("-")),
                            None => r.type_name.clone().unwrap_or_else(|| "-".into()),
                        },
                        r.publishers.join(","),
                        r.subscribers.join(",")
                    );
                }
                for r in rows.iter().filter(|r| r.type_conflict.is_some()) {
                    eprintln!(
                        "note: members disagree on the type of {} ({}): subscribers of another type drop its messages",
                        r.name,
                        r.type_conflict.as_deref().unwrap_or_default()
                    );
                }
            }
            for note in sniff::key_notes(&node) {
                eprintln!("{note}");
            }
        }
        Command::Echo {
            channel,
            count,
            for_secs,
            json,
        } => {
            let channel = resolve(&channel)?;
            let mut sub = node.channel(&format!("/{channel}")).subscribe_raw()?;
            let deadline = match for_secs {
                Some(s) => Some(tokio::time::Instant::now() + secs(s)?),
                None => None,
            };
            // Give discovery a moment, so the first messages already decode
            // by the type their publisher announces. Nothing is lost while
            // we wait: the subscription queues what arrives.
            // Within `--for`, if it is shorter.
            let within = |wait: Duration| match deadline {
                Some(d) => wait.min(d.saturating_duration_since(tokio::time::Instant::now())),
                None => wait,
            };
            // A publisher may be heard first by its 2.x heartbeat, which
            // has no types, before its gossip: a little longer for its type.
            // Reserved channels (`__nodes`) are every node's and announced
            // by none: nothing to wait for.
            let type_wait = match pulicast_tools::is_internal(&channel) {
                true => Duration::ZERO,
                false => match node
                    .channel(&format!("/{channel}"))
                    .wait_for_publisher(within(PUBLISHER_WAIT))
                    .await
                {
                    Ok(_) => within(TYPE_WAIT),
                    Err(_) => {
                        eprintln!("{}", unknown_channel_note(&node, &channel));
                        Duration::ZERO
                    }
                },
            };
            let mut hint =
                pulicast_tools::poll_for(type_wait, || sniff::announced_type(&node, &channel))
                    .await;
            let mut hint_checked = Instant::now();
            let mut printed = 0u64;
            let stop = pulicast_tools::stop_requested();
            tokio::pin!(stop);
            while count.is_none_or(|n| printed < n) {
                let next = async {
                    match deadline {
                        Some(d) => tokio::time::timeout_at(d, sub.recv()).await.ok().flatten(),
                        None => sub.recv().await,
                    }
                };
                let message = tokio::select! {
                    message = next => message,
                    _ = &mut stop => None,
                };
                let Some(message) = message else { break };
                if hint.is_none() && hint_checked.elapsed() > Duration::from_millis(200) {
                    hint = sniff::announced_type(&node, &channel);
                    hint_checked = Instant::now();
                }
                if json {
                    pulicast_tools::outln!(
                        "{}",
                        sniff::echo_json(&channel, &message, hint.as_ref())
                    );
                } else {
                    pulicast_tools::outln!(
                        "{}",
                        sniff::echo_line(&channel, &message, hint.as_ref())
                    );
                }
                printed += 1;
            }
            if printed == 0 {
                for note in sniff::key_notes(&node) {
                    eprintln!("{note}");
                }
            }
        }
        Command::Hz { channel, for_secs } => {
            let channel = resolve(&channel)?;
            if !pulicast_tools::is_internal(&channel)
                && node
                    .channel(&format!("/{channel}"))
                    .wait_for_publisher(PUBLISHER_WAIT)
                    .await
                    .is_err()
            {
                eprintln!("{}", unknown_channel_note(&node, &channel));
            }
            let mut watch = ChannelWatch::new(&node);
            watch.watch(&channel)?;
            report_loop(for_secs, || {
                let meters = watch.meters();
                let m = meters.get(&channel).cloned().unwrap_or_default();
                let mut lines = vec![hz_line(&channel, &m)];
                // Two publishers interleave: each one's own rate and jitter too.
                let sources = watch.source_meters(&channel);
                if sources.len() > 1 {
                    let members = node.discovery().live_members();
                    for (source, m) in sources {
                        let who = members
                            .iter()
                            .find(|p| p.data_address == Some(source))
                            .map_or_else(String::new, |p| format!(" ({})", p.name));
                        lines.push(hz_line(&format!("  from {source}{who}"), &m));
                    }
                }
                lines.join("\n")
            })
            .await?;
        }
        Command::Completions { .. } => {}
        Command::Bw { channel, for_secs } => {
            let channel = channel.map(|c| resolve(&c)).transpose()?;
            let mut watch = ChannelWatch::new(&node);
            if let Some(c) = &channel {
                watch.watch(c)?;
            }
            let all = channel.is_none();
            if all {
                // Let discovery reveal the channels before measuring starts.
                tokio::time::sleep(Duration::from_millis(300)).await;
                watch.watch_announced()?;
                watch.watch(pulicast_discovery::compat::NODES_CHANNEL)?;
            }
            let discovery_start = node.discovery().stats().map(|s| s.bytes_in).unwrap_or(0);
            let discovery_since = Instant::now();
            report_loop(for_secs, || {
                if all {
                    // Channels appear as discovery reveals them.
                    let _ = watch.watch_announced();
                    let _ = watch.watch(pulicast_discovery::compat::NODES_CHANNEL);
                }
                let window = watch.elapsed();
                let mut lines = Vec::new();
                for (name, m) in watch.meters() {
                    lines.push(format!(
                        "{name}: {:.0} B/s ({} messages, {:.0} B mean)",
                        m.bandwidth(window),
                        m.count,
                        m.bytes as f64 / m.count.max(1) as f64
                    ));
                }
                if all {
                    let gossip =
                        node.discovery().stats().map(|s| s.bytes_in).unwrap_or(0) - discovery_start;
                    lines.push(format!(
                        "{} (gossip): {:.0} B/s",
                        pulicast::DISCOVERY_CHANNEL,
                        gossip as f64 / discovery_since.elapsed().as_secs_f64().max(1e-9)
                    ));
                }
                lines.join("\n")
            })
            .await?;
        }
    }
    node.stop();
    Ok(())
}

/// One line of `hz`: rate and interval statistics of `m`.
fn hz_line(label: &str, m: &sniff::RateMeter) -> String {
    match m.intervals() {
        Some((mean, min, max, sd)) => format!(
            "{label}: {:.2} Hz  interval mean {:.2} ms  min {:.2} ms  max {:.2} ms  jitter (sd) {:.2} ms  n={}  loss {:.1}%",
            1.0 / mean, mean * 1e3, min * 1e3, max * 1e3, sd * 1e3, m.count, m.loss() * 100.0
        ),
        None => format!("{label}: {} messages so far", m.count),
    }
}

/// Says that nobody announces `channel` (yet) and which channels exist.
fn unknown_channel_note(node: &pulicast::Node, channel: &str) -> String {
    let mut known: Vec<String> = node
        .discovery()
        .live_members()
        .into_iter()
        .flat_map(|m| m.channels)
        .filter(|c| c.publishes)
        .map(|c| c.name)
        .collect();
    known.sort();
    known.dedup();
    let list = if known.is_empty() {
        "none".to_string()
    } else {
        known.join(", ")
    };
    format!("note: no member publishes {channel:?} (yet); waiting. Published channels: {list}")
}

/// Prints `report()` every second until `for_secs` passes (or forever), and
/// once more at the end.
async fn report_loop(for_secs: Option<f64>, mut report: impl FnMut() -> String) -> Result<()> {
    let end = match for_secs {
        Some(s) => Some(Instant::now() + secs(s)?),
        None => None,
    };
    // One listener for the whole run: no Ctrl-C falls between waits.
    let ctrl_c = pulicast_tools::stop_requested();
    tokio::pin!(ctrl_c);
    loop {
        let left = end.map(|e| e.saturating_duration_since(Instant::now()));
        let wait = left
            .unwrap_or(Duration::from_secs(1))
            .min(Duration::from_secs(1));
        tokio::select! {
            _ = tokio::time::sleep(wait) => {}
            _ = &mut ctrl_c => break,
        }
        if left.is_some_and(|l| l <= wait) {
            break;
        }
        pulicast_tools::outln!("{}", report());
    }
    pulicast_tools::outln!("{}", report());
    Ok(())
}

/// Prints a table (nothing for none).
fn print_text_table(text: &str) {
    for line in text.lines() {
        pulicast_tools::outln!("{line}");
    }
}

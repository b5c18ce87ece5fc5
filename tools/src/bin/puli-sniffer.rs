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
use pulicast_tools::inspect;
use pulicast_tools::sniff::{self, ChannelWatch};

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
    /// With the dashboard: hidden channels too (settings' `.config/...`,
    /// services' `.services/...`), which are left out otherwise (`h` at
    /// the terminal toggles them).
    #[arg(long)]
    all: bool,
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
    Echo(inspect::EchoArgs),
    /// Message rate of one channel: mean, min/max interval, jitter.
    Hz(inspect::HzArgs),
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
        /// With all channels: hidden ones too (settings', services').
        #[arg(long)]
        all: bool,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let runtime = match tokio::runtime::Runtime::new() {
        Ok(rt) => rt,
        Err(e) => {
            pulicast_tools::errln!("puli-sniffer: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(cli)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            pulicast_tools::errln!("puli-sniffer: {e:#}");
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
        pulicast_tools::dashboard::run(&node, cli.net.port, cli.for_secs, cli.all).await?;
        node.stop();
        return Ok(());
    };
    let namespace = cli.net.namespace.as_str();
    match command {
        Command::Nodes { for_secs, json } => {
            tokio::time::sleep(secs(for_secs)?).await;
            inspect::print_nodes(&node, json, None)?;
        }
        Command::Services { for_secs, json } => {
            tokio::time::sleep(secs(for_secs)?).await;
            inspect::print_services(&node, json)?;
        }
        Command::Channels {
            for_secs,
            json,
            all,
        } => {
            // A zero window would show no measurements: the sniffer always
            // measures, over at least a moment.
            let window = secs(for_secs)?.max(Duration::from_millis(1));
            let stop = pulicast_tools::stop_requested();
            inspect::channels(&node, window, all, json, stop).await?;
        }
        Command::Echo(args) => {
            inspect::echo(&node, namespace, &args, pulicast_tools::stop_requested()).await?;
        }
        Command::Hz(args) => {
            inspect::hz(&node, namespace, &args, pulicast_tools::stop_requested()).await?;
        }
        Command::Completions { .. } => {}
        Command::Bw {
            channel,
            for_secs,
            all: hidden_too,
        } => {
            let channel = channel.map(|c| resolve(&c)).transpose()?;
            let mut watch = ChannelWatch::new(&node);
            if let Some(c) = &channel {
                watch.watch(c)?;
            }
            let all = channel.is_none();
            if all {
                // Let discovery reveal the channels before measuring starts.
                tokio::time::sleep(Duration::from_millis(300)).await;
                watch.watch_announced();
                watch.watch(pulicast::NODES_CHANNEL)?;
            }
            let discovery_start = node.discovery().stats().map(|s| s.bytes_in).unwrap_or(0);
            let discovery_since = Instant::now();
            let stop = pulicast_tools::stop_requested();
            inspect::report_loop(for_secs, stop, || {
                if all {
                    // Channels appear as discovery reveals them.
                    watch.watch_announced();
                    let _ = watch.watch(pulicast::NODES_CHANNEL);
                }
                let window = watch.elapsed();
                let mut lines = Vec::new();
                for (name, m) in watch.meters() {
                    let internal = name == pulicast::NODES_CHANNEL;
                    if all && !hidden_too && !internal && pulicast::is_hidden_channel(&name) {
                        continue;
                    }
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

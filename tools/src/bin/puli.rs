//! `puli`: act on a pulicast fleet from the command line.
//!
//! ```text
//! puli pub CHANNEL VALUE [--type auto|string|int|float|bool|bytes|json] [--rate HZ] [--count N]
//! puli bench discovery --nodes 50 --channels 20
//! ```

use std::process::ExitCode;

use std::time::Duration;

use clap::{Parser, Subcommand};
use pulicast_tools::bench::discovery;
use pulicast_tools::flags::NetArgs;
use pulicast_tools::publish::{self, ValueType};

#[derive(Parser)]
#[command(
    name = "puli",
    version,
    about = "Act on a pulicast fleet: benchmarks, and more to come"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Publish a value on a channel, as a program would.
    ///
    /// Plain values go as the Pulicast 2.x primitive messages (Python peers
    /// read them); with --type json (or when the channel's native type is
    /// announced) the JSON value is encoded into that type.
    Pub(PubArgs),
    /// Measure pulicast against its targets (separate processes on loopback).
    #[command(subcommand)]
    Bench(Bench),
}

#[derive(Subcommand)]
enum Bench {
    /// Discovery: join convergence, graceful leave, crash detection and
    /// steady-state traffic of N nodes with C channels each, compared with
    /// what Pulicast 2.x heartbeats cost for the same fleet.
    Discovery(discovery::Args),
    /// One member of the discovery benchmark (started by `bench discovery`).
    #[command(hide = true)]
    DiscoveryMember(discovery::MemberArgs),
}

#[derive(clap::Args)]
struct PubArgs {
    #[command(flatten)]
    net: NetArgs,
    /// Channel name (relative to --namespace, or absolute with a leading /).
    channel: String,
    /// The value: text, a number, true/false, hex bytes, or JSON.
    #[arg(allow_hyphen_values = true)]
    value: String,
    /// How to read VALUE.
    #[arg(long = "type", value_enum, default_value_t = ValueType::Auto)]
    ty: ValueType,
    /// Publish this many times per second (default: once).
    #[arg(long)]
    rate: Option<f64>,
    /// Publish this many times (default: once, or forever with --rate).
    #[arg(long)]
    count: Option<u64>,
    /// How long to listen to discovery first, to learn the channel's type.
    #[arg(long, default_value_t = 0.5)]
    wait: f64,
}

async fn publish(args: PubArgs) -> anyhow::Result<()> {
    let node = args.net.node("puli-pub").start().await?;
    let channel = node.try_channel(&args.channel)?;
    let (period, count) = publish::plan(args.rate, args.count)?;
    if args.wait > 0.0 {
        // Discovery tells us the channel's type, if anyone announces one.
        let _ = channel
            .wait_for_publisher(Duration::from_secs_f64(args.wait.min(60.0)))
            .await;
        if channel.subscribers().is_empty() && publish::announced(&channel).is_none() {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }
    let announced = publish::announced(&channel);
    let message = publish::outgoing(&args.value, args.ty, announced.as_ref(), channel.name())?;
    let mut sent = 0u64;
    let mut tick = period.map(tokio::time::interval);
    while count.is_none_or(|n| sent < n) {
        if let Some(tick) = tick.as_mut() {
            tokio::select! {
                _ = tick.tick() => {}
                _ = tokio::signal::ctrl_c() => break,
            }
        }
        message.publish(&channel)?;
        sent += 1;
    }
    eprintln!("published {sent} message(s) on {}", channel.name());
    // Let the last datagrams leave before the node (and its socket) goes.
    tokio::time::sleep(Duration::from_millis(20)).await;
    node.stop();
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Pub(args) => tokio::runtime::Runtime::new()
            .map_err(anyhow::Error::from)
            .and_then(|rt| rt.block_on(publish(args))),
        Command::Bench(Bench::Discovery(args)) => discovery::run(&args),
        Command::Bench(Bench::DiscoveryMember(args)) => discovery::member(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("puli: {e:#}");
            ExitCode::FAILURE
        }
    }
}

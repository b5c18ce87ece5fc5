//! `puli-sniffer`: see the fleet. Observes, never publishes data (the
//! dashboard's settings view pokes settings: a read that changes nothing).
//!
//! ```text
//! puli-sniffer                      (the live dashboard)
//! puli-sniffer nodes [NAME] [--for SECS] [--json]
//! puli-sniffer channels [--for SECS] [--json] [--all]
//! puli-sniffer services [--for SECS] [--json]
//! puli-sniffer echo CHANNEL [--count N] [--for SECS] [--json]
//! puli-sniffer hz CHANNEL [--for SECS]
//! puli-sniffer bw [CHANNEL] [--for SECS]
//! ```
//!
//! The commands are [`pulicast_tools::inspect::Inspect`], which `puli shell`
//! takes too.

use std::process::ExitCode;

use anyhow::Result;
use clap::{Parser, Subcommand};
use pulicast_tools::flags::NetArgs;
use pulicast_tools::inspect::{Inspect, Listening};
use pulicast_tools::sniff;

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
    #[command(flatten)]
    Inspect(Inspect),
    /// Print a shell completion script (bash, zsh, fish, elvish, powershell).
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
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

async fn run(cli: Cli) -> Result<()> {
    let command = match cli.command {
        Some(Command::Completions { shell }) => {
            let mut command = <Cli as clap::CommandFactory>::command();
            clap_complete::generate(shell, &mut command, "puli-sniffer", &mut std::io::stdout());
            return Ok(());
        }
        Some(Command::Inspect(command)) => Some(command),
        None => None,
    };
    let node = sniff::start(&cli.net).await?;
    let result = match command {
        None => pulicast_tools::dashboard::run(&node, cli.net.port, cli.for_secs, cli.all).await,
        Some(command) => {
            // As in the shell: a command that runs until stopped ends on a
            // signal as at its end; the others are interrupted at once.
            let interrupt = pulicast_tools::stop_requested();
            let stop = pulicast_tools::stop_requested();
            let interruptible = !command.ends_on_stop();
            tokio::select! {
                result = command.run(&node, &cli.net.namespace, Listening::Fresh, stop) => result,
                () = interrupt, if interruptible => Err(anyhow::anyhow!("interrupted")),
            }
        }
    };
    node.stop();
    result
}

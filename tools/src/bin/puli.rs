//! `puli`: act on a pulicast fleet from the command line.
//!
//! ```text
//! puli bench discovery --nodes 50 --channels 20
//! ```

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use pulicast_tools::bench::discovery;

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

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
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

//! `puli`: act on a pulicast fleet from the command line.
//!
//! ```text
//! puli pub CHANNEL VALUE [--type auto|string|int|float|bool|bytes|json] [--rate HZ] [--count N]
//! puli record FILE.mcap [CHANNEL|NAMESPACE/...] [--for SECS]
//! puli play FILE.mcap [--speed X] [--loop] [--channels ...]
//! puli recover DAMAGED.mcap [--output FIXED.mcap]
//! puli bench discovery --nodes 50 --channels 20
//! puli bench call [--size B] [--callers 1,16]
//! puli bench web [--channels 50] [--rate 100] [--clients 5] [--secs 20]
//! puli config list | get NAME | set NAME VALUE | unset NAME | reset NAME
//! puli config pull [FILE] | push FILE [--reset-first|--unset-first] | diff FILE
//! puli call SERVICE[@NODE] JSON [--all] [--timeout S] [--json]
//! puli shell [--script FILE] [--exit-on-error] [--echo]
//! puli web [--http-port 8780] [--listen ADDR] [--key NS=KEY] [--foxglove]
//! puli foxglove [--ws-port 8765] [--listen ADDR] [--key NS=KEY]
//! ```

use std::process::ExitCode;

use std::time::Duration;

use clap::{Parser, Subcommand};
use pulicast_tools::bench::{call as call_bench, discovery, fastpath};
use pulicast_tools::config;
use pulicast_tools::flags::NetArgs;
use pulicast_tools::publish;
use pulicast_tools::record;

#[derive(Parser)]
#[command(
    name = "puli",
    version,
    about = "Act on a pulicast fleet: publish, record, play back, benchmark"
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
    /// Record channels to an MCAP file (payloads byte-identical, with channel
    /// and schema metadata so other MCAP readers open it).
    Record(RecordArgs),
    /// Play an MCAP recording back with its original timing.
    ///
    /// A recording whose recorder was killed before it closed the file is
    /// played up to its last whole chunk, with a note of what was lost.
    Play(PlayArgs),
    /// Rewrite a recording that was never closed (its recorder killed
    /// outright, or the power lost) as a whole MCAP file, with every message
    /// that can be read.
    Recover(RecoverArgs),
    /// Read and change the fleet's distributed settings; pull, push and
    /// diff files in the Pulicast 2.x puliconf format (TOML).
    Config(ConfigArgs),
    /// Call a service: the request as JSON, encoded into the type its
    /// servers announce; progress and the reply printed as JSON. Exits
    /// non-zero, saying why, when no reply comes.
    Call(pulicast_tools::call::CallArgs),
    /// An interactive inspector: nodes, channels, services and settings,
    /// echo, hz, pub, call, get/set/push/pull, with completion of live
    /// names and history. Reads a script from --script FILE or from a
    /// standard input that is not a terminal.
    Shell(pulicast_tools::shell::ShellArgs),
    /// A node serving services, for multi-process tests and benchmarks.
    #[command(hide = true)]
    Serve(pulicast_tools::call::ServeArgs),
    /// A node owning settings, for multi-process tests.
    #[command(hide = true)]
    ConfigOwner(pulicast_tools::config::OwnerArgs),
    /// Print a shell completion script (bash, zsh, fish, elvish, powershell).
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
    /// Measure pulicast against its targets (separate processes on loopback).
    #[command(subcommand)]
    Bench(Bench),
    /// The fleet in a browser: runs `puli-web` with these arguments (see
    /// `puli web --help`), which serves a live page on loopback behind a
    /// token it prints.
    #[command(disable_help_flag = true)]
    Web {
        /// Passed to `puli-web`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// The fleet to Foxglove (or Lichtblick): runs `puli-web --foxglove
    /// --no-page` with these arguments (`--ws-port`, default 8765), which
    /// prints the address to connect to, with its token.
    #[command(disable_help_flag = true)]
    Foxglove {
        /// Passed to `puli-web`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
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
    /// Throughput: messages/s, MB/s, loss, CPU per message and peak RSS of a
    /// publisher and a subscriber process, against the raw socket.
    Thr(fastpath::ThrArgs),
    /// Latency: ping-pong round trips between two processes, against the raw
    /// socket.
    Lat(fastpath::LatArgs),
    /// Service calls: round trip p50/p99 against a raw request/reply in the
    /// same run, and calls/s with concurrent callers.
    Call(call_bench::Args),
    /// A channel through two bridges (`puli-bridge`) next to plain Zenoh:
    /// runs `puli-bridge bench` with these arguments (see its --help).
    Bridge {
        /// Passed to `puli-bridge bench`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Serving a fleet to browsers and to Foxglove (`puli-web`): runs
    /// `puli-web-bench` with these arguments (see its --help).
    Web {
        /// Passed to `puli-web-bench`.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// A role of the call benchmark.
    #[command(hide = true)]
    CallServer(call_bench::RoleArgs),
    /// A role of the call benchmark.
    #[command(hide = true)]
    CallCaller(call_bench::RoleArgs),
    /// Memory: a subscriber's RSS after many messages (a tenth, and all).
    Mem(fastpath::MemArgs),
    /// A role of the memory benchmark.
    #[command(hide = true)]
    MemSub(fastpath::RoleArgs),
    /// A role of the throughput and latency benchmarks.
    #[command(hide = true)]
    ThrPub(fastpath::RoleArgs),
    /// A role of the throughput and latency benchmarks.
    #[command(hide = true)]
    ThrSub(fastpath::RoleArgs),
    /// A role of the throughput and latency benchmarks.
    #[command(hide = true)]
    LatPing(fastpath::RoleArgs),
    /// A role of the throughput and latency benchmarks.
    #[command(hide = true)]
    LatPong(fastpath::RoleArgs),
}

#[derive(clap::Args)]
struct PubArgs {
    #[command(flatten)]
    net: NetArgs,
    #[command(flatten)]
    opts: publish::PubOpts,
}

#[derive(clap::Args)]
struct ConfigArgs {
    #[command(flatten)]
    net: NetArgs,
    /// The whole command ends within this many seconds.
    #[arg(long, global = true, default_value_t = 10.0)]
    timeout: f64,
    /// `list`, `pull`, `push` and `diff` wait until no new setting has
    /// appeared for this many seconds (as puliconf, 2 s).
    #[arg(long, global = true, default_value_t = 2.0)]
    quiet: f64,
    /// Print JSON instead of text (list, get, set, unset, reset).
    #[arg(long, global = true)]
    json: bool,
    /// `get`, `set`, `unset`, `reset`: wait for an owner up to --timeout.
    /// Without it, a setting that no node owns once discovery has settled
    /// (about half a second) fails then, naming the nearest one that exists.
    #[arg(long, global = true)]
    wait: bool,
    #[command(subcommand)]
    command: ConfigCommand,
}

#[derive(Subcommand)]
enum ConfigCommand {
    /// Every setting: value, type, owner, and what it is.
    List,
    #[command(flatten)]
    Setting(config::SettingCommand),
}

#[derive(clap::Args)]
struct RecordArgs {
    #[command(flatten)]
    net: NetArgs,
    /// The file to write.
    file: std::path::PathBuf,
    /// Channels (`rover1/pose`) or namespaces (`rover1/...`); all when none.
    channels: Vec<String>,
    /// Stop after this many seconds (default: at Ctrl-C).
    #[arg(long = "for")]
    for_secs: Option<f64>,
    /// Messages each channel may queue before the recorder falls behind.
    #[arg(long, default_value_t = 1 << 16)]
    queue: usize,
}

#[derive(clap::Args)]
struct PlayArgs {
    #[command(flatten)]
    net: NetArgs,
    /// The MCAP file.
    file: std::path::PathBuf,
    /// Play faster (2) or slower (0.5) than recorded.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Start again at the end, until Ctrl-C.
    #[arg(long = "loop")]
    repeat: bool,
    /// Only these channels or namespaces (`rover1/...`).
    #[arg(long, num_args = 1..)]
    channels: Vec<String>,
}

#[derive(clap::Args)]
struct RecoverArgs {
    /// The damaged recording.
    file: std::path::PathBuf,
    /// Where to write the whole file (default: FILE with `.recovered.mcap`).
    #[arg(long, short)]
    output: Option<std::path::PathBuf>,
}

fn recover(args: RecoverArgs) -> anyhow::Result<()> {
    let bytes = record::read_file(&args.file)?;
    let output = args
        .output
        .unwrap_or_else(|| args.file.with_extension("recovered.mcap"));
    if output == args.file {
        anyhow::bail!("--output must differ from the damaged file");
    }
    let found = record::recover(&bytes, &output)?;
    match found.describe() {
        Some(what) => pulicast_tools::errln!("{}: {what}", args.file.display()),
        None => pulicast_tools::errln!("{}: the file is whole", args.file.display()),
    }
    pulicast_tools::outln!(
        "{} messages written to {}",
        found.messages,
        output.display()
    );
    Ok(())
}

async fn record(args: RecordArgs) -> anyhow::Result<()> {
    let selection = record::Selection::new(&args.channels, &args.net.namespace)?;
    let duration = args
        .for_secs
        .map(|s| {
            if (0.0..=604_800.0).contains(&s) {
                Ok(Duration::from_secs_f64(s))
            } else {
                Err(anyhow::anyhow!(
                    "--for must be between 0 and 604800 seconds"
                ))
            }
        })
        .transpose()?;
    let output = record::Output::create(&args.file)?;
    let node = args
        .net
        .node("puli-record")?
        .queue_capacity(args.queue.max(1))
        .start()
        .await?;
    pulicast_tools::errln!("recording to {} ...", output.path().display());
    let stats = record::record(&node, output, &selection, duration).await?;
    node.stop();
    let received: u64 = stats.received.values().sum();
    let written: u64 = stats.written.values().sum();
    for (channel, n) in &stats.written {
        pulicast_tools::outln!("{channel}: {n} messages");
    }
    pulicast_tools::outln!(
        "{written} messages on {} channels written to {} ({} bytes); received {received}, dropped by full queues {}",
        stats.written.len(),
        args.file.display(),
        stats.bytes,
        stats.queue_drops
    );
    if stats.skipped > 0 {
        pulicast_tools::errln!(
            "puli: {} announced names are no channel names and were not recorded",
            stats.skipped
        );
    }
    if written != received {
        anyhow::bail!("{} received messages were not written", received - written);
    }
    Ok(())
}

async fn play(args: PlayArgs) -> anyhow::Result<()> {
    let bytes = record::read_file(&args.file)?;
    let selection = record::Selection::new(&args.channels, &args.net.namespace)?;
    let readable = record::readable(&bytes)?;
    if let Some(what) = readable.describe() {
        pulicast_tools::errln!(
            "puli: warning: {}: {what}; `puli recover {}` writes a whole copy",
            args.file.display(),
            args.file.display()
        );
    }
    let node = args.net.node("puli-play")?.start().await?;
    let loops = if args.repeat { None } else { Some(1) };
    let stats = record::play(&node, &bytes, &readable, &selection, args.speed, loops).await?;
    tokio::time::sleep(Duration::from_millis(20)).await;
    node.stop();
    let total: u64 = stats.published.values().sum();
    pulicast_tools::outln!(
        "{total} messages published on {} channels",
        stats.published.len()
    );
    if stats.skipped > 0 {
        pulicast_tools::outln!("{} messages on reserved channels skipped", stats.skipped);
    }
    Ok(())
}

async fn publish(args: PubArgs) -> anyhow::Result<()> {
    let node = args.net.node("puli-pub")?.start().await?;
    // One listener for the whole run: no Ctrl-C falls between ticks.
    let sent = publish::run_on(&node, &args.opts, pulicast_tools::stop_requested()).await;
    let name = node
        .try_channel(&args.opts.channel)
        .map(|c| c.name().to_string());
    if let (Ok(sent), Ok(name)) = (&sent, name) {
        pulicast_tools::errln!("published {sent} message(s) on {name}");
    }
    // Let the last datagrams leave before the node (and its socket) goes.
    tokio::time::sleep(Duration::from_millis(20)).await;
    node.stop();
    sent.map(|_| ())
}

async fn config(args: ConfigArgs) -> anyhow::Result<()> {
    let timeout = pulicast_tools::flags::seconds("--timeout", args.timeout)?;
    let quiet = pulicast_tools::flags::seconds("--quiet", args.quiet)?;
    let node = args.net.node("puli-config")?.start().await?;
    let settings = node.fleet_settings();
    let command = match &args.command {
        ConfigCommand::List => None,
        ConfigCommand::Setting(c) => Some(c),
    };
    let how = config::How {
        timeout,
        quiet,
        json: args.json,
        wait: args.wait,
    };
    let result = config::run(&settings, &node.discovery(), command, &how).await;
    node.stop();
    result
}

fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Runtime::new()?)
}

/// Runs `bin` (with `args`), a binary of another crate of the workspace
/// (`puli-bridge` depends on Zenoh, `puli-web` on a web server: the tools
/// depend on neither), found next to this one or on the PATH.
fn run_sibling(bin: &str, args: &[&str], rest: &[String]) -> anyhow::Result<()> {
    let beside = std::env::current_exe()
        .ok()
        .and_then(|exe| Some(exe.parent()?.join(bin)))
        .filter(|p| p.exists());
    let program = beside.unwrap_or_else(|| bin.into());
    // Which build runs, so a stale one is seen.
    let mut shown = program.display().to_string();
    for a in args {
        shown += &format!(" {a}");
    }
    eprintln!("puli: running {shown}");
    let mut command = std::process::Command::new(&program);
    command.args(args).args(rest);
    let failed = |e: std::io::Error| {
        anyhow::anyhow!(
            "running {}: {e} (build it with `cargo build --release -p {bin}`)",
            program.display()
        )
    };
    // In its place, where it can: Ctrl-C, the exit status and the PID a
    // script waits on are then the program's own.
    #[cfg(unix)]
    {
        use std::os::unix::process::CommandExt;
        Err(failed(command.exec()))
    }
    #[cfg(not(unix))]
    {
        let status = command.status().map_err(failed)?;
        if !status.success() {
            anyhow::bail!("{bin} ended with {status}");
        }
        Ok(())
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Pub(args) => runtime().and_then(|rt| rt.block_on(publish(args))),
        Command::Record(args) => runtime().and_then(|rt| rt.block_on(record(args))),
        Command::Play(args) => runtime().and_then(|rt| rt.block_on(play(args))),
        Command::Recover(args) => recover(args),
        Command::Config(args) => runtime().and_then(|rt| rt.block_on(config(args))),
        Command::Call(args) => {
            runtime().and_then(|rt| rt.block_on(pulicast_tools::call::run(args)))
        }
        Command::Shell(args) => match pulicast_tools::shell::run(args) {
            Ok(true) => Ok(()),
            // Each failure was reported as it happened.
            Ok(false) => return ExitCode::FAILURE,
            Err(e) => Err(e),
        },
        Command::Serve(args) => {
            runtime().and_then(|rt| rt.block_on(pulicast_tools::call::serve(args)))
        }
        Command::ConfigOwner(args) => runtime().and_then(|rt| rt.block_on(config::own(args))),
        Command::Completions { shell } => {
            clap_complete::generate(
                shell,
                &mut <Cli as clap::CommandFactory>::command(),
                "puli",
                &mut std::io::stdout(),
            );
            Ok(())
        }
        Command::Web { args } => run_sibling("puli-web", &[], &args),
        Command::Foxglove { args } => run_sibling("puli-web", &["--foxglove", "--no-page"], &args),
        Command::Bench(Bench::Discovery(args)) => discovery::run(&args),
        Command::Bench(Bench::DiscoveryMember(args)) => discovery::member(&args),
        Command::Bench(Bench::Thr(args)) => fastpath::thr(&args),
        Command::Bench(Bench::Lat(args)) => fastpath::lat(&args),
        Command::Bench(Bench::Call(args)) => call_bench::run(&args),
        Command::Bench(Bench::Bridge { args }) => run_sibling("puli-bridge", &["bench"], &args),
        Command::Bench(Bench::Web { args }) => run_sibling("puli-web-bench", &[], &args),
        Command::Bench(Bench::CallServer(args)) => call_bench::server(&args),
        Command::Bench(Bench::CallCaller(args)) => call_bench::caller(&args),
        Command::Bench(Bench::Mem(args)) => fastpath::mem(&args),
        Command::Bench(Bench::MemSub(args)) => fastpath::mem_sub(&args),
        Command::Bench(Bench::ThrPub(args)) => fastpath::thr_pub(&args),
        Command::Bench(Bench::ThrSub(args)) => fastpath::thr_sub(&args),
        Command::Bench(Bench::LatPing(args)) => fastpath::lat_ping(&args),
        Command::Bench(Bench::LatPong(args)) => fastpath::lat_pong(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            pulicast_tools::errln!("puli: {e:#}");
            ExitCode::FAILURE
        }
    }
}

//! `puli-bridge`: see the crate documentation and docs/bridge.md.

use anyhow::Result;
use clap::Parser;
use puli_bridge::options::Sub;
use puli_bridge::{Bridge, Options};

fn main() -> Result<()> {
    let options = Options::parse();
    match &options.command {
        Some(Sub::Bench(args)) => return puli_bridge::bench::run(args),
        Some(Sub::BenchRole(args)) => return puli_bridge::bench::role(args),
        None => {}
    }
    tokio::runtime::Runtime::new()?.block_on(bridge(options))
}

async fn bridge(options: Options) -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        // Colour codes only where a person reads them, not in a log file.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let bridge = Bridge::start(&options).await?;
    tracing::info!(
        prefix = %options.prefix,
        session = format!("{:016x}", bridge.node().compat_session_id() as u64),
        "bridge running"
    );
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let mut report = tokio::time::interval(if options.report.is_zero() {
        std::time::Duration::from_secs(3600 * 24 * 365)
    } else {
        options.report
    });
    report.tick().await;
    loop {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => break,
            _ = term.recv() => break,
            _ = report.tick() => {
                tracing::info!(stats = %serde_json::to_string(&bridge.stats())?, "bridge counters");
            }
        }
    }
    let stats = bridge.stats();
    bridge.stop().await;
    // The last counters on stdout, one JSON line, for scripts and tests.
    println!("{}", serde_json::to_string(&stats)?);
    Ok(())
}

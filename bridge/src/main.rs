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
    let mut stop = stop_signals()?;
    let mut report = tokio::time::interval(if options.report.is_zero() {
        std::time::Duration::from_secs(3600 * 24 * 365)
    } else {
        options.report
    });
    report.tick().await;
    loop {
        tokio::select! {
            _ = stop.recv() => break,
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

/// How long the bridge may take to end after SIGTERM or SIGINT before it
/// exits without finishing (its Zenoh session, its node's leave).
const END_WITHIN: std::time::Duration = std::time::Duration::from_millis(1800);

/// SIGTERM and SIGINT, heard on a thread of their own (with a runtime of
/// its own), so that a bridge whose runtime is busy still hears them; from
/// the first one, the process ends within [`END_WITHIN`] however busy.
fn stop_signals() -> Result<tokio::sync::mpsc::Receiver<()>> {
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let listening = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            listening.block_on(async move {
                use tokio::signal::unix::{signal, SignalKind};
                let signals = signal(SignalKind::terminate())
                    .and_then(|t| Ok((t, signal(SignalKind::interrupt())?)));
                let (mut term, mut int) = match signals {
                    Ok(s) => {
                        let _ = ready_tx.send(Ok(()));
                        s
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                        return;
                    }
                };
                tokio::select! {
                    _ = term.recv() => {}
                    _ = int.recv() => {}
                }
                let _ = tx.send(()).await;
                tokio::time::sleep(END_WITHIN).await;
                eprintln!("puli-bridge: not ended within {END_WITHIN:?} of the signal; exiting");
                std::process::exit(1);
            });
        })?;
    ready_rx.recv()??;
    Ok(rx)
}

//! The process harness: every row runs as separate role processes (this
//! program started again), so that each side's CPU and memory are its own.
//! Spawning roles, reading their one-line JSON reports, telling them to
//! end, their usage from /proc, and the statistics the drivers report;
//! `bench call` borrows it too.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use serde_json::Value;

use super::{Path, Setup};

/// How long blocking consumers wait per call before they look whether the
/// run is over.
pub(super) const POLL_END: Duration = Duration::from_millis(50);

/// CPU seconds (user + system) and peak RSS (KiB) of this process, from
/// /proc (USER_HZ ticks of 10 ms: runs last about a second or more).
pub(super) fn usage() -> (f64, u64) {
    let cpu = std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|stat| {
            // Fields after the command name, which may contain spaces.
            let rest = stat.rsplit_once(')')?.1;
            let fields: Vec<&str> = rest.split_whitespace().collect();
            let utime: f64 = fields.get(11)?.parse().ok()?;
            let stime: f64 = fields.get(12)?.parse().ok()?;
            Some((utime + stime) / 100.0)
        })
        .unwrap_or(0.0);
    (cpu, status_kb("VmHWM:"))
}

/// A KiB figure of /proc/self/status (`VmHWM:` peak, `VmRSS:` current).
pub(super) fn status_kb(field: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|status| {
            let line = status.lines().find(|l| l.starts_with(field))?;
            line.split_whitespace().nth(1)?.parse().ok()
        })
        .unwrap_or(0)
}

/// Becomes ready when the orchestrator writes a line (or closes) stdin.
pub(super) fn end_signal() -> std::sync::mpsc::Receiver<()> {
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = std::io::stdin().read_line(&mut line);
        let _ = tx.send(());
    });
    rx
}

/// The single-threaded runtime every role runs on: the benchmark measures
/// one receive thread per process, like the raw baseline.
pub(super) fn current_thread() -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
}

pub(super) fn emit(v: Value) {
    crate::outln!("{v}");
}

pub(super) fn spawn_role(role: &str, path: Path, setup: Setup) -> Result<Child> {
    let mut args = vec![
        "bench".to_string(),
        role.into(),
        "--path".into(),
        path.name().into(),
        "--port".into(),
        setup.port.to_string(),
        "--size".into(),
        setup.size.to_string(),
        "--count".into(),
        setup.count.to_string(),
    ];
    if let Some(secs) = setup.for_secs {
        args.extend(["--for".into(), secs.to_string()]);
    }
    if let Some(delay) = setup.batch {
        args.extend(["--batch-us".into(), delay.as_micros().to_string()]);
    }
    if let Some(spin) = setup.spin {
        args.extend(["--spin-us".into(), spin.as_micros().to_string()]);
    }
    if let Some(queue) = setup.queue {
        args.extend(["--queue".into(), queue.to_string()]);
    }
    args.extend(["--channels".into(), setup.channels.to_string()]);
    if let Some(rate) = setup.rate {
        args.extend(["--rate".into(), rate.to_string()]);
    }
    args.extend(["--rcvbuf".into(), setup.rcvbuf.to_string()]);
    args.extend(["--seal".into(), setup.seal.name().into()]);
    spawn_self(&args)
}

/// Starts this program again with `args` (a benchmark role), its stdin
/// and stdout piped.
pub(crate) fn spawn_self(args: &[String]) -> Result<Child> {
    Command::new(std::env::current_exe()?)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .context("starting a benchmark process")
}

/// Starts a role that announces `{"ready": true}` and waits for it.
pub(super) fn spawn_ready(role: &str, path: Path, setup: Setup) -> Result<Child> {
    let mut child = spawn_role(role, path, setup)?;
    let ready = read_json(&mut child)?;
    if ready["ready"] != true {
        bail!("{role} not ready: {ready}");
    }
    Ok(child)
}

/// Tells a subscriber role that the publisher is done (after a grace period
/// for datagrams in flight) and reads its report.
pub(super) fn finish_sub(sub: &mut Child) -> Result<Value> {
    std::thread::sleep(Duration::from_millis(300));
    if let Some(stdin) = sub.stdin.as_mut() {
        writeln!(stdin, "end")?;
    }
    let report = read_json(sub)?;
    let _ = sub.wait();
    Ok(report)
}

pub(crate) fn read_json(child: &mut Child) -> Result<Value> {
    let stdout = child.stdout.as_mut().context("no stdout")?;
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line)?;
    serde_json::from_str(&line).with_context(|| format!("unexpected output {line:?}"))
}
pub(super) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    if v.is_empty() {
        return 0.0;
    }
    v[v.len() / 2]
}

pub(crate) fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

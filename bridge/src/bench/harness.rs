//! The process harness of `puli-bridge bench`: every role and bridge runs
//! as this binary started again, so the measurements cross real process
//! boundaries; this is how they are started, heard from, logged and
//! killed.

use std::io::{BufRead, BufReader};
use std::net::{Ipv4Addr, TcpListener};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use serde_json::Value;

/// `--logs`: where the processes' logs go, if anywhere.
pub(super) static LOGS: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();

/// The standard error of the next process called `what`: a new file in
/// `--logs` (numbered in the order the processes start), or nowhere.
fn log_file(what: &str) -> Result<Stdio> {
    static STARTED: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let Some(dir) = LOGS.get() else {
        return Ok(Stdio::null());
    };
    let n = STARTED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let path = dir.join(format!("{n:02}-{what}.log"));
    let file =
        std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
    Ok(Stdio::from(file))
}

/// A process of this binary, its stdout lines read by a thread; killed
/// (our own child, by its handle) when dropped.
pub(super) struct Proc {
    pub(super) child: Child,
    lines: mpsc::Receiver<Value>,
    what: String,
}

impl Proc {
    pub(super) fn start(args: &[String], what: &str) -> Result<Proc> {
        let mut child = Command::new(std::env::current_exe()?)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(log_file(what)?)
            .spawn()
            .with_context(|| format!("starting {what}"))?;
        let stdout = child.stdout.take().context("stdout")?;
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Ok(v) = serde_json::from_str(&line) {
                    if tx.send(v).is_err() {
                        break;
                    }
                }
            }
        });
        Ok(Proc {
            child,
            lines,
            what: what.to_owned(),
        })
    }

    /// The next line with `key`, within `within`.
    pub(super) fn wait_for(&self, key: &str, within: Duration) -> Result<Value> {
        let deadline = Instant::now() + within;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(v) if v.get(key).is_some() => return Ok(v),
                Ok(_) => {}
                Err(_) => bail!("{}: no {key:?} within {within:?}", self.what),
            }
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub(super) fn free_tcp() -> Result<u16> {
    Ok(TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?
        .local_addr()?
        .port())
}

pub(super) fn role_proc(role: &str, extra: &[String]) -> Result<Proc> {
    let mut args = vec!["bench-role".to_string(), role.to_string()];
    args.extend_from_slice(extra);
    let p = Proc::start(&args, role)?;
    p.wait_for("ready", Duration::from_secs(20))?;
    Ok(p)
}

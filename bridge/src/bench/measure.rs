//! The measurements of `puli-bridge bench`: round trips and throughput
//! bursts over a path (pulicast or Zenoh), with the CPU each process on
//! the path spent; the driver in `mod.rs` runs them row by row and
//! reports them.

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use pulicast::{Bytes, Node};
use serde_json::{json, Value};

use super::harness::{role_proc, Proc};
use super::{unix_ms, DATA, WARM};

/// How long a round trip may take before it counts as lost (and as this
/// long in the percentiles).
const ROUND_LIMIT: Duration = Duration::from_secs(1);

/// How a pinger or sender reaches the other side.
pub(super) enum Path<'a> {
    Pulicast(&'a Node),
    Zenoh(&'a zenoh::Session),
}

/// Where a pinger or sender puts its messages.
enum Out {
    Pulicast(pulicast::Channel),
    Zenoh(zenoh::pubsub::Publisher<'static>),
}

impl Out {
    async fn new(path: &Path<'_>, name: &'static str) -> Result<Out> {
        Ok(match path {
            Path::Pulicast(node) => Out::Pulicast(node.channel(name)),
            Path::Zenoh(session) => Out::Zenoh(
                session
                    .declare_publisher(name)
                    .await
                    .map_err(|e| anyhow!("{e}"))?,
            ),
        })
    }

    /// Batches a pulicast sender's messages (`None`: one datagram each
    /// again); Zenoh batches its own.
    fn set_batching(&self, delay: Option<Duration>) -> Result<()> {
        if let Out::Pulicast(channel) = self {
            match delay {
                Some(delay) => channel.enable_batching(delay)?,
                None => channel.disable_batching()?,
            }
        }
        Ok(())
    }

    /// Sends what a batching sender holds.
    fn flush(&self) -> Result<()> {
        if let Out::Pulicast(channel) = self {
            channel.flush()?;
        }
        Ok(())
    }

    async fn send(&self, bytes: Vec<u8>) -> Result<()> {
        match self {
            Out::Pulicast(channel) => Ok(channel.publish_bytes(&bytes)?),
            Out::Zenoh(publisher) => publisher.put(bytes).await.map_err(|e| anyhow!("{e}")),
        }
    }
}

/// A message of `size` bytes: its kind, then a counter.
fn message(size: usize, kind: u8, n: u64) -> Vec<u8> {
    let mut m = vec![0u8; size.max(9)];
    m[0] = kind;
    m[1..9].copy_from_slice(&n.to_be_bytes());
    m
}

/// Round trips, one at a time, after a warm-up that waits for the path;
/// returns (p50, p99) in microseconds and the rounds lost.
pub(super) async fn round_trips(
    path: Path<'_>,
    size: usize,
    rounds: usize,
) -> Result<(f64, f64, usize)> {
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<Bytes>();
    // Kept alive for the rows: the pong subscription of either kind.
    let _guard: Box<dyn std::any::Any + Send> = match &path {
        Path::Pulicast(node) => {
            let sub = node.channel("bench/pong").subscribe_raw_with(move |m| {
                let _ = tx.send(m.value);
            })?;
            Box::new(sub)
        }
        Path::Zenoh(session) => {
            let sub = session
                .declare_subscriber("bench/pong")
                .callback(move |s| {
                    let _ = tx.send(Bytes::from(s.payload().to_bytes().into_owned()));
                })
                .await
                .map_err(|e| anyhow!("{e}"))?;
            Box::new(sub)
        }
    };
    let out = Out::new(&path, "bench/ping").await?;
    // Warm-up: the path is up once a ping comes back.
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if Instant::now() > deadline {
            bail!("no pong within 30 s");
        }
        out.send(message(size, WARM, 0)).await?;
        if tokio::time::timeout(Duration::from_millis(100), rx.recv())
            .await
            .is_ok()
        {
            break;
        }
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    while rx.try_recv().is_ok() {}
    let mut samples = Vec::with_capacity(rounds);
    let mut lost = 0;
    for n in 1..=rounds as u64 {
        let started = Instant::now();
        out.send(message(size, DATA, n)).await?;
        let until = started + ROUND_LIMIT;
        loop {
            let left = until.saturating_duration_since(Instant::now());
            match tokio::time::timeout(left, rx.recv()).await {
                Ok(Some(m)) if m.get(1..9) == Some(&n.to_be_bytes()[..]) => {
                    samples.push(started.elapsed().as_secs_f64() * 1e6);
                    break;
                }
                Ok(Some(_)) => {}
                _ => {
                    lost += 1;
                    samples.push(ROUND_LIMIT.as_secs_f64() * 1e6);
                    break;
                }
            }
        }
    }
    samples.sort_by(f64::total_cmp);
    Ok((percentile(&samples, 0.5), percentile(&samples, 0.99), lost))
}

/// What a burst row sends: `count` messages of `size` bytes, `runs`
/// times, the sender batching with `batch` if given.
#[derive(Debug, Clone, Copy)]
pub(super) struct Load {
    pub(super) size: usize,
    pub(super) count: usize,
    pub(super) runs: usize,
    pub(super) batch: Option<Duration>,
}

/// Bursts to a sink; `watched`: the processes of the path besides this
/// one (the sender), by name: bridges, the sink.
pub(super) async fn burst(
    path: Path<'_>,
    sink: &Proc,
    load: Load,
    watched: &[(&'static str, u32)],
) -> Result<Burst> {
    let out = Out::new(&path, "bench/data").await?;
    let names: Vec<&'static str> = std::iter::once("sender")
        .chain(watched.iter().map(|(name, _)| *name))
        .collect();
    let mut runs = Vec::with_capacity(load.runs);
    for _ in 0..load.runs.max(1) {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if Instant::now() > deadline {
                bail!("the sink heard no warm-up within 30 s");
            }
            out.send(message(load.size, WARM, 0)).await?;
            if sink.wait_for("warm", Duration::from_millis(100)).is_ok() {
                break;
            }
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
        out.set_batching(load.batch)?;
        let cpu_before = cpu_ns(watched);
        let first_send = unix_ms();
        for n in 0..load.count as u64 {
            out.send(message(load.size, DATA, n)).await?;
        }
        out.flush()?;
        let sent_ms = unix_ms() - first_send;
        out.set_batching(None)?;
        // Nothing arrived at all: no report comes, and the run is all loss.
        let report = sink.wait_for("received", Duration::from_secs(60)).ok();
        let cpu_after = cpu_ns(watched);
        let reported_at = unix_ms();
        let Some(report) = report else {
            runs.push(Run {
                rate: 0.0,
                loss: 1.0,
                duplicates: 0,
                sent_ms,
                cpu_us: vec![None; names.len()],
            });
            continue;
        };
        let received = report["received"].as_f64().unwrap_or(0.0);
        let last_ms = report["last_unix_ms"].as_f64().unwrap_or(first_send);
        // The CPU readings ran on after the last receive, while the sink
        // made sure the burst was over: what the processes spend idle over
        // as long, measured right after, is taken off.
        let idle = Duration::from_secs_f64(((reported_at - last_ms) / 1e3).max(0.0));
        let base_before = cpu_ns(watched);
        tokio::time::sleep(BASELINE).await;
        let base_after = cpu_ns(watched);
        let scale = idle.as_secs_f64() / BASELINE.as_secs_f64();
        let cpu_us = (0..names.len())
            .map(|i| {
                let used = cpu_after[i]?.checked_sub(cpu_before[i]?)? as f64;
                let idle = base_after[i]?.checked_sub(base_before[i]?)? as f64 * scale;
                Some((used - idle).max(0.0) / 1e3 / received.max(1.0))
            })
            .collect();
        let secs = ((last_ms - first_send) / 1e3).max(1e-3);
        runs.push(Run {
            rate: received / secs,
            loss: 1.0 - received / load.count as f64,
            duplicates: report["duplicates"].as_u64().unwrap_or(0),
            sent_ms,
            cpu_us,
        });
    }
    let duplicates = runs.iter().map(|r| r.duplicates).sum();
    // The median run by rate (the lower of two middle ones): its figures
    // go together.
    runs.sort_by(|a, b| a.rate.total_cmp(&b.rate));
    let median = runs.swap_remove((runs.len() - 1) / 2);
    Ok(Burst {
        rate: median.rate,
        loss: median.loss,
        duplicates,
        sent_ms: median.sent_ms,
        cpu_us: names.into_iter().zip(median.cpu_us).collect(),
    })
}

/// How long a run's idle CPU is measured, to take it off the run's.
const BASELINE: Duration = Duration::from_millis(300);

/// One burst's figures.
#[derive(Debug, Clone)]
struct Run {
    /// Distinct messages received a second, first send to last receive.
    rate: f64,
    /// Share of the burst not received.
    loss: f64,
    /// Messages received more than once.
    duplicates: u64,
    /// How long the sender took to send the burst.
    sent_ms: f64,
    /// CPU µs per message received, by process (the sender first); `None`
    /// where a reading failed.
    cpu_us: Vec<Option<f64>>,
}

/// A row's figures: the median run's rate, loss, sending time and CPU,
/// and the duplicates of all runs.
#[derive(Debug, Clone)]
pub(super) struct Burst {
    pub(super) rate: f64,
    loss: f64,
    duplicates: u64,
    sent_ms: f64,
    /// CPU µs per message received, by process (the sender first).
    cpu_us: Vec<(&'static str, Option<f64>)>,
}

/// CPU time in ns of this process and of each of `pids` (every thread's,
/// from `/proc/<pid>/task/*/schedstat`); `None` for one that can't be read.
fn cpu_ns(pids: &[(&str, u32)]) -> Vec<Option<u64>> {
    let of = |dir: String| -> Option<u64> {
        let mut total = 0u64;
        for task in std::fs::read_dir(dir).ok()? {
            let stat = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
            total += stat.split_whitespace().next()?.parse::<u64>().ok()?;
        }
        Some(total)
    };
    std::iter::once(of("/proc/self/task".into()))
        .chain(pids.iter().map(|(_, p)| of(format!("/proc/{p}/task"))))
        .collect()
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

impl Burst {
    pub(super) fn json(&self) -> Value {
        json!({
            "msgs_per_s": self.rate,
            "loss": self.loss,
            "duplicates": self.duplicates,
            "sent_ms": self.sent_ms,
            "cpu_us_per_msg": self.cpu_us.iter().map(|(_, us)| *us).sum::<Option<f64>>(),
            "cpu_us_per_msg_by_process": self
                .cpu_us
                .iter()
                .map(|(name, us)| (name.to_string(), json!(us)))
                .collect::<serde_json::Map<_, _>>(),
        })
    }
}

/// The sink's arguments: its site, and whether it takes batches whole.
fn sink_args(port: u16, many: bool) -> Vec<String> {
    let mut args = vec!["--port".to_string(), port.to_string()];
    if many {
        args.push("--many".into());
    }
    args
}

/// Bursts to a new pulicast sink on `port`: with default settings, or
/// tuned (a batching sender, a sink that uses `recv_many`); `watched`: the
/// bridges on the way.
pub(super) async fn pulicast_burst(
    node: &Node,
    port: u16,
    load: Load,
    watched: &[(&'static str, u32)],
) -> Result<Burst> {
    let sink = role_proc("sink-pulicast", &sink_args(port, load.batch.is_some()))?;
    let mut pids = watched.to_vec();
    pids.push(("sink", sink.child.id()));
    burst(Path::Pulicast(node), &sink, load, &pids).await
}

//! `puli-bridge bench` (and `puli bench bridge`, which runs it): a channel
//! from site A to site B through two bridges, next to plain Zenoh peer to
//! peer on the same link, in the same run.
//!
//! Every role is its own process (this binary, started again), on
//! loopback: the two sites are two pulicast ports of one host (multicast
//! at TTL 0 on the loopback interface), the Zenoh link is TCP on
//! 127.0.0.1. Everything runs with default settings: the bridges as
//! `puli-bridge` runs by default, the plain Zenoh peers with Zenoh's
//! defaults (multicast scouting off, as for the bridges).
//!
//! Rows, for 64 B and 64 KiB messages:
//!
//! - **round trip**: a ping on site A, echoed on site B, back on site A;
//!   one at a time; p50 and p99. Next to it plain Zenoh's (put, echoed by
//!   a Zenoh subscriber that puts back), and pulicast's own on one site
//!   (two local hops each way with the bridges: the ping goes talker ->
//!   bridge A, bridge B -> echo, and the pong echo -> bridge B, bridge A ->
//!   talker).
//! - **throughput**: bursts of `--count` numbered messages, sent as fast
//!   as the sender's API returns; messages received (distinct) per second
//!   from the first send to the last receive (one host, one clock), and the
//!   share lost, the median of `--runs` bursts; next to plain Zenoh's and
//!   pulicast's on one site (the local hop alone). With each row, the CPU
//!   time of every process on the path (sender, bridges, sink) per message
//!   received, from /proc: on one host the processes share its cores, so
//!   a path that costs more CPU a message can't run as fast as one that
//!   costs less.
//! - **throughput, tuned** (labelled apart, `--batch`): the sender batches
//!   (`Channel::enable_batching`) and the sink uses `recv_many`, as
//!   `docs/performance.md` advises for a fast stream of small messages.
//!   Plain Zenoh batches small messages by default, so its row is the same.
//!
//! A round trip that got no answer within a second counts as one second.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{Ipv4Addr, TcpListener};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use pulicast::{Bytes, Node};
use serde_json::{json, Value};

/// `puli-bridge bench`'s arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct BenchArgs {
    /// Message sizes in bytes.
    #[arg(long, value_delimiter = ',', default_values_t = [64, 65536])]
    pub sizes: Vec<usize>,
    /// Round trips per row.
    #[arg(long, default_value_t = 1000)]
    pub rounds: usize,
    /// Messages per throughput burst of 64 B (fewer for larger ones, the
    /// same number of bytes at most 64 MiB).
    #[arg(long, default_value_t = 20_000)]
    pub count: usize,
    /// The tuned rows, labelled apart: the sending node batches with this
    /// delay (`Channel::enable_batching`, as `docs/performance.md` advises
    /// for a fast stream of small messages) and the sink takes its messages
    /// with `recv_many`. `0s` leaves them out.
    #[arg(long, default_value = "1ms", value_parser = humantime::parse_duration)]
    pub batch: Duration,
    /// A directory for every process's log (it must exist); the bridges
    /// then log their counters every second, which shows where a loss
    /// happened.
    #[arg(long, value_name = "DIR")]
    pub logs: Option<PathBuf>,
    /// Bursts per throughput row; the row shows the median.
    #[arg(long, default_value_t = 3)]
    pub runs: usize,
    /// One JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// A role of the benchmark, in a process of its own.
#[derive(clap::Args, Debug, Clone)]
pub struct RoleArgs {
    /// Which.
    #[arg(value_enum)]
    pub role: Role,
    /// The pulicast port (pulicast roles).
    #[arg(long, default_value_t = 0)]
    pub port: u16,
    /// The Zenoh endpoint to listen on (Zenoh roles).
    #[arg(long, default_value = "")]
    pub listen: String,
    /// A pulicast sink takes what waits with `recv_many` (the loop for a
    /// batched stream), not one `recv` a message.
    #[arg(long)]
    pub many: bool,
}

/// The roles.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Echoes `bench/ping` on `bench/pong`, on a pulicast site.
    EchoPulicast,
    /// Counts `bench/data` on a pulicast site.
    SinkPulicast,
    /// Echoes `bench/ping` on `bench/pong`, on Zenoh.
    EchoZenoh,
    /// Counts `bench/data` on Zenoh.
    SinkZenoh,
}

/// First byte of a message: warm-up (the path is being set up) or data.
const WARM: u8 = 0;
const DATA: u8 = 1;

/// Most messages a `--many` sink takes at once (the queue's default
/// capacity).
const MANY: usize = 1024;

/// How long a sink waits after the last data message before it reports.
const IDLE: Duration = Duration::from_secs(1);

/// How long a round trip may take before it counts as lost (and as this
/// long in the percentiles).
const ROUND_LIMIT: Duration = Duration::from_secs(1);

/// Runs a role until its parent closes its stdin.
pub fn role(args: &RoleArgs) -> Result<()> {
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(async move {
        match args.role {
            Role::EchoPulicast | Role::SinkPulicast => {
                let node = site_node("bench-role", args.port).await?;
                let echo = args.role == Role::EchoPulicast;
                let name = if echo { "bench/ping" } else { "bench/data" };
                let mut sub = node.channel(name).subscribe_raw()?;
                let pong = node.channel("bench/pong");
                say(&json!({"ready": true}));
                let mut sink = Sink::default();
                let mut many = Vec::with_capacity(MANY);
                loop {
                    let wait = sink.wait();
                    let got = match args.many {
                        true => tokio::time::timeout(wait, sub.recv_many(&mut many, MANY))
                            .await
                            .map(|n| (n > 0).then_some(())),
                        false => tokio::time::timeout(wait, sub.recv())
                            .await
                            .map(|m| m.map(|m| many.push(m))),
                    };
                    match got {
                        Ok(Some(())) => {}
                        Ok(None) => break,
                        Err(_) => {
                            sink.report();
                            continue;
                        }
                    }
                    for m in many.drain(..) {
                        if echo {
                            pong.publish_bytes(&m.value)?;
                        } else {
                            sink.take(&m.value);
                        }
                    }
                }
                Ok(())
            }
            Role::EchoZenoh | Role::SinkZenoh => {
                let session = zenoh_session(&args.listen, "").await?;
                let echo = args.role == Role::EchoZenoh;
                let key = if echo { "bench/ping" } else { "bench/data" };
                let sub = session
                    .declare_subscriber(key)
                    .await
                    .map_err(|e| anyhow!("{e}"))?;
                let pong = session
                    .declare_publisher("bench/pong")
                    .await
                    .map_err(|e| anyhow!("{e}"))?;
                say(&json!({"ready": true}));
                let mut sink = Sink::default();
                loop {
                    let wait = sink.wait();
                    let sample = match tokio::time::timeout(wait, sub.recv_async()).await {
                        Ok(Ok(s)) => s,
                        Ok(Err(_)) => break,
                        Err(_) => {
                            sink.report();
                            continue;
                        }
                    };
                    let bytes = sample.payload().to_bytes();
                    if echo {
                        pong.put(bytes.to_vec()).await.map_err(|e| anyhow!("{e}"))?;
                    } else {
                        sink.take(&bytes);
                    }
                }
                Ok(())
            }
        }
    })
}

/// A sink's count: it reports `{"warm": true}` at each warm-up message
/// before data, and `{"received", "duplicates", "last_unix_ms"}` once data
/// stopped for [`IDLE`].
#[derive(Default)]
struct Sink {
    received: u64,
    seen: std::collections::HashSet<u64>,
    first: Option<Instant>,
    last: Option<Instant>,
}

impl Sink {
    fn take(&mut self, m: &[u8]) {
        match m.first() {
            // Every warm-up message is answered until data comes, so a
            // burst that never arrived leaves the sink ready for the next.
            Some(&WARM) if self.first.is_none() => say(&json!({"warm": true})),
            Some(&DATA) => {
                let now = Instant::now();
                self.first.get_or_insert(now);
                self.last = Some(now);
                self.received += 1;
                if let Some(n) = m.get(1..9) {
                    let mut b = [0; 8];
                    b.copy_from_slice(n);
                    self.seen.insert(u64::from_be_bytes(b));
                }
            }
            _ => {}
        }
    }

    fn wait(&self) -> Duration {
        match self.last {
            Some(last) => IDLE
                .saturating_sub(last.elapsed())
                .max(Duration::from_millis(1)),
            None => Duration::from_secs(3600),
        }
    }

    /// Reports a finished burst and gets ready for the next.
    fn report(&mut self) {
        if let Some(last) = self.last {
            // The wall clock of the last receive: the sender, on this host,
            // times the burst from its first send.
            let last_ms = unix_ms() - last.elapsed().as_secs_f64() * 1e3;
            say(&json!({
                "received": self.seen.len(),
                "duplicates": self.received - self.seen.len() as u64,
                "last_unix_ms": last_ms,
            }));
            *self = Sink::default();
        }
    }
}

fn unix_ms() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1e3)
}

fn say(v: &Value) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{v}");
    let _ = out.flush();
}

async fn site_node(name: &str, port: u16) -> Result<Node> {
    Ok(Node::new(name)
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .start()
        .await?)
}

async fn zenoh_session(listen: &str, connect: &str) -> Result<zenoh::Session> {
    let mut config = zenoh::Config::default();
    let mut set = |k: &str, v: String| config.insert_json5(k, &v).map_err(|e| anyhow!("{e}"));
    set("mode", "\"peer\"".into())?;
    set("scouting/multicast/enabled", "false".into())?;
    if !listen.is_empty() {
        set("listen/endpoints", format!("[\"{listen}\"]"))?;
    }
    if !connect.is_empty() {
        set("connect/endpoints", format!("[\"{connect}\"]"))?;
    }
    zenoh::open(config).await.map_err(|e| anyhow!("{e}"))
}

/// `--logs`: where the processes' logs go, if anywhere.
static LOGS: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();

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
struct Proc {
    child: Child,
    lines: mpsc::Receiver<Value>,
    what: String,
}

impl Proc {
    fn start(args: &[String], what: &str) -> Result<Proc> {
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
    fn wait_for(&self, key: &str, within: Duration) -> Result<Value> {
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

fn free_tcp() -> Result<u16> {
    Ok(TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?
        .local_addr()?
        .port())
}

fn role_proc(role: &str, extra: &[String]) -> Result<Proc> {
    let mut args = vec!["bench-role".to_string(), role.to_string()];
    args.extend_from_slice(extra);
    let p = Proc::start(&args, role)?;
    p.wait_for("ready", Duration::from_secs(20))?;
    Ok(p)
}

/// How a pinger or sender reaches the other side.
enum Path<'a> {
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
async fn round_trips(path: Path<'_>, size: usize, rounds: usize) -> Result<(f64, f64, usize)> {
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
struct Load {
    size: usize,
    count: usize,
    runs: usize,
    batch: Option<Duration>,
}

/// Bursts to a sink; `watched`: the processes of the path besides this
/// one (the sender), by name: bridges, the sink.
async fn burst(
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
struct Burst {
    rate: f64,
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

/// Runs the benchmark and prints its table (or JSON).
pub fn run(args: &BenchArgs) -> Result<()> {
    let rt = tokio::runtime::Runtime::new()?;
    rt.block_on(bench(args))
}

impl Burst {
    fn json(&self) -> Value {
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
async fn pulicast_burst(
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

async fn bench(args: &BenchArgs) -> Result<()> {
    let (pa, pb) = (pulicast::unused_port()?, pulicast::unused_port()?);
    let link = format!("tcp/127.0.0.1:{}", free_tcp()?);
    let prefix = format!("bench{}", std::process::id());
    let batch = (!args.batch.is_zero()).then_some(args.batch);
    if let Some(dir) = &args.logs {
        let _ = LOGS.set(dir.clone());
    }
    let report = if args.logs.is_some() { "1s" } else { "0s" };
    let mut rows: HashMap<String, Value> = HashMap::new();
    let node_a = site_node("bench-talker", pa).await?;
    for &size in &args.sizes {
        if !(9..=pulicast::MAX_MESSAGE).contains(&size) {
            bail!(
                "--sizes: {size} B is not between 9 B (a kind and a number) and {} B",
                pulicast::MAX_MESSAGE
            );
        }
        // The same bytes as the 64 B burst, at least 200 messages, at most
        // 64 MiB.
        let most = ((64usize << 20) / size).max(1);
        let count = if size <= 64 {
            args.count
        } else {
            (args.count * 64 / size).max(200).min(most)
        };
        let load = Load {
            size,
            count,
            runs: args.runs,
            batch: None,
        };
        let tuned_load = batch.map(|d| Load {
            batch: Some(d),
            ..load
        });
        eprintln!("bench: {size} B: pulicast on one site");
        // Pulicast on one site: the local hops alone.
        let (local, local_thr, local_tuned) = {
            let echo = role_proc("echo-pulicast", &["--port".into(), pa.to_string()])?;
            let rtt = round_trips(Path::Pulicast(&node_a), size, args.rounds).await?;
            drop(echo);
            let thr = pulicast_burst(&node_a, pa, load, &[]).await?;
            let tuned = match tuned_load {
                Some(load) => Some(pulicast_burst(&node_a, pa, load, &[]).await?),
                None => None,
            };
            (rtt, thr, tuned)
        };
        eprintln!("bench: {size} B: plain Zenoh");
        let zenoh_link = format!("tcp/127.0.0.1:{}", free_tcp()?);
        let (zenoh_rtt, zenoh_thr) = {
            let _echo = role_proc("echo-zenoh", &["--listen".into(), zenoh_link.clone()])?;
            let session = zenoh_session("", &zenoh_link).await?;
            let rtt = round_trips(Path::Zenoh(&session), size, args.rounds).await?;
            drop(_echo);
            let sink_link = format!("tcp/127.0.0.1:{}", free_tcp()?);
            let sink = role_proc("sink-zenoh", &["--listen".into(), sink_link.clone()])?;
            let session2 = zenoh_session("", &sink_link).await?;
            let thr = burst(
                Path::Zenoh(&session2),
                &sink,
                load,
                &[("sink", sink.child.id())],
            )
            .await?;
            let _ = session.close().await;
            let _ = session2.close().await;
            (rtt, thr)
        };
        eprintln!("bench: {size} B: through two bridges");
        let (bridged_rtt, bridged_thr, bridged_tuned) = {
            let bridge = |port: u16, site: &str, link_flag: &str| -> Result<Proc> {
                let args: Vec<String> = [
                    "--prefix",
                    &prefix,
                    "--site",
                    site,
                    "--port",
                    &port.to_string(),
                    "--interface",
                    "127.0.0.1",
                    "--report",
                    report,
                    link_flag,
                    &link,
                ]
                .iter()
                .map(|s| s.to_string())
                .collect();
                Proc::start(&args, site)
            };
            let a = bridge(pa, "bench-a", "--listen")?;
            let b = bridge(pb, "bench-b", "--connect")?;
            let rtt = {
                let _echo = role_proc("echo-pulicast", &["--port".into(), pb.to_string()])?;
                round_trips(Path::Pulicast(&node_a), size, args.rounds).await?
            };
            let bridges = [("bridge_a", a.child.id()), ("bridge_b", b.child.id())];
            let thr = pulicast_burst(&node_a, pb, load, &bridges).await?;
            let tuned = match tuned_load {
                Some(load) => Some(pulicast_burst(&node_a, pb, load, &bridges).await?),
                None => None,
            };
            (rtt, thr, tuned)
        };
        let expected = zenoh_rtt.0 + 2.0 * local.0;
        let tuned = match (bridged_tuned, local_tuned, batch) {
            (Some(bridged), Some(local), Some(delay)) => json!({
                "batch_ms": delay.as_secs_f64() * 1e3,
                "bridged": bridged.json(),
                "pulicast_one_site": local.json(),
                "ratio": bridged.rate / zenoh_thr.rate.max(1e-9),
                "ratio_to_one_site": bridged.rate / local.rate.max(1e-9),
            }),
            _ => Value::Null,
        };
        rows.insert(
            size.to_string(),
            json!({
                "size": size,
                "messages": count,
                "rtt_us": {
                    "bridged": {"p50": bridged_rtt.0, "p99": bridged_rtt.1, "lost": bridged_rtt.2},
                    "zenoh": {"p50": zenoh_rtt.0, "p99": zenoh_rtt.1, "lost": zenoh_rtt.2},
                    "pulicast_one_site": {"p50": local.0, "p99": local.1, "lost": local.2},
                    "ratio_to_zenoh_plus_local_hops": bridged_rtt.0 / expected,
                },
                "throughput": {
                    "bridged": bridged_thr.json(),
                    "zenoh": zenoh_thr.json(),
                    "pulicast_one_site": local_thr.json(),
                    "ratio": bridged_thr.rate / zenoh_thr.rate.max(1e-9),
                    "ratio_to_one_site": bridged_thr.rate / local_thr.rate.max(1e-9),
                },
                "throughput_tuned": tuned,
            }),
        );
    }
    node_a.stop();
    let mut sizes: Vec<usize> = args.sizes.clone();
    sizes.sort_unstable();
    if args.json {
        let all: Vec<&Value> = sizes
            .iter()
            .filter_map(|s| rows.get(&s.to_string()))
            .collect();
        println!("{}", json!({"rows": all}));
        return Ok(());
    }
    println!("round trip, one at a time (us)      p50       p99    lost");
    for s in &sizes {
        let r = &rows[&s.to_string()]["rtt_us"];
        for (label, key) in [
            ("through two bridges", "bridged"),
            ("plain Zenoh", "zenoh"),
            ("pulicast, one site", "pulicast_one_site"),
        ] {
            println!(
                "  {s:>6} B {label:<22} {:>9.0} {:>9.0} {:>7}",
                r[key]["p50"].as_f64().unwrap_or(0.0),
                r[key]["p99"].as_f64().unwrap_or(0.0),
                r[key]["lost"]
            );
        }
        println!(
            "  {s:>6} B bridged / (Zenoh + 2 x one site) at p50: {:.2} (target <= 1.5)",
            r["ratio_to_zenoh_plus_local_hops"].as_f64().unwrap_or(0.0)
        );
    }
    // A CPU figure, or "-" where a reading failed.
    let us = |v: &Value| v.as_f64().map_or("-".to_string(), |us| format!("{us:.2}"));
    let print_burst = |s: usize, label: &str, b: &Value| {
        println!(
            "  {s:>6} B {label:<22} {:>9.0} {:>8.1}% {:>5} {:>6.0} ms {:>8}",
            b["msgs_per_s"].as_f64().unwrap_or(0.0),
            b["loss"].as_f64().unwrap_or(0.0) * 100.0,
            b["duplicates"],
            b["sent_ms"].as_f64().unwrap_or(0.0),
            us(&b["cpu_us_per_msg"])
        );
        if let Some(by) = b["cpu_us_per_msg_by_process"].as_object() {
            let by: Vec<String> = by
                .iter()
                .map(|(name, v)| format!("{name} {}", us(v)))
                .collect();
            println!("           CPU us/msg by process: {}", by.join(", "));
        }
    };
    let print_ratios = |s: usize, t: &Value, tail: &str| {
        println!(
            "  {s:>6} B bridged / Zenoh: {:.2} (target >= 0.8); bridged / one site: {:.2}{tail}",
            t["ratio"].as_f64().unwrap_or(0.0),
            t["ratio_to_one_site"].as_f64().unwrap_or(0.0),
        );
    };
    println!(
        "throughput, bursts of --count, median of {}, defaults\n                                    msgs/s      loss  dups  sent in  CPU us/msg",
        args.runs
    );
    for s in &sizes {
        let r = &rows[&s.to_string()];
        let t = &r["throughput"];
        print_burst(*s, "through two bridges", &t["bridged"]);
        print_burst(*s, "plain Zenoh", &t["zenoh"]);
        print_burst(*s, "pulicast, one site", &t["pulicast_one_site"]);
        print_ratios(*s, t, &format!("; burst of {}", r["messages"]));
    }
    if let Some(delay) = batch {
        println!(
            "throughput, tuned: the sender batches ({delay:?}), the sink uses recv_many; plain Zenoh as above"
        );
        for s in &sizes {
            let r = &rows[&s.to_string()];
            let t = &r["throughput_tuned"];
            print_burst(*s, "through two bridges", &t["bridged"]);
            print_burst(*s, "pulicast, one site", &t["pulicast_one_site"]);
            print_ratios(*s, t, "");
        }
    }
    Ok(())
}

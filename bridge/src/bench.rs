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
//! - **throughput**: a burst of `--count` numbered messages, sent as fast
//!   as the sender's API returns; messages received (distinct) per second
//!   from the first send to the last receive (one host, one clock), and the
//!   share lost; next to plain Zenoh's. A round trip that got no answer
//!   within a second counts as one second.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{Ipv4Addr, TcpListener};
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

/// How long a sink waits after the last data message before it reports.
const IDLE: Duration = Duration::from_secs(2);

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
                loop {
                    let wait = sink.wait();
                    let m = match tokio::time::timeout(wait, sub.recv()).await {
                        Ok(Some(m)) => m.value,
                        Ok(None) => break,
                        Err(_) => {
                            sink.report();
                            continue;
                        }
                    };
                    if echo {
                        pong.publish_bytes(&m)?;
                    } else {
                        sink.take(&m);
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

/// A sink's count: it reports `{"warm": true}` at the first warm-up
/// message, and `{"received", "bytes", "secs"}` once data stopped for
/// [`IDLE`].
#[derive(Default)]
struct Sink {
    warm: bool,
    received: u64,
    seen: std::collections::HashSet<u64>,
    first: Option<Instant>,
    last: Option<Instant>,
}

impl Sink {
    fn take(&mut self, m: &[u8]) {
        match m.first() {
            Some(&WARM) if !self.warm => {
                self.warm = true;
                say(&json!({"warm": true}));
            }
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
            *self = Sink {
                warm: false,
                ..Sink::default()
            };
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
            .stderr(Stdio::null())
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

/// A burst of `count` messages to a sink; returns (messages a second
/// received, share lost).
async fn burst(path: Path<'_>, sink: &Proc, size: usize, count: usize) -> Result<Burst> {
    let out = Out::new(&path, "bench/data").await?;
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if Instant::now() > deadline {
            bail!("the sink heard no warm-up within 30 s");
        }
        out.send(message(size, WARM, 0)).await?;
        if sink.wait_for("warm", Duration::from_millis(100)).is_ok() {
            break;
        }
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let first_send = unix_ms();
    for n in 0..count as u64 {
        out.send(message(size, DATA, n)).await?;
    }
    let sent_for = unix_ms() - first_send;
    // Nothing arrived at all: no report comes, and the row is all loss.
    let Ok(report) = sink.wait_for("received", Duration::from_secs(60)) else {
        return Ok(Burst {
            rate: 0.0,
            loss: 1.0,
            duplicates: 0,
            sent_ms: sent_for,
        });
    };
    let received = report["received"].as_f64().unwrap_or(0.0);
    let secs =
        ((report["last_unix_ms"].as_f64().unwrap_or(first_send) - first_send) / 1e3).max(1e-3);
    Ok(Burst {
        rate: received / secs,
        loss: 1.0 - received / count as f64,
        duplicates: report["duplicates"].as_u64().unwrap_or(0),
        sent_ms: sent_for,
    })
}

/// One burst's figures.
#[derive(Debug, Clone, Copy)]
struct Burst {
    /// Distinct messages received a second, first send to last receive.
    rate: f64,
    /// Share of the burst not received.
    loss: f64,
    /// Messages received more than once.
    duplicates: u64,
    /// How long the sender took to send the burst.
    sent_ms: f64,
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

async fn bench(args: &BenchArgs) -> Result<()> {
    let (pa, pb) = (pulicast::unused_port()?, pulicast::unused_port()?);
    let link = format!("tcp/127.0.0.1:{}", free_tcp()?);
    let prefix = format!("bench{}", std::process::id());
    let mut rows: HashMap<String, Value> = HashMap::new();
    let node_a = site_node("bench-talker", pa).await?;
    for &size in &args.sizes {
        if !(9..=pulicast::wire::fragment::MAX_MESSAGE).contains(&size) {
            bail!(
                "--sizes: {size} B is not between 9 B (a kind and a number) and {} B",
                pulicast::wire::fragment::MAX_MESSAGE
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
        eprintln!("bench: {size} B: pulicast on one site");
        // Pulicast on one site: the local hops alone.
        let local = {
            let _echo = role_proc("echo-pulicast", &["--port".into(), pa.to_string()])?;
            round_trips(Path::Pulicast(&node_a), size, args.rounds).await?
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
            let thr = burst(Path::Zenoh(&session2), &sink, size, count).await?;
            let _ = session.close().await;
            let _ = session2.close().await;
            (rtt, thr)
        };
        eprintln!("bench: {size} B: through two bridges");
        let (bridged_rtt, bridged_thr) = {
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
                    "0s",
                    link_flag,
                    &link,
                ]
                .iter()
                .map(|s| s.to_string())
                .collect();
                Proc::start(&args, site)
            };
            let _a = bridge(pa, "bench-a", "--listen")?;
            let _b = bridge(pb, "bench-b", "--connect")?;
            let rtt = {
                let _echo = role_proc("echo-pulicast", &["--port".into(), pb.to_string()])?;
                round_trips(Path::Pulicast(&node_a), size, args.rounds).await?
            };
            let sink = role_proc("sink-pulicast", &["--port".into(), pb.to_string()])?;
            let thr = burst(Path::Pulicast(&node_a), &sink, size, count).await?;
            (rtt, thr)
        };
        let expected = zenoh_rtt.0 + 2.0 * local.0;
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
                    "bridged": {"msgs_per_s": bridged_thr.rate, "loss": bridged_thr.loss, "duplicates": bridged_thr.duplicates, "sent_ms": bridged_thr.sent_ms},
                    "zenoh": {"msgs_per_s": zenoh_thr.rate, "loss": zenoh_thr.loss, "duplicates": zenoh_thr.duplicates, "sent_ms": zenoh_thr.sent_ms},
                    "ratio": bridged_thr.rate / zenoh_thr.rate.max(1e-9),
                },
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
    println!("throughput, a burst                 msgs/s      loss  dups  sent in");
    for s in &sizes {
        let r = &rows[&s.to_string()];
        let t = &r["throughput"];
        for (label, key) in [("through two bridges", "bridged"), ("plain Zenoh", "zenoh")] {
            println!(
                "  {s:>6} B {label:<22} {:>9.0} {:>8.1}% {:>5} {:>6.0} ms",
                t[key]["msgs_per_s"].as_f64().unwrap_or(0.0),
                t[key]["loss"].as_f64().unwrap_or(0.0) * 100.0,
                t[key]["duplicates"],
                t[key]["sent_ms"].as_f64().unwrap_or(0.0)
            );
        }
        println!(
            "  {s:>6} B bridged / Zenoh: {:.2} (target >= 0.8), burst of {}",
            t["ratio"].as_f64().unwrap_or(0.0),
            r["messages"]
        );
    }
    Ok(())
}

//! `puli bench thr` and `puli bench lat`: pulicast against the raw socket.
//!
//! Every measurement runs twice in the same invocation, interleaved: once
//! through pulicast, once through a plain socket2 UDP multicast socket (one
//! datagram per message, the same sizes, the same process layout, the same
//! 4 MiB receive buffer). Results are reported as ratios ours/raw, which
//! survive a noisy machine better than absolute figures.
//!
//! - `thr`: a publisher process sends N messages as fast as it can; a
//!   subscriber process counts them. Rate is measured at the subscriber
//!   (first to last message); loss is 1 - received/sent; CPU per message and
//!   peak RSS come from `getrusage` in each process.
//! - `lat`: a pinger process publishes on `ping` and waits for the pong that a
//!   ponger process publishes back on receipt; round trips in microseconds.

use std::io::{BufRead, BufReader, Write};
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use pulicast::Node;
use serde_json::{json, Value};
use socket2::{Domain, Protocol, Socket, Type};

use crate::unix_ns;

/// Receive buffer both sides ask for by default (pulicast's default).
const RCVBUF: usize = pulicast::DEFAULT_RECEIVE_BUFFER;
/// Largest message size measured (pulicast's limit is 64 MiB).
const MAX_SIZE: usize = 64 << 20;
/// The raw baseline sends larger messages as datagrams of this size.
const RAW_CHUNK: usize = 60_000;

/// Which path a run measures.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Path {
    /// Plain UDP multicast, one datagram per message.
    Raw,
    /// A pulicast node publishing and subscribing.
    Pulicast,
}

/// Whether pulicast's channels are sealed in a run (see `docs/security.md`).
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Seal {
    /// Plain Pulicast 2.x datagrams.
    #[default]
    None,
    /// Sealed: authenticated, replay-protected, readable.
    Auth,
    /// Sealed and encrypted.
    Encrypt,
}

impl Seal {
    fn name(self) -> &'static str {
        match self {
            Seal::None => "none",
            Seal::Auth => "auth",
            Seal::Encrypt => "encrypt",
        }
    }
}

/// Options of `puli bench thr`.
#[derive(clap::Args, Debug, Clone)]
pub struct ThrArgs {
    /// Message sizes in bytes (comma-separated). Above one datagram, pulicast
    /// fragments; the raw baseline sends the same bytes as 60 000-byte
    /// datagrams.
    #[arg(long, value_delimiter = ',', default_values_t = [8usize, 64, 1024, 8192, 60000, 1 << 20, 16 << 20])]
    pub size: Vec<usize>,
    /// Messages per run (default: about 1 s worth at raw speed, at most 200 000).
    #[arg(long, conflicts_with = "for_secs")]
    pub count: Option<u64>,
    /// Publish for this many seconds per run instead of a count.
    #[arg(long = "for", value_name = "SECS")]
    pub for_secs: Option<f64>,
    /// Batch pulicast's messages with this maximum delay (e.g. `1ms`,
    /// `200us`); the raw baseline still sends one datagram per message.
    #[arg(long, value_name = "DELAY", value_parser = humantime::parse_duration)]
    pub batch: Option<Duration>,
    /// How long pulicast's receive loops poll before parking (see
    /// `NodeBuilder::receive_spin`; `0s` parks at once like the raw
    /// baseline's blocking receive).
    #[arg(long, value_name = "DURATION", value_parser = humantime::parse_duration)]
    pub spin: Option<Duration>,
    /// Receive buffer both paths ask for, in bytes (the kernel grants at
    /// most `net.core.rmem_max`, and reports twice that).
    #[arg(long, value_name = "BYTES", default_value_t = RCVBUF)]
    pub rcvbuf: usize,
    /// Runs of each path per size; the median is reported.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
    /// Seal pulicast's channels with a fleet key (`auth`), and encrypt
    /// them too (`encrypt`); the raw baseline stays plain.
    #[arg(long, value_enum, default_value_t = Seal::None)]
    pub seal: Seal,
    /// UDP port (default: a free one).
    #[arg(long)]
    pub port: Option<u16>,
    /// One JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// Options of `puli bench lat`.
#[derive(clap::Args, Debug, Clone)]
pub struct LatArgs {
    /// Message size in bytes.
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// Round trips per run.
    #[arg(long, default_value_t = 5000)]
    pub rounds: u64,
    /// Runs of each path; interleaved, all samples pooled.
    #[arg(long, default_value_t = 2)]
    pub runs: usize,
    /// The pinger batches with this maximum delay (e.g. `1ms`): the round
    /// trip then shows the latency batching adds.
    #[arg(long, value_name = "DELAY", value_parser = humantime::parse_duration)]
    pub batch: Option<Duration>,
    /// Seal pulicast's channels (`auth`), and encrypt them too (`encrypt`).
    #[arg(long, value_enum, default_value_t = Seal::None)]
    pub seal: Seal,
    /// How long pulicast's receive loops poll before parking (see
    /// `NodeBuilder::receive_spin`; `0s` parks at once like the raw
    /// baseline's blocking receive).
    #[arg(long, value_name = "DURATION", value_parser = humantime::parse_duration)]
    pub spin: Option<Duration>,
    /// UDP port (default: a free one).
    #[arg(long)]
    pub port: Option<u16>,
    /// One JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// Options of `puli bench mem`.
#[derive(clap::Args, Debug, Clone)]
pub struct MemArgs {
    /// Message size in bytes.
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// Messages in all; RSS is compared after a tenth of them and at the end.
    #[arg(long, default_value_t = 10_000_000)]
    pub messages: u64,
    /// UDP port (default: a free one).
    #[arg(long)]
    pub port: Option<u16>,
}

/// Options of the hidden role processes.
#[derive(clap::Args, Debug, Clone)]
pub struct RoleArgs {
    #[arg(long, value_enum)]
    path: Path,
    #[arg(long)]
    port: u16,
    #[arg(long)]
    size: usize,
    #[arg(long, default_value_t = 0)]
    count: u64,
    /// Publisher: stop after this many seconds, whatever the count.
    #[arg(long = "for")]
    for_secs: Option<f64>,
    /// Publisher: batch with this delay, in microseconds.
    #[arg(long)]
    batch_us: Option<u64>,
    /// Receive spin, in microseconds (default: the library's).
    #[arg(long)]
    spin_us: Option<u64>,
    /// Receive buffer to ask for.
    #[arg(long, default_value_t = RCVBUF)]
    rcvbuf: usize,
    /// Seal the channels.
    #[arg(long, value_enum, default_value_t = Seal::None)]
    seal: Seal,
}

impl RoleArgs {
    fn batch(&self) -> Option<Duration> {
        self.batch_us.map(Duration::from_micros)
    }

    async fn node(&self, name: &str) -> Result<Node> {
        let spin = self
            .spin_us
            .map_or(pulicast::DEFAULT_RECEIVE_SPIN, Duration::from_micros);
        let mut builder = Node::new(name)
            .port(self.port)
            .interface(Ipv4Addr::LOCALHOST)
            .queue_capacity(1 << 16)
            .receive_spin(spin)
            .receive_buffer(self.rcvbuf)
            .keys_from_env(false);
        if self.seal != Seal::None {
            // A key known to everyone who reads this: fine for measuring.
            builder = builder
                .key("/", pulicast::Key::from_bytes([0x42; 32]))
                .encrypt(self.seal == Seal::Encrypt);
        }
        Ok(builder.start().await?)
    }

    /// Until when a publisher may send (bounded even without `--for`).
    fn send_deadline(&self) -> Instant {
        let secs = self.for_secs.unwrap_or(600.0).clamp(0.0, 600.0);
        Instant::now() + Duration::from_secs_f64(secs)
    }
}

/// What a role process is told besides its role and path.
#[derive(Debug, Clone, Copy, Default)]
struct Setup {
    port: u16,
    size: usize,
    count: u64,
    for_secs: Option<f64>,
    batch: Option<Duration>,
    spin: Option<Duration>,
    rcvbuf: usize,
    seal: Seal,
}

/// CPU seconds (user + system) and peak RSS (KiB) of this process, from
/// /proc (USER_HZ ticks of 10 ms: runs last about a second or more).
fn usage() -> (f64, u64) {
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
fn status_kb(field: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|status| {
            let line = status.lines().find(|l| l.starts_with(field))?;
            line.split_whitespace().nth(1)?.parse().ok()
        })
        .unwrap_or(0)
}

/// Becomes ready when the orchestrator writes a line (or closes) stdin.
fn end_signal() -> std::sync::mpsc::Receiver<()> {
    let (tx, rx) = std::sync::mpsc::channel::<()>();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = std::io::stdin().read_line(&mut line);
        let _ = tx.send(());
    });
    rx
}

/// What a subscriber role counted.
#[derive(Default)]
struct Tally {
    received: u64,
    bytes: u64,
    first: u128,
    last: u128,
}

impl Tally {
    /// Counts one message; the clock is read for the first only.
    fn record(&mut self, len: usize) {
        if self.received == 0 {
            self.first = unix_ns();
            self.last = self.first;
        }
        self.received += 1;
        self.bytes += len as u64;
    }

    /// Marks the time of the latest arrival: called after each message or
    /// each run of queued messages, so reading the clock does not dominate
    /// what is measured at millions of messages per second.
    fn stamp(&mut self) {
        self.last = unix_ns();
    }
}

fn group(name: &str, port: u16) -> SocketAddrV4 {
    SocketAddrV4::new(pulicast::group_for(name), port)
}

fn raw_sender() -> Result<UdpSocket> {
    let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    s.set_multicast_if_v4(&Ipv4Addr::LOCALHOST)?;
    s.set_multicast_ttl_v4(0)?;
    s.set_multicast_loop_v4(true)?;
    s.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0)).into())?;
    Ok(s.into())
}

fn raw_receiver(group: SocketAddrV4, rcvbuf: usize) -> Result<UdpSocket> {
    let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    s.set_reuse_address(true)?;
    s.set_multicast_all_v4(false)?;
    let _ = s.set_recv_buffer_size(rcvbuf);
    s.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, group.port())).into())?;
    s.join_multicast_v4(group.ip(), &Ipv4Addr::LOCALHOST)?;
    Ok(s.into())
}

/// The single-threaded runtime every role runs on: the benchmark measures
/// one receive thread per process, like the raw baseline.
fn current_thread() -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
}

fn emit(v: Value) {
    crate::outln!("{v}");
}

/// The throughput publisher role.
pub fn thr_pub(args: &RoleArgs) -> Result<()> {
    let payload = vec![0xa5u8; args.size];
    let start;
    let mut sent = 0u64;
    // The clock is read once per 256 messages: cheap, and still bounded.
    let deadline = args.send_deadline();
    let running = |sent: u64| sent < args.count && (sent % 256 != 0 || Instant::now() < deadline);
    match args.path {
        Path::Raw => {
            let socket = raw_sender()?;
            let to = group("bench/thr", args.port);
            start = Instant::now();
            while running(sent) {
                for chunk in payload.chunks(RAW_CHUNK) {
                    socket.send_to(chunk, to)?;
                }
                sent += 1;
            }
        }
        Path::Pulicast => {
            let runtime = current_thread()?;
            let node = runtime.block_on(args.node("thr-pub"))?;
            let channel = node.channel("bench/thr");
            if let Some(delay) = args.batch() {
                channel.enable_batching(delay)?;
            }
            start = Instant::now();
            while running(sent) {
                channel.publish_bytes(&payload)?;
                sent += 1;
            }
            channel.flush()?;
        }
    }
    let secs = start.elapsed().as_secs_f64();
    let (cpu, rss) = usage();
    emit(json!({"sent": sent, "secs": secs, "cpu_s": cpu, "rss_kb": rss}));
    Ok(())
}

/// The throughput subscriber role: counts until told `end` on stdin.
pub fn thr_sub(args: &RoleArgs) -> Result<()> {
    let end = end_signal();
    let mut tally = Tally::default();
    match args.path {
        Path::Raw => {
            let socket = raw_receiver(group("bench/thr", args.port), args.rcvbuf)?;
            socket.set_read_timeout(Some(Duration::from_millis(50)))?;
            let mut buf = vec![0u8; 65536];
            emit(json!({"ready": true}));
            loop {
                match socket.recv_from(&mut buf) {
                    Ok((n, _)) => {
                        tally.record(n);
                        tally.stamp();
                    }
                    Err(_) if end.try_recv().is_ok() => break,
                    Err(_) => {}
                }
            }
        }
        Path::Pulicast => {
            let runtime = current_thread()?;
            runtime.block_on(async {
                let node = args.node("thr-sub").await?;
                let mut sub = node.channel("bench/thr").subscribe_raw()?;
                emit(json!({"ready": true}));
                loop {
                    // What is queued is taken without a timer (which would
                    // read the clock per message); the timer only guards
                    // the wait.
                    let before = tally.received;
                    while let Some(m) = sub.try_recv() {
                        tally.record(m.value.len());
                    }
                    if tally.received > before {
                        tally.stamp();
                    }
                    match tokio::time::timeout(Duration::from_millis(50), sub.recv()).await {
                        Ok(Some(m)) => {
                            tally.record(m.value.len());
                            tally.stamp();
                        }
                        _ if end.try_recv().is_ok() => break,
                        _ => {}
                    }
                }
                anyhow::Ok(())
            })?;
        }
    }
    let Tally {
        received,
        bytes,
        first,
        last,
    } = tally;
    let (cpu, rss) = usage();
    emit(json!({
        "received": received, "bytes": bytes, "first_ns": first as f64, "last_ns": last as f64,
        "cpu_s": cpu, "rss_kb": rss,
    }));
    Ok(())
}

/// The memory subscriber role: reports RSS after a tenth of `count`
/// messages and at the end (stdin `end`).
pub fn mem_sub(args: &RoleArgs) -> Result<()> {
    let rx = end_signal();
    let runtime = current_thread()?;
    runtime.block_on(async {
        let node = args.node("mem-sub").await?;
        let mut sub = node.channel("bench/thr").subscribe_raw()?;
        emit(json!({"ready": true}));
        let mut received = 0u64;
        let mark = (args.count / 10).max(1);
        loop {
            match tokio::time::timeout(Duration::from_millis(50), sub.recv()).await {
                Ok(Some(_)) => {
                    received += 1;
                    if received == mark {
                        emit(json!({"received": received, "rss_kb": status_kb("VmRSS:")}));
                    }
                }
                _ => {
                    if rx.try_recv().is_ok() {
                        break;
                    }
                }
            }
        }
        emit(json!({"received": received, "rss_kb": status_kb("VmRSS:")}));
        anyhow::Ok(())
    })
}

/// Runs `puli bench mem`: subscriber memory after many messages.
pub fn mem(args: &MemArgs) -> Result<()> {
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let setup = Setup {
        port,
        size: args.size,
        count: args.messages,
        ..Setup::default()
    };
    let mut sub = spawn_ready("mem-sub", Path::Pulicast, setup)?;
    let mut publisher = spawn_role("thr-pub", Path::Pulicast, setup)?;
    let first = read_json(&mut sub)?;
    let sent = read_json(&mut publisher)?;
    let _ = publisher.wait();
    let last = finish_sub(&mut sub)?;
    let (early, late) = (
        first["rss_kb"].as_f64().unwrap_or(0.0),
        last["rss_kb"].as_f64().unwrap_or(0.0),
    );
    crate::outln!(
        "subscriber RSS after {} messages: {:.1} MB; after {}: {:.1} MB ({:+.1} %); {} sent",
        first["received"],
        early / 1024.0,
        last["received"],
        late / 1024.0,
        (late / early.max(1.0) - 1.0) * 100.0,
        sent["sent"]
    );
    Ok(())
}

/// The latency ponger role: echoes every ping as a pong until stdin closes.
pub fn lat_pong(args: &RoleArgs) -> Result<()> {
    match args.path {
        Path::Raw => {
            let rx = raw_receiver(group("bench/ping", args.port), args.rcvbuf)?;
            let tx = raw_sender()?;
            let to = group("bench/pong", args.port);
            rx.set_read_timeout(Some(Duration::from_millis(200)))?;
            let mut buf = vec![0u8; 65536];
            emit(json!({"ready": true}));
            let deadline = Instant::now() + Duration::from_secs(600);
            while Instant::now() < deadline {
                if let Ok((n, _)) = rx.recv_from(&mut buf) {
                    if n == 0 {
                        break;
                    }
                    tx.send_to(&buf[..n], to)?;
                }
            }
        }
        Path::Pulicast => {
            let runtime = current_thread()?;
            runtime.block_on(async {
                let node = args.node("lat-pong").await?;
                let mut pings = node.channel("bench/ping").subscribe_raw()?;
                let pong = node.channel("bench/pong");
                emit(json!({"ready": true}));
                let deadline = tokio::time::Instant::now() + Duration::from_secs(600);
                while let Ok(Some(m)) = tokio::time::timeout_at(deadline, pings.recv()).await {
                    if m.value.is_empty() {
                        break;
                    }
                    pong.publish_bytes(&m.value)?;
                }
                anyhow::Ok(())
            })?;
        }
    }
    Ok(())
}

/// The latency pinger role: `count` round trips, one at a time.
pub fn lat_ping(args: &RoleArgs) -> Result<()> {
    let payload = vec![0x5au8; args.size.max(1)];
    let mut samples = Vec::with_capacity(args.count as usize);
    let timeout = Duration::from_secs(1);
    let mut lost = 0u64;
    match args.path {
        Path::Raw => {
            let tx = raw_sender()?;
            let rx = raw_receiver(group("bench/pong", args.port), args.rcvbuf)?;
            rx.set_read_timeout(Some(timeout))?;
            let to = group("bench/ping", args.port);
            let mut buf = vec![0u8; 65536];
            // Warm up, so the first samples don't carry setup costs.
            for round in 0..args.count + 100 {
                let t = Instant::now();
                tx.send_to(&payload, to)?;
                match rx.recv_from(&mut buf) {
                    Ok(_) if round >= 100 => samples.push(t.elapsed().as_secs_f64() * 1e6),
                    Ok(_) => {}
                    Err(_) => lost += 1,
                }
            }
            tx.send_to(&[], to)?;
        }
        Path::Pulicast => {
            let runtime = current_thread()?;
            runtime.block_on(async {
                let node = args.node("lat-ping").await?;
                let mut pongs = node.channel("bench/pong").subscribe_raw()?;
                let ping = node.channel("bench/ping");
                if let Some(delay) = args.batch() {
                    ping.enable_batching(delay)?;
                }
                for round in 0..args.count + 100 {
                    let t = Instant::now();
                    ping.publish_bytes(&payload)?;
                    match tokio::time::timeout(timeout, pongs.recv()).await {
                        Ok(Some(_)) if round >= 100 => {
                            samples.push(t.elapsed().as_secs_f64() * 1e6)
                        }
                        Ok(Some(_)) => {}
                        _ => lost += 1,
                    }
                }
                ping.publish_bytes(&[])?;
                anyhow::Ok(())
            })?;
        }
    }
    emit(json!({"samples_us": samples, "lost": lost}));
    Ok(())
}

fn spawn_role(role: &str, path: Path, setup: Setup) -> Result<Child> {
    let exe = std::env::current_exe()?;
    let path = match path {
        Path::Raw => "raw",
        Path::Pulicast => "pulicast",
    };
    let mut args = vec![
        "bench".to_string(),
        role.into(),
        "--path".into(),
        path.into(),
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
    if setup.rcvbuf != 0 {
        args.extend(["--rcvbuf".into(), setup.rcvbuf.to_string()]);
    }
    args.extend(["--seal".into(), setup.seal.name().into()]);
    Command::new(exe)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .context("starting a benchmark process")
}

/// Starts a role that announces `{"ready": true}` and waits for it.
fn spawn_ready(role: &str, path: Path, setup: Setup) -> Result<Child> {
    let mut child = spawn_role(role, path, setup)?;
    let ready = read_json(&mut child)?;
    if ready["ready"] != true {
        bail!("{role} not ready: {ready}");
    }
    Ok(child)
}

/// Tells a subscriber role that the publisher is done (after a grace period
/// for datagrams in flight) and reads its report.
fn finish_sub(sub: &mut Child) -> Result<Value> {
    std::thread::sleep(Duration::from_millis(300));
    if let Some(stdin) = sub.stdin.as_mut() {
        writeln!(stdin, "end")?;
    }
    let report = read_json(sub)?;
    let _ = sub.wait();
    Ok(report)
}

fn read_json(child: &mut Child) -> Result<Value> {
    let stdout = child.stdout.as_mut().context("no stdout")?;
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line)?;
    serde_json::from_str(&line).with_context(|| format!("unexpected output {line:?}"))
}

/// One throughput run's figures.
#[derive(Debug, Clone, Copy, Default)]
struct ThrRun {
    rate: f64,
    loss: f64,
    pub_cpu_per_msg_us: f64,
    sub_cpu_per_msg_us: f64,
    pub_rss_kb: f64,
    sub_rss_kb: f64,
}

fn thr_run(path: Path, setup: Setup) -> Result<ThrRun> {
    let size = setup.size;
    let mut sub = spawn_ready("thr-sub", path, Setup { count: 0, ..setup })?;
    let mut publisher = spawn_role("thr-pub", path, setup)?;
    let sent = read_json(&mut publisher)?;
    let _ = publisher.wait();
    let got = finish_sub(&mut sub)?;
    // Counted in bytes, so that a raw "message" sent as several datagrams
    // and a fragmented pulicast message compare alike.
    let received = got["received"].as_f64().unwrap_or(0.0);
    let messages = got["bytes"].as_f64().unwrap_or(0.0) / size as f64;
    let span =
        (got["last_ns"].as_f64().unwrap_or(0.0) - got["first_ns"].as_f64().unwrap_or(0.0)) / 1e9;
    let sent_n = sent["sent"].as_f64().unwrap_or(0.0);
    // The span runs from the first to the last arrival: one arrival's worth
    // of bytes is outside it.
    let in_span = messages * (received - 1.0).max(0.0) / received.max(1.0);
    Ok(ThrRun {
        rate: if span > 0.0 { in_span / span } else { 0.0 },
        loss: if sent_n > 0.0 {
            (1.0 - messages / sent_n).max(0.0)
        } else {
            0.0
        },
        pub_cpu_per_msg_us: sent["cpu_s"].as_f64().unwrap_or(0.0) / sent_n.max(1.0) * 1e6,
        sub_cpu_per_msg_us: got["cpu_s"].as_f64().unwrap_or(0.0) / received.max(1.0) * 1e6,
        pub_rss_kb: sent["rss_kb"].as_f64().unwrap_or(0.0),
        sub_rss_kb: got["rss_kb"].as_f64().unwrap_or(0.0),
    })
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    if v.is_empty() {
        return 0.0;
    }
    v[v.len() / 2]
}

fn summarize(runs: &[ThrRun]) -> ThrRun {
    let m = |f: fn(&ThrRun) -> f64| median(runs.iter().map(f).collect());
    ThrRun {
        rate: m(|r| r.rate),
        loss: m(|r| r.loss),
        pub_cpu_per_msg_us: m(|r| r.pub_cpu_per_msg_us),
        sub_cpu_per_msg_us: m(|r| r.sub_cpu_per_msg_us),
        pub_rss_kb: m(|r| r.pub_rss_kb),
        sub_rss_kb: m(|r| r.sub_rss_kb),
    }
}

/// Runs `puli bench thr`.
pub fn thr(args: &ThrArgs) -> Result<()> {
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let mut results = Vec::new();
    if !args.json {
        crate::outln!(
            "throughput, publisher and subscriber in separate processes, loopback multicast, {} B receive buffers asked for (net.core.rmem_max {}) (median of {} runs each, interleaved)",
            args.rcvbuf,
            std::fs::read_to_string("/proc/sys/net/core/rmem_max").map_or("unknown".into(), |s| s.trim().to_string()),
            args.rounds
        );
        if let Some(delay) = args.batch {
            crate::outln!("pulicast batches with a maximum delay of {delay:?}; raw sends one datagram per message");
        }
        match args.seal {
            Seal::None => {}
            Seal::Auth => crate::outln!(
                "pulicast seals every datagram (authenticated, replay-protected); raw is plain"
            ),
            Seal::Encrypt => {
                crate::outln!("pulicast seals and encrypts every datagram; raw is plain")
            }
        }
        crate::outln!(
            "{:>9} {:>12} {:>12} {:>7} {:>10} {:>10} {:>13} {:>17} {:>15}",
            "size B",
            "raw msg/s",
            "ours msg/s",
            "ratio",
            "raw MB/s",
            "ours MB/s",
            "loss raw/ours",
            "CPU/msg pub,sub",
            "RSS pub,sub MB"
        );
    }
    for &size in &args.size {
        if size == 0 || size > MAX_SIZE {
            bail!("sizes must be between 1 and {MAX_SIZE} bytes");
        }
        let count = match (args.count, args.for_secs) {
            (Some(count), _) => count,
            (None, Some(_)) => u64::MAX,
            (None, None) => (2_000_000_000u64 / (size as u64 + 64)).clamp(20, 200_000),
        };
        let raw_setup = Setup {
            port,
            size,
            count,
            for_secs: args.for_secs,
            batch: None,
            spin: args.spin,
            rcvbuf: args.rcvbuf,
            seal: Seal::None,
        };
        // Batched, the publisher reaches many times the raw rate: the same
        // count would take a fraction of the time to send.
        let ours_setup = Setup {
            batch: args.batch,
            seal: args.seal,
            count: match (args.batch, args.count, args.for_secs) {
                (Some(_), None, None) => count.saturating_mul(10),
                _ => count,
            },
            ..raw_setup
        };
        let (mut raw, mut ours) = (Vec::new(), Vec::new());
        for _ in 0..args.rounds.max(1) {
            raw.push(thr_run(Path::Raw, raw_setup)?);
            ours.push(thr_run(Path::Pulicast, ours_setup)?);
        }
        let (r, o) = (summarize(&raw), summarize(&ours));
        let ratio = if r.rate > 0.0 { o.rate / r.rate } else { 0.0 };
        results.push(json!({
            "size": size, "count": count, "batch_us": args.batch.map(|d| d.as_micros() as u64), "seal": args.seal.name(),
            "raw": {"msgs_per_s": r.rate, "mb_per_s": r.rate * size as f64 / 1e6, "loss": r.loss, "pub_cpu_us_per_msg": r.pub_cpu_per_msg_us, "sub_cpu_us_per_msg": r.sub_cpu_per_msg_us, "pub_rss_kb": r.pub_rss_kb, "sub_rss_kb": r.sub_rss_kb},
            "pulicast": {"msgs_per_s": o.rate, "mb_per_s": o.rate * size as f64 / 1e6, "loss": o.loss, "pub_cpu_us_per_msg": o.pub_cpu_per_msg_us, "sub_cpu_us_per_msg": o.sub_cpu_per_msg_us, "pub_rss_kb": o.pub_rss_kb, "sub_rss_kb": o.sub_rss_kb},
            "ratio": ratio,
        }));
        if !args.json {
            crate::outln!(
                "{size:>9} {:>12.0} {:>12.0} {:>7.2} {:>10.1} {:>10.1} {:>6.1}%/{:>4.1}% {:>8.2},{:>4.2} µs {:>7.1},{:>5.1}",
                r.rate,
                o.rate,
                ratio,
                r.rate * size as f64 / 1e6,
                o.rate * size as f64 / 1e6,
                r.loss * 100.0,
                o.loss * 100.0,
                o.pub_cpu_per_msg_us,
                o.sub_cpu_per_msg_us,
                o.pub_rss_kb / 1024.0,
                o.sub_rss_kb / 1024.0
            );
        }
    }
    if args.json {
        crate::outln!(
            "{}",
            json!({"benchmark": "thr", "port": port, "results": results})
        );
    }
    Ok(())
}

fn lat_run(path: Path, setup: Setup) -> Result<(Vec<f64>, u64)> {
    let mut pong = spawn_ready("lat-pong", path, Setup { count: 0, ..setup })?;
    let mut ping = spawn_role("lat-ping", path, setup)?;
    let result = read_json(&mut ping)?;
    let _ = ping.wait();
    drop(pong.stdin.take());
    let deadline = Instant::now() + Duration::from_secs(3);
    while Instant::now() < deadline {
        if let Ok(Some(_)) = pong.try_wait() {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    // Only our own child, by its handle.
    if let Ok(None) = pong.try_wait() {
        let _ = pong.kill();
        let _ = pong.wait();
    }
    let samples = result["samples_us"]
        .as_array()
        .map(|a| a.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default();
    Ok((samples, result["lost"].as_u64().unwrap_or(0)))
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// Runs `puli bench lat`.
pub fn lat(args: &LatArgs) -> Result<()> {
    if args.size == 0 || args.size > RAW_CHUNK {
        bail!("--size must be between 1 and {RAW_CHUNK} bytes");
    }
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let (mut raw, mut ours) = (Vec::new(), Vec::new());
    let (mut raw_lost, mut ours_lost) = (0, 0);
    let setup = Setup {
        port,
        size: args.size,
        count: args.rounds,
        spin: args.spin,
        ..Setup::default()
    };
    for _ in 0..args.runs.max(1) {
        let (s, l) = lat_run(Path::Raw, setup)?;
        raw.extend(s);
        raw_lost += l;
        let batch = args.batch;
        let seal = args.seal;
        let (s, l) = lat_run(
            Path::Pulicast,
            Setup {
                batch,
                seal,
                ..setup
            },
        )?;
        ours.extend(s);
        ours_lost += l;
    }
    raw.sort_by(|a, b| a.total_cmp(b));
    ours.sort_by(|a, b| a.total_cmp(b));
    let stats = |v: &[f64]| [0.5, 0.9, 0.99, 1.0].map(|p| percentile(v, p));
    let (r, o) = (stats(&raw), stats(&ours));
    if args.json {
        crate::outln!(
            "{}",
            json!({
                "benchmark": "lat", "size": args.size, "rounds": raw.len(),
                "batch_us": args.batch.map(|d| d.as_micros() as u64), "seal": args.seal.name(),
                "raw_us": {"p50": r[0], "p90": r[1], "p99": r[2], "max": r[3], "lost": raw_lost},
                "pulicast_us": {"p50": o[0], "p90": o[1], "p99": o[2], "max": o[3], "lost": ours_lost},
                "ratio": {"p50": o[0] / r[0], "p99": o[2] / r[2]},
            })
        );
        return Ok(());
    }
    crate::outln!("round trip, {} B, ping and pong in separate processes, loopback multicast ({} round trips each), pulicast sealing: {}", args.size, raw.len(), args.seal.name());
    crate::outln!(
        "{:>10} {:>9} {:>9} {:>9} {:>9} {:>6}",
        "",
        "p50 µs",
        "p90 µs",
        "p99 µs",
        "max µs",
        "lost"
    );
    crate::outln!(
        "{:>10} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>6}",
        "raw",
        r[0],
        r[1],
        r[2],
        r[3],
        raw_lost
    );
    crate::outln!(
        "{:>10} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>6}",
        "pulicast",
        o[0],
        o[1],
        o[2],
        o[3],
        ours_lost
    );
    crate::outln!(
        "{:>10} {:>9.2} {:>9.2} {:>9.2} {:>9.2}",
        "ratio",
        o[0] / r[0],
        o[1] / r[1],
        o[2] / r[2],
        o[3] / r[3]
    );
    if let Some(delay) = args.batch {
        crate::outln!(
            "the pinger batched with a maximum delay of {delay:?}: {:.1} µs added at p50, {:.1} µs at p99",
            o[0] - r[0],
            o[2] - r[2]
        );
    }
    Ok(())
}

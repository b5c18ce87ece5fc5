//! `puli bench thr` and `puli bench lat`: pulicast, received the ways users
//! receive, against the raw socket received two ways.
//!
//! Every measurement runs each row in the same invocation, interleaved:
//! two raw baselines (a plain socket2 UDP multicast socket, one datagram per
//! message, the same sizes, the same process layout and receive buffer),
//! one blocking in `recv` and one busy-polling a non-blocking socket, and
//! pulicast with default settings, one row per consumer style: `recv().await`
//! on the user's runtime, the blocking `recv_timeout` loop, `recv_many`
//! draining, and a callback handler. Ratios are against the blocking raw
//! socket, which survive a noisy machine better than absolute figures; the
//! busy-polling row shows the wake-up floor, so "faster than raw" can't come
//! from comparing a spinning receiver with a blocking one.
//!
//! - `thr`: a publisher process sends for a time (`--for`) as fast as it
//!   can; a subscriber process counts. Rate is measured at the subscriber
//!   (first to last message); loss is 1 - received/sent; CPU per message
//!   and peak RSS come from /proc in each process.
//! - `lat`: a pinger process publishes on `ping` and waits for the pong that
//!   a ponger process publishes back on receipt; round trips in
//!   microseconds.

use std::io::{BufRead, BufReader, Write};
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4, UdpSocket};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use pulicast::{Node, NodeBuilder};
use serde_json::{json, Value};
use socket2::{Domain, Protocol, Socket, Type};

use crate::unix_ns;

/// Receive buffer both sides ask for by default (pulicast's default).
const RCVBUF: usize = pulicast::DEFAULT_RECEIVE_BUFFER;
/// Largest message size measured (pulicast's limit is 64 MiB).
const MAX_SIZE: usize = 64 << 20;
/// The raw baseline sends larger messages as datagrams of this size.
const RAW_CHUNK: usize = 60_000;
/// Most messages a `recv_many` consumer takes per call.
const MANY: usize = 1024;
/// How long blocking consumers wait per call before they look whether the
/// run is over.
const POLL_END: Duration = Duration::from_millis(50);

/// How a row sends and receives.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Path {
    /// Plain UDP multicast, a blocking `recv` per datagram.
    Raw,
    /// Plain UDP multicast, a non-blocking socket polled in a loop
    /// (busy-polling: no wake-ups, a whole core).
    RawSpin,
    /// pulicast, `Subscription::recv().await` on the program's own
    /// current-thread runtime (`NodeBuilder::start`).
    Await,
    /// pulicast, a `NodeBuilder::start_blocking` node and a
    /// `Subscription::recv_timeout` loop (the blocking facade).
    Timeout,
    /// pulicast, a `start_blocking` node and `recv_many_timeout`, up to
    /// 1024 messages per call.
    Many,
    /// pulicast, a `start_blocking` node and a `subscribe_raw_with`
    /// handler.
    Callback,
}

impl Path {
    fn name(self) -> &'static str {
        match self {
            Path::Raw => "raw",
            Path::RawSpin => "raw-spin",
            Path::Await => "await",
            Path::Timeout => "timeout",
            Path::Many => "many",
            Path::Callback => "callback",
        }
    }

    /// What the row is, for the table.
    fn label(self) -> &'static str {
        match self {
            Path::Raw => "raw, blocking recv",
            Path::RawSpin => "raw, busy-polling recv",
            Path::Await => "pulicast, recv().await",
            Path::Timeout => "pulicast, recv_timeout",
            Path::Many => "pulicast, recv_many",
            Path::Callback => "pulicast, callback",
        }
    }

    fn is_raw(self) -> bool {
        matches!(self, Path::Raw | Path::RawSpin)
    }
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
    /// The rows to run (comma-separated), interleaved in each round.
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [Path::Raw, Path::RawSpin, Path::Await, Path::Timeout, Path::Many, Path::Callback])]
    pub rows: Vec<Path>,
    /// Seconds each publisher sends per run.
    #[arg(long = "for", value_name = "SECS", default_value_t = 1.0)]
    pub for_secs: f64,
    /// Send this many messages per run instead (stopping at `--for` anyway).
    #[arg(long)]
    pub count: Option<u64>,
    /// Publish at most this many messages per second (default: as fast as
    /// the publisher can), to see what receiving costs at a robot's rates:
    /// CPU/msg x rate is the subscriber's share of a core.
    #[arg(long, value_name = "HZ")]
    pub rate: Option<f64>,
    /// Publish round-robin on this many channels, all subscribed by the
    /// subscriber process (the raw rows: one socket per channel, one
    /// blocking thread per socket, or one thread polling them all).
    #[arg(long, default_value_t = 1)]
    pub channels: usize,
    /// Batch pulicast's messages with this maximum delay (e.g. `1ms`,
    /// `200us`); the raw baseline still sends one datagram per message.
    #[arg(long, value_name = "DELAY", value_parser = humantime::parse_duration)]
    pub batch: Option<Duration>,
    /// Not the default: how long pulicast's receive loops poll before
    /// parking (`NodeBuilder::receive_spin`).
    #[arg(long, value_name = "DURATION", value_parser = humantime::parse_duration)]
    pub spin: Option<Duration>,
    /// Not the default: each subscription's queue capacity
    /// (`NodeBuilder::queue_capacity`).
    #[arg(long, value_name = "MESSAGES")]
    pub queue: Option<usize>,
    /// Receive buffer every row asks for, in bytes (the kernel grants at
    /// most `net.core.rmem_max`, and reports twice that).
    #[arg(long, value_name = "BYTES", default_value_t = RCVBUF)]
    pub rcvbuf: usize,
    /// Runs of each row per size; the median is reported.
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
    /// The rows to run (comma-separated), interleaved in each run
    /// (`many` is the same as `timeout` for one message at a time).
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [Path::Raw, Path::RawSpin, Path::Await, Path::Timeout, Path::Callback])]
    pub rows: Vec<Path>,
    /// Round trips per run.
    #[arg(long, default_value_t = 5000)]
    pub rounds: u64,
    /// Runs of each row; interleaved, all samples pooled.
    #[arg(long, default_value_t = 2)]
    pub runs: usize,
    /// The pinger batches with this maximum delay (e.g. `1ms`): the round
    /// trip then shows the latency batching adds.
    #[arg(long, value_name = "DELAY", value_parser = humantime::parse_duration)]
    pub batch: Option<Duration>,
    /// Seal pulicast's channels (`auth`), and encrypt them too (`encrypt`).
    #[arg(long, value_enum, default_value_t = Seal::None)]
    pub seal: Seal,
    /// Not the default: how long pulicast's receive loops poll before
    /// parking (`NodeBuilder::receive_spin`).
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
    #[arg(long, default_value_t = u64::MAX)]
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
    /// Queue capacity (default: the library's).
    #[arg(long)]
    queue: Option<usize>,
    /// Channels, published round-robin, each subscribed.
    #[arg(long, default_value_t = 1)]
    channels: usize,
    /// Publisher: at most this many messages per second (default: as fast
    /// as it can).
    #[arg(long)]
    rate: Option<f64>,
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

    /// The node as a user makes it: the library's defaults, on loopback,
    /// with what the flags changed.
    fn builder(&self, name: &str) -> NodeBuilder {
        let mut builder = Node::new(name)
            .port(self.port)
            .interface(Ipv4Addr::LOCALHOST)
            .receive_buffer(self.rcvbuf)
            .keys_from_env(false);
        if let Some(us) = self.spin_us {
            builder = builder.receive_spin(Duration::from_micros(us));
        }
        if let Some(capacity) = self.queue {
            builder = builder.queue_capacity(capacity);
        }
        if self.seal != Seal::None {
            // A key known to everyone who reads this: fine for measuring.
            builder = builder
                .key("/", pulicast::Key::from_bytes([0x42; 32]))
                .encrypt(self.seal == Seal::Encrypt);
        }
        builder
    }

    /// Until when a publisher may send (bounded even without `--for`).
    fn send_deadline(&self) -> Instant {
        let secs = self.for_secs.unwrap_or(600.0).clamp(0.0, 600.0);
        Instant::now() + Duration::from_secs_f64(secs)
    }
}

/// What a role process is told besides its role and path.
#[derive(Debug, Clone, Copy)]
struct Setup {
    port: u16,
    size: usize,
    count: u64,
    for_secs: Option<f64>,
    batch: Option<Duration>,
    spin: Option<Duration>,
    queue: Option<usize>,
    channels: usize,
    rate: Option<f64>,
    rcvbuf: usize,
    seal: Seal,
}

impl Setup {
    fn new(port: u16, size: usize) -> Self {
        Self {
            port,
            size,
            count: u64::MAX,
            for_secs: None,
            batch: None,
            spin: None,
            queue: None,
            channels: 1,
            rate: None,
            rcvbuf: RCVBUF,
            seal: Seal::None,
        }
    }
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
    /// `received` and `bytes` when `last` was read: the rate is theirs.
    stamped: (u64, u64),
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
        self.stamped = (self.received, self.bytes);
    }

    /// What several consumers counted together: from the first arrival
    /// to the last.
    fn merge(tallies: Vec<Tally>) -> Tally {
        let counted: Vec<Tally> = tallies.into_iter().filter(|t| t.received > 0).collect();
        Tally {
            received: counted.iter().map(|t| t.received).sum(),
            bytes: counted.iter().map(|t| t.bytes).sum(),
            first: counted.iter().map(|t| t.first).min().unwrap_or(0),
            last: counted.iter().map(|t| t.last).max().unwrap_or(0),
            stamped: (
                counted.iter().map(|t| t.stamped.0).sum(),
                counted.iter().map(|t| t.stamped.1).sum(),
            ),
        }
    }
}

pub(crate) fn group(name: &str, port: u16) -> SocketAddrV4 {
    SocketAddrV4::new(pulicast::group_for(name), port)
}

pub(crate) fn raw_sender() -> Result<UdpSocket> {
    let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    s.set_multicast_if_v4(&Ipv4Addr::LOCALHOST)?;
    s.set_multicast_ttl_v4(0)?;
    s.set_multicast_loop_v4(true)?;
    s.bind(&SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0)).into())?;
    Ok(s.into())
}

pub(crate) fn raw_receiver(group: SocketAddrV4, rcvbuf: usize) -> Result<UdpSocket> {
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

/// A non-blocking raw receiver, for busy-polling.
fn raw_spinning_receiver(group: SocketAddrV4, rcvbuf: usize) -> Result<UdpSocket> {
    let socket = raw_receiver(group, rcvbuf)?;
    socket.set_nonblocking(true)?;
    Ok(socket)
}

/// Polls a non-blocking socket until a datagram comes or `give_up` says so
/// (asked every 4096 polls).
fn spin_recv(
    socket: &UdpSocket,
    buf: &mut [u8],
    mut give_up: impl FnMut() -> bool,
) -> Option<usize> {
    let mut polls = 0u32;
    loop {
        match socket.recv_from(buf) {
            Ok((n, _)) => return Some(n),
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                polls = polls.wrapping_add(1);
                if polls % 4096 == 0 && give_up() {
                    return None;
                }
                std::hint::spin_loop();
            }
            Err(_) => return None,
        }
    }
}

/// The name of throughput channel `i`.
fn thr_channel(i: usize) -> String {
    format!("bench/thr{i}")
}

/// The throughput publisher role: raw for the raw rows, a pulicast node
/// (`start_blocking`, defaults) for the others; round-robin over the
/// channels.
pub fn thr_pub(args: &RoleArgs) -> Result<()> {
    let payload = vec![0xa5u8; args.size];
    let start;
    let mut sent = 0u64;
    let channels = args.channels.max(1);
    // The clock is read once per 256 messages: cheap, and still bounded.
    let deadline = args.send_deadline();
    let interval = args.rate.map(|r| Duration::from_secs_f64(1.0 / r));
    let mut next = Instant::now();
    let mut running = |sent: u64| {
        if let Some(interval) = interval {
            // Paced: each message waits for its slot.
            let now = Instant::now();
            if now < next {
                std::thread::sleep(next - now);
            }
            next += interval;
            return sent < args.count && Instant::now() < deadline;
        }
        sent < args.count && (sent % 256 != 0 || Instant::now() < deadline)
    };
    if args.path.is_raw() {
        let socket = raw_sender()?;
        let to: Vec<SocketAddrV4> = (0..channels)
            .map(|i| group(&thr_channel(i), args.port))
            .collect();
        start = Instant::now();
        while running(sent) {
            let to = to[sent as usize % channels];
            for chunk in payload.chunks(RAW_CHUNK) {
                socket.send_to(chunk, to)?;
            }
            sent += 1;
        }
    } else {
        let node = args.builder("thr-pub").start_blocking()?;
        let to: Vec<pulicast::Channel> = (0..channels)
            .map(|i| node.channel(&thr_channel(i)))
            .collect();
        for channel in &to {
            if let Some(delay) = args.batch() {
                channel.enable_batching(delay)?;
            }
        }
        start = Instant::now();
        while running(sent) {
            to[sent as usize % channels].publish_bytes(&payload)?;
            sent += 1;
        }
        for channel in &to {
            channel.flush()?;
        }
    }
    let secs = start.elapsed().as_secs_f64();
    let (cpu, rss) = usage();
    emit(json!({"sent": sent, "secs": secs, "cpu_s": cpu, "rss_kb": rss}));
    Ok(())
}

/// Whether the orchestrator said `end`, for the consumer threads of one
/// subscriber process.
type Ended = Arc<std::sync::atomic::AtomicBool>;

fn ended(end: &Ended) -> bool {
    end.load(std::sync::atomic::Ordering::Relaxed)
}

/// One consumer thread per channel, each counting into its own tally;
/// `ready` once all are set up, and the tallies when `end` is set.
fn per_channel_threads(
    channels: usize,
    end: &Ended,
    consume: impl Fn(usize, &Ended, &std::sync::Barrier) -> Result<Tally> + Send + Sync + 'static,
) -> Result<Vec<Tally>> {
    let consume = Arc::new(consume);
    let barrier = Arc::new(std::sync::Barrier::new(channels + 1));
    let threads: Vec<_> = (0..channels)
        .map(|i| {
            let (consume, end, barrier) =
                (Arc::clone(&consume), Arc::clone(end), Arc::clone(&barrier));
            std::thread::spawn(move || consume(i, &end, &barrier))
        })
        .collect();
    barrier.wait();
    emit(json!({"ready": true}));
    threads
        .into_iter()
        .map(|t| {
            t.join()
                .unwrap_or_else(|_| Err(anyhow::anyhow!("a consumer panicked")))
        })
        .collect()
}

/// The throughput subscriber role: counts, the row's way, on every
/// channel, until told `end` on stdin.
pub fn thr_sub(args: &RoleArgs) -> Result<()> {
    let channels = args.channels.max(1);
    let end: Ended = Arc::default();
    let stdin_end = Arc::clone(&end);
    // The same, for async consumers: no timer per message.
    let (end_tx, end_rx) = tokio::sync::watch::channel(false);
    let signal = end_signal();
    std::thread::spawn(move || {
        let _ = signal.recv();
        stdin_end.store(true, std::sync::atomic::Ordering::Relaxed);
        let _ = end_tx.send(true);
    });
    let (rcvbuf, port) = (args.rcvbuf, args.port);
    let tallies = match args.path {
        Path::Raw => per_channel_threads(channels, &end, move |i, end, ready| {
            let socket = raw_receiver(group(&thr_channel(i), port), rcvbuf)?;
            socket.set_read_timeout(Some(POLL_END))?;
            let mut buf = vec![0u8; 65536];
            let mut tally = Tally::default();
            ready.wait();
            loop {
                match socket.recv_from(&mut buf) {
                    Ok((n, _)) => {
                        tally.record(n);
                        tally.stamp();
                    }
                    Err(_) if ended(end) => break,
                    Err(_) => {}
                }
            }
            Ok(tally)
        })?,
        Path::RawSpin => {
            // One thread polls every socket in turn, never parking.
            let sockets = (0..channels)
                .map(|i| raw_spinning_receiver(group(&thr_channel(i), port), rcvbuf))
                .collect::<Result<Vec<_>>>()?;
            let mut buf = vec![0u8; 65536];
            let mut tally = Tally::default();
            emit(json!({"ready": true}));
            let mut polls = 0u32;
            while polls % 4096 != 0 || !ended(&end) {
                polls = polls.wrapping_add(1);
                let mut any = false;
                for socket in &sockets {
                    if let Ok((n, _)) = socket.recv_from(&mut buf) {
                        tally.record(n);
                        tally.stamp();
                        any = true;
                    }
                }
                if !any {
                    std::hint::spin_loop();
                }
            }
            vec![tally]
        }
        Path::Await => {
            let runtime = current_thread()?;
            runtime.block_on(async {
                let node = args.builder("thr-sub").start().await?;
                let mut tasks = Vec::new();
                for i in 0..channels {
                    let mut sub = node.channel(&thr_channel(i)).subscribe_raw()?;
                    let mut end = end_rx.clone();
                    tasks.push(tokio::spawn(async move {
                        let mut tally = Tally::default();
                        // Made once, and polled after the subscription
                        // (biased): the loop costs what a plain
                        // `while let Some(m) = sub.recv().await` costs.
                        let ended = end.wait_for(|&ended| ended);
                        tokio::pin!(ended);
                        loop {
                            tokio::select! {
                                biased;
                                m = sub.recv() => match m {
                                    Some(m) => {
                                        tally.record(m.value.len());
                                        tally.stamp();
                                    }
                                    None => break,
                                },
                                _ = &mut ended => break,
                            }
                        }
                        tally
                    }));
                }
                emit(json!({"ready": true}));
                let mut tallies = Vec::new();
                for task in tasks {
                    tallies.push(task.await?);
                }
                anyhow::Ok(tallies)
            })?
        }
        Path::Timeout => {
            let node = Arc::new(args.builder("thr-sub").start_blocking()?);
            per_channel_threads(channels, &end, move |i, end, ready| {
                let mut sub = node.channel(&thr_channel(i)).subscribe_raw()?;
                let mut tally = Tally::default();
                ready.wait();
                loop {
                    match sub.recv_timeout(POLL_END) {
                        Some(m) => {
                            tally.record(m.value.len());
                            tally.stamp();
                        }
                        None if ended(end) => break,
                        None => {}
                    }
                }
                Ok(tally)
            })?
        }
        Path::Many => {
            let node = Arc::new(args.builder("thr-sub").start_blocking()?);
            per_channel_threads(channels, &end, move |i, end, ready| {
                let mut sub = node.channel(&thr_channel(i)).subscribe_raw()?;
                let mut batch = Vec::with_capacity(MANY);
                let mut tally = Tally::default();
                ready.wait();
                loop {
                    batch.clear();
                    if sub.recv_many_timeout(&mut batch, MANY, POLL_END) == 0 {
                        if ended(end) {
                            break;
                        }
                        continue;
                    }
                    for m in &batch {
                        tally.record(m.value.len());
                    }
                    tally.stamp();
                }
                Ok(tally)
            })?
        }
        Path::Callback => {
            let node = args.builder("thr-sub").start_blocking()?;
            let counted = Arc::new(Mutex::new(Tally::default()));
            // Paced, the clock is cheap next to the wait between messages.
            let stamp_every = if args.rate.is_some() { 1 } else { 64 };
            let subs = (0..channels)
                .map(|i| {
                    let tally = Arc::clone(&counted);
                    node.channel(&thr_channel(i)).subscribe_raw_with(
                        move |m: pulicast::Message<pulicast::Bytes>| {
                            let mut tally = tally.lock().unwrap_or_else(|p| p.into_inner());
                            tally.record(m.value.len());
                            // The clock every 64 messages, as a queue
                            // consumer reads it once per run it takes; the
                            // rate is taken up to the last stamp.
                            if tally.received % stamp_every == 0 {
                                tally.stamp();
                            }
                        },
                    )
                })
                .collect::<pulicast::Result<Vec<_>>>()?;
            emit(json!({"ready": true}));
            while !ended(&end) {
                std::thread::sleep(POLL_END);
            }
            drop(subs);
            let tally = std::mem::take(&mut *counted.lock().unwrap_or_else(|p| p.into_inner()));
            vec![tally]
        }
    };
    let tally = Tally::merge(tallies);
    let Tally {
        received,
        bytes,
        first,
        last,
        stamped,
    } = tally;
    let (cpu, rss) = usage();
    emit(json!({
        "received": received, "bytes": bytes, "first_ns": first as f64, "last_ns": last as f64,
        "stamped_received": stamped.0, "stamped_bytes": stamped.1,
        "cpu_s": cpu, "rss_kb": rss,
    }));
    Ok(())
}

/// The memory subscriber role: reports RSS after a tenth of `count`
/// messages and at the end (stdin `end`).
pub fn mem_sub(args: &RoleArgs) -> Result<()> {
    let end = end_signal();
    let node = args.builder("mem-sub").start_blocking()?;
    let mut sub = node.channel(&thr_channel(0)).subscribe_raw()?;
    emit(json!({"ready": true}));
    let mut received = 0u64;
    let mark = (args.count / 10).max(1);
    loop {
        match sub.recv_timeout(POLL_END) {
            Some(_) => {
                received += 1;
                if received == mark {
                    emit(json!({"received": received, "rss_kb": status_kb("VmRSS:")}));
                }
            }
            None if end.try_recv().is_ok() => break,
            None => {}
        }
    }
    emit(json!({"received": received, "rss_kb": status_kb("VmRSS:")}));
    Ok(())
}

/// Runs `puli bench mem`: subscriber memory after many messages.
pub fn mem(args: &MemArgs) -> Result<()> {
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let setup = Setup {
        count: args.messages,
        ..Setup::new(port, args.size)
    };
    let mut sub = spawn_ready("mem-sub", Path::Timeout, setup)?;
    let mut publisher = spawn_role("thr-pub", Path::Timeout, setup)?;
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

/// The latency ponger role: echoes every ping as a pong, the row's way,
/// until stdin closes (or an empty ping comes).
pub fn lat_pong(args: &RoleArgs) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(600);
    match args.path {
        Path::Raw | Path::RawSpin => {
            let ping = group("bench/ping", args.port);
            let rx = raw_receiver(ping, args.rcvbuf)?;
            let tx = raw_sender()?;
            let to = group("bench/pong", args.port);
            let mut buf = vec![0u8; 65536];
            let spin = args.path == Path::RawSpin;
            if spin {
                rx.set_nonblocking(true)?;
            } else {
                rx.set_read_timeout(Some(Duration::from_millis(200)))?;
            }
            emit(json!({"ready": true}));
            while Instant::now() < deadline {
                let got = if spin {
                    spin_recv(&rx, &mut buf, || Instant::now() > deadline)
                } else {
                    rx.recv_from(&mut buf).ok().map(|(n, _)| n)
                };
                match got {
                    Some(0) => break,
                    Some(n) => {
                        tx.send_to(&buf[..n], to)?;
                    }
                    None => {}
                }
            }
        }
        Path::Await => {
            let runtime = current_thread()?;
            runtime.block_on(async {
                let node = args.builder("lat-pong").start().await?;
                let mut pings = node.channel("bench/ping").subscribe_raw()?;
                let pong = node.channel("bench/pong");
                emit(json!({"ready": true}));
                let deadline = tokio::time::Instant::from_std(deadline);
                while let Ok(Some(m)) = tokio::time::timeout_at(deadline, pings.recv()).await {
                    if m.value.is_empty() {
                        break;
                    }
                    pong.publish_bytes(&m.value)?;
                }
                anyhow::Ok(())
            })?;
        }
        Path::Timeout | Path::Many => {
            let node = args.builder("lat-pong").start_blocking()?;
            let mut pings = node.channel("bench/ping").subscribe_raw()?;
            let pong = node.channel("bench/pong");
            emit(json!({"ready": true}));
            while Instant::now() < deadline {
                match pings.recv_timeout(Duration::from_millis(200)) {
                    Some(m) if m.value.is_empty() => break,
                    Some(m) => pong.publish_bytes(&m.value)?,
                    None => {}
                }
            }
        }
        Path::Callback => {
            let end = end_signal();
            let node = args.builder("lat-pong").start_blocking()?;
            let pong = node.channel("bench/pong");
            let _pings = node.channel("bench/ping").subscribe_raw_with(
                move |m: pulicast::Message<pulicast::Bytes>| {
                    if !m.value.is_empty() {
                        let _ = pong.publish_bytes(&m.value);
                    }
                },
            )?;
            emit(json!({"ready": true}));
            let _ = end.recv_timeout(Duration::from_secs(600));
        }
    }
    Ok(())
}

/// Round trips the pinger does before it keeps samples: the first carry
/// setup costs.
const WARM_UP: u64 = 100;

/// A callback pinger's state: its handler sends the next ping.
struct Pinging {
    sent_at: Instant,
    round: u64,
    samples: Vec<f64>,
    lost: u64,
}

/// The latency pinger role: `count` round trips, one at a time.
pub fn lat_ping(args: &RoleArgs) -> Result<()> {
    let payload = vec![0x5au8; args.size.max(1)];
    let rounds = args.count.saturating_add(WARM_UP);
    let mut samples = Vec::with_capacity(args.count as usize);
    let timeout = Duration::from_secs(1);
    let mut lost = 0u64;
    let mut keep = |round: u64, t: Instant| {
        if round >= WARM_UP {
            samples.push(t.elapsed().as_secs_f64() * 1e6);
        }
    };
    match args.path {
        Path::Raw | Path::RawSpin => {
            let tx = raw_sender()?;
            let rx = raw_receiver(group("bench/pong", args.port), args.rcvbuf)?;
            let spin = args.path == Path::RawSpin;
            if spin {
                rx.set_nonblocking(true)?;
            } else {
                rx.set_read_timeout(Some(timeout))?;
            }
            let to = group("bench/ping", args.port);
            let mut buf = vec![0u8; 65536];
            for round in 0..rounds {
                let t = Instant::now();
                tx.send_to(&payload, to)?;
                let got = if spin {
                    spin_recv(&rx, &mut buf, || t.elapsed() > timeout)
                } else {
                    rx.recv_from(&mut buf).ok().map(|(n, _)| n)
                };
                match got {
                    Some(_) => keep(round, t),
                    None => lost += 1,
                }
            }
            tx.send_to(&[], to)?;
        }
        Path::Await => {
            let runtime = current_thread()?;
            runtime.block_on(async {
                let node = args.builder("lat-ping").start().await?;
                let mut pongs = node.channel("bench/pong").subscribe_raw()?;
                let ping = node.channel("bench/ping");
                if let Some(delay) = args.batch() {
                    ping.enable_batching(delay)?;
                }
                for round in 0..rounds {
                    let t = Instant::now();
                    ping.publish_bytes(&payload)?;
                    match tokio::time::timeout(timeout, pongs.recv()).await {
                        Ok(Some(_)) => keep(round, t),
                        _ => lost += 1,
                    }
                }
                ping.publish_bytes(&[])?;
                anyhow::Ok(())
            })?;
        }
        Path::Timeout | Path::Many => {
            let node = args.builder("lat-ping").start_blocking()?;
            let mut pongs = node.channel("bench/pong").subscribe_raw()?;
            let ping = node.channel("bench/ping");
            if let Some(delay) = args.batch() {
                ping.enable_batching(delay)?;
            }
            for round in 0..rounds {
                let t = Instant::now();
                ping.publish_bytes(&payload)?;
                match pongs.recv_timeout(timeout) {
                    Some(_) => keep(round, t),
                    None => lost += 1,
                }
            }
            ping.publish_bytes(&[])?;
        }
        Path::Callback => {
            let node = args.builder("lat-ping").start_blocking()?;
            let ping = node.channel("bench/ping");
            if let Some(delay) = args.batch() {
                ping.enable_batching(delay)?;
            }
            let state = Arc::new(Mutex::new(Pinging {
                sent_at: Instant::now(),
                round: 0,
                samples: Vec::with_capacity(args.count as usize),
                lost: 0,
            }));
            let (handler_state, next) = (Arc::clone(&state), ping.clone());
            let handler_payload = payload.clone();
            // Each pong's handler records the round trip and sends the
            // next ping: no thread in between.
            let pongs = node.channel("bench/pong").subscribe_raw_with(
                move |_: pulicast::Message<pulicast::Bytes>| {
                    let mut s = handler_state.lock().unwrap_or_else(|p| p.into_inner());
                    if s.round >= WARM_UP {
                        let rtt = s.sent_at.elapsed().as_secs_f64() * 1e6;
                        s.samples.push(rtt);
                    }
                    s.round += 1;
                    if s.round < rounds {
                        s.sent_at = Instant::now();
                        let _ = next.publish_bytes(&handler_payload);
                    }
                },
            )?;
            state.lock().unwrap_or_else(|p| p.into_inner()).sent_at = Instant::now();
            ping.publish_bytes(&payload)?;
            // Watch for the end, and for a lost pong: send again after the
            // timeout. Bounded: every timeout counts a loss, and losses end
            // the run.
            let started = Instant::now();
            loop {
                std::thread::sleep(Duration::from_millis(10));
                let mut s = state.lock().unwrap_or_else(|p| p.into_inner());
                if s.round >= rounds || started.elapsed() > Duration::from_secs(600) {
                    break;
                }
                if s.sent_at.elapsed() > timeout {
                    s.lost += 1;
                    s.round += 1;
                    if s.lost > 100 {
                        break;
                    }
                    s.sent_at = Instant::now();
                    ping.publish_bytes(&payload)?;
                }
            }
            drop(pongs);
            ping.publish_bytes(&[])?;
            let mut s = state.lock().unwrap_or_else(|p| p.into_inner());
            samples = std::mem::take(&mut s.samples);
            lost = s.lost;
        }
    }
    emit(json!({"samples_us": samples, "lost": lost}));
    Ok(())
}

fn spawn_role(role: &str, path: Path, setup: Setup) -> Result<Child> {
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

pub(crate) fn read_json(child: &mut Child) -> Result<Value> {
    let stdout = child.stdout.as_mut().context("no stdout")?;
    let mut line = String::new();
    BufReader::new(stdout).read_line(&mut line)?;
    serde_json::from_str(&line).with_context(|| format!("unexpected output {line:?}"))
}
fn median(mut v: Vec<f64>) -> f64 {
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
    let mut sub = spawn_ready("thr-sub", path, setup)?;
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
    // The span runs from the first arrival to the last stamped one: one
    // arrival's worth of bytes is outside it.
    let stamped = got["stamped_received"].as_f64().unwrap_or(0.0);
    let stamped_messages = got["stamped_bytes"].as_f64().unwrap_or(0.0) / size as f64;
    let in_span = stamped_messages * (stamped - 1.0).max(0.0) / stamped.max(1.0);
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

/// The settings that are not the library's defaults, for the header.
fn not_default(spin: Option<Duration>, queue: Option<usize>) -> String {
    let mut changed = Vec::new();
    if let Some(spin) = spin {
        changed.push(format!("receive_spin {spin:?}"));
    }
    if let Some(queue) = queue {
        changed.push(format!("queue_capacity {queue}"));
    }
    if changed.is_empty() {
        "pulicast with default settings".into()
    } else {
        format!(
            "pulicast with default settings except {}",
            changed.join(", ")
        )
    }
}

/// Runs `puli bench thr`.
pub fn thr(args: &ThrArgs) -> Result<()> {
    if args.rows.is_empty() {
        bail!("--rows names no row");
    }
    if let Some(&size) = args.size.iter().find(|&&s| s == 0 || s > MAX_SIZE) {
        bail!("size {size}: sizes must be between 1 and {MAX_SIZE} bytes");
    }
    if !(args.for_secs > 0.0 && args.for_secs <= 600.0) {
        bail!("--for must be above 0 and at most 600 seconds");
    }
    if args.rate.is_some_and(|r| !(r > 0.0 && r.is_finite())) {
        bail!("--rate must be above 0");
    }
    if !(1..=64).contains(&args.channels) {
        bail!("--channels must be between 1 and 64");
    }
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let mut results = Vec::new();
    if !args.json {
        crate::outln!(
            "throughput, publisher and subscriber in separate processes, loopback multicast, {} channel(s), publishing {} for {} s per run, {} B receive buffers asked for (net.core.rmem_max {}), median of {} runs each, interleaved",
            args.channels,
            args.rate.map_or("as fast as it can".into(), |r| format!("{r} msg/s")),
            args.for_secs,
            args.rcvbuf,
            std::fs::read_to_string("/proc/sys/net/core/rmem_max").map_or("unknown".into(), |s| s.trim().to_string()),
            args.rounds
        );
        crate::outln!("{}", not_default(args.spin, args.queue));
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
    }
    for &size in &args.size {
        let raw_setup = Setup {
            count: args.count.unwrap_or(u64::MAX),
            for_secs: Some(args.for_secs),
            channels: args.channels,
            rate: args.rate,
            rcvbuf: args.rcvbuf,
            ..Setup::new(port, size)
        };
        let ours_setup = Setup {
            batch: args.batch,
            seal: args.seal,
            spin: args.spin,
            queue: args.queue,
            ..raw_setup
        };
        let mut runs: Vec<Vec<ThrRun>> = vec![Vec::new(); args.rows.len()];
        for _ in 0..args.rounds.max(1) {
            for (row, &path) in args.rows.iter().enumerate() {
                let setup = if path.is_raw() { raw_setup } else { ours_setup };
                runs[row].push(thr_run(path, setup)?);
            }
        }
        let summary: Vec<ThrRun> = runs.iter().map(|r| summarize(r)).collect();
        let base = args
            .rows
            .iter()
            .position(|&p| p == Path::Raw)
            .map(|i| summary[i].rate);
        let ratio = |rate: f64| base.filter(|&b| b > 0.0).map(|b| rate / b);
        let rows: serde_json::Map<String, Value> = args
            .rows
            .iter()
            .zip(&summary)
            .map(|(path, r)| {
                let row = json!({
                    "msgs_per_s": r.rate, "mb_per_s": r.rate * size as f64 / 1e6,
                    "vs_raw": ratio(r.rate), "loss": r.loss,
                    "pub_cpu_us_per_msg": r.pub_cpu_per_msg_us, "sub_cpu_us_per_msg": r.sub_cpu_per_msg_us,
                    "pub_rss_kb": r.pub_rss_kb, "sub_rss_kb": r.sub_rss_kb,
                });
                (path.name().to_string(), row)
            })
            .collect();
        results.push(json!({"size": size, "rows": rows}));
        if args.json {
            continue;
        }
        crate::outln!("");
        crate::outln!(
            "  {:<24} {:>10} {:>7} {:>10} {:>6} {:>18} {:>15}",
            format!("{size} B"),
            "msg/s",
            "x raw",
            "MB/s",
            "loss",
            "CPU/msg pub,sub",
            "RSS pub,sub MB"
        );
        for (path, r) in args.rows.iter().zip(&summary) {
            crate::outln!(
                "  {:<24} {:>10.0} {:>7} {:>10.1} {:>5.1}% {:>8.2},{:>5.2} µs {:>7.1},{:>5.1}",
                path.label(),
                r.rate,
                ratio(r.rate).map_or("-".into(), |x| format!("{x:.2}")),
                r.rate * size as f64 / 1e6,
                r.loss * 100.0,
                r.pub_cpu_per_msg_us,
                r.sub_cpu_per_msg_us,
                r.pub_rss_kb / 1024.0,
                r.sub_rss_kb / 1024.0
            );
        }
    }
    if args.json {
        crate::outln!(
            "{}",
            json!({
                "benchmark": "thr", "port": port, "for_secs": args.for_secs, "channels": args.channels, "rate": args.rate,
                "batch_us": args.batch.map(|d| d.as_micros() as u64), "seal": args.seal.name(),
                "spin_us": args.spin.map(|d| d.as_micros() as u64), "queue": args.queue,
                "results": results,
            })
        );
    }
    Ok(())
}

fn lat_run(path: Path, setup: Setup) -> Result<(Vec<f64>, u64)> {
    let mut pong = spawn_ready("lat-pong", path, setup)?;
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

/// The raw row a pulicast row's latency compares with: a thread that
/// blocks with a blocking `recv`, one that never parks (a receive loop
/// that spins, a handler on it) with a busy-polling one.
fn lat_baseline(path: Path) -> Path {
    match path {
        Path::Raw | Path::Timeout | Path::Many => Path::Raw,
        Path::RawSpin | Path::Await | Path::Callback => Path::RawSpin,
    }
}

/// Runs `puli bench lat`.
pub fn lat(args: &LatArgs) -> Result<()> {
    if args.size == 0 || args.size > RAW_CHUNK {
        bail!("--size must be between 1 and {RAW_CHUNK} bytes");
    }
    if args.rows.is_empty() {
        bail!("--rows names no row");
    }
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let setup = Setup {
        count: args.rounds,
        ..Setup::new(port, args.size)
    };
    let ours = Setup {
        batch: args.batch,
        seal: args.seal,
        spin: args.spin,
        ..setup
    };
    let mut samples: Vec<Vec<f64>> = vec![Vec::new(); args.rows.len()];
    let mut lost = vec![0u64; args.rows.len()];
    for _ in 0..args.runs.max(1) {
        for (row, &path) in args.rows.iter().enumerate() {
            let (s, l) = lat_run(path, if path.is_raw() { setup } else { ours })?;
            samples[row].extend(s);
            lost[row] += l;
        }
    }
    let stats: Vec<[f64; 4]> = samples
        .iter_mut()
        .map(|v| {
            v.sort_by(|a, b| a.total_cmp(b));
            [0.5, 0.9, 0.99, 1.0].map(|p| percentile(v, p))
        })
        .collect();
    let of = |path: Path| args.rows.iter().position(|&p| p == path).map(|i| stats[i]);
    let ratios = |path: Path, s: &[f64; 4]| {
        of(lat_baseline(path))
            .filter(|b| b[0] > 0.0 && b[2] > 0.0)
            .map(|b| (s[0] / b[0], s[2] / b[2]))
    };
    if args.json {
        let rows: serde_json::Map<String, Value> = args
            .rows
            .iter()
            .zip(&stats)
            .zip(&lost)
            .map(|((&path, s), lost)| {
                let ratio = ratios(path, s);
                let row = json!({
                    "p50": s[0], "p90": s[1], "p99": s[2], "max": s[3], "lost": lost,
                    "baseline": lat_baseline(path).name(),
                    "p50_ratio": ratio.map(|r| r.0), "p99_ratio": ratio.map(|r| r.1),
                });
                (path.name().to_string(), row)
            })
            .collect();
        crate::outln!(
            "{}",
            json!({
                "benchmark": "lat", "size": args.size, "rounds": args.rounds * args.runs.max(1) as u64,
                "batch_us": args.batch.map(|d| d.as_micros() as u64), "seal": args.seal.name(),
                "spin_us": args.spin.map(|d| d.as_micros() as u64),
                "rows_us": rows,
            })
        );
        return Ok(());
    }
    crate::outln!(
        "round trip, {} B, ping and pong in separate processes, loopback multicast ({} round trips per row), {}, sealing: {}",
        args.size,
        args.rounds * args.runs.max(1) as u64,
        not_default(args.spin, None),
        args.seal.name()
    );
    crate::outln!(
        "  {:<24} {:>8} {:>8} {:>8} {:>8} {:>5}   {:<8} {:>6} {:>6}",
        "",
        "p50 µs",
        "p90 µs",
        "p99 µs",
        "max µs",
        "lost",
        "vs",
        "p50 x",
        "p99 x"
    );
    for ((&path, s), lost) in args.rows.iter().zip(&stats).zip(&lost) {
        let (p50, p99) = match ratios(path, s) {
            Some((a, b)) if !path.is_raw() => (format!("{a:.2}"), format!("{b:.2}")),
            _ => ("-".into(), "-".into()),
        };
        crate::outln!(
            "  {:<24} {:>8.1} {:>8.1} {:>8.1} {:>8.1} {:>5}   {:<8} {:>6} {:>6}",
            path.label(),
            s[0],
            s[1],
            s[2],
            s[3],
            lost,
            if path.is_raw() {
                ""
            } else {
                lat_baseline(path).name()
            },
            p50,
            p99
        );
    }
    if let Some(delay) = args.batch {
        crate::outln!("the pingers batch with a maximum delay of {delay:?}");
    }
    Ok(())
}

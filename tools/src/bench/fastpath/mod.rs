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
//!
//! One idea per file: `harness` starts the role processes and reads their
//! reports (and is borrowed by the other benchmarks), `raw` is the plain
//! socket baseline, and `thr`, `lat` and `mem` each hold their roles next
//! to the driver that runs them. What they share, the options and what a
//! role is told, stays here.

mod harness;
mod lat;
mod mem;
mod raw;
mod thr;

pub use lat::{lat, lat_ping, lat_pong};
pub use mem::{mem, mem_sub};
pub use thr::{thr, thr_pub, thr_sub};

pub(crate) use harness::{percentile, read_json, spawn_self};
pub(crate) use raw::{group, raw_receiver, raw_sender};

use std::net::Ipv4Addr;
use std::time::{Duration, Instant};

use pulicast::{Node, NodeBuilder};

/// Receive buffer both sides ask for by default (pulicast's default).
const RCVBUF: usize = pulicast::DEFAULT_RECEIVE_BUFFER;

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

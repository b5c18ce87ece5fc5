//! `puli bench thr`: the publisher and subscriber roles, one per row's way
//! of sending and receiving, and the driver that runs them, round after
//! round, and tabulates the medians. What a subscriber counts (`Tally`)
//! lives here because only these roles count.

use std::net::SocketAddrV4;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use parking_lot::Mutex;
use serde_json::{json, Value};

use crate::unix_ns;

use super::harness::{
    current_thread, emit, end_signal, finish_sub, median, read_json, spawn_ready, spawn_role,
    usage, POLL_END,
};
use super::raw::{group, raw_receiver, raw_sender, raw_spinning_receiver, RAW_CHUNK};
use super::{not_default, Path, RoleArgs, Seal, Setup, ThrArgs};

/// Largest message size measured (pulicast's limit is 64 MiB).
const MAX_SIZE: usize = 64 << 20;
/// Most messages a `recv_many` consumer takes per call.
const MANY: usize = 1024;

/// The name of throughput channel `i`.
pub(super) fn thr_channel(i: usize) -> String {
    format!("bench/thr{i}")
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
        // As a long-running publisher is: it has heard of its subscriber
        // (and so paces large messages to its buffer) before it starts.
        // Bounded: a subscriber not heard of in 5 s starts it anyway.
        let heard_by = Instant::now() + Duration::from_secs(5);
        while to.iter().any(|c| c.subscribers().is_empty()) && Instant::now() < heard_by {
            std::thread::sleep(Duration::from_millis(10));
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
                            let mut tally = tally.lock();
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
            let tally = std::mem::take(&mut *counted.lock());
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

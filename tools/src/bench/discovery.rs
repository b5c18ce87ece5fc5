//! `puli bench discovery`: N nodes as separate processes on loopback.
//!
//! The orchestrator starts N member processes (this same binary, hidden
//! subcommand `bench discovery-member`), each one node with C published
//! channels. Members print every discovery event with a wall-clock timestamp
//! (all processes share the host's clock) and answer `stats` and `leave` on
//! stdin. From those lines the orchestrator measures, in order:
//!
//! 1. cold start: from the last member's start until every member knows every
//!    other with all of its channels;
//! 2. steady state: discovery bytes sent per node per second, over a window;
//! 3. one more join: from the new member's start until it knows everyone's
//!    channels and everyone knows its channels;
//! 4. graceful leave: from a member's stop until every other has seen it leave;
//! 5. crash: from `kill -9` of a member until every other has declared it
//!    failed.
//!
//! The 2.x comparison is exact arithmetic, not a guess: the size of the
//! `pulicast_node` heartbeat datagram that a Pulicast 2.x node with the same
//! name and channels sends every period, from the same encoder our nodes use
//! for their compatibility heartbeat.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::net::Ipv4Addr;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use pulicast::{ChannelAnnouncement, DiscoveryEvent, Node};
use pulicast_discovery::compat::{Heartbeat, NODES_CHANNEL};
use pulicast_proto::wire::{self, zcm};
use serde_json::{json, Value};

use crate::unix_ns;

/// UDP and IPv4 headers per datagram, for wire-level figures.
const IP_UDP_HEADERS: u64 = 28;

/// Options of `puli bench discovery`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Number of nodes (processes).
    #[arg(long, default_value_t = 50)]
    pub nodes: usize,
    /// Channels each node publishes.
    #[arg(long, default_value_t = 20)]
    pub channels: usize,
    /// UDP port for the run (default: a free one).
    #[arg(long)]
    pub port: Option<u16>,
    /// Heartbeat period in milliseconds.
    #[arg(long, default_value_t = 100)]
    pub heartbeat_ms: u64,
    /// Length of the steady-state traffic window, seconds.
    #[arg(long, default_value_t = 5.0)]
    pub steady_secs: f64,
    /// Don't send 2.x heartbeats from the members (gossip only).
    #[arg(long)]
    pub no_compat: bool,
    /// Print one JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Busy loops to run beside the fleet for the whole run (threads of
    /// this process that only spin): discovery on a loaded machine.
    #[arg(long, default_value_t = 0)]
    pub load: usize,
}

/// Busy loops for `--load`, stopped (and joined) when dropped.
struct Load {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Load {
    fn start(n: usize) -> Self {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let threads = (0..n)
            .map(|_| {
                let stop = std::sync::Arc::clone(&stop);
                std::thread::spawn(move || {
                    let mut x = 0u64;
                    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                        x = std::hint::black_box(
                            x.wrapping_mul(6364136223846793005).wrapping_add(1),
                        );
                    }
                })
            })
            .collect();
        Self { stop, threads }
    }
}

impl Drop for Load {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// Options of one member process.
#[derive(clap::Args, Debug, Clone)]
pub struct MemberArgs {
    #[arg(long)]
    port: u16,
    #[arg(long)]
    index: usize,
    #[arg(long)]
    channels: usize,
    #[arg(long)]
    heartbeat_ms: u64,
    #[arg(long)]
    no_compat: bool,
    /// Exit after this long whatever happens, so no member outlives a run.
    #[arg(long, default_value_t = 300)]
    max_secs: u64,
}

fn member_name(index: usize) -> String {
    format!("rover{index:02}")
}

fn channel_name(j: usize) -> String {
    format!("sensor{j:02}")
}

fn emit(value: Value) {
    crate::outln!("{value}");
}

/// Runs one member until told to leave, stdin closes, or `max_secs` pass.
pub fn member(args: &MemberArgs) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async {
        use tokio::io::AsyncBufReadExt;
        let name = member_name(args.index);
        let node = Node::new(&name)
            .namespace(&name)
            .port(args.port)
            .interface(Ipv4Addr::LOCALHOST)
            .heartbeat_period(Duration::from_millis(args.heartbeat_ms))
            .compat_heartbeat(!args.no_compat)
            .start()
            .await?;
        let mut events = node.discovery().events();
        let channels: Vec<_> = (0..args.channels)
            .map(|j| node.channel(&channel_name(j)))
            .collect();
        for channel in &channels {
            channel.publish(&0i64)?;
        }
        emit(json!({"t": unix_ns() as f64, "event": "started"}));
        let mut stdin = tokio::io::BufReader::new(tokio::io::stdin()).lines();
        // Channels seen per member: a member is "complete" once all of its
        // channels are known, which is what convergence means here.
        let mut known: std::collections::HashMap<String, std::collections::HashSet<String>> =
            std::collections::HashMap::new();
        let mut complete: std::collections::HashSet<String> = std::collections::HashSet::new();
        let mut missed = 0;
        let mut reconcile = tokio::time::interval(Duration::from_millis(50));
        let deadline = tokio::time::sleep(Duration::from_secs(args.max_secs));
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                _ = &mut deadline => break,
                line = stdin.next_line() => match line {
                    Ok(Some(line)) => match line.trim() {
                        "leave" => {
                            let t = unix_ns();
                            node.stop();
                            emit(json!({"t": t as f64, "event": "stopped"}));
                            break;
                        }
                        "stats" => {
                            let stats = node.discovery().stats().unwrap_or_default();
                            emit(json!({
                                "t": unix_ns() as f64,
                                "event": "stats",
                                "bytes_out": stats.bytes_out,
                                "datagrams_out": stats.datagrams_out,
                            }));
                        }
                        _ => {}
                    },
                    _ => break,
                },
                _ = reconcile.tick() => {
                    // A member joining a large fleet gets more events at
                    // once than the stream holds (1024); on a busy machine
                    // it falls behind and misses some. The state is whole:
                    // read what is complete from it, as the API says to.
                    if events.missed() > missed {
                        missed = events.missed();
                        let t = unix_ns() as f64;
                        for m in node.discovery().live_members() {
                            let channels = known.entry(m.name.clone()).or_default();
                            channels.extend(m.channels.iter().map(|c| c.name.clone()));
                            if channels.len() >= args.channels && complete.insert(m.name.clone()) {
                                emit(json!({"t": t, "event": "complete", "name": m.name}));
                            }
                        }
                    }
                }
                event = events.recv() => {
                    let Some(event) = event else { break };
                    let t = unix_ns() as f64;
                    let (kind, name) = match event {
                        DiscoveryEvent::Joined(m) => ("joined", m.name),
                        DiscoveryEvent::Left { name, .. } => ("left", name),
                        DiscoveryEvent::Failed { name, .. } => ("failed", name),
                        DiscoveryEvent::Suspected { name, .. } => ("suspected", name),
                        DiscoveryEvent::Recovered { name, .. } => ("recovered", name),
                        DiscoveryEvent::ChannelAppeared { member, channel, .. } => {
                            let channels = known.entry(member.clone()).or_default();
                            channels.insert(channel.name);
                            if channels.len() >= args.channels && complete.insert(member.clone()) {
                                emit(json!({"t": t, "event": "complete", "name": member}));
                            }
                            continue;
                        }
                        DiscoveryEvent::ChannelDisappeared { member, channel, .. } => {
                            if let Some(channels) = known.get_mut(&member) {
                                channels.remove(&channel.name);
                            }
                            complete.remove(&member);
                            continue;
                        }
                        _ => continue,
                    };
                    emit(json!({"t": t, "event": kind, "name": name}));
                }
            }
        }
        Ok(())
    })
}

/// What the members have reported so far.
#[derive(Default)]
struct Seen {
    started: HashMap<usize, f64>,
    stopped: HashMap<usize, f64>,
    /// (observer, event, subject name) -> first time.
    events: HashMap<(usize, String, String), f64>,
    stats: HashMap<usize, Vec<(f64, u64, u64)>>,
    suspicions: usize,
}

impl Seen {
    fn apply(&mut self, from: usize, line: &Value) {
        let t = line["t"].as_f64().unwrap_or(0.0);
        let event = line["event"].as_str().unwrap_or("");
        match event {
            "started" => {
                self.started.insert(from, t);
            }
            "stopped" => {
                self.stopped.insert(from, t);
            }
            "stats" => {
                let bytes = line["bytes_out"].as_u64().unwrap_or(0);
                let datagrams = line["datagrams_out"].as_u64().unwrap_or(0);
                self.stats
                    .entry(from)
                    .or_default()
                    .push((t, bytes, datagrams));
            }
            other => {
                if other == "suspected" {
                    self.suspicions += 1;
                }
                let name = line["name"].as_str().unwrap_or("").to_string();
                self.events
                    .entry((from, other.to_string(), name))
                    .or_insert(t);
            }
        }
    }

    fn when(&self, observer: usize, event: &str, subject: usize) -> Option<f64> {
        self.events
            .get(&(observer, event.to_string(), member_name(subject)))
            .copied()
    }

    /// The time the last of `observers` saw `event` about `subject`.
    fn all_saw(&self, observers: &[usize], event: &str, subject: usize) -> Option<f64> {
        observers
            .iter()
            .filter(|o| **o != subject)
            .map(|o| self.when(*o, event, subject))
            .try_fold(0.0f64, |acc, t| t.map(|t| acc.max(t)))
    }
}

struct Fleet {
    exe: std::path::PathBuf,
    args: Args,
    port: u16,
    children: HashMap<usize, (Child, Option<ChildStdin>)>,
    tx: mpsc::Sender<(usize, Value)>,
    rx: Receiver<(usize, Value)>,
    seen: Seen,
}

impl Fleet {
    fn spawn(&mut self, index: usize) -> Result<()> {
        let mut command = Command::new(&self.exe);
        command.args([
            "bench",
            "discovery-member",
            "--port",
            &self.port.to_string(),
            "--index",
            &index.to_string(),
            "--channels",
            &self.args.channels.to_string(),
            "--heartbeat-ms",
            &self.args.heartbeat_ms.to_string(),
        ]);
        if self.args.no_compat {
            command.arg("--no-compat");
        }
        let mut child = command
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("starting a member process")?;
        let stdout = child.stdout.take().context("member stdout")?;
        let stdin = child.stdin.take();
        let tx = self.tx.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Ok(value) = serde_json::from_str::<Value>(&line) {
                    if tx.send((index, value)).is_err() {
                        break;
                    }
                }
            }
        });
        self.children.insert(index, (child, stdin));
        Ok(())
    }

    fn tell(&mut self, index: usize, command: &str) -> Result<()> {
        let (_, stdin) = self.children.get_mut(&index).context("no such member")?;
        let stdin = stdin.as_mut().context("member stdin closed")?;
        writeln!(stdin, "{command}").context("writing to a member")?;
        stdin.flush()?;
        Ok(())
    }

    /// Reads reports until `done` holds; fails after `limit`.
    fn wait(&mut self, what: &str, limit: Duration, done: impl Fn(&Seen) -> bool) -> Result<()> {
        let deadline = Instant::now() + limit;
        while !done(&self.seen) {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                bail!("timed out after {limit:?} waiting for {what}");
            }
            if let Ok((from, line)) = self.rx.recv_timeout(left.min(Duration::from_millis(100))) {
                self.seen.apply(from, &line);
            }
        }
        Ok(())
    }

    /// Drains what arrived, without waiting.
    fn drain(&mut self) {
        while let Ok((from, line)) = self.rx.try_recv() {
            self.seen.apply(from, &line);
        }
    }

    fn live(&self) -> Vec<usize> {
        let mut v: Vec<usize> = self.children.keys().copied().collect();
        v.sort_unstable();
        v
    }

    fn shutdown(&mut self) {
        for (_, (child, stdin)) in self.children.iter_mut() {
            drop(stdin.take());
            let deadline = Instant::now() + Duration::from_secs(3);
            while Instant::now() < deadline {
                if let Ok(Some(_)) = child.try_wait() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            // Only our own children, by their handles.
            if let Ok(None) = child.try_wait() {
                let _ = child.kill();
                let _ = child.wait();
            }
        }
        self.children.clear();
    }
}

impl Drop for Fleet {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// Bytes of the datagram a 2.x node called `name` with these channels sends
/// every heartbeat period.
pub fn compat_heartbeat_bytes(name: &str, channels: &[String], period: Duration) -> usize {
    let mut announced = vec![ChannelAnnouncement {
        name: NODES_CHANNEL.into(),
        period_ns: period.as_nanos() as i64,
        is_published: true,
        is_subscribed: true,
    }];
    announced.extend(channels.iter().map(|c| ChannelAnnouncement {
        name: c.clone(),
        period_ns: 0,
        is_published: true,
        is_subscribed: false,
    }));
    let mut payload = Vec::new();
    zcm::encode_heartbeat(
        &Heartbeat {
            name: name.into(),
            session_id: 0,
            channels: announced,
        },
        &mut payload,
    );
    payload.len() + wire::HEADER_OVERHEAD + NODES_CHANNEL.len()
}

/// Runs the benchmark and prints its report.
pub fn run(args: &Args) -> Result<()> {
    if args.nodes < 3 {
        bail!("--nodes must be at least 3 (one leaves, one crashes)");
    }
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let (tx, rx) = mpsc::channel();
    let mut fleet = Fleet {
        exe: std::env::current_exe()?,
        args: args.clone(),
        port,
        children: HashMap::new(),
        tx,
        rx,
        seen: Seen::default(),
    };
    let n = args.nodes;
    let period = Duration::from_millis(args.heartbeat_ms);
    if !args.json {
        crate::errln!(
            "starting {n} nodes with {} channels each on 127.0.0.1:{port}{} ...",
            args.channels,
            match args.load {
                0 => String::new(),
                l => format!(", {l} busy loops beside them"),
            }
        );
    }
    let load = Load::start(args.load);

    // 1. Cold start.
    for i in 0..n {
        fleet.spawn(i)?;
    }
    let all: Vec<usize> = (0..n).collect();
    fleet.wait("all members to start", Duration::from_secs(60), |s| {
        s.started.len() == n
    })?;
    fleet.wait("full convergence", Duration::from_secs(60), |s| {
        all.iter()
            .all(|&j| s.all_saw(&all, "complete", j).is_some())
    })?;
    let last_start = fleet.seen.started.values().copied().fold(0.0, f64::max);
    let converged = all
        .iter()
        .filter_map(|&j| fleet.seen.all_saw(&all, "complete", j))
        .fold(0.0, f64::max);
    let cold_ms = (converged - last_start) / 1e6;

    // 2. Steady state.
    std::thread::sleep(Duration::from_secs(1));
    fleet.drain();
    let suspicions_before = fleet.seen.suspicions;
    for i in 0..n {
        fleet.tell(i, "stats")?;
    }
    fleet.wait("stats", Duration::from_secs(10), |s| {
        (0..n).all(|i| s.stats.get(&i).is_some_and(|v| !v.is_empty()))
    })?;
    std::thread::sleep(Duration::from_secs_f64(args.steady_secs));
    for i in 0..n {
        fleet.tell(i, "stats")?;
    }
    fleet.wait("stats", Duration::from_secs(10), |s| {
        (0..n).all(|i| s.stats.get(&i).is_some_and(|v| v.len() >= 2))
    })?;
    let mut rates = Vec::new();
    let mut datagram_rates = Vec::new();
    for i in 0..n {
        let v = &fleet.seen.stats[&i];
        let (t0, b0, d0) = v[0];
        let (t1, b1, d1) = v[v.len() - 1];
        let secs = (t1 - t0) / 1e9;
        rates.push((b1 - b0) as f64 / secs);
        datagram_rates.push((d1 - d0) as f64 / secs);
    }
    let steady_suspicions = fleet.seen.suspicions - suspicions_before;
    let ours_payload = rates.iter().sum::<f64>() / n as f64;
    let ours_datagrams = datagram_rates.iter().sum::<f64>() / n as f64;
    let ours_wire = ours_payload + ours_datagrams * IP_UDP_HEADERS as f64;
    let channels: Vec<String> = (0..args.channels)
        .map(|j| format!("{}/{}", member_name(7), channel_name(j)))
        .collect();
    let hb = compat_heartbeat_bytes(&member_name(7), &channels, period);
    let per_sec = 1.0 / period.as_secs_f64();
    let compat_payload = hb as f64 * per_sec;
    let compat_wire = (hb as u64 + IP_UDP_HEADERS) as f64 * per_sec;

    // 3. One more node joins the converged fleet.
    fleet.spawn(n)?;
    let with_new: Vec<usize> = (0..=n).collect();
    fleet.wait("the new member to start", Duration::from_secs(30), |s| {
        s.started.contains_key(&n)
    })?;
    fleet.wait("the join to converge", Duration::from_secs(30), |s| {
        s.all_saw(&with_new, "complete", n).is_some()
            && (0..n).all(|j| s.when(n, "complete", j).is_some())
    })?;
    let join_start = fleet.seen.started[&n];
    let seen_by_all = fleet
        .seen
        .all_saw(&with_new, "complete", n)
        .unwrap_or(join_start);
    let saw_all = (0..n)
        .filter_map(|j| fleet.seen.when(n, "complete", j))
        .fold(0.0, f64::max);
    let join_ms = (seen_by_all.max(saw_all) - join_start) / 1e6;

    // 4. Graceful leave of member 0.
    fleet.tell(0, "leave")?;
    fleet.wait("the leaver to stop", Duration::from_secs(10), |s| {
        s.stopped.contains_key(&0)
    })?;
    let observers: Vec<usize> = (1..=n).collect();
    fleet.wait("everyone to see the leave", Duration::from_secs(10), |s| {
        s.all_saw(&observers, "left", 0).is_some()
    })?;
    let leave_ms =
        (fleet.seen.all_saw(&observers, "left", 0).unwrap_or(0.0) - fleet.seen.stopped[&0]) / 1e6;
    if let Some((mut child, _)) = fleet.children.remove(&0) {
        let _ = child.wait();
    }

    // 5. Crash of member 1.
    let observers: Vec<usize> = (2..=n).collect();
    let killed_at = unix_ns() as f64;
    if let Some((mut child, _)) = fleet.children.remove(&1) {
        child.kill().context("killing member 1")?;
        let _ = child.wait();
    }
    fleet.wait("everyone to see the crash", Duration::from_secs(30), |s| {
        s.all_saw(&observers, "failed", 1).is_some()
    })?;
    let crash_ms = (fleet.seen.all_saw(&observers, "failed", 1).unwrap_or(0.0) - killed_at) / 1e6;
    fleet.drain();
    let falsely_failed: std::collections::BTreeSet<String> = fleet
        .seen
        .events
        .keys()
        .filter(|(_, e, subject)| e == "failed" && subject != &member_name(1))
        .map(|(_, _, subject)| subject.clone())
        .collect();
    let false_failures = fleet
        .seen
        .events
        .keys()
        .filter(|(_, e, subject)| e == "failed" && subject != &member_name(1))
        .count();
    let live = fleet.live();
    fleet.shutdown();
    drop(load);

    let crash_target = period.as_secs_f64() * 3000.0 + 100.0;
    let ratio_payload = compat_payload / ours_payload;
    let ratio_wire = compat_wire / ours_wire;
    let report = json!({
        "nodes": n,
        "channels": args.channels,
        "heartbeat_ms": args.heartbeat_ms,
        "compat_heartbeat": !args.no_compat,
        "load": args.load,
        "port": port,
        "cold_start_convergence_ms": cold_ms,
        "join_convergence_ms": join_ms,
        "graceful_leave_ms": leave_ms,
        "crash_detection_ms": crash_ms,
        "discovery_bytes_per_s_per_node": ours_payload,
        "discovery_wire_bytes_per_s_per_node": ours_wire,
        "discovery_datagrams_per_s_per_node": ours_datagrams,
        "compat_heartbeat_bytes": hb,
        "compat_bytes_per_s_per_node": compat_payload,
        "compat_wire_bytes_per_s_per_node": compat_wire,
        "ratio_payload": ratio_payload,
        "ratio_wire": ratio_wire,
        "suspicions_in_steady_state": steady_suspicions,
        "false_failures": false_failures,
        "falsely_failed": falsely_failed,
        "members_at_end": live.len(),
        "targets": {
            "convergence_ms": 1000.0,
            "graceful_leave_ms": 100.0,
            "crash_detection_ms": crash_target,
            "traffic_ratio": 10.0,
        },
    });
    if args.json {
        crate::outln!("{report}");
        return Ok(());
    }
    let verdict = |ok: bool| if ok { "ok" } else { "MISSED" };
    crate::outln!(
        "discovery benchmark: {n} nodes x {} channels, heartbeat {} ms, 2.x heartbeats {}, loopback port {port}, {} busy loops",
        args.channels,
        args.heartbeat_ms,
        if args.no_compat { "off" } else { "on" },
        args.load
    );
    crate::outln!("{:<44} {:>16} {:>12}  ", "measure", "result", "target");
    let row = |name: &str, result: String, target: String, ok: bool| {
        crate::outln!("{name:<44} {result:>16} {target:>12}  {}", verdict(ok));
    };
    row(
        "full convergence, cold start of all nodes",
        format!("{cold_ms:.0} ms"),
        "< 1000 ms".into(),
        cold_ms < 1000.0,
    );
    row(
        "one more node joins, seen by all / sees all",
        format!("{join_ms:.0} ms"),
        "< 1000 ms".into(),
        join_ms < 1000.0,
    );
    row(
        "graceful leave, seen by all",
        format!("{leave_ms:.1} ms"),
        "< 100 ms".into(),
        leave_ms < 100.0,
    );
    row(
        "crash (kill -9), seen by all",
        format!("{crash_ms:.0} ms"),
        format!("<= {crash_target:.0} ms"),
        crash_ms <= crash_target,
    );
    crate::outln!(
        "{:<44} {:>16} {:>12}",
        "discovery traffic per node (payload / wire)",
        format!("{ours_payload:.0} / {ours_wire:.0} B/s"),
        ""
    );
    crate::outln!(
        "{:<44} {:>16} {:>12}",
        "2.x heartbeats per node, same fleet",
        format!("{compat_payload:.0} / {compat_wire:.0} B/s"),
        ""
    );
    row(
        "2.x / ours (payload; wire)",
        format!("{ratio_payload:.1}x; {ratio_wire:.1}x"),
        ">= 10x".into(),
        ratio_payload >= 10.0,
    );
    crate::outln!(
        "{:<44} {:>16}",
        "suspicions in steady state / false failures",
        format!("{steady_suspicions} / {false_failures}")
    );
    Ok(())
}

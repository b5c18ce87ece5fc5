//! `puli bench call`: service calls between two processes on loopback,
//! next to a raw-socket request/reply in the same run.
//!
//! Like for like: the raw baseline does what a call does on the wire (the
//! request multicast to a group, the reply sent straight back to the
//! sender's socket), with blocking sockets. Our rows use default settings
//! and documented usage: `client.call(&req).await` on tokio's default
//! runtime, and `call_blocking` on a `start_blocking` node; the server is
//! `serve` with an async handler.

use std::io::Write;
use std::net::Ipv4Addr;
use std::process::Child;
use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use serde_json::{json, Value};

use super::fastpath::{group, percentile, raw_receiver, raw_sender, read_json, spawn_self};

/// The service and the raw baseline's group.
const SERVICE: &str = "bench/echo";
/// The namespace the nearest row calls from: `bench/robot/arm/echo` and
/// `bench/robot/echo` are searched before the server's `bench/echo`.
const NEAREST_FROM: &str = "bench/robot/arm";
/// Calls before samples are kept: the first carry setup costs.
const WARM_UP: u64 = 100;

/// `puli bench call`'s arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Request (and reply) size in bytes.
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// Round trips per row and run.
    #[arg(long, default_value_t = 3000)]
    pub rounds: u64,
    /// Runs; the rows are interleaved in each, all samples pooled.
    #[arg(long, default_value_t = 2)]
    pub runs: usize,
    /// Concurrent callers of the throughput rows.
    #[arg(long, value_delimiter = ',', default_values_t = [1, 16])]
    pub callers: Vec<usize>,
    /// Seconds each throughput row calls for.
    #[arg(long = "for", default_value_t = 2.0)]
    pub for_secs: f64,
    /// UDP port (default: a free one).
    #[arg(long)]
    pub port: Option<u16>,
    /// One JSON object instead of the table.
    #[arg(long)]
    pub json: bool,
}

/// What a role process does.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Path {
    /// Raw blocking sockets.
    Raw,
    /// Raw sockets of tokio (`tokio::net::UdpSocket`), default runtime.
    RawAsync,
    /// `Client::call(..).await`, tokio's default runtime.
    Async,
    /// `Client::call_blocking` on a `start_blocking` node.
    Blocking,
    /// `Client::call(..).await` on a client made `nearest()` in namespace
    /// `bench/robot/arm`: the server is found at the third level out.
    Nearest,
}

/// A role of the call benchmark (a hidden command).
#[derive(clap::Args, Debug)]
pub struct RoleArgs {
    /// Which path.
    #[arg(long, value_enum)]
    pub path: Path,
    /// UDP port.
    #[arg(long)]
    pub port: u16,
    /// Request size.
    #[arg(long, default_value_t = 64)]
    pub size: usize,
    /// Round trips to time (a caller).
    #[arg(long, default_value_t = 0)]
    pub rounds: u64,
    /// Concurrent callers, calling for `--for` seconds (a caller; 0: time
    /// `--rounds` round trips instead).
    #[arg(long, default_value_t = 0)]
    pub callers: usize,
    /// Seconds the callers call for.
    #[arg(long = "for", default_value_t = 2.0)]
    pub for_secs: f64,
}

fn node(name: &str, port: u16) -> pulicast::NodeBuilder {
    pulicast::Node::new(name)
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .keys_from_env(false)
}

/// The server role: answers until told `end` on stdin (or 600 s).
pub fn server(args: &RoleArgs) -> Result<()> {
    match args.path {
        Path::Raw => {
            let rx = raw_receiver(group(SERVICE, args.port), 4 << 20)?;
            rx.set_read_timeout(Some(Duration::from_millis(200)))?;
            let tx = raw_sender()?;
            println!("{}", json!({"ready": true}));
            let deadline = Instant::now() + Duration::from_secs(600);
            let mut buf = vec![0u8; 65536];
            while Instant::now() < deadline {
                if let Ok((n, from)) = rx.recv_from(&mut buf) {
                    if n == 0 {
                        break;
                    }
                    tx.send_to(&buf[..n], from)?;
                }
            }
            Ok(())
        }
        Path::Async | Path::Blocking | Path::RawAsync | Path::Nearest => {
            let runtime = tokio::runtime::Runtime::new()?;
            runtime.block_on(async {
                let node = node("bench-server", args.port).start().await?;
                let _server = node.serve(SERVICE, |request: Vec<u8>| async move {
                    Ok::<_, pulicast::Fault>(request)
                })?;
                println!("{}", json!({"ready": true}));
                let end = tokio::task::spawn_blocking(|| {
                    let mut line = String::new();
                    let _ = std::io::stdin().read_line(&mut line);
                });
                let _ = tokio::time::timeout(Duration::from_secs(600), end).await;
                node.stop();
                anyhow::Ok(())
            })
        }
    }
}

/// The caller role: round trips timed one at a time (`--rounds`), or
/// calls/s of `--callers` concurrent callers.
pub fn caller(args: &RoleArgs) -> Result<()> {
    let payload = vec![0x5au8; args.size.max(1)];
    let report = match (args.path, args.callers) {
        (Path::Raw, _) => {
            let socket = raw_sender()?;
            socket.set_read_timeout(Some(Duration::from_secs(1)))?;
            let to = group(SERVICE, args.port);
            let mut buf = vec![0u8; 65536];
            let mut samples = Vec::new();
            let mut lost = 0;
            for round in 0..args.rounds + WARM_UP {
                let t = Instant::now();
                socket.send_to(&payload, to)?;
                match socket.recv_from(&mut buf) {
                    Ok(_) if round >= WARM_UP => samples.push(t.elapsed().as_secs_f64() * 1e6),
                    Ok(_) => {}
                    Err(_) => lost += 1,
                }
            }
            socket.send_to(&[], to)?;
            json!({"samples_us": samples, "failed": lost})
        }
        (Path::RawAsync, _) => tokio::runtime::Runtime::new()?.block_on(async {
            let socket = raw_sender()?;
            socket.set_nonblocking(true)?;
            let socket = tokio::net::UdpSocket::from_std(socket)?;
            let to = group(SERVICE, args.port);
            let mut buf = vec![0u8; 65536];
            let mut samples = Vec::new();
            let mut lost = 0;
            let wait = Duration::from_secs(1);
            for round in 0..args.rounds + WARM_UP {
                let t = Instant::now();
                socket.send_to(&payload, to).await?;
                match tokio::time::timeout(wait, socket.recv_from(&mut buf)).await {
                    Ok(Ok(_)) if round >= WARM_UP => samples.push(t.elapsed().as_secs_f64() * 1e6),
                    Ok(Ok(_)) => {}
                    _ => lost += 1,
                }
            }
            socket.send_to(&[], to).await?;
            anyhow::Ok(json!({"samples_us": samples, "failed": lost}))
        })?,
        (Path::Blocking, _) => {
            let node = node("bench-caller", args.port).start_blocking()?;
            let client = node.client::<Vec<u8>, Vec<u8>>(SERVICE)?;
            let mut samples = Vec::new();
            let mut failed = 0;
            for round in 0..args.rounds + WARM_UP {
                let t = Instant::now();
                match client.call_blocking(&payload) {
                    Ok(_) if round >= WARM_UP => samples.push(t.elapsed().as_secs_f64() * 1e6),
                    Ok(_) => {}
                    Err(_) => failed += 1,
                }
            }
            json!({"samples_us": samples, "failed": failed})
        }
        (Path::Async, 0) | (Path::Nearest, _) => {
            tokio::runtime::Runtime::new()?.block_on(async {
                // The node lives as long as its client calls.
                let (_node, client) = match args.path {
                    Path::Nearest => {
                        let node = node("bench-caller", args.port)
                            .namespace(NEAREST_FROM)
                            .start()
                            .await?;
                        let name = SERVICE.rsplit('/').next().unwrap_or(SERVICE);
                        let client = node.client::<Vec<u8>, Vec<u8>>(name)?.nearest()?;
                        (node, client)
                    }
                    _ => {
                        let node = node("bench-caller", args.port).start().await?;
                        let client = node.client::<Vec<u8>, Vec<u8>>(SERVICE)?;
                        (node, client)
                    }
                };
                let mut samples = Vec::new();
                let mut failed = 0;
                for round in 0..args.rounds + WARM_UP {
                    let t = Instant::now();
                    match client.call(&payload).await {
                        Ok(_) if round >= WARM_UP => samples.push(t.elapsed().as_secs_f64() * 1e6),
                        Ok(_) => {}
                        Err(_) => failed += 1,
                    }
                }
                anyhow::Ok(json!({"samples_us": samples, "failed": failed}))
            })?
        }
        (Path::Async, callers) => tokio::runtime::Runtime::new()?.block_on(async {
            let node = node("bench-caller", args.port).start().await?;
            let client = node.client::<Vec<u8>, Vec<u8>>(SERVICE)?;
            // Warm: the server is known and answers.
            client.call(&payload).await?;
            let span = Duration::from_secs_f64(args.for_secs.clamp(0.1, 60.0));
            let start = Instant::now();
            let tasks: Vec<_> = (0..callers)
                .map(|_| {
                    let client = client.clone();
                    let payload = payload.clone();
                    tokio::spawn(async move {
                        let (mut ok, mut failed) = (0u64, 0u64);
                        while start.elapsed() < span {
                            match client.call(&payload).await {
                                Ok(_) => ok += 1,
                                Err(_) => failed += 1,
                            }
                        }
                        (ok, failed)
                    })
                })
                .collect();
            let (mut ok, mut failed) = (0, 0);
            for task in tasks {
                let (o, f) = task.await?;
                ok += o;
                failed += f;
            }
            let secs = start.elapsed().as_secs_f64();
            anyhow::Ok(json!({"calls": ok, "failed": failed, "secs": secs}))
        })?,
    };
    println!("{report}");
    Ok(())
}

fn spawn(role: &str, path: Path, port: u16, extra: &[String]) -> Result<Child> {
    let name = match path {
        Path::Raw => "raw",
        Path::RawAsync => "raw-async",
        Path::Async => "async",
        Path::Blocking => "blocking",
        Path::Nearest => "nearest",
    };
    let mut args = vec![
        "bench".to_string(),
        role.to_string(),
        "--path".into(),
        name.into(),
        "--port".into(),
        port.to_string(),
    ];
    args.extend_from_slice(extra);
    spawn_self(&args)
}

fn ready(child: &mut Child) -> Result<()> {
    let line = read_json(child)?;
    if line["ready"] != true {
        bail!("a server did not start: {line}");
    }
    Ok(())
}

fn end(mut server: Child) {
    if let Some(stdin) = server.stdin.as_mut() {
        let _ = writeln!(stdin, "end");
    }
    let deadline = Instant::now() + Duration::from_secs(5);
    while Instant::now() < deadline {
        if let Ok(Some(_)) = server.try_wait() {
            return;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    // Our own child, by its handle.
    let _ = server.kill();
    let _ = server.wait();
}

fn run_caller(path: Path, port: u16, extra: &[String]) -> Result<Value> {
    let mut child = spawn("call-caller", path, port, extra)?;
    let report = read_json(&mut child)?;
    let _ = child.wait();
    Ok(report)
}

/// Runs `puli bench call`.
pub fn run(args: &Args) -> Result<()> {
    if args.size == 0 || args.size > 60_000 {
        bail!("--size must be between 1 and 60000 bytes");
    }
    let port = match args.port {
        Some(p) => p,
        None => pulicast::unused_port()?,
    };
    let size = args.size.to_string();
    let rounds = args.rounds.to_string();
    let timed = vec![
        "--size".to_string(),
        size.clone(),
        "--rounds".into(),
        rounds,
    ];
    let mut samples: [Vec<f64>; 5] = Default::default();
    let mut failed = [0u64; 5];
    let paths = [
        Path::Raw,
        Path::RawAsync,
        Path::Async,
        Path::Blocking,
        Path::Nearest,
    ];
    for _ in 0..args.runs.max(1) {
        for (row, &path) in paths.iter().enumerate() {
            let raw = matches!(path, Path::Raw | Path::RawAsync);
            let server_path = if raw { Path::Raw } else { Path::Async };
            let mut server = spawn("call-server", server_path, port, &[])?;
            ready(&mut server)?;
            let report = run_caller(path, port, &timed);
            end(server);
            let report = report?;
            if let Some(s) = report["samples_us"].as_array() {
                samples[row].extend(s.iter().filter_map(Value::as_f64));
            }
            failed[row] += report["failed"].as_u64().unwrap_or(0);
        }
    }
    let stats: Vec<[f64; 3]> = samples
        .iter_mut()
        .map(|v| {
            v.sort_by(|a, b| a.total_cmp(b));
            [0.5, 0.99, 1.0].map(|p| percentile(v, p))
        })
        .collect();
    let mut throughput = Vec::new();
    let mut server = spawn("call-server", Path::Async, port, &[])?;
    ready(&mut server)?;
    for &callers in &args.callers {
        let extra = vec![
            "--size".to_string(),
            size.clone(),
            "--callers".into(),
            callers.max(1).to_string(),
            "--for".into(),
            args.for_secs.to_string(),
        ];
        let report = run_caller(Path::Async, port, &extra)?;
        let calls = report["calls"].as_u64().unwrap_or(0);
        let secs = report["secs"].as_f64().unwrap_or(1.0).max(1e-9);
        let failed = report["failed"].as_u64().unwrap_or(0);
        throughput.push((callers.max(1), calls as f64 / secs, failed));
    }
    end(server);
    let raw_p50 = stats[0][0];
    // Like for like: the async call against raw async sockets, the
    // blocking call against raw blocking ones.
    let baseline = |i: usize| match i {
        2 | 4 => Some(1),
        3 => Some(0),
        _ => None,
    };
    let ratio = |i: usize| {
        let base = stats[baseline(i)?][0];
        (base > 0.0).then(|| stats[i][0] / base)
    };
    if args.json {
        let row = |i: usize| {
            json!({"p50_us": stats[i][0], "p99_us": stats[i][1], "max_us": stats[i][2],
                   "failed": failed[i], "p50_vs_raw": ratio(i)})
        };
        let rates: Vec<Value> = throughput
            .iter()
            .map(|(c, r, f)| json!({"callers": c, "calls_per_s": r, "failed": f}))
            .collect();
        crate::outln!(
            "{}",
            json!({"benchmark": "call", "size": args.size,
                   "rounds": args.rounds * args.runs.max(1) as u64,
                   "raw": row(0), "raw_async": row(1), "async": row(2), "blocking": row(3),
                   "nearest": row(4),
                   "throughput": rates})
        );
        return Ok(());
    }
    crate::outln!(
        "service call round trip, {} B request and reply, server and caller in separate processes, loopback ({} round trips per row), default settings",
        args.size,
        args.rounds * args.runs.max(1) as u64
    );
    crate::outln!(
        "  {:<34} {:>8} {:>8} {:>8} {:>6}  {:>12}",
        "",
        "p50 µs",
        "p99 µs",
        "max µs",
        "failed",
        "p50 vs"
    );
    let labels = [
        "raw, blocking sockets",
        "raw, tokio sockets (default runtime)",
        "call().await (default runtime)",
        "call_blocking (start_blocking node)",
        "call().await, nearest(), 3rd level",
    ];
    for (i, label) in labels.iter().enumerate() {
        let vs = match ratio(i) {
            None => "-".to_string(),
            Some(r) => format!("{r:.2}x row {}", baseline(i).map_or(0, |b| b + 1)),
        };
        crate::outln!(
            "  {:<34} {:>8.1} {:>8.1} {:>8.1} {:>6}  {:>12}",
            label,
            stats[i][0],
            stats[i][1],
            stats[i][2],
            failed[i],
            vs
        );
    }
    crate::outln!("calls/s, call().await, {} s per row:", args.for_secs);
    for (callers, rate, failed) in &throughput {
        crate::outln!("  {callers:>3} concurrent callers: {rate:>10.0} calls/s ({failed} failed)");
    }
    if raw_p50 > 0.0 {
        crate::outln!(
            "  (raw request/reply, one at a time: {:.0} round trips/s at its p50)",
            1e6 / raw_p50
        );
    }
    Ok(())
}

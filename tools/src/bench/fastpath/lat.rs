//! `puli bench lat`: the pinger and ponger roles, one per row's way of
//! receiving, and the driver that pools their round trips and compares
//! each pulicast row with the raw row that waits the same way.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use parking_lot::Mutex;
use serde_json::{json, Value};

use super::harness::{
    current_thread, emit, end_signal, percentile, read_json, spawn_ready, spawn_role,
};
use super::raw::{group, raw_receiver, raw_sender, spin_recv, RAW_CHUNK};
use super::{not_default, LatArgs, Path, RoleArgs, Setup};

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
                    let mut s = handler_state.lock();
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
            state.lock().sent_at = Instant::now();
            ping.publish_bytes(&payload)?;
            // Watch for the end, and for a lost pong: send again after the
            // timeout. Bounded: every timeout counts a loss, and losses end
            // the run.
            let started = Instant::now();
            loop {
                std::thread::sleep(Duration::from_millis(10));
                let mut s = state.lock();
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
            let mut s = state.lock();
            samples = std::mem::take(&mut s.samples);
            lost = s.lost;
        }
    }
    emit(json!({"samples_us": samples, "lost": lost}));
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

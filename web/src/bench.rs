//! `puli bench web` (`puli-web-bench`): what serving a fleet to browsers
//! and to Foxglove costs. A fleet of `--channels` channels at `--rate`
//! Hz each (in this process) is served by `puli-web` (a process of its
//! own, as users run it), first to `--clients` socket clients that act as
//! the page does (each watching 16 channels, decimated), then, restarted
//! with `--foxglove --no-page`, to as many Foxglove clients (each
//! subscribed to every channel, every message). For each: the server's
//! CPU (% of one core) and resident memory (each minute, to see it flat),
//! the latency from a message's publication to its arrival at a client's
//! socket (p50, p99), and what the clients got of what was published. A
//! plain pulicast subscriber of the same channels, in this process, is
//! the baseline.
//!
//! Every message is `(t_ns, v)`: its publication time, nanoseconds since
//! the epoch, and a value.

use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{anyhow, Context as _, Result};
use futures_util::{SinkExt, StreamExt};
use serde_json::{json, Value};
use tokio_tungstenite::tungstenite::{client::IntoClientRequest, Message};

/// `puli bench web`'s arguments.
#[derive(clap::Parser, Debug, Clone)]
#[command(name = "puli-web-bench", version)]
pub struct Args {
    /// Channels of the fleet.
    #[arg(long, default_value_t = 50)]
    pub channels: usize,
    /// Messages a second on each channel.
    #[arg(long, default_value_t = 100.0)]
    pub rate: f64,
    /// Clients of each server.
    #[arg(long, default_value_t = 5)]
    pub clients: usize,
    /// Seconds measured for each server (after two of warm-up).
    #[arg(long, default_value_t = 20.0)]
    pub secs: f64,
    /// Only the page's server, not Foxglove's.
    #[arg(long)]
    pub page_only: bool,
    /// The `puli-web` binary (default: beside this one).
    #[arg(long)]
    pub server: Option<std::path::PathBuf>,
    /// Print the results as one JSON line.
    #[arg(long)]
    pub json: bool,
}

fn now_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

/// Latencies (ms) and counts one side saw.
#[derive(Default)]
struct Seen {
    latencies_ms: Vec<f64>,
    /// Messages the frames stand for (a page bucket stands for `n`).
    messages: u64,
    frames: u64,
}

impl Seen {
    fn add(&mut self, t_ns: f64, stands_for: u64) {
        let ms = (now_ns() as f64 - t_ns) / 1e6;
        // Bounded: a long run keeps a sample.
        if self.latencies_ms.len() < 1_000_000 {
            self.latencies_ms.push(ms);
        }
        self.messages += stands_for;
        self.frames += 1;
    }
}

fn percentile(sorted: &[f64], p: f64) -> Option<f64> {
    let last = sorted.len().checked_sub(1)?;
    let i = ((last as f64) * p).round() as usize;
    sorted.get(i.min(last)).copied()
}

/// CPU time (ns) of `pid`'s threads, from /proc/PID/task/*/schedstat.
fn cpu_ns(pid: u32) -> Option<u64> {
    let mut total = 0u64;
    for task in std::fs::read_dir(format!("/proc/{pid}/task")).ok()? {
        let stat = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
        total += stat.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(total)
}

/// Resident memory (KiB) of `pid`.
fn rss_kb(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// A `puli-web` of ours, stopped by its own handle when dropped.
struct Server {
    child: Child,
    said: Value,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_server(program: &std::path::Path, port: u16, extra: &[&str]) -> Result<Server> {
    use std::io::BufRead;
    let port = port.to_string();
    let mut child = Command::new(program)
        .args(["--json", "--port", &port, "--interface", "127.0.0.1"])
        .args(extra)
        .env_remove(pulicast::KEYS_ENV)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .with_context(|| format!("starting {}", program.display()))?;
    let stdout = child.stdout.take().ok_or_else(|| anyhow!("no stdout"))?;
    let mut line = String::new();
    std::io::BufReader::new(stdout).read_line(&mut line)?;
    let said: Value =
        serde_json::from_str(&line).with_context(|| format!("its first line {line:?}"))?;
    Ok(Server { child, said })
}

/// The server's CPU (% of a core) and memory while `clients` run for
/// `secs`, then what they saw.
struct Measured {
    cpu_percent: Option<f64>,
    rss_kb: Vec<u64>,
    seen: Seen,
    /// Messages published while measuring.
    published: u64,
}

async fn measure(
    server: &Server,
    secs: f64,
    seen: Arc<Mutex<Seen>>,
    published: &AtomicU64,
) -> Measured {
    let pid = server.child.id();
    // Warm-up: clients connected, feeds started.
    tokio::time::sleep(Duration::from_secs(2)).await;
    *seen.lock().unwrap_or_else(|e| e.into_inner()) = Seen::default();
    let (cpu0, t0) = (cpu_ns(pid), Instant::now());
    let published0 = published.load(Ordering::Relaxed);
    let mut rss = vec![rss_kb(pid).unwrap_or(0)];
    let end = t0 + Duration::from_secs_f64(secs);
    while Instant::now() < end {
        let left = end.saturating_duration_since(Instant::now());
        tokio::time::sleep(left.min(Duration::from_secs(60))).await;
        rss.push(rss_kb(pid).unwrap_or(0));
    }
    let cpu = match (cpu0, cpu_ns(pid)) {
        (Some(a), Some(b)) => {
            Some((b.saturating_sub(a)) as f64 / 1e9 / t0.elapsed().as_secs_f64() * 100.0)
        }
        _ => None,
    };
    let taken = std::mem::take(&mut *seen.lock().unwrap_or_else(|e| e.into_inner()));
    Measured {
        cpu_percent: cpu,
        rss_kb: rss,
        seen: taken,
        published: published.load(Ordering::Relaxed) - published0,
    }
}

/// A client as the page is one: watches `names`, reads the buckets.
async fn page_client(url: String, names: Vec<String>, seen: Arc<Mutex<Seen>>) -> Result<()> {
    let ws = url
        .replacen("http://", "ws://", 1)
        .replacen("/?token=", "/ws?token=", 1);
    let (mut socket, _) = tokio_tungstenite::connect_async(ws.into_client_request()?).await?;
    // As the page does: channels picked from the fleet the server shows.
    while let Some(frame) = socket.next().await {
        let Message::Text(text) = frame? else {
            continue;
        };
        let frame: Value = serde_json::from_str(text.as_str())?;
        let shown: Vec<&str> = frame["channels"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|c| c["name"].as_str())
            .collect();
        if frame["kind"] == "fleet" && names.iter().all(|n| shown.contains(&n.as_str())) {
            break;
        }
    }
    socket
        .send(Message::Text(
            json!({"op": "watch", "channels": names}).to_string().into(),
        ))
        .await?;
    while let Some(frame) = socket.next().await {
        let Message::Text(text) = frame? else {
            continue;
        };
        let frame: Value = serde_json::from_str(text.as_str())?;
        if frame["kind"] != "samples" {
            continue;
        }
        let mut seen = seen.lock().unwrap_or_else(|e| e.into_inner());
        for b in frame["buckets"].as_array().into_iter().flatten() {
            // The newest message of the bucket: its publication time.
            if let Some(t) = b["v"]["[0]"][0].as_f64() {
                seen.add(t, b["n"].as_u64().unwrap_or(0));
            }
        }
    }
    Ok(())
}

/// A Foxglove client: subscribes to every bench channel advertised,
/// reads every message.
async fn foxglove_client(url: String, seen: Arc<Mutex<Seen>>) -> Result<()> {
    let mut request = url.into_client_request()?;
    request
        .headers_mut()
        .insert("Sec-WebSocket-Protocol", "foxglove.sdk.v1".parse()?);
    let (mut socket, _) = tokio_tungstenite::connect_async(request).await?;
    let mut next_sub = 0u32;
    while let Some(frame) = socket.next().await {
        match frame? {
            Message::Text(text) => {
                let op: Value = serde_json::from_str(text.as_str())?;
                if op["op"] != "advertise" {
                    continue;
                }
                let mut subscriptions = Vec::new();
                for c in op["channels"].as_array().into_iter().flatten() {
                    if c["topic"].as_str().is_some_and(|t| t.starts_with("bench/")) {
                        next_sub += 1;
                        subscriptions.push(json!({"id": next_sub, "channelId": c["id"]}));
                    }
                }
                if !subscriptions.is_empty() {
                    let subscribe = json!({"op": "subscribe", "subscriptions": subscriptions});
                    socket
                        .send(Message::Text(subscribe.to_string().into()))
                        .await?;
                }
            }
            Message::Binary(data) if data.first() == Some(&1) && data.len() > 13 => {
                let payload: Value = serde_json::from_slice(&data[13..])?;
                if let Some(t) = payload[0].as_f64() {
                    seen.lock().unwrap_or_else(|e| e.into_inner()).add(t, 1);
                }
            }
            _ => {}
        }
    }
    Ok(())
}

fn report(name: &str, m: &Measured, published: u64, clients: usize, per_client: f64) -> Value {
    let mut sorted = m.seen.latencies_ms.clone();
    sorted.sort_by(f64::total_cmp);
    let expected = published as f64 * per_client;
    json!({
        "server": name,
        "cpu_percent_of_a_core": m.cpu_percent,
        "rss_kb": m.rss_kb,
        "latency_ms_p50": percentile(&sorted, 0.5),
        "latency_ms_p99": percentile(&sorted, 0.99),
        "frames": m.seen.frames,
        "messages_reaching_clients": m.seen.messages,
        "messages_expected": expected.round(),
        "clients": clients,
    })
}

/// Runs the benchmark.
pub async fn run(args: Args) -> Result<()> {
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if args.channels == 0 || args.clients == 0 || !positive(args.rate) || !positive(args.secs) {
        anyhow::bail!("--channels, --clients, --rate and --secs must be more than 0");
    }
    let program = match &args.server {
        Some(p) => p.clone(),
        None => std::env::current_exe()?
            .parent()
            .ok_or_else(|| anyhow!("no directory of this program"))?
            .join("puli-web"),
    };
    let port = pulicast::unused_port()?;
    let node = pulicast::Node::new("bench-fleet")
        .port(port)
        .interface(std::net::Ipv4Addr::LOCALHOST)
        .keys_from_env(false)
        .start()
        .await?;
    let names: Vec<String> = (0..args.channels)
        .map(|i| format!("bench/c{i:03}"))
        .collect();
    // The baseline: a plain subscriber of every channel, in this process.
    let baseline = Arc::new(Mutex::new(Seen::default()));
    let mut subs = Vec::new();
    for name in &names {
        let seen = Arc::clone(&baseline);
        subs.push(node.channel(&format!("/{name}")).subscribe_with(
            move |m: pulicast::Message<(u64, f64)>| {
                seen.lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .add(m.value.0 as f64, 1);
            },
        )?);
    }
    let published = Arc::new(AtomicU64::new(0));
    let publishing = {
        let channels: Vec<pulicast::Channel> = names
            .iter()
            .map(|n| node.channel(&format!("/{n}")))
            .collect();
        let published = Arc::clone(&published);
        let period = Duration::from_secs_f64(1.0 / args.rate);
        let limit = Instant::now() + Duration::from_secs_f64(2.0 * (args.secs + 4.0) + 30.0);
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            let mut i = 0u64;
            // Bounded in time, whatever happens to the rest.
            while Instant::now() < limit {
                tick.tick().await;
                for c in &channels {
                    if c.publish(&(now_ns(), i as f64)).is_ok() {
                        published.fetch_add(1, Ordering::Relaxed);
                    }
                }
                i += 1;
            }
        })
    };
    // Discovery sees the channels before the servers start.
    tokio::time::sleep(Duration::from_secs(1)).await;
    let mut results = Vec::new();

    // The page's server: each client watches 16 channels, spread.
    {
        let server = start_server(&program, port, &["--http-port", "0"])?;
        let url = server.said["url"]
            .as_str()
            .ok_or_else(|| anyhow!("no url"))?
            .to_string();
        let seen = Arc::new(Mutex::new(Seen::default()));
        let watch = 16.min(names.len());
        let mut clients = Vec::new();
        for k in 0..args.clients {
            let mine: Vec<String> = (0..watch)
                .map(|j| names[(k * watch + j) % names.len()].clone())
                .collect();
            clients.push(tokio::spawn(page_client(
                url.clone(),
                mine,
                Arc::clone(&seen),
            )));
        }
        let measured = measure(&server, args.secs, seen, &published).await;
        let during = measured.published;
        for c in clients {
            c.abort();
        }
        let share = watch as f64 / names.len() as f64 * args.clients as f64;
        results.push(report("page", &measured, during, args.clients, share));
    }

    if !args.page_only {
        let server = start_server(
            &program,
            port,
            &["--foxglove", "--no-page", "--ws-port", "0"],
        )?;
        let url = server.said["foxglove_url"]
            .as_str()
            .ok_or_else(|| anyhow!("no foxglove_url"))?
            .to_string();
        let seen = Arc::new(Mutex::new(Seen::default()));
        let mut clients = Vec::new();
        for _ in 0..args.clients {
            clients.push(tokio::spawn(foxglove_client(
                url.clone(),
                Arc::clone(&seen),
            )));
        }
        let measured = measure(&server, args.secs, seen, &published).await;
        let during = measured.published;
        for c in clients {
            c.abort();
        }
        results.push(report(
            "foxglove",
            &measured,
            during,
            args.clients,
            args.clients as f64,
        ));
    }
    publishing.abort();
    let base = std::mem::take(&mut *baseline.lock().unwrap_or_else(|e| e.into_inner()));
    let mut sorted = base.latencies_ms;
    sorted.sort_by(f64::total_cmp);
    let summary = json!({
        "fleet": {"channels": args.channels, "rate_hz": args.rate, "messages_per_s": args.channels as f64 * args.rate},
        "servers": results,
        "baseline_pulicast_subscriber": {
            "latency_ms_p50": percentile(&sorted, 0.5),
            "latency_ms_p99": percentile(&sorted, 0.99),
        },
        "targets": {"cpu_percent_of_a_core_below": 20, "latency_ms_p50_below": 50},
    });
    drop(subs);
    node.stop();
    if args.json {
        println!("{summary}");
        return Ok(());
    }
    println!(
        "puli bench web: {} channels at {} Hz ({} msg/s), {} clients a server, {} s each",
        args.channels,
        args.rate,
        args.channels as f64 * args.rate,
        args.clients,
        args.secs
    );
    println!(
        "{:<10} {:>8} {:>10} {:>10} {:>12} {:>14}  rss KiB (each minute)",
        "server", "cpu %", "p50 ms", "p99 ms", "frames", "msgs/expected"
    );
    for r in summary["servers"].as_array().into_iter().flatten() {
        let f = |k: &str| r[k].as_f64().map_or("-".to_string(), |v| format!("{v:.1}"));
        println!(
            "{:<10} {:>8} {:>10} {:>10} {:>12} {:>14}  {}",
            r["server"].as_str().unwrap_or("?"),
            f("cpu_percent_of_a_core"),
            f("latency_ms_p50"),
            f("latency_ms_p99"),
            r["frames"].as_u64().unwrap_or(0),
            format!(
                "{}/{}",
                r["messages_reaching_clients"], r["messages_expected"]
            ),
            r["rss_kb"]
        );
    }
    let b = &summary["baseline_pulicast_subscriber"];
    println!(
        "baseline (a pulicast subscriber, in the bench): p50 {:.2} ms, p99 {:.2} ms",
        b["latency_ms_p50"].as_f64().unwrap_or(f64::NAN),
        b["latency_ms_p99"].as_f64().unwrap_or(f64::NAN)
    );
    println!("targets: server CPU below 20 % of a core, latency p50 below 50 ms, memory flat");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_of_a_sorted_sample() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), Some(51.0));
        assert_eq!(percentile(&v, 0.99), Some(99.0));
        assert_eq!(percentile(&[], 0.5), None);
    }
}

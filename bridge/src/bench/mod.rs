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
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Result};
use serde_json::{json, Value};

mod harness;
mod measure;
mod roles;

use harness::{free_tcp, role_proc, Proc, LOGS};
use measure::{burst, pulicast_burst, round_trips, Load, Path};
pub use roles::role;
use roles::{site_node, zenoh_session};

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

fn unix_ms() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64() * 1e3)
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

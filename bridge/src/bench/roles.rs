//! What each role process of `puli-bridge bench` does (an echo or a sink,
//! on a pulicast site or on Zenoh), and how every process of the bench,
//! the driver too, joins a site or opens a Zenoh session: the other end
//! of the measurements, kept apart from the side that times them.

use std::io::Write;
use std::net::Ipv4Addr;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use pulicast::Node;
use serde_json::{json, Value};

use super::{unix_ms, Role, RoleArgs, DATA, WARM};

/// Most messages a `--many` sink takes at once (the queue's default
/// capacity).
const MANY: usize = 1024;

/// How long a sink waits after the last data message before it reports.
const IDLE: Duration = Duration::from_secs(1);

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
                let mut many = Vec::with_capacity(MANY);
                loop {
                    let wait = sink.wait();
                    let got = match args.many {
                        true => tokio::time::timeout(wait, sub.recv_many(&mut many, MANY))
                            .await
                            .map(|n| (n > 0).then_some(())),
                        false => tokio::time::timeout(wait, sub.recv())
                            .await
                            .map(|m| m.map(|m| many.push(m))),
                    };
                    match got {
                        Ok(Some(())) => {}
                        Ok(None) => break,
                        Err(_) => {
                            sink.report();
                            continue;
                        }
                    }
                    for m in many.drain(..) {
                        if echo {
                            pong.publish_bytes(&m.value)?;
                        } else {
                            sink.take(&m.value);
                        }
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

/// A sink's count: it reports `{"warm": true}` at each warm-up message
/// before data, and `{"received", "duplicates", "last_unix_ms"}` once data
/// stopped for [`IDLE`].
#[derive(Default)]
struct Sink {
    received: u64,
    seen: std::collections::HashSet<u64>,
    first: Option<Instant>,
    last: Option<Instant>,
}

impl Sink {
    fn take(&mut self, m: &[u8]) {
        match m.first() {
            // Every warm-up message is answered until data comes, so a
            // burst that never arrived leaves the sink ready for the next.
            Some(&WARM) if self.first.is_none() => say(&json!({"warm": true})),
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
            *self = Sink::default();
        }
    }
}

fn say(v: &Value) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{v}");
    let _ = out.flush();
}

pub(super) async fn site_node(name: &str, port: u16) -> Result<Node> {
    Ok(Node::new(name)
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .start()
        .await?)
}

pub(super) async fn zenoh_session(listen: &str, connect: &str) -> Result<zenoh::Session> {
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

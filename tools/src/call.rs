//! What `puli call` does: call a service with a request typed as JSON,
//! encoded into the request type its servers announce, and print the
//! progress and the reply as JSON. One deadline covers the wait for
//! discovery and the call.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use pulicast::text::decode_payload;
use pulicast::{CallEvent, Node, RawCall, ServiceEnd, TypeInfo};
use serde_json::{json, Value};

use crate::flags::NetArgs;
use crate::publish::{self, Outgoing, ValueType};

/// How long the servers `--all` found must stay the same before it calls.
const SETTLE: Duration = Duration::from_millis(300);

/// `puli call`'s arguments.
#[derive(clap::Args, Debug)]
pub struct CallArgs {
    #[command(flatten)]
    net: NetArgs,
    /// What to call, and how.
    #[command(flatten)]
    pub call: CallOpts,
}

/// What to call, and how: `puli call`'s and `puli shell`'s `call`.
#[derive(clap::Args, Debug, Clone)]
pub struct CallOpts {
    /// The service (relative to --namespace, or absolute with a leading /);
    /// `NAME@NODE` calls that node's server only.
    pub service: String,
    /// The request, as JSON (a plain number or text for the 2.x
    /// primitive types).
    #[arg(allow_hyphen_values = true)]
    pub request: String,
    /// Call every server and print each one's answer.
    #[arg(long)]
    pub all: bool,
    /// Call the nearest server: this node's configuration (--config) before
    /// none, each from --namespace out to the root; a server that is busy,
    /// gone, silent or of other types is passed over for the next.
    #[arg(long)]
    pub nearest: bool,
    /// The whole command (discovery and the call) ends within this many
    /// seconds.
    #[arg(long, default_value_t = 5.0)]
    pub timeout: f64,
    /// Wait for a server to appear, up to --timeout. Without it, a service
    /// that no node serves once discovery has settled (about half a
    /// second) fails then, naming the nearest service that exists.
    #[arg(long)]
    pub wait: bool,
    /// One JSON object per line: `{"node", "progress"}`, `{"node",
    /// "reply"}` or `{"node", "error"}`.
    #[arg(long)]
    pub json: bool,
}

/// The service's name without its target, and the target.
fn split_target(service: &str) -> (&str, Option<&str>) {
    match service.split_once('@') {
        Some((name, node)) => (name, Some(node)),
        None => (service, None),
    }
}

/// The types the servers of `service` announce (those of `target` only,
/// if given), once discovery knows one.
pub fn server_types(node: &Node, service: &str, target: Option<&str>) -> Option<ServiceEnd> {
    node.discovery()
        .services()
        .into_iter()
        .find(|s| s.name == service)?
        .servers
        .into_iter()
        .find(|s| target.is_none_or(|t| t == s.node))
}

/// Encodes the request `text` into the server's request type.
pub fn encode_request(text: &str, request: Option<&TypeInfo>, service: &str) -> Result<Vec<u8>> {
    // A JSON string for a text type is its content, as a person means it.
    let unquoted = match serde_json::from_str::<Value>(text) {
        Ok(Value::String(s)) if request.is_some_and(|t| t.name == "string_msg") => s,
        _ => text.to_string(),
    };
    let outgoing = publish::outgoing(&unquoted, ValueType::Auto, request, service)?;
    Ok(match outgoing {
        Outgoing::Bytes(bytes) => bytes,
        Outgoing::Primitive(p) => {
            let mut out = Vec::new();
            p.encode(&mut out);
            out
        }
    })
}

/// A message as JSON, decoded with the type announced for it.
pub fn message_json(message: &[u8], ty: Option<&TypeInfo>) -> Value {
    decode_payload(message, ty).value
}

/// One line of output for an event of `call` (which went to `node`).
pub fn event_line(
    call: &RawCall,
    event: CallEvent,
    types: &ServiceEnd,
    json_out: bool,
    all: bool,
) -> String {
    let node = call.node().to_string();
    let prefix = if all {
        format!("{node}: ")
    } else {
        String::new()
    };
    match (event, json_out) {
        (CallEvent::Progress(m), json_out) => {
            let value = message_json(&m, types.progress.as_ref());
            match json_out {
                true => json!({"node": node, "progress": value}).to_string(),
                false => format!("{prefix}progress {value}"),
            }
        }
        (
            CallEvent::Reply {
                message,
                missed_progress,
            },
            json_out,
        ) => {
            let value = message_json(&message, types.reply.as_ref());
            match json_out {
                true => json!({"node": node, "reply": value, "missed_progress": missed_progress})
                    .to_string(),
                false => format!("{prefix}{value}"),
            }
        }
        (other, true) => json!({"node": node, "error": call.error(other).to_string()}).to_string(),
        (other, false) => format!("{prefix}error: {}", call.error(other)),
    }
}

/// Follows one call to its end, printing each event but a failure of a
/// single call (`all` false), which is returned, as the command's error.
/// Returns whether it ended with a reply.
async fn follow(
    mut call: RawCall,
    types: &Reading<'_>,
    json_out: bool,
    all: bool,
) -> Result<(), pulicast::Error> {
    while let Some(event) = call.next().await {
        if !all && event.is_final() && !matches!(event, CallEvent::Reply { .. }) {
            return Err(call.error(event));
        }
        let line = event_line(&call, event, types.of(call.node()), json_out, all);
        crate::outln!("{line}");
    }
    match call.ended_with_reply() {
        true => Ok(()),
        false => Err(call.error(CallEvent::TimedOut)),
    }
}

/// The types a call's answers are read with: those of the server that
/// answers, as discovery announces them (the servers a nearest call walks
/// may serve other names, of other types), else those the request was
/// encoded for.
struct Reading<'a> {
    encoded_for: &'a ServiceEnd,
    by_node: HashMap<String, ServiceEnd>,
}

impl Reading<'_> {
    fn of(&self, node: &str) -> &ServiceEnd {
        self.by_node.get(node).unwrap_or(self.encoded_for)
    }
}

/// Runs `puli call`.
pub async fn run(args: CallArgs) -> Result<()> {
    // A bad --timeout fails before a node starts.
    crate::flags::seconds("--timeout", args.call.timeout)?;
    let node = args.net.node("puli-call")?.start().await?;
    let result = call(&node, &args.call).await;
    node.stop();
    result
}

/// Makes the call `args` describes from `node`, printing progress and
/// replies; the error says why no reply came.
pub async fn call(node: &Node, args: &CallOpts) -> Result<()> {
    let timeout = crate::flags::seconds("--timeout", args.timeout)?;
    let started = Instant::now();
    let deadline = started + timeout;
    // Whole milliseconds, which is what errors show.
    let left = || {
        let left = deadline.saturating_duration_since(Instant::now());
        Duration::from_millis(u64::try_from(left.as_millis()).unwrap_or(u64::MAX))
    };
    let mut client = node.raw_client(&args.service)?;
    if args.nearest {
        client = client.nearest()?;
    }
    let full = client.service();
    let (name, target) = split_target(&full);
    // The types to encode the request in: the first server's a call tries
    // (a nearest client's may serve other names than `name`).
    let types_now = || match args.nearest {
        false => server_types(node, name, target),
        true => client.servers().first().and_then(|first| {
            let (service, server) = split_target(first);
            server_types(node, service, server)
        }),
    };
    if args.nearest {
        // The nearest is only known once the fleet is: a server further
        // out may be heard of first.
        node.discovery().settle(left()).await;
    }
    // Found as soon as discovery shows a server; given up on once it has
    // settled without one, unless told to wait (a server starting).
    let give_up = async {
        if args.wait {
            std::future::pending::<()>().await;
        }
        node.discovery().settle(left()).await;
    };
    let found = tokio::select! {
        biased;
        found = crate::poll_for(left(), types_now) => found,
        () = give_up => types_now(),
    };
    let Some(types) = found else {
        return Err(no_server(node, &full, name, target, started.elapsed()));
    };
    let message = encode_request(&args.request, types.request.as_ref(), &full)?;
    let by_node = match args.nearest {
        false => HashMap::new(),
        true => client
            .servers()
            .iter()
            .filter_map(|server| {
                let (service, node_name) = split_target(server);
                let types = server_types(node, service, node_name)?;
                Some((types.node.clone(), types))
            })
            .collect(),
    };
    let reading = Reading {
        encoded_for: &types,
        by_node,
    };
    if !args.all {
        let call = client.start(&message, left()).await?;
        return Ok(follow(call, &reading, args.json, false).await?);
    }
    // Every server: discovery finds them one by one, so wait until the set
    // stays the same for a moment (within the deadline).
    let mut known = client.servers();
    let mut calm = Instant::now();
    while calm.elapsed() < SETTLE && !left().is_zero() {
        tokio::time::sleep(Duration::from_millis(20)).await;
        let now = client.servers();
        if now != known {
            known = now;
            calm = Instant::now();
        }
    }
    let mut calls = Vec::new();
    let mut refused = 0;
    for (server, call) in client.start_all(&message, left()).await? {
        match call {
            Ok(call) => calls.push(call),
            Err(e) => {
                refused += 1;
                let line = match args.json {
                    true => json!({"node": server, "error": e.to_string()}).to_string(),
                    false => format!("{server}: error: {e}"),
                };
                crate::outln!("{line}");
            }
        }
    }
    let followed = calls
        .into_iter()
        .map(|c| follow(c, &reading, args.json, true));
    let replies = futures_util::future::join_all(followed).await;
    let failed = refused + replies.iter().filter(|r| r.is_err()).count();
    match failed {
        0 => Ok(()),
        n => Err(anyhow!(
            "{full}: {n} of {} servers did not reply",
            replies.len() + refused
        )),
    }
}

/// Why nothing serves `full` (`name`, at `target` if given), with the
/// service or node that was probably meant.
fn no_server(
    node: &Node,
    full: &str,
    name: &str,
    target: Option<&str>,
    waited: Duration,
) -> anyhow::Error {
    let services = node.discovery().services();
    let served: Vec<&str> = services
        .iter()
        .filter(|s| !s.servers.is_empty())
        .map(|s| s.name.as_str())
        .collect();
    let waited = Duration::from_millis(u64::try_from(waited.as_millis()).unwrap_or(u64::MAX));
    let whom = match target {
        Some(t) => {
            let servers: Vec<&str> = services
                .iter()
                .filter(|s| s.name == name)
                .flat_map(|s| s.servers.iter().map(|e| e.node.as_str()))
                .collect();
            match servers.is_empty() {
                true => format!(
                    "no node serves {name}{}",
                    crate::suggest::did_you_mean(name, served.iter().copied())
                ),
                false => format!(
                    "node {t} does not serve it{}",
                    crate::suggest::did_you_mean(t, servers.iter().copied())
                ),
            }
        }
        None => format!(
            "no node serves it{}",
            crate::suggest::did_you_mean(name, served.iter().copied())
        ),
    };
    anyhow!("no server of {full}: {whom} (waited {waited:?})")
}

/// A request of the `plan` service of `puli serve`.
#[derive(serde::Serialize, serde::Deserialize, pulicast::Schema, Debug, Clone, PartialEq)]
pub struct PlanRequest {
    /// Where to.
    pub goal: (f64, f64),
    /// In how many steps.
    pub steps: u32,
}

/// The reply of the `plan` service of `puli serve`.
#[derive(serde::Serialize, serde::Deserialize, pulicast::Schema, Debug, Clone, PartialEq)]
pub struct PlanReply {
    /// The way points.
    pub points: Vec<(f64, f64)>,
    /// The server node.
    pub by: String,
}

/// `puli serve`'s arguments: a node that serves a few services, for
/// multi-process tests and the call benchmark.
#[derive(clap::Args, Debug)]
pub struct ServeArgs {
    #[command(flatten)]
    net: NetArgs,
    /// The node's name.
    #[arg(long)]
    pub name: String,
    /// Milliseconds between the progress messages of `count`.
    #[arg(long, default_value_t = 20)]
    pub step_ms: u64,
    /// Stop after this many seconds.
    #[arg(long = "for", default_value_t = 60.0)]
    pub for_secs: f64,
}

/// Runs `puli serve`: in its namespace, `echo` (text back), `double`
/// (an i64 times two), `plan` ([`PlanRequest`] to [`PlanReply`]) and
/// `count` (a u32 `n`: `n` progress messages, `--step-ms` apart, then
/// `"counted n"`).
pub async fn serve(args: ServeArgs) -> Result<()> {
    use pulicast::{CallContext, Fault};
    let node = args.net.node(&args.name)?.start().await?;
    let by = args.name.clone();
    let step = Duration::from_millis(args.step_ms);
    let _echo = node.serve("echo", |s: String| async move { Ok::<_, Fault>(s) })?;
    let _double = node.serve("double", |x: i64| async move {
        x.checked_mul(2).ok_or(Fault::msg("too large to double"))
    })?;
    let _plan = node.serve("plan", move |p: PlanRequest| {
        let by = by.clone();
        async move {
            if p.steps > 10_000 {
                return Err(Fault::new(1001, format!("{} steps is too many", p.steps)));
            }
            let points = (0..p.steps)
                .map(|i| {
                    (
                        p.goal.0 * f64::from(i) / f64::from(p.steps.max(1)),
                        p.goal.1,
                    )
                })
                .collect();
            Ok(PlanReply { points, by })
        }
    })?;
    let _count =
        node.server("count")
            .serve_with(move |n: u32, call: CallContext<u32>| async move {
                for i in 0..n {
                    call.progress(&i)?;
                    tokio::time::sleep(step).await;
                }
                Ok::<_, Fault>(format!("counted {n}"))
            })?;
    crate::errln!("READY {}", json!({"node": args.name}));
    let stop = crate::stop_requested();
    tokio::select! {
        _ = tokio::time::sleep(crate::flags::seconds("--for", args.for_secs)?) => {}
        _ = stop => {}
    }
    node.stop();
    Ok(())
}

//! The read-only commands that `puli-sniffer` runs once and `puli shell`
//! runs on its long-lived node: nodes, channels, services, echo, hz and
//! bw. [`Inspect`] is their one grammar: both front ends flatten it into
//! their own commands, so a flag added here exists in both. Each prints
//! to stdout and takes a `stop` future, so the sniffer ends them on a
//! signal and the shell on Ctrl-C, which returns to its prompt.

use std::future::Future;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use pulicast::{resolve_name, MemberView, Node};
use serde_json::Value;

use crate::sniff::{self, ChannelWatch};

/// How long `echo` and `hz` listen for a publisher before saying that none
/// is known (what arrives meanwhile is kept).
pub const PUBLISHER_WAIT: Duration = Duration::from_secs(2);

/// How much longer `echo` listens for the type a publisher announces, when
/// the publisher was heard before its type.
pub const TYPE_WAIT: Duration = Duration::from_secs(1);

/// The commands that look at the fleet, as `puli-sniffer` and `puli shell`
/// both take them.
#[derive(clap::Subcommand, Debug, Clone)]
pub enum Inspect {
    /// The nodes discovery knows: name, session, host, state, channels;
    /// with a NAME, that node only.
    Nodes(NodesArgs),
    /// The channels: type, publishers, subscribers; rate, bandwidth and
    /// loss measured over --for.
    Channels(ChannelsArgs),
    /// The services: who serves and who calls each, with the request,
    /// reply and progress types.
    Services(ServicesArgs),
    /// Print the messages of one channel, decoded to text.
    Echo(EchoArgs),
    /// Message rate of one channel: mean, min/max interval, jitter.
    Hz(HzArgs),
    /// Bandwidth of one channel, or of all (discovery included).
    Bw(BwArgs),
}

/// `nodes`' arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct NodesArgs {
    /// Only the node of this name.
    pub name: Option<String>,
    /// Listen this many seconds before printing (default: 1 in
    /// puli-sniffer, which starts listening now; 0 in the shell, which has
    /// been listening).
    #[arg(long = "for")]
    pub for_secs: Option<f64>,
    /// One JSON array instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// `channels`' arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct ChannelsArgs {
    /// Measure rate, bandwidth and loss over this many seconds (default:
    /// 2 in puli-sniffer; 0 in the shell, which then shows the rate
    /// publishers announce).
    #[arg(long = "for")]
    pub for_secs: Option<f64>,
    /// Hidden channels too (settings' `.config/...`, any part starting
    /// with `.`), which are left out otherwise, as in Pulicast 2.x.
    #[arg(long)]
    pub all: bool,
    /// One JSON array instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// `services`' arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct ServicesArgs {
    /// Listen this many seconds before printing (default: 1 in
    /// puli-sniffer, 0 in the shell).
    #[arg(long = "for")]
    pub for_secs: Option<f64>,
    /// One JSON array instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// `bw`'s arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct BwArgs {
    /// Channel name; all channels when left out.
    pub channel: Option<String>,
    /// Stop after this many seconds (default: run until interrupted).
    #[arg(long = "for")]
    pub for_secs: Option<f64>,
    /// With all channels: hidden ones too (settings', services').
    #[arg(long)]
    pub all: bool,
}

/// How long the node running a command has been listening: a node that
/// just started hears the fleet only after a while, so its commands
/// listen first (the sniffer); a long-lived one has heard it (the shell).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Listening {
    /// Started for this command.
    Fresh,
    /// Running for a while.
    Long,
}

impl Listening {
    fn default_for(self, fresh: f64) -> f64 {
        match self {
            Listening::Fresh => fresh,
            Listening::Long => 0.0,
        }
    }

    /// Waits `--for` seconds, or by default `fresh` for a fresh node and
    /// none for a long-lived one, before a command prints what it heard.
    async fn listen(self, for_secs: Option<f64>, fresh: f64) -> Result<()> {
        let wait = secs(for_secs.unwrap_or(self.default_for(fresh)))?;
        tokio::time::sleep(wait).await;
        Ok(())
    }
}

impl Inspect {
    /// Whether the command ends by itself, as at its end, when `stop`
    /// resolves (the others are interrupted).
    pub fn ends_on_stop(&self) -> bool {
        !matches!(self, Inspect::Nodes(_) | Inspect::Services(_))
    }

    /// Runs the command on `node`, names read under `namespace`.
    pub async fn run(
        &self,
        node: &Node,
        namespace: &str,
        listening: Listening,
        stop: impl Future<Output = ()>,
    ) -> Result<()> {
        match self {
            Inspect::Nodes(a) => {
                listening.listen(a.for_secs, 1.0).await?;
                print_nodes(node, a.json, a.name.as_deref())
            }
            Inspect::Channels(a) => {
                let window = secs(a.for_secs.unwrap_or(listening.default_for(2.0)))?;
                // A fresh node always measures, over at least a moment: a
                // zero window would show nothing it heard.
                let window = match listening {
                    Listening::Fresh => window.max(Duration::from_millis(1)),
                    Listening::Long => window,
                };
                channels(node, window, a.all, a.json, stop).await
            }
            Inspect::Services(a) => {
                listening.listen(a.for_secs, 1.0).await?;
                print_services(node, a.json)
            }
            Inspect::Echo(a) => echo(node, namespace, a, stop).await,
            Inspect::Hz(a) => hz(node, namespace, a, stop).await,
            Inspect::Bw(a) => bw(node, namespace, a, stop).await,
        }
    }
}

/// `echo`'s arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct EchoArgs {
    /// Channel name (relative to --namespace, or absolute with a leading /).
    pub channel: String,
    /// Stop after this many messages.
    #[arg(long)]
    pub count: Option<u64>,
    /// Stop after this many seconds.
    #[arg(long = "for")]
    pub for_secs: Option<f64>,
    /// One JSON object per line.
    #[arg(long)]
    pub json: bool,
}

/// `hz`'s arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct HzArgs {
    /// Channel name.
    pub channel: String,
    /// Stop after this many seconds (default: run until interrupted).
    #[arg(long = "for")]
    pub for_secs: Option<f64>,
}

fn secs(s: f64) -> Result<Duration> {
    crate::flags::seconds("--for", s)
}

/// Prints the members discovery knows, as a table or one JSON array;
/// `only` keeps the members of that name (an error if there are none).
pub fn print_nodes(node: &Node, json: bool, only: Option<&str>) -> Result<()> {
    let mut members = node.discovery().members();
    if let Some(name) = only {
        members.retain(|m| m.name == name);
        if members.is_empty() {
            return Err(anyhow!("no node named {name:?} is known"));
        }
    }
    members.sort_by(|a, b| (&a.name, a.key).cmp(&(&b.name, b.key)));
    if json {
        let all: Vec<Value> = members.iter().map(sniff::node_json).collect();
        crate::outln!("{}", Value::Array(all));
        return Ok(());
    }
    crate::outln!(
        "{:<20} {:<20} {:<8} {:<12} {:<22} {:>4} {:>4}  HOST",
        "NAME",
        "SESSION",
        "STATE",
        "CONFIG",
        "ADDRESS",
        "PUB",
        "SUB"
    );
    for m in &members {
        crate::outln!("{}", node_line(m));
    }
    // One node asked for by name: what it publishes and subscribes too.
    if only.is_some() {
        for m in &members {
            for c in &m.channels {
                let role = match (c.publishes, c.subscribes) {
                    (true, true) => "pub+sub",
                    (true, false) => "pub",
                    _ => "sub",
                };
                let ty = c
                    .message_type
                    .as_ref()
                    .map_or_else(|| "-".to_string(), sniff::type_display);
                crate::outln!("  {role:<8} {:<32} {ty}", crate::one_line(&c.name));
            }
        }
    }
    for note in sniff::key_notes(node) {
        crate::errln!("{note}");
    }
    Ok(())
}

fn node_line(m: &MemberView) -> String {
    let session = m
        .session
        .map(|s| s.to_string()[..18].to_string())
        .unwrap_or_else(|| format!("2.x {:x}", m.key));
    let state = format!("{:?}", m.state).to_lowercase();
    let pubs = m.channels.iter().filter(|c| c.publishes).count();
    let subs = m.channels.iter().filter(|c| c.subscribes).count();
    let contested = m
        .contested_by
        .map(|a| format!("  (session also announced from {a}: one is an impostor)"))
        .unwrap_or_default();
    let remote = m
        .remote
        .as_ref()
        .map(|r| {
            format!(
                "  (site {}, via bridge {:x})",
                crate::one_line(&r.site),
                r.bridge
            )
        })
        .unwrap_or_default();
    let config = match m.config.as_str() {
        "" => "-",
        config => config,
    };
    // Names, hosts and configurations come from the network: none may
    // forge a row.
    format!(
        "{:<20} {:<20} {:<8} {:<12} {:<22} {:>4} {:>4}  {}{}{}",
        crate::one_line(&m.name),
        session,
        state,
        crate::one_line(config),
        m.address,
        pubs,
        subs,
        crate::one_line(&m.host),
        remote,
        contested
    )
}

/// Prints the services discovery knows, as a table or one JSON array.
pub fn print_services(node: &Node, json: bool) -> Result<()> {
    let services = node.discovery().services();
    if json {
        crate::outln!("{}", sniff::services_json(&services));
    } else {
        print_text(&sniff::services_table(&services));
    }
    Ok(())
}

/// Prints the channels: their types, publishers and subscribers, and
/// with a `window` longer than zero their rate, bandwidth and loss as
/// measured over it (without, the rate its publishers announce). Hidden
/// channels only when `all`.
pub async fn channels(
    node: &Node,
    window: Duration,
    all: bool,
    json: bool,
    stop: impl Future<Output = ()>,
) -> Result<()> {
    let mut watch = ChannelWatch::new(node);
    let measured = !window.is_zero();
    if measured {
        let deadline = Instant::now() + window;
        tokio::pin!(stop);
        while Instant::now() < deadline {
            watch.watch_announced();
            let nap = Duration::from_millis(100).min(deadline - Instant::now());
            tokio::select! {
                _ = tokio::time::sleep(nap) => {}
                _ = &mut stop => break,
            }
        }
        if watch.unwatched() > 0 {
            crate::errln!(
                "note: {} announced channels not measured: at most {} are watched",
                watch.unwatched(),
                sniff::MAX_WATCHED
            );
        }
        if watch.unwatchable() > 0 {
            crate::errln!(
                "note: {} announced names are no channel names: listed (escaped), not measured",
                watch.unwatchable()
            );
        }
    }
    let mut rows = sniff::channel_rows(
        &node.discovery().members(),
        &watch.meters(),
        watch.elapsed(),
    );
    if !all {
        rows.retain(|r| !pulicast::is_hidden_channel(&r.name));
    }
    if json {
        let rows = rows.iter().map(|r| {
            let mut row = r.json();
            if !measured {
                row["bandwidth_bytes_per_s"] = Value::Null;
                row["loss"] = Value::Null;
            }
            row
        });
        crate::outln!("{}", Value::Array(rows.collect()));
    } else {
        crate::outln!(
            "{:<32} {:>9} {:>11} {:>6}  {:<16} PUBLISHERS / SUBSCRIBERS",
            "CHANNEL",
            "RATE Hz",
            "BW B/s",
            "LOSS",
            "TYPE"
        );
        let cell = |text: &str| crate::one_line(text).into_owned();
        for r in &rows {
            let (bandwidth, loss) = match measured {
                true => (
                    format!("{:.0}", r.bandwidth),
                    format!("{:.1}%", r.loss * 100.0),
                ),
                false => ("-".to_string(), "-".to_string()),
            };
            crate::outln!(
                "{:<32} {:>9.1} {:>11} {:>6}  {:<16} {} / {}",
                cell(&r.name),
                r.rate_hz,
                bandwidth,
                loss,
                match r.type_conflict {
                    Some(_) => format!("!{}", cell(r.type_name.as_deref().unwrap_or("-"))),
                    None => cell(r.type_name.as_deref().unwrap_or("-")),
                },
                cell(&r.publishers.join(",")),
                cell(&r.subscribers.join(","))
            );
        }
        for r in rows.iter().filter(|r| r.type_conflict.is_some()) {
            crate::errln!(
                "note: members disagree on the type of {} ({}): subscribers of another type drop its messages",
                r.name,
                r.type_conflict.as_deref().unwrap_or_default()
            );
        }
    }
    for note in sniff::key_notes(node) {
        crate::errln!("{note}");
    }
    Ok(())
}

/// Prints the messages of one channel, decoded to text, until `--count`,
/// `--for` or `stop`.
pub async fn echo(
    node: &Node,
    namespace: &str,
    args: &EchoArgs,
    stop: impl Future<Output = ()>,
) -> Result<()> {
    let channel = resolve_name(&args.channel, namespace)?;
    let mut sub = node.channel(&format!("/{channel}")).subscribe_raw()?;
    let deadline = match args.for_secs {
        Some(s) => Some(tokio::time::Instant::now() + secs(s)?),
        None => None,
    };
    tokio::pin!(stop);
    // Give discovery a moment, so the first messages already decode by the
    // type their publisher announces. Nothing is lost while we wait: the
    // subscription queues what arrives. Within `--for`, if it is shorter.
    let within = |wait: Duration| match deadline {
        Some(d) => wait.min(d.saturating_duration_since(tokio::time::Instant::now())),
        None => wait,
    };
    // A publisher may be heard first by its 2.x heartbeat, which has no
    // types, before its gossip: a little longer for its type.
    let type_wait = match publisher_known(node, &channel, within(PUBLISHER_WAIT), &mut stop).await {
        None => return Ok(()),
        Some(true) => within(TYPE_WAIT),
        Some(false) => Duration::ZERO,
    };
    let hint = crate::poll_for(type_wait, || sniff::announced_type(node, &channel));
    let mut hint = tokio::select! {
        hint = hint => hint,
        _ = &mut stop => return Ok(()),
    };
    let mut hint_checked = Instant::now();
    let mut printed = 0u64;
    while args.count.is_none_or(|n| printed < n) {
        let next = async {
            match deadline {
                Some(d) => tokio::time::timeout_at(d, sub.recv()).await.ok().flatten(),
                None => sub.recv().await,
            }
        };
        let message = tokio::select! {
            message = next => message,
            _ = &mut stop => None,
        };
        let Some(message) = message else { break };
        if hint.is_none() && hint_checked.elapsed() > Duration::from_millis(200) {
            hint = sniff::announced_type(node, &channel);
            hint_checked = Instant::now();
        }
        match args.json {
            true => crate::outln!("{}", sniff::echo_json(&channel, &message, hint.as_ref())),
            false => crate::outln!("{}", sniff::echo_line(&channel, &message, hint.as_ref())),
        }
        printed += 1;
    }
    if printed == 0 {
        for note in sniff::key_notes(node) {
            crate::errln!("{note}");
        }
    }
    Ok(())
}

/// Prints one channel's rate every second, and once more at the end.
pub async fn hz(
    node: &Node,
    namespace: &str,
    args: &HzArgs,
    stop: impl Future<Output = ()>,
) -> Result<()> {
    let channel = resolve_name(&args.channel, namespace)?;
    // `--for` is the whole command: the wait for a publisher counts.
    let end = args
        .for_secs
        .map(secs)
        .transpose()?
        .map(|d| Instant::now() + d);
    let left = || end.map(|e| e.saturating_duration_since(Instant::now()));
    tokio::pin!(stop);
    // Measured from the start, so nothing that arrives meanwhile is lost.
    let mut watch = ChannelWatch::new(node);
    watch.watch(&channel)?;
    let wait = left().map_or(PUBLISHER_WAIT, |l| l.min(PUBLISHER_WAIT));
    if publisher_known(node, &channel, wait, &mut stop)
        .await
        .is_none()
    {
        return Ok(());
    }
    let for_secs = left().map(|l| l.as_secs_f64());
    report_loop(for_secs, stop, || {
        let meters = watch.meters();
        let m = meters.get(&channel).cloned().unwrap_or_default();
        let mut lines = vec![hz_line(&channel, &m)];
        // Two publishers interleave: each one's own rate and jitter too.
        let sources = watch.source_meters(&channel);
        if sources.len() > 1 {
            let members = node.discovery().live_members();
            for (source, m) in sources {
                let who = members
                    .iter()
                    .find(|p| p.data_address == Some(source))
                    .map_or_else(String::new, |p| format!(" ({})", p.name));
                lines.push(hz_line(&format!("  from {source}{who}"), &m));
            }
        }
        lines.join("\n")
    })
    .await
}

/// Waits up to `within` for discovery to know a publisher of `channel`,
/// and says so on stderr when it does not: whether one is known, or
/// `None` if `stop` came first. Reserved channels (`__nodes`) are every
/// node's and announced by none: nothing to wait for.
async fn publisher_known(
    node: &Node,
    channel: &str,
    within: Duration,
    stop: &mut std::pin::Pin<&mut impl Future<Output = ()>>,
) -> Option<bool> {
    if crate::is_internal(channel) {
        return Some(false);
    }
    let watched = node.channel(&format!("/{channel}"));
    let found = tokio::select! {
        found = watched.wait_for_publisher(within) => found.is_ok(),
        () = stop.as_mut() => return None,
    };
    if !found {
        crate::errln!("{}", unknown_channel_note(node, channel));
    }
    Some(found)
}

/// One line of `hz`: rate and interval statistics of `m`.
fn hz_line(label: &str, m: &sniff::RateMeter) -> String {
    match m.intervals() {
        Some((mean, min, max, sd)) => format!(
            "{label}: {:.2} Hz  interval mean {:.2} ms  min {:.2} ms  max {:.2} ms  jitter (sd) {:.2} ms  n={}  loss {:.1}%",
            1.0 / mean, mean * 1e3, min * 1e3, max * 1e3, sd * 1e3, m.count, m.loss() * 100.0
        ),
        None => format!("{label}: {} messages so far", m.count),
    }
}

/// Says that nobody announces `channel` (yet), which channel was probably
/// meant, and which channels exist: hidden ones (settings', services')
/// only when `channel` is hidden itself.
pub fn unknown_channel_note(node: &Node, channel: &str) -> String {
    let hidden = pulicast::is_hidden_channel(channel);
    // At most the first 10 000 names, whatever a fleet announces.
    let mut known: Vec<String> = node
        .discovery()
        .live_members()
        .into_iter()
        .flat_map(|m| m.channels)
        .filter(|c| c.publishes && (hidden || !pulicast::is_hidden_channel(&c.name)))
        .map(|c| c.name)
        .take(crate::suggest::MAX_CANDIDATES)
        .collect();
    known.sort();
    known.dedup();
    let meant = crate::suggest::did_you_mean(channel, known.iter().map(String::as_str));
    // The first few: a fleet may announce hundreds of thousands.
    const LISTED: usize = 20;
    let list = match known.len() {
        0 => "none".to_string(),
        n if n <= LISTED => known.join(", "),
        n => format!("{}, and {} more", known[..LISTED].join(", "), n - LISTED),
    };
    format!(
        "note: no member publishes {channel:?} (yet){meant}; waiting. Published channels: {list}"
    )
}

/// Prints `report()` every second until `for_secs` passes, `stop`
/// resolves, or forever, and once more at the end.
pub async fn report_loop(
    for_secs: Option<f64>,
    stop: impl Future<Output = ()>,
    mut report: impl FnMut() -> String,
) -> Result<()> {
    let end = match for_secs {
        Some(s) => Some(Instant::now() + secs(s)?),
        None => None,
    };
    tokio::pin!(stop);
    loop {
        let left = end.map(|e| e.saturating_duration_since(Instant::now()));
        let wait = left
            .unwrap_or(Duration::from_secs(1))
            .min(Duration::from_secs(1));
        tokio::select! {
            _ = tokio::time::sleep(wait) => {}
            _ = &mut stop => break,
        }
        if left.is_some_and(|l| l <= wait) {
            break;
        }
        crate::outln!("{}", report());
    }
    crate::outln!("{}", report());
    Ok(())
}

/// Prints text that may span lines (nothing for none).
pub fn print_text(text: &str) {
    let text = text.trim_end();
    if !text.is_empty() {
        crate::outln!("{text}");
    }
}

/// Prints the bandwidth of one channel, or of all (discovery's gossip
/// included), every second until `--for` or `stop`.
pub async fn bw(
    node: &Node,
    namespace: &str,
    args: &BwArgs,
    stop: impl Future<Output = ()>,
) -> Result<()> {
    let channel = args
        .channel
        .as_deref()
        .map(|c| resolve_name(c, namespace))
        .transpose()?;
    let mut watch = ChannelWatch::new(node);
    if let Some(c) = &channel {
        watch.watch(c)?;
    }
    let all = channel.is_none();
    if all {
        // Let discovery reveal the channels before measuring starts.
        tokio::time::sleep(Duration::from_millis(300)).await;
        watch.watch_announced();
        watch.watch(pulicast::NODES_CHANNEL)?;
    }
    let discovery_start = node.discovery().stats().map(|s| s.bytes_in).unwrap_or(0);
    let discovery_since = Instant::now();
    report_loop(args.for_secs, stop, || {
        if all {
            // Channels appear as discovery reveals them.
            watch.watch_announced();
            let _ = watch.watch(pulicast::NODES_CHANNEL);
        }
        let window = watch.elapsed();
        let mut lines = Vec::new();
        for (name, m) in watch.meters() {
            let internal = name == pulicast::NODES_CHANNEL;
            if all && !args.all && !internal && pulicast::is_hidden_channel(&name) {
                continue;
            }
            lines.push(format!(
                "{name}: {:.0} B/s ({} messages, {:.0} B mean)",
                m.bandwidth(window),
                m.count,
                m.bytes as f64 / m.count.max(1) as f64
            ));
        }
        if all {
            let gossip = node
                .discovery()
                .stats()
                .map(|s| s.bytes_in)
                .unwrap_or(0)
                .saturating_sub(discovery_start);
            lines.push(format!(
                "{} (gossip): {:.0} B/s",
                pulicast::DISCOVERY_CHANNEL,
                gossip as f64 / discovery_since.elapsed().as_secs_f64().max(1e-9)
            ));
        }
        lines.join("\n")
    })
    .await
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_remote_member_says_where_it_is() {
        let info = pulicast::MemberInfo {
            session: [7; 16],
            name: "rover".into(),
            namespace: String::new(),
            host: "far-host".into(),
            pid: 1,
            start_time_ms: 0,
            data_port: 4000,
            channels: vec![],
            config: String::new(),
            extensions: Vec::new(),
        };
        let mut m = MemberView::from_info(&info, "127.0.0.1:5000".parse().unwrap());
        assert!(!node_line(&m).contains("via bridge"));
        m.remote = Some(pulicast::Remote::new(0xab, "robot\x1b[2J"));
        let line = node_line(&m);
        assert!(
            line.contains("(site robot\\u{1b}[2J, via bridge ab)"),
            "{line}"
        );
    }
}

//! The fleet as the page shows it: the members discovery knows (this
//! server's own node left out), made into one JSON frame when discovery
//! changes, at most every [`EVERY`], and handed to the clients through a
//! `watch` channel (as [`Utf8Bytes`], so each client's copy is a
//! reference, not the bytes). A client that reads slowly skips frames: it
//! only ever gets the newest, so a stalled browser holds one frame, not a
//! backlog.
//!
//! What strangers announce is bounded here by the server's own choice: at
//! most [`MAX_MEMBERS`] members and [`MAX_CHANNELS`] channel names of each
//! (the counts say how many there are), and names cut to [`MAX_NAME`]
//! bytes, so a hostile member can't make every frame (and every browser's
//! table) as large as discovery's own bounds.

use std::time::Duration;

use axum::extract::ws::Utf8Bytes;
use pulicast_tools::sniff::{self, ChannelWatch};
use serde_json::{json, Value};
use tokio::sync::watch;

/// The longest a change waits before it is shown, and the shortest time
/// between two frames.
pub const EVERY: Duration = Duration::from_millis(500);

/// Most members in a frame (the rest counted in `truncated`).
pub const MAX_MEMBERS: usize = 1024;

/// Most channels of a member in a frame (`more_channels` says when it
/// has more).
pub const MAX_CHANNELS: usize = 64;

/// Longest name in a frame, in bytes (a longer one is cut, on a
/// character boundary, and ends in `…`).
pub const MAX_NAME: usize = 256;

/// `name`, cut to [`MAX_NAME`] bytes on a character boundary (then
/// ending in `…`).
pub fn cut(name: &str) -> String {
    cut_to(name, MAX_NAME)
}

/// `text`, cut to `limit` bytes on a character boundary (then ending in
/// `…`).
pub fn cut_to(text: &str, limit: usize) -> String {
    if text.len() <= limit {
        return text.to_string();
    }
    let mut end = limit;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}…", &text[..end])
}

fn member(m: &pulicast::MemberView) -> Value {
    let shown = &m.channels[..m.channels.len().min(MAX_CHANNELS)];
    let names = |pred: fn(&pulicast::ChannelInfo) -> bool| -> Vec<String> {
        shown
            .iter()
            .filter(|c| pred(c))
            .map(|c| cut(&c.name))
            .collect()
    };
    json!({
        "key": m.key,
        "name": cut(&m.name),
        "namespace": cut(&m.namespace),
        "state": format!("{:?}", m.state).to_lowercase(),
        "address": m.address.to_string(),
        "site": m.remote.as_ref().map(|r| cut(&r.site)),
        "compat": m.compat,
        "publishes": names(|c| c.publishes),
        "subscribes": names(|c| c.subscribes),
        "more_channels": m.channels.len() > MAX_CHANNELS,
    })
}

/// Most channels in a frame (the rest counted in `channels_truncated`).
pub const MAX_FLEET_CHANNELS: usize = 1024;

/// Most services in a frame (the rest counted in `services_truncated`).
pub const MAX_SERVICES: usize = 256;

/// Most names of a channel's publishers or subscribers, or of a
/// service's servers or clients, in a frame.
pub const MAX_ENDS: usize = 64;

/// Most bytes of the names of a channel's publishers or subscribers, or
/// of a service's servers or clients, in a frame: a row made bulky by
/// many long names would take other rows' room.
pub const MAX_END_BYTES: usize = 2048;

/// The names of `all` a frame shows (at most [`MAX_ENDS`] and
/// [`MAX_END_BYTES`]), and how many more there are.
fn names(all: impl IntoIterator<Item = impl AsRef<str>>) -> (Vec<String>, usize) {
    let (mut shown, mut more, mut bytes) = (Vec::new(), 0, 0);
    for name in all {
        let name = cut(name.as_ref());
        if more > 0 || shown.len() >= MAX_ENDS || bytes + name.len() > MAX_END_BYTES {
            more += 1;
            continue;
        }
        bytes += name.len();
        shown.push(name);
    }
    (shown, more)
}

/// A rate as shown: three significant digits, so a frame changes when
/// the rate does, not with every jitter of the clock.
fn shown_rate(hz: f64) -> f64 {
    if !hz.is_finite() || hz <= 0.0 {
        return 0.0;
    }
    let scale = 10f64.powi(2 - hz.log10().floor() as i32);
    (hz * scale).round() / scale
}

/// Most bytes of a fleet frame's JSON: members may take half, channels
/// three eighths, services an eighth. Each count's bound alone would let
/// a hostile fleet make frames of tens of megabytes (a thousand members
/// of 64 long channel names each), sent to every client.
pub const MAX_FRAME: usize = 1 << 20;

/// The items of `all` that fit in `budget` bytes of JSON, in order (the
/// first that does not fit ends them).
fn within(all: impl Iterator<Item = Value>, budget: usize) -> Vec<Value> {
    let mut used = 0usize;
    let mut out = Vec::new();
    for item in all {
        let len = json_len(&item).saturating_add(1);
        if used + len > budget {
            break;
        }
        used += len;
        out.push(item);
    }
    out
}

/// The bytes of `item`'s JSON.
fn json_len(item: &Value) -> usize {
    struct Count(usize);
    impl std::io::Write for Count {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            self.0 += buf.len();
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let mut len = Count(0);
    match serde_json::to_writer(&mut len, item) {
        Ok(()) => len.0,
        Err(_) => usize::MAX,
    }
}

/// The channels each live member announces (not hidden), as owners for
/// [`crate::fair::choose`]: what it publishes before what it only
/// subscribes, in its own order.
pub fn channel_owners(members: &[pulicast::MemberView]) -> Vec<Vec<&str>> {
    members
        .iter()
        .filter(|m| m.is_live())
        .map(|m| {
            let published = m.channels.iter().filter(|c| c.publishes);
            let subscribed = m.channels.iter().filter(|c| !c.publishes);
            published
                .chain(subscribed)
                .map(|c| c.name.as_str())
                .filter(|n| !pulicast::is_hidden_channel(n))
                .collect()
        })
        .collect()
}

/// The services each server serves, by server key, as owners for
/// [`crate::fair::choose`].
pub fn service_owners(services: &[pulicast::ServiceInfo]) -> Vec<Vec<&str>> {
    let mut by_server: std::collections::BTreeMap<i64, Vec<&str>> = Default::default();
    for s in services {
        for end in &s.servers {
            by_server.entry(end.key).or_default().push(&s.name);
        }
    }
    by_server.into_values().collect()
}

/// Of `items` (JSON objects with a `name`), those `chosen` by
/// [`crate::fair::choose`], listed by name (as a frame lists them).
fn shown(items: &std::collections::HashMap<&str, (Value, usize)>, chosen: &[&str]) -> Vec<Value> {
    let mut names = chosen.to_vec();
    names.sort_unstable();
    names
        .into_iter()
        .filter_map(|n| items.get(n).map(|(v, _)| v.clone()))
        .collect()
}

/// The fleet frame of `node`'s discovery now, with the rates `watch` has
/// measured: the members, the channels (who publishes and subscribes
/// each: the connection graph), and the services.
pub fn frame(node: &pulicast::Node, watch: &ChannelWatch) -> Value {
    let discovery = node.discovery();
    let own = discovery.local().key;
    // Channels beyond what a frame shows are not even copied (one more,
    // to tell there are more).
    let mut all = discovery.members_within(MAX_CHANNELS + 1);
    all.retain(|m| m.key != own);
    all.sort_by(|a, b| a.name.cmp(&b.name).then(a.key.cmp(&b.key)));
    let members = within(all.iter().take(MAX_MEMBERS).map(member), MAX_FRAME / 2);
    let truncated = all.len() - members.len();

    let rows = sniff::channel_rows(&all, &watch.meters(), watch.elapsed());
    let rows: std::collections::HashMap<&str, (Value, usize)> = rows
        .iter()
        .filter(|r| !pulicast::is_hidden_channel(&r.name))
        // Only what a member announces: a meter alone (a channel whose
        // members left) is history, not the fleet.
        .filter(|r| !r.publishers.is_empty() || !r.subscribers.is_empty())
        .map(|r| {
            let (publishers, publishers_more) = names(&r.publishers);
            let (subscribers, subscribers_more) = names(&r.subscribers);
            let row = json!({
                "name": cut(&r.name),
                "publishers": publishers,
                "publishers_more": publishers_more,
                "subscribers": subscribers,
                "subscribers_more": subscribers_more,
                "type": r.type_name.as_deref().map(cut),
                "type_conflict": r.type_conflict.as_deref().map(cut),
                "rate_hz": shown_rate(r.rate_hz),
                "loss": (r.loss * 1000.0).round() / 1000.0,
            });
            let len = json_len(&row) + 1;
            (r.name.as_str(), (row, len))
        })
        .collect();
    // Which channels a full frame shows is chosen member by member, with
    // a share of the places and bytes each (crate::fair).
    let owners: Vec<Vec<&str>> = channel_owners(&all)
        .into_iter()
        .map(|o| o.into_iter().filter(|n| rows.contains_key(n)).collect())
        .collect();
    let chosen = crate::fair::choose(owners, MAX_FLEET_CHANNELS, MAX_FRAME * 3 / 8, |n| {
        rows.get(n).map_or(usize::MAX, |(_, len)| *len)
    });
    let channels = shown(&rows, &chosen);
    let channels_truncated = rows.len() - channels.len();

    let mut services = discovery.services();
    services.retain(|s| !s.servers.is_empty());
    let items: std::collections::HashMap<&str, (Value, usize)> = services
        .iter()
        .map(|s| {
            let end = s.server_types();
            let ty = |t: Option<&pulicast::TypeInfo>| t.map(|t| cut(&sniff::type_display(t)));
            let (servers, servers_more) = names(s.servers.iter().map(|e| &e.node));
            let (clients, clients_more) =
                names(s.clients.iter().filter(|e| e.key != own).map(|e| &e.node));
            let row = json!({
                "name": cut(&s.name),
                "servers": servers,
                "servers_more": servers_more,
                "clients": clients,
                "clients_more": clients_more,
                "request": ty(end.and_then(|e| e.request.as_ref())),
                "reply": ty(end.and_then(|e| e.reply.as_ref())),
                "progress": ty(end.and_then(|e| e.progress.as_ref())),
                "sealed": end.is_some_and(|e| e.sealed),
            });
            let len = json_len(&row) + 1;
            (s.name.as_str(), (row, len))
        })
        .collect();
    // Chosen server by server, as channels are member by member.
    let chosen = crate::fair::choose(
        service_owners(&services),
        MAX_SERVICES,
        MAX_FRAME / 8,
        |n| items.get(n).map_or(usize::MAX, |(_, len)| *len),
    );
    let shown_services = shown(&items, &chosen);
    let services_truncated = items.len() - shown_services.len();
    let services = shown_services;

    json!({
        "kind": "fleet",
        "members": members,
        "truncated": truncated,
        "channels": channels,
        "channels_truncated": channels_truncated,
        "services": services,
        "services_truncated": services_truncated,
    })
}

/// How often the rates are measured again and the frame rebuilt when
/// discovery is quiet.
pub const RATES_EVERY: Duration = Duration::from_secs(1);

/// Makes frames of `node`'s fleet until it stops: at once, then after each
/// discovery change (several within [`EVERY`] make one frame), and every
/// [`RATES_EVERY`] regardless, for the rates and for states that age
/// (suspect, dead). A frame like the last is not sent again.
///
/// The rates come from watching every announced channel without taking
/// part in it ([`ChannelWatch::quiet`]): the server is no subscriber in
/// anyone's eyes.
pub fn spawn(node: pulicast::Node) -> watch::Receiver<Utf8Bytes> {
    let mut meters = ChannelWatch::new(&node).quiet();
    meters.watch_announced();
    let (tx, rx) = watch::channel(Utf8Bytes::from(frame(&node, &meters).to_string()));
    tokio::spawn(async move {
        let mut events = node.discovery().events();
        loop {
            let changed = tokio::time::timeout(RATES_EVERY, events.recv()).await;
            if matches!(changed, Ok(None)) || node.is_stopped() || tx.is_closed() {
                return;
            }
            if changed.is_ok() {
                // Let a burst of changes settle into one frame.
                tokio::time::sleep(EVERY).await;
                while let Ok(Some(_)) = tokio::time::timeout(Duration::ZERO, events.recv()).await {}
            }
            meters.watch_announced();
            let next = frame(&node, &meters).to_string();
            tx.send_if_modified(|last| {
                let new = last.as_str() != next;
                if new {
                    *last = Utf8Bytes::from(next);
                }
                new
            });
        }
    });
    rx
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_frame_takes_what_fits_its_budget_in_order() {
        let items = (0..100).map(|i| json!({ "name": "x".repeat(90), "i": i }));
        let kept = within(items, 1000);
        // An item is about 110 bytes of JSON.
        assert!((8..=9).contains(&kept.len()), "{}", kept.len());
        assert_eq!(kept[0]["i"], 0);
        let total: usize = kept.iter().map(|v| v.to_string().len() + 1).sum();
        assert!(total <= 1000);
    }

    #[test]
    fn rates_are_shown_to_three_digits() {
        assert_eq!(shown_rate(0.0), 0.0);
        assert_eq!(shown_rate(f64::NAN), 0.0);
        assert_eq!(shown_rate(49.87), 49.9);
        assert_eq!(shown_rate(1003.4), 1000.0);
        assert_eq!(shown_rate(0.012345), 0.0123);
    }

    #[test]
    fn long_names_are_cut_on_a_character() {
        let long = "é".repeat(MAX_NAME);
        let shown = cut(&long);
        assert!(shown.len() <= MAX_NAME + "…".len());
        assert!(shown.ends_with('…'));
        assert_eq!(cut("rover1/pose"), "rover1/pose");
    }
}

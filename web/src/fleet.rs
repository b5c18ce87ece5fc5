//! The fleet as the page shows it: the members discovery knows (this
//! server's own node left out), made into one JSON frame when discovery
//! changes, at most every [`EVERY`], and handed to the clients through a
//! `watch` channel. A client that reads slowly skips frames: it only ever
//! gets the newest, so a stalled browser holds one frame, not a backlog.
//!
//! What strangers announce is bounded here by the server's own choice: at
//! most [`MAX_MEMBERS`] members and [`MAX_CHANNELS`] channel names of each
//! (the counts say how many there are), and names cut to [`MAX_NAME`]
//! bytes, so a hostile member can't make every frame (and every browser's
//! table) as large as discovery's own bounds.

use std::sync::Arc;
use std::time::Duration;

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

fn cut(name: &str) -> String {
    if name.len() <= MAX_NAME {
        return name.to_string();
    }
    let mut end = MAX_NAME;
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    format!("{}…", &name[..end])
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

/// The fleet frame of `node`'s discovery now.
pub fn frame(node: &pulicast::Node) -> Value {
    let discovery = node.discovery();
    let own = discovery.local().key;
    // Channels beyond what a frame shows are not even copied (one more,
    // to tell there are more).
    let mut all = discovery.members_within(MAX_CHANNELS + 1);
    all.retain(|m| m.key != own);
    all.sort_by(|a, b| a.name.cmp(&b.name).then(a.key.cmp(&b.key)));
    let truncated = all.len().saturating_sub(MAX_MEMBERS);
    let members: Vec<Value> = all.iter().take(MAX_MEMBERS).map(member).collect();
    json!({ "kind": "fleet", "members": members, "truncated": truncated })
}

/// Makes frames of `node`'s fleet until it stops: at once, then after each
/// discovery change (several within [`EVERY`] make one frame), and every
/// few seconds regardless, for states that age (suspect, dead). A frame
/// like the last is not sent again.
pub fn spawn(node: pulicast::Node) -> watch::Receiver<Arc<str>> {
    let (tx, rx) = watch::channel(Arc::<str>::from(frame(&node).to_string()));
    tokio::spawn(async move {
        let mut events = node.discovery().events();
        loop {
            let changed = tokio::time::timeout(EVERY * 6, events.recv()).await;
            if matches!(changed, Ok(None)) || node.is_stopped() || tx.is_closed() {
                return;
            }
            // Let a burst of changes settle into one frame.
            tokio::time::sleep(EVERY).await;
            while let Ok(Some(_)) = tokio::time::timeout(Duration::ZERO, events.recv()).await {}
            let next = frame(&node).to_string();
            tx.send_if_modified(|last| {
                let new = **last != *next;
                if new {
                    *last = Arc::from(next.as_str());
                }
                new
            });
        }
    });
    rx
}

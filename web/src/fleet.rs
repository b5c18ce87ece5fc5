//! The fleet as the page shows it: every member discovery knows (this
//! server's own node left out), made into one JSON frame when discovery
//! changes, at most every [`EVERY`], and handed to the clients through a
//! `watch` channel. A client that reads slowly skips frames: it only ever
//! gets the newest, so a stalled browser holds one frame, not a backlog.

use std::sync::Arc;
use std::time::Duration;

use serde_json::{json, Value};
use tokio::sync::watch;

/// The longest a change waits before it is shown, and the shortest time
/// between two frames.
pub const EVERY: Duration = Duration::from_millis(500);

/// The fleet frame of `node`'s discovery now.
pub fn frame(node: &pulicast::Node) -> Value {
    let discovery = node.discovery();
    let own = discovery.local().key;
    let mut members: Vec<Value> = discovery
        .members()
        .iter()
        .filter(|m| m.key != own)
        .map(pulicast_tools::sniff::node_json)
        .collect();
    members.sort_by(|a, b| {
        let name = |v: &Value| v["name"].as_str().unwrap_or_default().to_string();
        name(a).cmp(&name(b))
    });
    json!({ "kind": "fleet", "members": members })
}

/// Makes frames of `node`'s fleet until it stops: at once, then after each
/// discovery change (several within [`EVERY`] make one frame), and every
/// few seconds regardless, for states that age (suspect, dead).
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
            let frame = Arc::<str>::from(frame(&node).to_string());
            if tx.send(frame).is_err() {
                return;
            }
        }
    });
    rx
}

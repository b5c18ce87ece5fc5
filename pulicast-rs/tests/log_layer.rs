//! A log layer may call back into the node: the drop lines of the receive
//! path are written after the receiver is unlocked (`docs/architecture.md`,
//! "Locks"). Here a `tracing` layer reads `Node::stats` and
//! `Node::key_uses` on every warning, on the same thread as the receive
//! loop; were a drop logged under the receiver's lock, the first one would
//! deadlock (a watchdog turns that into a failure instead of a hang).

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::{eventually, free_port, node, raw_sender, send_raw};
use pulicast::{DropReason, Node};
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::layer::{Context, Layer, SubscriberExt};

/// Reads the node's counters from inside the log, on every warning.
struct StatsOnWarn {
    node: Arc<Mutex<Option<Node>>>,
    calls: Arc<AtomicU64>,
}

impl<S: Subscriber> Layer<S> for StatsOnWarn {
    fn on_event(&self, event: &Event<'_>, _: Context<'_, S>) {
        if *event.metadata().level() != Level::WARN {
            return;
        }
        if let Some(node) = self.node.lock().unwrap().as_ref() {
            let _ = node.stats();
            let _ = node.key_uses();
            self.calls.fetch_add(1, Ordering::Relaxed);
        }
    }
}

#[test]
fn a_log_layer_may_read_the_stats_while_drops_are_logged() {
    let done = Arc::new(AtomicBool::new(false));
    let watched = Arc::clone(&done);
    std::thread::spawn(move || {
        let deadline = Instant::now() + Duration::from_secs(30);
        while Instant::now() < deadline {
            if watched.load(Ordering::Relaxed) {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        eprintln!("the receive loop deadlocked on a log layer calling Node::stats");
        std::process::abort();
    });
    let slot = Arc::new(Mutex::new(None));
    let calls = Arc::new(AtomicU64::new(0));
    let layer = StatsOnWarn {
        node: Arc::clone(&slot),
        calls: Arc::clone(&calls),
    };
    let subscriber = tracing_subscriber::registry().with(layer);
    // One thread: the receive loop runs where the layer is the default.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    tracing::subscriber::with_default(subscriber, || {
        runtime.block_on(async {
            let port = free_port();
            let node = node("log_layer", port).start().await.unwrap();
            let _sub = node.channel("a").subscribe::<u64>().unwrap();
            *slot.lock().unwrap() = Some(node.clone());
            let raw = raw_sender();
            // The channel name runs past the end: dropped, and the first
            // drop of its reason is always logged.
            for _ in 0..10 {
                send_raw(&raw, "a", port, b"PULI\x05a");
            }
            eventually("a logged drop read the stats", || {
                calls.load(Ordering::Relaxed) > 0
            })
            .await;
            assert!(node.stats().dropped(DropReason::NamePastEnd) > 0);
            slot.lock().unwrap().take();
        });
    });
    done.store(true, Ordering::Relaxed);
}

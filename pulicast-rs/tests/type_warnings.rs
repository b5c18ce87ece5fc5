//! What a subscriber of the wrong type is told: both types named in the
//! node's warnings, read here as a user's `tracing` subscriber shows them.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::sync::{Arc, Mutex};

use common::*;
use pulicast::{DropReason, Schema};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Schema, Debug)]
struct Twist {
    linear: f64,
    angular: f64,
}

#[derive(Serialize, Deserialize, Schema, Debug)]
struct Odometry {
    x: f64,
    y: f64,
    heading: f64,
}

/// Everything the library logs in this process, as text.
#[derive(Clone, Default)]
struct Log(Arc<Mutex<Vec<u8>>>);

impl std::io::Write for Log {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Log {
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.0.lock().unwrap()).into_owned()
    }
}

/// Publishes until the log holds every one of `what` (at most 10 s).
async fn until_logged(log: &Log, what: &[&str], publish: impl Fn()) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while !what.iter().all(|w| log.text().contains(w)) {
        assert!(
            std::time::Instant::now() < deadline,
            "{what:?} not in {}",
            log.text()
        );
        publish();
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subscriber_of_the_wrong_type_is_told_both_types() {
    let log = Log::default();
    let writer = log.clone();
    tracing_subscriber::fmt()
        .with_writer(move || writer.clone())
        .with_ansi(false)
        .init();

    let port = free_port();
    let controller = node("controller", port).start().await.unwrap();
    let mut twists = controller
        .channel("rover1/ctrl")
        .subscribe::<Twist>()
        .unwrap();
    // A 2.x message: its type is known by its fingerprint.
    let text = node("texter", port).start().await.unwrap();
    let status = text.channel("rover1/ctrl");
    until_logged(
        &log,
        &[
            "dropped a message of another type: expected Twist, got string_msg",
            "subscribes to rover1/ctrl as Twist, but texter publishes string_msg there",
        ],
        || status.publish("Go LEFT!").unwrap(),
    )
    .await;
    text.stop();
    // A native type: named by what its publisher announces.
    let odometry = node("odometer", port).start().await.unwrap();
    let ctrl = odometry.channel("rover1/ctrl");
    let odometry_sent = || {
        ctrl.publish(&Odometry {
            x: 1.0,
            y: 2.0,
            heading: 0.5,
        })
        .unwrap()
    };
    until_logged(
        &log,
        &["subscribes to rover1/ctrl as Twist, but odometer publishes Odometry there"],
        &odometry_sent,
    )
    .await;
    assert!(controller.stats().dropped(DropReason::WrongType) > 0);
    assert!(twists.try_recv().is_none());
    // Said once per member and type, however many messages it sends and
    // however many checks (one a second) see it.
    for _ in 0..50 {
        odometry_sent();
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    let logged = log.text();
    assert_eq!(
        logged.matches("but odometer publishes Odometry").count(),
        1,
        "{logged}"
    );
}

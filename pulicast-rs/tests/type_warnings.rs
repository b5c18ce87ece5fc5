//! What the library tells a user through `tracing` (read here as a user's
//! subscriber shows it): a subscriber of the wrong type is told both types,
//! and a node pinned to loopback says once what it can't hear.

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

/// The process's log, from a subscriber installed once.
fn log() -> Log {
    static LOG: std::sync::OnceLock<Log> = std::sync::OnceLock::new();
    LOG.get_or_init(|| {
        let log = Log::default();
        let writer = log.clone();
        tracing_subscriber::fmt()
            .with_writer(move || writer.clone())
            .with_ansi(false)
            .init();
        log
    })
    .clone()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_pinned_to_loopback_says_once_what_it_cannot_hear() {
    let log = log();
    let port = free_port();
    let first = node("pinned_one", port).start().await.unwrap();
    let second = node("pinned_two", port).start().await.unwrap();
    // Where the routes send multicast from: a network, or only loopback.
    let probe = std::net::UdpSocket::bind("0.0.0.0:0").unwrap();
    let network = probe.connect(("239.0.0.0", port)).is_ok()
        && !probe.local_addr().unwrap().ip().is_loopback();
    let said = log.text().matches("pinned to 127.0.0.1").count();
    if network {
        assert_eq!(said, 1, "{}", log.text());
        assert!(log
            .text()
            .contains("not Pulicast 2.x nodes started with their defaults"));
    } else {
        assert_eq!(said, 0, "{}", log.text());
    }
    drop((first, second));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subscriber_of_the_wrong_type_is_told_both_types() {
    let log = log();

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
    // Said once per channel and type, however many messages it sends and
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

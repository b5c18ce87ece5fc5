//! Distributed settings between nodes on loopback: a tool's requests are
//! checked and confirmed by the owner, on the 2.x puliconf wire. Every
//! wait is bounded.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use common::{free_port, node, WAIT};
use pulicast::wire::setting::{Request, RocAck};
use pulicast::wire::zcm::{fingerprint, Primitive};
use pulicast::{Bytes, Check, Error, Message};

/// A tool's side, by hand: sends requests, returns confirmations.
struct Tool {
    requests: pulicast::Channel,
    confirmations: mpsc::Receiver<Vec<u8>>,
    _sub: pulicast::CallbackSubscription,
    _node: pulicast::Node,
}

impl Tool {
    fn new(port: u16, confirmation: &str) -> Self {
        let node = node("tool", port).start_blocking().unwrap();
        let (tx, confirmations) = mpsc::channel();
        let sub = node
            .channel(&format!("/{confirmation}"))
            .subscribe_raw_with(move |m: Message<Bytes>| {
                let _ = tx.send(m.value.to_vec());
            })
            .unwrap();
        let requests = node.channel(&format!("/{confirmation}.r"));
        Self {
            requests,
            confirmations,
            _sub: sub,
            _node: node,
        }
    }

    /// Sends `request` until a confirmation comes (the first may go out
    /// before the owner's subscription is joined), and returns it.
    fn ask(&self, request: &[u8]) -> Vec<u8> {
        let start = Instant::now();
        loop {
            self.requests.publish_bytes(request).unwrap();
            if let Ok(c) = self.confirmations.recv_timeout(Duration::from_millis(200)) {
                return c;
            }
            assert!(start.elapsed() < WAIT, "no confirmation");
        }
    }
}

fn value(p: Primitive) -> Vec<u8> {
    let mut out = Vec::new();
    p.encode(&mut out);
    out
}

fn special(r: Request<'_>) -> Vec<u8> {
    let mut out = Vec::new();
    r.encode(&mut out);
    out
}

#[test]
fn a_tool_reads_and_changes_a_setting_within_its_checks() {
    let port = free_port();
    let owner = node("owner", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let speed = owner
        .setting_checked("max_speed", 1.5f64, vec![Check::Range(0.0, 2.0)])
        .unwrap();
    assert_eq!(speed.name(), "rover1/max_speed");
    let seen = Arc::new(Mutex::new(Vec::new()));
    let watched = Arc::clone(&seen);
    speed.on_change(move |v| watched.lock().unwrap().push(v.copied()));

    let tool = Tool::new(port, "rover1/.config/max_speed");
    let poked = tool.ask(&special(Request::Poke));
    let ack = RocAck::decode(&poked).unwrap();
    assert_eq!(ack.fingerprint, fingerprint::DOUBLE_MSG);
    assert_eq!(ack.value, 1.5f64.to_be_bytes());
    assert_eq!(ack.message, "must be in [0, 2]");

    let accepted = tool.ask(&value(Primitive::Double(0.5)));
    let ack = RocAck::decode(&accepted).unwrap();
    assert_eq!((ack.message, ack.value), ("", &0.5f64.to_be_bytes()[..]));
    assert_eq!(speed.get(), Some(0.5));

    let refused = tool.ask(&value(Primitive::Double(9.0)));
    let ack = RocAck::decode(&refused).unwrap();
    assert_eq!(
        (ack.message, ack.value),
        ("must be in [0, 2]", &0.5f64.to_be_bytes()[..])
    );
    let wrong = tool.ask(&value(Primitive::String("fast".into())));
    assert!(RocAck::decode(&wrong)
        .unwrap()
        .message
        .contains("double_msg"));
    let garbage = tool.ask(&[1, 2, 3]);
    assert!(!RocAck::decode(&garbage).unwrap().message.is_empty());
    assert_eq!(speed.get(), Some(0.5));

    let reset = tool.ask(&special(Request::Reset));
    assert_eq!(RocAck::decode(&reset).unwrap().value, 1.5f64.to_be_bytes());
    assert_eq!(*seen.lock().unwrap(), [Some(0.5), Some(1.5)]);

    // The owner's own change is confirmed to the fleet too.
    assert!(speed.set(1.0).unwrap());
    let pushed = tool.confirmations.recv_timeout(WAIT).unwrap();
    assert_eq!(RocAck::decode(&pushed).unwrap().value, 1.0f64.to_be_bytes());
    assert!(matches!(speed.set(5.0), Err(Error::SettingRefused { .. })));
}

#[test]
fn bad_declarations_are_errors() {
    let port = free_port();
    let owner = node("owner", port).start_blocking().unwrap();
    assert!(matches!(
        owner.setting_checked("gain", 20i64, vec![Check::AtMost(10)]),
        Err(Error::SettingRefused { .. })
    ));
    assert!(matches!(
        owner.setting("bad name\n", 1i64),
        Err(Error::InvalidName { .. })
    ));
    let unset = owner.setting("mode", "auto".to_string()).unwrap();
    let tool = Tool::new(port, ".config/mode");
    let ack = tool.ask(&special(Request::Unset));
    assert!(!RocAck::decode(&ack).unwrap().is_set());
    assert_eq!(unset.get(), None);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn changes_can_be_awaited_and_end_with_the_setting() {
    let port = free_port();
    let owner = node("owner", port).start().await.unwrap();
    let gain = owner.setting("gain", 1i64).unwrap();
    let mut changes = gain.changes();
    gain.set(2).unwrap();
    gain.set(2).unwrap(); // no change, nothing to tell
    let got = tokio::time::timeout(WAIT, changes.changed()).await.unwrap();
    assert_eq!(got, Some(Some(2)));
    // A tool's request is a change too.
    let tool = std::thread::spawn(move || {
        let tool = Tool::new(port, ".config/gain");
        tool.ask(&special(Request::Unset))
    });
    let got = tokio::time::timeout(WAIT, changes.changed()).await.unwrap();
    assert_eq!(got, Some(None));
    let _ = tool.join().unwrap();
    drop(gain);
    let got = tokio::time::timeout(WAIT, changes.changed()).await.unwrap();
    assert_eq!(got, None);
}

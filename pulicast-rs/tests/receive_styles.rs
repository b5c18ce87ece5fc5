//! The ways to receive besides one `recv` per message: handlers on the
//! receive path (`subscribe_with` and its variants) and draining
//! (`recv_many`, `try_iter`). Loopback multicast pinned to 127.0.0.1 with
//! TTL 0; every wait has a timeout.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use common::{eventually, free_port, node, packet, raw_sender, send_raw, WAIT};
use pulicast::{Bytes, DropReason, Message, Node};

fn blocking_node(name: &str, port: u16) -> Node {
    node(name, port).start_blocking().unwrap()
}

/// Waits (bounded) until `cond` holds, on a plain thread.
fn wait_until(what: &str, mut cond: impl FnMut() -> bool) {
    let start = Instant::now();
    while !cond() {
        assert!(start.elapsed() < WAIT, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn a_handler_gets_every_message_in_order_and_skips_other_types() {
    let port = free_port();
    let node = blocking_node("handled", port);
    let (tx, rx) = mpsc::channel();
    let channel = node.channel("styles/values");
    let _values = channel
        .subscribe_with(move |m: Message<i64>| tx.send((m.value, m.seq, m.lead)).unwrap())
        .unwrap();
    for i in 0..100i64 {
        channel.publish(&i).unwrap();
        if i == 50 {
            // Another type on the same channel: skipped and counted.
            channel.publish(&"not a number").unwrap();
        }
    }
    let got: Vec<_> = (0..100).map(|_| rx.recv_timeout(WAIT).unwrap()).collect();
    let values: Vec<i64> = got.iter().map(|g| g.0).collect();
    assert_eq!(values, (0..100).collect::<Vec<_>>());
    assert!(got.iter().all(|g| g.2 >= 1));
    wait_until("the wrong type to be counted", || {
        node.stats().dropped(DropReason::WrongType) == 1
    });
    assert_eq!(node.stats().messages_delivered, 100);
    assert!(rx.try_recv().is_err());
}

#[test]
fn raw_and_ordered_handlers() {
    let port = free_port();
    let node = blocking_node("handled", port);
    let raws = Arc::new(Mutex::new(Vec::new()));
    let kept = Arc::clone(&raws);
    let _raw = node
        .channel("styles/raw")
        .subscribe_raw_with(move |m: Message<Bytes>| kept.lock().unwrap().push(m.value))
        .unwrap();
    let ordered = Arc::new(Mutex::new(Vec::new()));
    let kept = Arc::clone(&ordered);
    let _ordered = node
        .channel("styles/ordered")
        .subscribe_ordered_with(move |m: Message<Vec<u8>>| kept.lock().unwrap().push(m.seq))
        .unwrap();
    node.channel("styles/raw")
        .publish_bytes(&[1, 2, 3])
        .unwrap();

    // A sender whose datagrams arrive out of order: 0, 2, 1 (late), 3.
    let sender = raw_sender();
    for seq in [0, 2, 1, 3] {
        send_raw(
            &sender,
            "styles/ordered",
            port,
            &packet("styles/ordered", seq, b"x"),
        );
    }
    wait_until("the raw message", || raws.lock().unwrap().len() == 1);
    assert_eq!(&raws.lock().unwrap()[0][..], &[1, 2, 3]);
    wait_until("the ordered messages", || {
        ordered.lock().unwrap().len() == 3
    });
    assert_eq!(*ordered.lock().unwrap(), [0, 2, 3]);
    wait_until("the late one to be counted", || {
        node.stats().out_of_order_skipped == 1
    });
}

/// The handler runs with nothing of the node locked: what robot code does
/// in a callback (answer on another channel, read stats, subscribe more,
/// drop its own subscription) works and does not deadlock.
#[test]
fn a_handler_may_publish_subscribe_read_stats_and_unsubscribe_itself() {
    let port = free_port();
    let node = Arc::new(blocking_node("reentrant", port));
    let (pongs_tx, pongs) = mpsc::channel();
    let _pongs = node
        .channel("styles/pong")
        .subscribe_with(move |m: Message<i64>| pongs_tx.send(m.value).unwrap())
        .unwrap();

    let me: Arc<Mutex<Option<pulicast::CallbackSubscription>>> = Arc::default();
    let extra: Arc<Mutex<Vec<pulicast::Subscription<i64>>>> = Arc::default();
    let (handle, n, keep) = (Arc::clone(&node), Arc::clone(&me), Arc::clone(&extra));
    let calls = Arc::new(AtomicU64::new(0));
    let counted = Arc::clone(&calls);
    let ping = node
        .channel("styles/ping")
        .subscribe_with(move |m: Message<i64>| {
            counted.fetch_add(1, Ordering::Relaxed);
            handle
                .channel("styles/pong")
                .publish(&(m.value * 10))
                .unwrap();
            let _ = handle.stats();
            keep.lock()
                .unwrap()
                .push(handle.channel("styles/more").subscribe::<i64>().unwrap());
            if m.value == 2 {
                // Unsubscribes from inside its own call.
                drop(n.lock().unwrap().take());
            }
        })
        .unwrap();
    *me.lock().unwrap() = Some(ping);

    for i in 1..=2i64 {
        node.channel("styles/ping").publish(&i).unwrap();
        assert_eq!(pongs.recv_timeout(WAIT).unwrap(), i * 10);
    }
    assert!(me.lock().unwrap().is_none());
    // Gone: later pings reach nobody.
    node.channel("styles/ping").publish(&3i64).unwrap();
    node.channel("styles/more").publish(&7i64).unwrap();
    let mut more = extra.lock().unwrap().pop().unwrap();
    assert_eq!(more.recv_timeout(WAIT).unwrap().value, 7);
    assert_eq!(pongs.recv_timeout(Duration::from_millis(200)).ok(), None);
    assert_eq!(calls.load(Ordering::Relaxed), 2);
}

#[test]
fn a_dropped_handler_is_not_called_again() {
    let port = free_port();
    let node = blocking_node("dropping", port);
    let calls = Arc::new(AtomicU64::new(0));
    let counted = Arc::clone(&calls);
    let channel = node.channel("styles/drop");
    let subscription = channel
        .subscribe_with(move |_: Message<i64>| {
            counted.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
    // A canary queue on the same channel shows when a message was received.
    let mut canary = channel.subscribe::<i64>().unwrap();
    channel.publish(&1i64).unwrap();
    canary.recv_timeout(WAIT).unwrap();
    wait_until("the handler's call", || calls.load(Ordering::Relaxed) == 1);
    drop(subscription);
    channel.publish(&2i64).unwrap();
    canary.recv_timeout(WAIT).unwrap();
    assert_eq!(calls.load(Ordering::Relaxed), 1);
}

#[test]
fn a_panicking_handler_is_counted_and_called_again() {
    let port = free_port();
    let node = blocking_node("panicky", port);
    let (tx, rx) = mpsc::channel();
    let channel = node.channel("styles/panic");
    let _handler = channel
        .subscribe_with(move |m: Message<i64>| {
            assert!(m.value != 1, "the handler's own bug");
            tx.send(m.value).unwrap();
        })
        .unwrap();
    // Another channel on the same receive loop keeps working too.
    let mut other = node.channel("styles/other").subscribe::<i64>().unwrap();
    for i in 0..3i64 {
        channel.publish(&i).unwrap();
    }
    node.channel("styles/other").publish(&9i64).unwrap();
    assert_eq!(rx.recv_timeout(WAIT).unwrap(), 0);
    assert_eq!(rx.recv_timeout(WAIT).unwrap(), 2);
    assert_eq!(other.recv_timeout(WAIT).unwrap().value, 9);
    assert_eq!(node.stats().handler_panics, 1);
}

#[test]
fn a_handler_ends_when_the_node_stops() {
    let port = free_port();
    let node = blocking_node("stopping", port);
    let calls = Arc::new(AtomicU64::new(0));
    let counted = Arc::clone(&calls);
    let _kept = node
        .channel("styles/stop")
        .subscribe_with(move |_: Message<i64>| {
            counted.fetch_add(1, Ordering::Relaxed);
        })
        .unwrap();
    let other = blocking_node("publisher", port);
    other.channel("styles/stop").publish(&1i64).unwrap();
    wait_until("the first call", || calls.load(Ordering::Relaxed) == 1);
    node.stop();
    other.channel("styles/stop").publish(&2i64).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(calls.load(Ordering::Relaxed), 1);
}

#[test]
fn draining_takes_what_is_queued_in_one_call() {
    let port = free_port();
    let node = blocking_node("drained", port);
    let channel = node.channel("styles/drain");
    let mut sub = channel.subscribe::<i64>().unwrap();
    let mut out = Vec::new();
    assert_eq!(sub.try_recv_many(&mut out, 10), 0);
    assert_eq!(
        sub.recv_many_timeout(&mut out, 10, Duration::from_millis(20)),
        0
    );
    for i in 0..50i64 {
        channel.publish(&i).unwrap();
    }
    channel.publish(&"wrong type").unwrap();
    channel.publish(&50i64).unwrap();
    // Another type never takes a place in the queue.
    wait_until("everything queued", || sub.queued() == 51);
    assert_eq!(sub.recv_many_blocking(&mut out, 0), 0);
    assert_eq!(sub.recv_many_blocking(&mut out, 20), 20);
    assert_eq!(sub.recv_many_timeout(&mut out, 20, WAIT), 20);
    assert_eq!(sub.try_recv_many(&mut out, 10), 10);
    let rest: Vec<i64> = sub.try_iter().map(|m| m.value).collect();
    assert_eq!(rest, [50]);
    let values: Vec<i64> = out.iter().map(|m| m.value).collect();
    assert_eq!(values, (0..50).collect::<Vec<_>>());
    assert_eq!(node.stats().dropped(DropReason::WrongType), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn draining_asynchronously_and_ending_with_the_node() {
    let port = free_port();
    let node = node("drained", port).start().await.unwrap();
    let channel = node.channel("styles/drain_async");
    let mut sub = channel.subscribe::<i64>().unwrap();
    for i in 0..30i64 {
        channel.publish(&i).unwrap();
    }
    let mut out = Vec::new();
    while out.len() < 30 {
        let n = tokio::time::timeout(WAIT, sub.recv_many(&mut out, 8))
            .await
            .unwrap();
        assert!((1..=8).contains(&n));
    }
    let values: Vec<i64> = out.iter().map(|m| m.value).collect();
    assert_eq!(values, (0..30).collect::<Vec<_>>());
    eventually("nothing left queued", || sub.queued() == 0).await;
    node.stop();
    assert_eq!(sub.recv_many(&mut out, 8).await, 0);
}

/// The name of the thread a handler of `channel` runs on, for the next
/// message published there by `publish` after `after`.
fn handler_thread(node: &Node, channel: &str) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    let handler = node
        .channel(channel)
        .subscribe_with(move |_: Message<i64>| {
            let name = std::thread::current().name().unwrap_or("").to_string();
            let _ = tx.send(name);
        })
        .unwrap();
    // Kept for the node's life: the test's handler.
    std::mem::forget(handler);
    rx
}

/// A thread waiting in a blocking receive drives a `start_blocking` node
/// itself: the datagram wakes it, not the node's thread (no hand-off).
/// Once nobody waits, the node's own thread takes over again.
#[test]
fn a_blocking_receive_drives_the_node_and_the_node_thread_takes_over_after() {
    let port = free_port();
    let node = Arc::new(blocking_node("driven", port));
    let threads = handler_thread(&node, "styles/where");
    let mut idle = node.channel("styles/idle").subscribe::<i64>().unwrap();
    let publisher = Arc::clone(&node);
    let later = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(100));
        publisher.channel("styles/where").publish(&1i64).unwrap();
    });
    std::thread::Builder::new()
        .name("consumer".into())
        .spawn(move || {
            // Waits on a quiet channel: meanwhile it drives the node, so the
            // other channel's handler runs here.
            assert!(idle.recv_timeout(Duration::from_millis(400)).is_none());
        })
        .unwrap()
        .join()
        .unwrap();
    later.join().unwrap();
    assert_eq!(threads.recv_timeout(WAIT).unwrap(), "consumer");

    // Nobody waits now: the node's thread handles the next one.
    std::thread::sleep(Duration::from_millis(50));
    node.channel("styles/where").publish(&2i64).unwrap();
    let name = threads.recv_timeout(WAIT).unwrap();
    assert!(name.starts_with("pulicast-"), "{name}");
}

#[test]
fn several_threads_wait_at_once_and_each_gets_its_own() {
    let port = free_port();
    let node = Arc::new(blocking_node("several", port));
    let waiters: Vec<_> = (0..3i64)
        .map(|i| {
            let mut sub = node
                .channel(&format!("styles/several{i}"))
                .subscribe::<i64>()
                .unwrap();
            std::thread::spawn(move || sub.recv_timeout(WAIT).map(|m| m.value))
        })
        .collect();
    std::thread::sleep(Duration::from_millis(50));
    for i in 0..3i64 {
        node.channel(&format!("styles/several{i}"))
            .publish(&(i * 100))
            .unwrap();
    }
    let got: Vec<_> = waiters.into_iter().map(|w| w.join().unwrap()).collect();
    assert_eq!(got, [Some(0), Some(100), Some(200)]);
}

#[test]
fn stopping_the_node_ends_a_blocking_receive() {
    let port = free_port();
    let node = blocking_node("ending", port);
    let mut sub = node.channel("styles/end").subscribe::<i64>().unwrap();
    let waiter = std::thread::spawn(move || {
        let start = Instant::now();
        (sub.recv_blocking().map(|m| m.value), start.elapsed())
    });
    std::thread::sleep(Duration::from_millis(50));
    node.stop();
    let (got, waited) = waiter.join().unwrap();
    assert_eq!(got, None);
    assert!(waited < WAIT, "{waited:?}");
}

/// From inside another runtime (where `block_on` is not allowed) a
/// blocking receive waits the plain way, and still gets its message.
#[test]
fn a_blocking_receive_inside_a_runtime_waits_without_driving() {
    let port = free_port();
    let node = blocking_node("nested", port);
    let mut sub = node.channel("styles/nested").subscribe::<i64>().unwrap();
    let channel = node.channel("styles/nested");
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let got = runtime.block_on(async {
        channel.publish(&5i64).unwrap();
        sub.recv_timeout(WAIT).map(|m| m.value)
    });
    assert_eq!(got, Some(5));
}

/// A batch takes one slot of a subscription's queue, as one datagram; a
/// full queue drops the oldest batch whole, its messages counted.
#[test]
fn a_batch_takes_one_queue_slot_and_overflows_whole() {
    let port = free_port();
    let node = node("slots", port)
        .queue_capacity(2)
        .start_blocking()
        .unwrap();
    let channel = node.channel("styles/batched");
    let mut sub = channel.subscribe::<i64>().unwrap();
    channel.enable_batching(Duration::from_secs(1)).unwrap();
    for batch in 0..3i64 {
        for i in 0..100 {
            channel.publish(&(batch * 100 + i)).unwrap();
        }
        channel.flush().unwrap();
    }
    wait_until("the third batch to push out the first", || {
        node.stats().dropped(DropReason::QueueOverflow) == 100
    });
    assert_eq!(sub.queued(), 200);
    let mut out = Vec::new();
    while out.len() < 200 {
        assert!(sub.recv_many_timeout(&mut out, 1000, WAIT) > 0);
    }
    let values: Vec<i64> = out.iter().map(|m| m.value).collect();
    assert_eq!(values, (100..300).collect::<Vec<_>>());
}

/// Two handlers on one channel, each with its own run of messages: what
/// the first leaves (it panicked) is dropped, never handed to the second.
#[test]
fn what_one_handler_leaves_never_reaches_another() {
    let port = free_port();
    let node = blocking_node("runs", port);
    let channel = node.channel("styles/runs");
    let _first = channel
        .subscribe_with(|m: Message<i64>| assert!(m.value < 0, "the first handler's own bug"))
        .unwrap();
    let (tx, rx) = mpsc::channel();
    let _second = channel
        .subscribe_with(move |m: Message<i64>| tx.send(m.value).unwrap())
        .unwrap();
    // One batch with a message of another type in it: each typed handler
    // gets its messages as a run of its own, not the batch whole.
    channel.enable_batching(Duration::from_secs(1)).unwrap();
    for i in 0..5i64 {
        channel.publish(&i).unwrap();
        if i == 2 {
            channel.publish(&"text").unwrap();
        }
    }
    channel.flush().unwrap();
    let got: Vec<i64> = (0..5).map(|_| rx.recv_timeout(WAIT).unwrap()).collect();
    assert_eq!(got, [0, 1, 2, 3, 4]);
    assert!(rx.recv_timeout(Duration::from_millis(100)).is_err());
    assert_eq!(node.stats().handler_panics, 1);
}

/// A blocking receive inside a handler would stop the node that fills its
/// queue (the handler runs on the thread that receives): it returns at
/// once instead, and the node goes on.
#[test]
fn a_blocking_receive_inside_a_handler_does_not_wait() {
    let port = free_port();
    let node = blocking_node("inside", port);
    let mut other = node
        .channel("styles/other_queue")
        .subscribe::<i64>()
        .unwrap();
    let (tx, rx) = mpsc::channel();
    let _handler = node
        .channel("styles/inside")
        .subscribe_with(move |_: Message<i64>| {
            let start = Instant::now();
            let got = other.recv_timeout(Duration::from_secs(10));
            tx.send((got.map(|m| m.value), start.elapsed())).unwrap();
        })
        .unwrap();
    node.channel("styles/inside").publish(&1i64).unwrap();
    let (got, waited) = rx.recv_timeout(WAIT).unwrap();
    assert_eq!(got, None);
    assert!(waited < Duration::from_secs(1), "{waited:?}");
    node.channel("styles/inside").publish(&2i64).unwrap();
    assert!(rx.recv_timeout(WAIT).is_ok(), "the node goes on");
}

#[test]
fn the_longest_timeout_is_no_error() {
    let port = free_port();
    let node = blocking_node("forever", port);
    let channel = node.channel("styles/forever");
    let mut sub = channel.subscribe::<i64>().unwrap();
    channel.publish(&1i64).unwrap();
    channel.publish(&2i64).unwrap();
    wait_until("both queued", || sub.queued() == 2);
    assert_eq!(sub.recv_timeout(Duration::MAX).map(|m| m.value), Some(1));
    let mut out = Vec::new();
    assert_eq!(sub.recv_many_timeout(&mut out, 8, Duration::MAX), 1);
}

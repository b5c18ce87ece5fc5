//! The nearest server, in DROS's order (configuration outer, namespace
//! inner), between real nodes on loopback: calls go down the order as
//! servers stop, are busy, stay silent or can't answer, and come back to
//! the nearest when it returns.

mod common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use common::{eventually, free_port, node, WAIT};
use pulicast::{Error, Fault, Node};
use tokio::sync::Notify;

async fn start(name: &str, port: u16, namespace: &str, config: &str) -> Node {
    node(name, port)
        .namespace(namespace)
        .config(config)
        .start()
        .await
        .expect("a node starts")
}

/// A `laser` server that answers with its node's name, runs one call at
/// a time, and holds a call of `hold` until `release` is notified.
fn laser(n: &Node, release: &Arc<Notify>) -> pulicast::Server {
    let name = n.name().to_string();
    let release = Arc::clone(release);
    n.server("laser")
        .concurrency(1)
        .serve(move |request: String| {
            let (name, release) = (name.clone(), Arc::clone(&release));
            async move {
                if request == "hold" {
                    release.notified().await;
                }
                Ok::<String, Fault>(name)
            }
        })
        .expect("the laser serves")
}

/// `node`'s client of the nearest `laser` server.
fn nearest_laser(node: &Node) -> pulicast::Client<String, String> {
    node.client::<String, String>("laser")
        .expect("a client of laser")
        .nearest()
        .expect("its nearest search")
}

/// Calls until `server` answers, each call without error, within [`WAIT`].
async fn calls_reach(client: &pulicast::Client<String, String>, server: &str) {
    let deadline = Instant::now() + WAIT * 2;
    loop {
        let by = client.call(&"ping".to_string()).await.expect("no error");
        if by == server {
            return;
        }
        assert!(Instant::now() < deadline, "calls never reached {server}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calls_go_down_the_order_as_servers_stop_and_return_to_the_nearest() {
    let port = free_port();
    let release = Arc::new(Notify::new());
    let serving = |name: &'static str, namespace: &'static str, config: &'static str| {
        let release = Arc::clone(&release);
        async move {
            let n = start(name, port, namespace, config).await;
            let server = laser(&n, &release);
            (n, server)
        }
    };
    let (alice_rover1, first) = serving("alice_rover1", "rover1", "alice").await;
    let (alice_root, _second) = serving("alice_root", "", "alice").await;
    let (anyone_rover1, _third) = serving("anyone_rover1", "rover1", "").await;
    let (_anyone_root, _fourth) = serving("anyone_root", "", "").await;
    // Another configuration's server is never a candidate.
    let _bob = serving("bob_rover1", "rover1", "bob").await;

    let caller = start("caller", port, "rover1", "alice").await;
    let client = nearest_laser(&caller);
    eventually("the four servers to be known", || {
        client.servers().len() == 4
    })
    .await;
    assert_eq!(
        client.servers(),
        [
            "rover1/laser@alice_rover1",
            "laser@alice_root",
            "rover1/laser@anyone_rover1",
            "laser@anyone_root",
        ]
    );
    let ping_request = "ping".to_string();
    let ping = || client.call(&ping_request);
    for _ in 0..3 {
        assert_eq!(ping().await.unwrap(), "alice_rover1");
    }

    // Busy: the first holds a call, so the next goes to the second.
    let held = client.start(&"hold".to_string()).await.unwrap();
    assert_eq!(held.node(), "alice_rover1");
    eventually("the held call to run", || first.running() == 1).await;
    assert_eq!(ping().await.unwrap(), "alice_root");
    release.notify_one();
    assert_eq!(held.reply().await.unwrap(), "alice_rover1");
    assert_eq!(first.counts().busy, 1);

    // Each stops in turn; the calls go on down the order without error,
    // whether discovery has seen the stop yet or the call finds out.
    drop(first);
    alice_rover1.stop();
    assert_eq!(ping().await.unwrap(), "alice_root");
    alice_root.stop();
    assert_eq!(ping().await.unwrap(), "anyone_rover1");
    anyone_rover1.stop();
    assert_eq!(ping().await.unwrap(), "anyone_root");

    // The nearest comes back (a new process, as a restart is): the calls
    // return to it without the caller doing anything.
    let back = start("alice_rover1", port, "rover1", "alice").await;
    let _back = laser(&back, &release);
    calls_reach(&client, "alice_rover1").await;
    assert_eq!(ping().await.unwrap(), "alice_rover1");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_and_mistyped_servers_are_passed_over_and_the_error_lists_them() {
    let port = free_port();
    // A node that looks like a server of rover1/laser to discovery (it
    // takes the requests and announces replies) and never answers.
    let mute = start("mute", port, "rover1", "alice").await;
    let _requests = mute
        .channel("/rover1/.services/laser")
        .subscribe_raw()
        .unwrap();
    let replies = mute.channel("/rover1/.services/laser@reply");
    replies.publish_bytes(b"").unwrap();
    // A server of the name with other types.
    let numbers = start("numbers", port, "", "alice").await;
    let _numbers = numbers
        .serve("laser", |x: i64| async move { Ok::<i64, Fault>(x) })
        .unwrap();

    let caller = start("caller", port, "rover1", "alice").await;
    let client = nearest_laser(&caller);
    // Both known (the one of other types is left out of `servers`).
    eventually("both to be known", || {
        let laser_servers = |name: &str| {
            caller
                .discovery()
                .services()
                .iter()
                .find(|s| s.name == name)
                .map_or(0, |s| s.servers.len())
        };
        laser_servers("rover1/laser") == 1 && laser_servers("laser") == 1
    })
    .await;
    assert_eq!(client.servers(), ["rover1/laser@mute"]);
    // Nothing answers: the error says who was tried and why.
    let started = Instant::now();
    let err = client
        .call_within(&"ping".to_string(), Duration::from_secs(1))
        .await
        .unwrap_err();
    let Error::NoServer { reason, .. } = &err else {
        panic!("expected no server, got {err:?}");
    };
    assert!(reason.contains("mute (rover1/laser): silent"), "{reason}");
    assert!(reason.contains("numbers (laser)"), "{reason}");
    assert!(reason.contains("requests of type int64_msg"), "{reason}");
    assert!(started.elapsed() < Duration::from_secs(3));

    // A real server further out answers once it is there: a new client
    // (which has passed over nobody yet) tries the silent one for its
    // share first, then it.
    let release = Arc::new(Notify::new());
    let anyone = start("anyone", port, "", "").await;
    let _anyone = laser(&anyone, &release);
    let client = nearest_laser(&caller);
    eventually("the real server to be known", || {
        client.servers().len() == 2
    })
    .await;
    assert_eq!(client.servers(), ["rover1/laser@mute", "laser@anyone"]);
    let started = Instant::now();
    let by = client
        .call_within(&"ping".to_string(), Duration::from_secs(2))
        .await
        .unwrap();
    assert_eq!(by, "anyone");
    let waited = started.elapsed();
    assert!(
        waited >= Duration::from_millis(300),
        "the silent one had its share first: {waited:?}"
    );
    // Passed over lately, the silent one is tried last for a while: the
    // next calls don't wait for it.
    assert_eq!(client.servers(), ["laser@anyone", "rover1/laser@mute"]);
    for _ in 0..3 {
        let started = Instant::now();
        let by = client.call(&"ping".to_string()).await.unwrap();
        assert_eq!(by, "anyone");
        // Far below the silent one's share (2.5 s of the 5 s deadline).
        assert!(started.elapsed() < Duration::from_secs(1));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_that_refuses_the_request_is_passed_over() {
    // A raw client checks no types before sending: the nearest server,
    // which takes numbers, refuses text (its handler never runs), and the
    // call goes on to the next.
    let port = free_port();
    let numbers = start("numbers", port, "rover1", "").await;
    let _numbers = numbers
        .serve("laser", |x: i64| async move { Ok::<i64, Fault>(x) })
        .unwrap();
    let release = Arc::new(Notify::new());
    let text = start("text", port, "", "").await;
    let _text = laser(&text, &release);
    let caller = start("caller", port, "rover1", "").await;
    let client = caller.raw_client("laser").unwrap().nearest().unwrap();
    eventually("both to be known", || client.servers().len() == 2).await;
    assert_eq!(client.servers(), ["rover1/laser@numbers", "laser@text"]);
    let mut request = Vec::new();
    pulicast::Primitive::String("ping".into()).encode(&mut request);
    let mut call = client.start(&request, WAIT).await.unwrap();
    let mut reply = None;
    while let Some(event) = call.next().await {
        if let pulicast::CallEvent::Reply { message, .. } = event {
            reply = Some(message);
        }
    }
    assert_eq!(call.node(), "text");
    let mut expected = Vec::new();
    pulicast::Primitive::String("text".into()).encode(&mut expected);
    assert_eq!(reply, Some(expected));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_server_that_has_the_call_keeps_it_past_its_share() {
    let port = free_port();
    let slow = start("slow", port, "rover1", "").await;
    let _slow = slow
        .serve("laser", |request: String| async move {
            tokio::time::sleep(Duration::from_millis(2500)).await;
            Ok::<String, Fault>(format!("slow {request}"))
        })
        .unwrap();
    let release = Arc::new(Notify::new());
    let fast = start("fast", port, "", "").await;
    let _fast = laser(&fast, &release);
    let caller = start("caller", port, "rover1", "").await;
    let client = nearest_laser(&caller);
    eventually("both to be known", || client.servers().len() == 2).await;
    // Its share is two seconds of four; the call takes two and a half,
    // and stays: the server said it runs it when the request came again.
    let reply = client
        .call_within(&"scan".to_string(), Duration::from_secs(4))
        .await
        .unwrap();
    assert_eq!(reply, "slow scan");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn this_nodes_own_server_is_a_candidate_in_its_place() {
    let port = free_port();
    let release = Arc::new(Notify::new());
    let own = start("own", port, "rover1", "alice").await;
    let _root = laser(&own, &release);
    let near = start("near", port, "rover1", "alice").await;
    let _near = near
        .ns("/rover1/arm")
        .serve("laser", |_: String| async {
            Ok::<String, Fault>("arm".into())
        })
        .unwrap();
    // From rover1/arm, near's rover1/arm/laser comes before the own
    // node's rover1/laser; the own one is called without the network once
    // near's is gone.
    let client = own
        .ns("arm")
        .client::<String, String>("laser")
        .unwrap()
        .nearest()
        .unwrap();
    eventually("both to be known", || client.servers().len() == 2).await;
    assert_eq!(
        client.servers(),
        ["rover1/arm/laser@near", "rover1/laser@own"]
    );
    assert_eq!(client.call(&"x".to_string()).await.unwrap(), "arm");
    near.stop();
    calls_reach(&client, "own").await;
}

/// A publisher of its node's name on `laser` in its namespace, every
/// 20 ms while `on` holds (until its node stops).
fn publish_name(n: &Node, on: &Arc<std::sync::atomic::AtomicBool>) {
    let channel = n.channel("laser");
    let name = n.name().to_string();
    let on = Arc::clone(on);
    let node = n.clone();
    tokio::spawn(async move {
        let deadline = Instant::now() + Duration::from_secs(120);
        while !node.is_stopped() && Instant::now() < deadline {
            if on.load(std::sync::atomic::Ordering::Relaxed) {
                let _ = channel.publish(&name);
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
}

/// Receives until the subscription hears `node`, checking that every
/// message delivered is of the publisher heard; within [`WAIT`] * 2.
async fn hears(sub: &mut pulicast::NearestSubscription<String>, node: &str) {
    let deadline = Instant::now() + WAIT * 2;
    let mut messages = 0;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let event = tokio::time::timeout(left, sub.recv_event())
            .await
            .unwrap_or_else(|_| panic!("never heard {node}; hearing {:?}", sub.hearing()))
            .expect("the node runs");
        match event {
            pulicast::NearestEvent::Message(m) => {
                let heard = sub.hearing().expect("a message comes from the one heard");
                assert_eq!(m.value, heard.node, "a message of another publisher");
                assert_eq!(m.source, heard.source);
                if heard.node == node {
                    messages += 1;
                    if messages == 5 {
                        return;
                    }
                }
            }
            pulicast::NearestEvent::Switched { to, .. } => {
                messages = 0;
                let _ = to;
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nearest_subscription_moves_down_the_order_and_back() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let port = free_port();
    let on = |v: bool| Arc::new(AtomicBool::new(v));
    let (first_on, second_on) = (on(true), on(true));
    let alice_rover1 = start("alice_rover1", port, "rover1", "alice").await;
    publish_name(&alice_rover1, &first_on);
    let alice_root = start("alice_root", port, "", "alice").await;
    publish_name(&alice_root, &second_on);
    let anyone_rover1 = start("anyone_rover1", port, "rover1", "").await;
    publish_name(&anyone_rover1, &on(true));
    let anyone_root = start("anyone_root", port, "", "").await;
    publish_name(&anyone_root, &on(true));
    let bob_rover1 = start("bob_rover1", port, "rover1", "bob").await;
    publish_name(&bob_rover1, &on(true));

    // Announced, and before alice_rover1 in the tie (by name), but it
    // published once before the listener came and never since: nothing
    // of it to hear, so it takes nothing.
    let alice_mute = start("alice_mute", port, "rover1", "alice").await;
    alice_mute.channel("laser").publish("once").unwrap();

    let listener = start("listener", port, "rover1", "alice").await;
    eventually("the announcing-only publisher to be known", || {
        listener
            .discovery()
            .live_members()
            .iter()
            .any(|m| m.name == "alice_mute" && m.publishes("rover1/laser"))
    })
    .await;
    let mut laser = listener.subscribe_nearest::<String>("laser").unwrap();
    hears(&mut laser, "alice_rover1").await;
    let heard = laser.hearing().unwrap().clone();
    assert_eq!(
        (heard.channel.as_str(), heard.config.as_str()),
        ("rover1/laser", "alice")
    );

    // Stops (the node leaves): the next in the order, alice's fleet-wide.
    alice_rover1.stop();
    hears(&mut laser, "alice_root").await;
    // Goes quiet (alive, publishing nothing): the next, everyone's rover1.
    second_on.store(false, Ordering::Relaxed);
    hears(&mut laser, "anyone_rover1").await;
    // Publishes again: back to it, as it is nearer.
    second_on.store(true, Ordering::Relaxed);
    hears(&mut laser, "alice_root").await;
    alice_root.stop();
    anyone_rover1.stop();
    hears(&mut laser, "anyone_root").await;

    // The nearest comes back (a new process, as a restart is).
    let back = start("alice_rover1", port, "rover1", "alice").await;
    publish_name(&back, &first_on);
    hears(&mut laser, "alice_rover1").await;
    // A node of no configuration hears everyone's only, never alice's.
    let plain = start("plain", port, "rover1", "").await;
    let mut plain_laser = plain.subscribe_nearest::<String>("laser").unwrap();
    hears(&mut plain_laser, "anyone_root").await;
    drop(bob_rover1);
}

//! The servers' HTTP layer (`puli_web::http`) spoken to as an attacker
//! who has no token: connections that say nothing, headers a byte at a
//! time, more connections than there are places, a refused request that
//! would keep its connection. Each test runs the gate's real router (the
//! page's is served by the same function).
#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use puli_web::gate::Gate;
use puli_web::guard::Guard;
use puli_web::http::{Limits, Refused};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

const TOKEN: &str = "0123456789abcdef0123456789abcdef";
/// Far more than any limit below: a test fails by this only if a limit
/// does not hold.
const WAIT: Duration = Duration::from_secs(20);

struct Served {
    port: u16,
    refused: Arc<Refused>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    serving: tokio::task::JoinHandle<std::io::Result<()>>,
}

async fn serve(limits: Limits) -> Served {
    let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let guard = Guard::with_token(IpAddr::V4(Ipv4Addr::LOCALHOST), port, &[], TOKEN.into());
    // Nothing listens behind it: no test here gets as far as an upgrade.
    let gate = Gate::new(guard, SocketAddr::from((Ipv4Addr::LOCALHOST, 9)));
    let refused = Arc::new(Refused::default());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let serving = tokio::spawn(puli_web::http::serve_with(
        listener,
        gate.router(),
        async {
            let _ = stopped.await;
        },
        limits,
        Arc::clone(&refused),
    ));
    Served {
        port,
        refused,
        stop: Some(stop),
        serving,
    }
}

async fn connect(port: u16) -> TcpStream {
    TcpStream::connect((Ipv4Addr::LOCALHOST, port))
        .await
        .unwrap()
}

/// Reads until the server closes the connection (or resets it); how long
/// that took, or `None` if it did not within [`WAIT`].
async fn closed(stream: &mut TcpStream) -> Option<Duration> {
    let start = Instant::now();
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout(WAIT.saturating_sub(start.elapsed()), stream.read(&mut buf))
            .await
        {
            Err(_) => return None,
            Ok(Ok(0) | Err(_)) => return Some(start.elapsed()),
            Ok(Ok(_)) => continue,
        }
    }
}

/// One request on `stream`, kept alive; the answer's status, read by its
/// `Content-Length`.
async fn ask(stream: &mut TcpStream, port: u16, path: &str) -> u16 {
    let request = format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n");
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        let n = tokio::time::timeout(WAIT, stream.read(&mut byte))
            .await
            .expect("an answer in time")
            .unwrap();
        assert_eq!(n, 1, "closed before the answer's head: {head:?}");
        head.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&head).to_lowercase();
    let length: usize = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))
        .map_or(0, |v| v.trim().parse().unwrap());
    let mut body = vec![0u8; length];
    stream.read_exact(&mut body).await.unwrap();
    head.split(' ').nth(1).unwrap().parse().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_connection_that_says_nothing_or_a_header_a_byte_at_a_time_is_closed() {
    let timeout = Duration::from_secs(1);
    let served = serve(Limits {
        header_read_timeout: timeout,
        ..Limits::default()
    })
    .await;
    let port = served.port;
    // The control: a request sent at once is answered.
    let mut quick = connect(port).await;
    assert_eq!(
        ask(&mut quick, port, &format!("/?token={TOKEN}")).await,
        400
    );
    let mut silent = connect(port).await;
    let mut trickle = connect(port).await;
    trickle.write_all(b"GET / HTTP/1.1\r\n").await.unwrap();
    // A header byte every 100 ms, never its end: bounded, and it stops as
    // soon as the server closed the connection.
    let trickling = tokio::spawn(async move {
        for _ in 0..200 {
            if trickle.write_all(b"X").await.is_err() {
                return true;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        false
    });
    let silent_for = closed(&mut silent).await.expect("the silent one closed");
    assert!(silent_for >= timeout / 2, "{silent_for:?}");
    assert!(
        tokio::time::timeout(WAIT, trickling)
            .await
            .unwrap()
            .unwrap(),
        "the trickling one closed"
    );
    // Idle between requests counts too: the answered one goes as well.
    closed(&mut quick).await.expect("the idle one closed");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_beyond_the_cap_are_closed_at_once_and_counted_and_a_place_comes_back() {
    let served = serve(Limits {
        max_connections: 4,
        header_read_timeout: Duration::from_secs(60),
    })
    .await;
    let port = served.port;
    // Four connections the server holds (each answered, kept alive).
    let mut held = Vec::new();
    for _ in 0..4 {
        let mut c = connect(port).await;
        assert_eq!(ask(&mut c, port, &format!("/?token={TOKEN}")).await, 400);
        held.push(c);
    }
    let mut fifth = connect(port).await;
    let took = closed(&mut fifth).await.expect("the fifth one closed");
    assert!(took < Duration::from_secs(10), "{took:?}");
    assert_eq!(served.refused.over_capacity.load(Ordering::Relaxed), 1);
    // The held ones still work.
    assert_eq!(
        ask(&mut held[0], port, &format!("/?token={TOKEN}")).await,
        400
    );
    // One goes; its place comes back (when the server has seen it go).
    drop(held.pop());
    let mut served_again = false;
    for _ in 0..100 {
        let mut c = connect(port).await;
        let request = format!("GET /?token={TOKEN} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n");
        c.write_all(request.as_bytes()).await.unwrap();
        let mut first = [0u8; 12];
        if tokio::time::timeout(WAIT, c.read_exact(&mut first))
            .await
            .unwrap()
            .is_ok()
        {
            assert_eq!(&first, b"HTTP/1.1 400");
            served_again = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(served_again, "a place came back");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_head_over_16_kib_is_refused_and_closed() {
    let served = serve(Limits::default()).await;
    let port = served.port;
    let mut c = connect(port).await;
    let filler = "x".repeat(puli_web::http::MAX_HEADER_BYTES);
    let request = format!(
        "GET /?token={TOKEN} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nX-Fill: {filler}\r\n\r\n"
    );
    // The server may close while the rest is still being written.
    let _ = c.write_all(request.as_bytes()).await;
    let mut answer = Vec::new();
    let _ = tokio::time::timeout(WAIT, c.read_to_end(&mut answer)).await;
    let answer = String::from_utf8_lossy(&answer);
    assert!(answer.starts_with("HTTP/1.1 431"), "{answer}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn upgraded_websockets_leave_their_http_place() {
    // The page's own router (a node behind it), with 4 HTTP places.
    let udp = pulicast_tests::free_port();
    let node = pulicast::Node::new("puli-web")
        .interface(Ipv4Addr::LOCALHOST)
        .port(udp)
        .keys_from_env(false)
        .start()
        .await
        .unwrap();
    let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let guard = Guard::with_token(IpAddr::V4(Ipv4Addr::LOCALHOST), port, &[], TOKEN.into());
    let app = puli_web::server::App::new(&node, guard);
    let refused = Arc::new(Refused::default());
    let (_stop, stopped) = tokio::sync::oneshot::channel::<()>();
    tokio::spawn(puli_web::http::serve_with(
        listener,
        app.router(),
        async {
            let _ = stopped.await;
        },
        Limits {
            max_connections: 4,
            ..Limits::default()
        },
        Arc::clone(&refused),
    ));
    // Eight sockets, twice the places: each leaves its place once
    // upgraded (tried again briefly, as the server frees it a moment
    // after the upgrade).
    let mut sockets = Vec::new();
    let deadline = Instant::now() + WAIT;
    while sockets.len() < 8 {
        use tokio_tungstenite::tungstenite::client::IntoClientRequest;
        let request = format!("ws://127.0.0.1:{port}/ws?token={TOKEN}")
            .into_client_request()
            .unwrap();
        match tokio_tungstenite::connect_async(request).await {
            Ok((socket, _)) => sockets.push(socket),
            Err(e) => {
                assert!(Instant::now() < deadline, "{} open: {e}", sockets.len());
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        }
    }
    assert_eq!(app.clients(), 8);
    // And the page itself is still served.
    let mut c = connect(port).await;
    assert_eq!(ask(&mut c, port, &format!("/?token={TOKEN}")).await, 303);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_without_the_token_is_answered_and_its_connection_closed() {
    let served = serve(Limits {
        header_read_timeout: Duration::from_secs(60),
        ..Limits::default()
    })
    .await;
    let port = served.port;
    let mut c = connect(port).await;
    // Kept alive by HTTP/1.1's default, but not by the server.
    assert_eq!(ask(&mut c, port, "/").await, 401);
    let took = closed(&mut c).await.expect("closed after the refusal");
    assert!(took < Duration::from_secs(10), "{took:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stopping_closes_idle_connections_and_returns() {
    let mut served = serve(Limits {
        header_read_timeout: Duration::from_secs(60),
        ..Limits::default()
    })
    .await;
    let port = served.port;
    let mut idle = connect(port).await;
    assert_eq!(ask(&mut idle, port, &format!("/?token={TOKEN}")).await, 400);
    drop(served.stop.take());
    tokio::time::timeout(WAIT, &mut served.serving)
        .await
        .expect("serve returns once stopped")
        .unwrap()
        .unwrap();
    closed(&mut idle).await.expect("the idle one closed");
    assert!(
        TcpStream::connect((Ipv4Addr::LOCALHOST, port))
            .await
            .is_err(),
        "nothing listens after the stop"
    );
}

//! The page's guard and socket, spoken to as an attacker and as many
//! browsers would, over raw HTTP and WebSocket on loopback.
#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::{IpAddr, Ipv4Addr};
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use puli_web::guard::Guard;
use puli_web::server::App;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::Message;

const TOKEN: &str = "5e5ame0pen5e5ame0pen5e5ame0pen12";
const WAIT: Duration = Duration::from_secs(10);
const XSS: &str = "<img src=x onerror=alert(1)>";

struct Server {
    port: u16,
    udp: u16,
    app: App,
    _node: pulicast::Node,
    _stop: tokio::sync::oneshot::Sender<()>,
}

async fn node(name: &str, udp: u16) -> pulicast::Node {
    pulicast::Node::new(name)
        .interface(Ipv4Addr::LOCALHOST)
        .port(udp)
        .keys_from_env(false)
        .start()
        .await
        .expect("a node on loopback")
}

async fn server() -> Server {
    let udp = pulicast_tests::free_port();
    let node = node("puli-web", udp).await;
    let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0)).await.unwrap();
    let port = listener.local_addr().unwrap().port();
    let guard = Guard::with_token(IpAddr::V4(Ipv4Addr::LOCALHOST), port, &[], TOKEN.into());
    let app = App::new(&node, guard);
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let serving = app.clone();
    tokio::spawn(async move {
        let _ = serving
            .serve(listener, async {
                let _ = stopped.await;
            })
            .await;
    });
    Server {
        port,
        udp,
        app,
        _node: node,
        _stop: stop,
    }
}

/// One raw HTTP/1.1 request; the status, and the answer whole.
async fn http(port: u16, path: &str, headers: &[(&str, String)]) -> (u16, String) {
    let mut stream = TcpStream::connect((Ipv4Addr::LOCALHOST, port))
        .await
        .unwrap();
    let mut request = format!("GET {path} HTTP/1.1\r\nConnection: close\r\n");
    if !headers.iter().any(|(k, _)| k.eq_ignore_ascii_case("host")) {
        request += &format!("Host: 127.0.0.1:{port}\r\n");
    }
    for (k, v) in headers {
        request += &format!("{k}: {v}\r\n");
    }
    request += "\r\n";
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut answer = Vec::new();
    tokio::time::timeout(WAIT, stream.read_to_end(&mut answer))
        .await
        .expect("an answer in time")
        .unwrap();
    let answer = String::from_utf8_lossy(&answer).into_owned();
    let status = answer
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, answer)
}

fn cookie(port: u16) -> (&'static str, String) {
    ("Cookie", format!("puli_web_{port}={TOKEN}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_needs_the_token_its_own_host_and_its_own_origin() {
    let s = server().await;
    let port = s.port;
    // No token, a wrong one, a wrong cookie: refused.
    assert_eq!(http(port, "/", &[]).await.0, 401);
    assert_eq!(http(port, "/?token=0000", &[]).await.0, 401);
    assert_eq!(
        http(
            port,
            "/app.js",
            &[("Cookie", format!("puli_web_{port}=nope"))]
        )
        .await
        .0,
        401
    );
    assert_eq!(http(port, "/ws", &[]).await.0, 401);
    // The address printed at start: a cookie, and on to the page.
    let (status, answer) = http(port, &format!("/?token={TOKEN}"), &[]).await;
    assert_eq!(status, 303, "{answer}");
    assert!(
        answer.contains(&format!(
            "puli_web_{port}={TOKEN}; HttpOnly; SameSite=Strict"
        )),
        "{answer}"
    );
    assert!(
        answer.to_ascii_lowercase().contains("\r\nlocation: /\r\n"),
        "{answer}"
    );
    let (status, page) = http(port, "/", &[cookie(port)]).await;
    assert_eq!(status, 200, "{page}");
    assert!(page.contains("<title>pulicast fleet</title>"));
    let csp = page
        .lines()
        .find(|l| {
            l.to_ascii_lowercase()
                .starts_with("content-security-policy:")
        })
        .unwrap_or("");
    assert!(
        csp.contains("script-src 'self'") && !csp.contains("unsafe-inline"),
        "{csp}"
    );
    let header = |name: &str| {
        page.lines()
            .find(|l| l.to_ascii_lowercase().starts_with(&format!("{name}:")))
            .unwrap_or("")
            .to_string()
    };
    assert!(
        header("x-content-type-options").ends_with("nosniff"),
        "{page}"
    );
    assert!(header("cache-control").ends_with("no-store"), "{page}");
    assert!(header("referrer-policy").ends_with("no-referrer"), "{page}");
    assert!(
        header("cross-origin-resource-policy").ends_with("same-origin"),
        "{page}"
    );
    // The token in the query opens the page and the socket only.
    assert_eq!(
        http(port, &format!("/app.js?token={TOKEN}"), &[]).await.0,
        401
    );
    let (status, script) = http(port, "/app.js", &[cookie(port)]).await;
    assert!(status == 200 && script.contains("textContent"), "{script}");
    // Another host name (DNS rebinding), another site's page: refused,
    // even with the token.
    let evil_host = ("Host", format!("evil.example:{port}"));
    assert_eq!(http(port, "/", &[cookie(port), evil_host]).await.0, 403);
    let evil_origin = ("Origin", "http://evil.example".to_string());
    assert_eq!(
        http(port, "/", &[cookie(port), evil_origin.clone()])
            .await
            .0,
        403
    );
    let upgrade = [
        cookie(port),
        evil_origin,
        ("Upgrade", "websocket".into()),
        ("Connection", "Upgrade".into()),
        ("Sec-WebSocket-Version", "13".into()),
        ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ==".into()),
    ];
    assert_eq!(http(port, "/ws", &upgrade).await.0, 403);
    // The page's own origin is fine.
    let own = ("Origin", format!("http://127.0.0.1:{port}"));
    assert_eq!(http(port, "/", &[cookie(port), own]).await.0, 200);
}

type Socket = tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<TcpStream>>;

/// The page's socket, opened with the token as from `origin`.
async fn open(port: u16, origin: &str) -> Result<Socket, tokio_tungstenite::tungstenite::Error> {
    let mut request = format!("ws://127.0.0.1:{port}/ws?token={TOKEN}")
        .into_client_request()
        .unwrap();
    request
        .headers_mut()
        .insert("Origin", origin.parse().unwrap());
    tokio_tungstenite::connect_async(request)
        .await
        .map(|(socket, _)| socket)
}

async fn client(port: u16, origin: &str) -> Socket {
    let socket = tokio::time::timeout(WAIT, open(port, origin))
        .await
        .expect("connected in time")
        .expect("the socket opens");
    socket
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_member_announcing_more_channels_and_services_than_a_frame_holds_hides_no_one_elses() {
    let s = server().await;
    let origin = format!("http://127.0.0.1:{}", s.port);
    let mut socket = client(s.port, &origin).await;
    // The attacker: more channels and services than a frame shows, named
    // to come first in any list by name ('!' sorts before letters). A
    // member's channels beyond 64 are not shown anyway: it takes several
    // members to fill a frame's channels.
    let per_member = puli_web::fleet::MAX_CHANNELS + 1;
    let members = puli_web::fleet::MAX_FLEET_CHANNELS / per_member + 1;
    let mut hostiles = Vec::new();
    for m in 0..members {
        let hostile = node(&format!("a-hostile-{m:02}"), s.udp).await;
        for c in 0..per_member {
            let _ = hostile.channel(&format!("!h/{m:02}/{c:02}")).publish(&0u8);
        }
        hostiles.push(hostile);
    }
    let hostile = &hostiles[0];
    let mut held = Vec::new();
    for i in 0..puli_web::fleet::MAX_SERVICES + 44 {
        held.push(
            hostile
                .serve(&format!("!h/s{i:03}"), |x: u8| async move {
                    Ok::<u8, pulicast::Fault>(x)
                })
                .unwrap(),
        );
    }
    // The fleet: one channel and one service.
    let rover = node("rover", s.udp).await;
    let _serving = rover
        .serve("rover/distance_to", |(x, y): (f64, f64)| async move {
            Ok::<f64, pulicast::Fault>(x.hypot(y))
        })
        .unwrap();
    let pose = rover.channel("rover/pose");
    let publishing = tokio::spawn(async move {
        for i in 0..1000 {
            let _ = pose.publish(&f64::from(i));
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    let has = |f: &serde_json::Value, list: &str, name: &str| {
        f[list]
            .as_array()
            .is_some_and(|l| l.iter().any(|c| c["name"] == name))
    };
    // Once the attacker's announcement is whole (more than a frame holds
    // of either), the rover's channel and service are still shown.
    let frame = fleet_until(&mut socket, |f| {
        f["channels_truncated"].as_u64().unwrap_or(0) > 0
            && f["services_truncated"].as_u64().unwrap_or(0) > 0
            && has(f, "services", "rover/distance_to")
            && has(f, "channels", "rover/pose")
    })
    .await;
    let channels = frame["channels"].as_array().unwrap();
    let hostile_shown = channels
        .iter()
        .filter(|c| c["name"].as_str().unwrap().starts_with("!h/"))
        .count();
    assert!(hostile_shown > 0, "the attacker's are shown too, fairly");
    // Still listed by name.
    let names: Vec<&str> = channels
        .iter()
        .map(|c| c["name"].as_str().unwrap())
        .collect();
    assert!(names.windows(2).all(|w| w[0] <= w[1]), "{names:?}");
    publishing.abort();
}

/// The next fleet frame that `pred` accepts, within [`WAIT`].
async fn fleet_until(
    socket: &mut tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<TcpStream>>,
    pred: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let next = tokio::time::timeout_at(deadline, socket.next())
            .await
            .expect("a frame in time");
        let Some(Ok(Message::Text(text))) = next else {
            panic!("the socket ended: {next:?}");
        };
        let frame: serde_json::Value = serde_json::from_str(text.as_str()).unwrap();
        if frame["kind"] == "fleet" && pred(&frame) {
            return frame;
        }
    }
}

fn names(frame: &serde_json::Value) -> Vec<String> {
    frame["members"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|m| m["name"].as_str().map(str::to_string))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn twenty_clients_get_the_fleet_and_one_that_sends_garbage_is_closed_alone() {
    let s = server().await;
    let origin = format!("http://127.0.0.1:{}", s.port);
    let mut clients = Vec::new();
    for _ in 0..20 {
        clients.push(client(s.port, &origin).await);
    }
    // A member joins, under a name that is markup: every client hears of it,
    // as text in JSON (the page sets it as text: see the lint test).
    let rover = node(XSS, s.udp).await;
    rover.channel("pose").publish(&1.5f64).unwrap();
    for c in &mut clients {
        let frame = fleet_until(c, |f| names(f).iter().any(|n| n == XSS)).await;
        assert!(
            !names(&frame).contains(&"puli-web".to_string()),
            "the server's own node is left out"
        );
    }
    assert_eq!(s.app.clients(), 20);
    // Up to 64 at once; the next is refused.
    let mut more = Vec::new();
    for _ in 20..puli_web::server::MAX_CLIENTS {
        more.push(client(s.port, &origin).await);
    }
    let refused = open(s.port, &origin).await.expect_err("one too many");
    assert!(refused.to_string().contains("503"), "{refused}");
    drop(more);
    // One sends what the page never sends: it is closed, the others go on.
    let mut bad = clients.pop().unwrap();
    bad.send(Message::Binary(vec![0xde, 0xad].into()))
        .await
        .unwrap();
    let closed = tokio::time::timeout(WAIT, async {
        loop {
            match bad.next().await {
                Some(Ok(Message::Close(frame))) => return frame.map(|f| u16::from(f.code)),
                Some(Ok(_)) => continue,
                _ => return None,
            }
        }
    })
    .await
    .expect("closed in time");
    assert_eq!(closed, Some(1008));
    clients[0]
        .send(Message::Text(r#"{"op":"ping"}"#.into()))
        .await
        .unwrap();
    let other = node("rover2", s.udp).await;
    for c in &mut clients {
        fleet_until(c, |f| names(f).contains(&"rover2".to_string())).await;
    }
    drop(other);
    drop(bad);
    let deadline = tokio::time::Instant::now() + WAIT;
    while s.app.clients() != 19 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{} clients",
            s.app.clients()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[test]
fn the_page_sets_what_comes_from_the_network_as_text_only() {
    // Markup from the network could run only through these.
    let script = include_str!("../assets/app.js");
    for sink in [
        "innerHTML",
        "outerHTML",
        "insertAdjacentHTML",
        "document.write",
        "eval(",
        "new Function",
        "DOMParser",
        "createContextualFragment",
        "srcdoc",
        "javascript:",
        "setAttribute(\"on",
        "setAttribute('on",
        "setTimeout(\"",
        "setInterval(\"",
    ] {
        assert!(!script.contains(sink), "app.js uses {sink}");
    }
    // And the page has no script of its own inline (the policy would stop
    // it anyway): no <script> body, no on...= handler attribute.
    let page = include_str!("../assets/index.html");
    assert!(!page.contains("<script>"), "inline script in index.html");
    let handler = page.split(" on").skip(1).any(|rest| {
        let name: String = rest.chars().take_while(char::is_ascii_alphabetic).collect();
        !name.is_empty() && rest[name.len()..].starts_with('=')
    });
    assert!(!handler, "an on...= handler in index.html");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_gone_before_its_upgrade_gives_its_place_back() {
    let s = server().await;
    let origin = format!("http://127.0.0.1:{}", s.port);
    // All places but one taken: a place kept by a failed upgrade would
    // leave none for the next real client.
    let mut held = Vec::new();
    for _ in 1..puli_web::server::MAX_CLIENTS {
        held.push(client(s.port, &origin).await);
    }
    for _ in 0..10 {
        let mut stream = TcpStream::connect((Ipv4Addr::LOCALHOST, s.port))
            .await
            .unwrap();
        let request = format!(
            "GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nCookie: puli_web_{port}={TOKEN}\r\n\
             Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n\
             Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n\r\n",
            port = s.port
        );
        stream.write_all(request.as_bytes()).await.unwrap();
        // Reset, not closed: the upgrade fails under the server.
        socket2::SockRef::from(&stream)
            .set_linger(Some(Duration::ZERO))
            .unwrap();
        drop(stream);
    }
    let deadline = tokio::time::Instant::now() + WAIT;
    while s.app.clients() != puli_web::server::MAX_CLIENTS - 1 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{} places kept",
            s.app.clients()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The last place is there for a real client (a reset the server
    // handles late may hold it a moment: tried again, not forever), and
    // the one after is not.
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        match open(s.port, &origin).await {
            Ok(socket) => {
                held.push(socket);
                break;
            }
            Err(e) => assert!(
                tokio::time::Instant::now() < deadline,
                "the last place stays taken: {e}"
            ),
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let refused = open(s.port, &origin).await.expect_err("one too many");
    assert!(refused.to_string().contains("503"), "{refused}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_fleet_frame_has_the_connection_graph_rates_and_services_and_the_server_takes_no_part()
{
    let s = server().await;
    let origin = format!("http://127.0.0.1:{}", s.port);
    let mut socket = client(s.port, &origin).await;
    let rover = node("rover", s.udp).await;
    let controller = node("controller", s.udp).await;
    let mut poses = controller.channel("rover/pose").subscribe::<f64>().unwrap();
    let pose = rover.channel("rover/pose");
    let _serving = rover
        .serve("rover/distance_to", |(x, y): (f64, f64)| async move {
            Ok::<f64, pulicast::Fault>(x.hypot(y))
        })
        .unwrap();
    // 50 Hz, for at most 20 s (the test waits 10 at most).
    let publishing = tokio::spawn(async move {
        for i in 0..1000 {
            let _ = pose.publish(&f64::from(i));
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    let channel = |f: &serde_json::Value| -> Option<serde_json::Value> {
        f["channels"]
            .as_array()?
            .iter()
            .find(|c| c["name"] == "rover/pose")
            .cloned()
    };
    let frame = fleet_until(&mut socket, |f| {
        channel(f).is_some_and(|c| {
            let rate = c["rate_hz"].as_f64().unwrap_or(0.0);
            (25.0..=60.0).contains(&rate) && c["subscribers"] == serde_json::json!(["controller"])
        })
    })
    .await;
    let pose_row = channel(&frame).unwrap();
    assert_eq!(pose_row["publishers"], serde_json::json!(["rover"]));
    assert_eq!(pose_row["type"], "f64", "{pose_row}");
    let service = frame["services"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "rover/distance_to")
        .cloned()
        .unwrap_or_else(|| panic!("no service in {frame}"));
    assert_eq!(service["servers"], serde_json::json!(["rover"]));
    assert_eq!(service["request"], "(f64, f64)", "{service}");
    // Hidden channels (a service's, settings') are not in the table.
    for c in frame["channels"].as_array().unwrap() {
        assert!(!c["name"].as_str().unwrap().contains('@'), "{c}");
    }
    // The server measures every channel without subscribing any: in the
    // publisher's eyes the only subscriber is the controller.
    // (The watch began at least a second ago, for the rate; a subscription
    // is announced at once: two more seconds would show it.)
    assert!(poses.recv().await.is_some());
    let until = tokio::time::Instant::now() + Duration::from_secs(2);
    while tokio::time::Instant::now() < until {
        let seen: Vec<String> = rover
            .channel("rover/pose")
            .subscribers()
            .into_iter()
            .map(|m| m.name)
            .collect();
        assert_eq!(seen, ["controller"]);
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    publishing.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fast_channel_reaches_a_client_decimated_to_thirty_frames_a_second_with_every_message_counted(
) {
    let s = server().await;
    let origin = format!("http://127.0.0.1:{}", s.port);
    let mut socket = client(s.port, &origin).await;
    let fast = node("fast", s.udp).await;
    let x = fast.channel("fast/x");
    x.publish(&0.0f64).unwrap();
    // As the page does: a channel picked from the fleet, its type known.
    fleet_until(&mut socket, |f| {
        f["channels"].as_array().is_some_and(|cs| {
            cs.iter()
                .any(|c| c["name"] == "fast/x" && c["type"] == "f64")
        })
    })
    .await;
    socket
        .send(Message::Text(
            r#"{"op":"watch","channels":["/fast//x","rover/\u00e9","ghost/x"]}"#.into(),
        ))
        .await
        .unwrap();
    // 10 messages every 10 ms: about 1 kHz, 2000 messages.
    let mut publishing = tokio::spawn(async move {
        let mut sent = 0u64;
        for burst in 0..200 {
            for i in 0..10 {
                if x.publish(&f64::from(burst * 10 + i)).is_ok() {
                    sent += 1;
                }
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        sent
    });
    let mut watching = None;
    let (mut frames, mut messages, mut biggest, mut shown) = (0u32, 0u64, 0u64, 0u32);
    let mut sent = None;
    let started = tokio::time::Instant::now();
    let deadline = started + WAIT;
    // Until every message sent is counted in a bucket (or the wait ends).
    while sent != Some(messages) && tokio::time::Instant::now() < deadline {
        if sent.is_none() && publishing.is_finished() {
            sent = Some((&mut publishing).await.unwrap());
        }
        let Ok(Some(Ok(Message::Text(text)))) =
            tokio::time::timeout(Duration::from_millis(100), socket.next()).await
        else {
            continue;
        };
        let frame: serde_json::Value = serde_json::from_str(text.as_str()).unwrap();
        match frame["kind"].as_str() {
            Some("watching") => watching = Some(frame),
            Some("samples") => {
                frames += 1;
                for b in frame["buckets"].as_array().unwrap() {
                    assert_eq!(b["channel"], "fast/x");
                    assert_eq!(b["type"], "f64");
                    let n = b["n"].as_u64().unwrap();
                    messages += n;
                    biggest = biggest.max(n);
                    let [last, min, max] = [0, 1, 2].map(|i| b["v"]["value"][i].as_f64().unwrap());
                    assert!(min <= last && last <= max, "{b}");
                    shown += u32::from(b.get("last").is_some());
                }
            }
            _ => {}
        }
    }
    let secs = started.elapsed().as_secs_f64();
    let sent = sent.expect("the publisher done in time");
    let watching = watching.expect("an answer to the watch");
    assert_eq!(watching["channels"], serde_json::json!(["fast/x"]));
    assert!(watching["refused"]["rover/é"].is_string(), "{watching}");
    assert!(watching["refused"]["ghost/x"].is_string(), "{watching}");
    // At most 30 a second (and one for a late tick), whatever the rate; a
    // loaded machine sends fewer, never more.
    assert!(
        f64::from(frames) <= 30.0 * secs + 2.0,
        "{frames} frames in {secs:.1} s"
    );
    assert!(
        biggest > 5,
        "the buckets hold several messages each: {biggest}"
    );
    // Every message is counted (loopback may lose a few to a full queue).
    assert!(
        messages <= sent && messages as f64 >= 0.95 * sent as f64,
        "{messages} of {sent} messages counted"
    );
    assert!(
        f64::from(shown) <= 5.0 * secs + 2.0,
        "the message shown {shown} times in {secs:.1} s"
    );
    assert_eq!(s.app.watched(), 1);
    // Nothing watched: the feed stops.
    socket
        .send(Message::Text(r#"{"op":"watch","channels":[]}"#.into()))
        .await
        .unwrap();
    let deadline = tokio::time::Instant::now() + WAIT;
    while s.app.watched() != 0 {
        assert!(tokio::time::Instant::now() < deadline, "the feed kept");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    publishing.abort();
}

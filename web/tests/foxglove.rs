//! `puli foxglove` against the demo's rover, spoken to by a Foxglove
//! client: Node with `@foxglove/ws-protocol`, the library Foxglove's own
//! apps use (web/tests/foxglove-client). `.ci/run` installs Node and the
//! client's packages (`npm ci`) and sets `PULICAST_REQUIRE_NODE`, so there
//! a missing client fails the test; elsewhere it is skipped, saying so.
#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

#[allow(dead_code)] // the browser half is browser.rs's
mod harness;

use std::path::PathBuf;
use std::time::Duration;

use harness::{demo_member, found, puli_config};
use pulicast_tests::{loopback_node, Peer};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// `node` and the client's directory, if both are there.
fn client() -> Option<(PathBuf, PathBuf)> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/foxglove-client");
    let installed = dir.join("node_modules/@foxglove/ws-protocol").is_dir();
    match (found("node"), installed) {
        (Some(node), true) => Some((node, dir)),
        _ => {
            assert!(
                std::env::var_os("PULICAST_REQUIRE_NODE").is_none(),
                "node and the Foxglove test client are required here (PULICAST_REQUIRE_NODE): \
                 `npm ci --prefix web/tests/foxglove-client`"
            );
            eprintln!(
                "skipped: no node, or no `npm ci --prefix web/tests/foxglove-client` (.ci/run does both)"
            );
            None
        }
    }
}

/// `puli foxglove` on the fleet at `udp`, on any free port; its address.
fn puli_foxglove(udp: u16) -> (Peer, String, u16, String) {
    let (server, said) = harness::puli_serving("foxglove", udp, &["--ws-port", "0"]);
    let url = said["foxglove_url"].as_str().unwrap().to_string();
    let port = u16::try_from(said["foxglove_port"].as_u64().unwrap()).unwrap();
    let token = said["foxglove_token"].as_str().unwrap().to_string();
    assert!(url.starts_with("ws://127.0.0.1:"), "{url}");
    assert!(
        said.get("url").is_none(),
        "no page with `puli foxglove`: {said}"
    );
    (server, url, port, token)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_foxglove_client_subscribes_calls_gets_and_sets_a_parameter_and_publishes_into_the_fleet()
{
    let Some((node_bin, dir)) = client() else {
        return;
    };
    let udp = pulicast_tests::free_port();
    let _rover = demo_member("rover", "rover1", udp);
    let listener = loopback_node("listener", udp).await;
    let mut commands = listener
        .channel("rover1/cmd_pose")
        .subscribe::<pulicast_examples::Pose>()
        .unwrap();
    let (_server, url, _, _) = puli_foxglove(udp);
    let script = dir.join("client.js");
    let script = script.to_str().unwrap();
    let foxglove = Peer::spawn(
        &node_bin,
        &[
            script,
            &url,
            "rover1/pose",
            "rover1/distance_to",
            "[3, 4]",
            "rover1/max_speed",
            "1.25",
            "rover1/cmd_pose",
            r#"{"x": 1, "y": 2, "heading": 0.5}"#,
            "nobody/listens",
        ],
    );
    let mut said = Vec::new();
    while let Some(line) = foxglove.next_json(Duration::from_secs(40)) {
        let end = line["event"] == "done" || line["event"] == "timeout";
        said.push(line);
        if end {
            break;
        }
    }
    let event = |name: &str| -> Vec<&serde_json::Value> {
        said.iter().filter(|l| l["event"] == name).collect()
    };
    assert!(
        !event("done").is_empty(),
        "the client did not see everything: {said:#?}\nserver: {}",
        _server.stderr()
    );
    let info = event("serverInfo")[0];
    for capability in [
        "clientPublish",
        "parameters",
        "parametersSubscribe",
        "services",
        "connectionGraph",
    ] {
        assert!(
            info["capabilities"]
                .as_array()
                .unwrap()
                .iter()
                .any(|c| c == capability),
            "{info}"
        );
    }
    // The channel, with a JSON Schema of its type; its messages as JSON.
    let advertised = event("advertised")[0];
    assert_eq!(advertised["encoding"], "json");
    assert_eq!(advertised["schemaEncoding"], "jsonschema");
    assert_eq!(advertised["schemaName"], "Pose");
    let schema: serde_json::Value =
        serde_json::from_str(advertised["schema"].as_str().unwrap()).unwrap();
    for field in ["x", "y", "heading"] {
        assert_eq!(schema["properties"][field]["type"], "number", "{schema}");
    }
    let message = event("message")[0];
    assert_eq!(message["topic"], "rover1/pose");
    assert!(message["json"]["heading"].is_number(), "{message}");
    // The service, called with JSON.
    let service = event("service")[0];
    assert_eq!(service["request"]["encoding"], "json", "{service}");
    assert_eq!(event("reply")[0]["json"], 5.0);
    // The parameter: read, set, and the owner holds the new value.
    let got = event("parameterValues")
        .into_iter()
        .find(|p| p["id"] == "get")
        .unwrap();
    assert_eq!(got["parameters"][0]["name"], "rover1/max_speed", "{got}");
    assert_eq!(got["parameters"][0]["value"], 0.5, "{got}");
    let set = event("parameterValues")
        .into_iter()
        .find(|p| p["id"] == "set")
        .unwrap();
    assert_eq!(set["parameters"][0]["value"], 1.25, "{set}");
    assert_eq!(
        puli_config(udp, &["get", "rover1/max_speed"]).await["value"],
        "1.25"
    );
    // The connection graph names the rover as the pose's publisher.
    let graph = event("graph")
        .into_iter()
        .rev()
        .find(|g| {
            g["publishedTopics"]
                .as_array()
                .is_some_and(|t| t.iter().any(|t| t["name"] == "rover1/pose"))
        })
        .unwrap();
    let pose = graph["publishedTopics"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["name"] == "rover1/pose")
        .unwrap();
    assert_eq!(
        pose["publisherIds"],
        serde_json::json!(["rover1"]),
        "{graph}"
    );
    // A message into a channel no member announces goes nowhere, and the
    // client is told why: once, not for each of the twenty or so it sent
    // in the 2 s after (the server tells at most every 5 s).
    let refused: Vec<_> = event("status")
        .into_iter()
        .filter(|s| s["message"].as_str().unwrap().contains("nobody/listens"))
        .collect();
    let done = event("done")[0];
    assert_eq!(done["refusedStatuses"], 1, "{said:#?}");
    assert!(done["sentAfterFirst"].as_u64().unwrap() >= 5, "{done}");
    assert_eq!(refused[0]["level"], 1, "a warning: {}", refused[0]);
    // What the client published reached a node of the fleet, typed.
    let got = tokio::time::timeout(Duration::from_secs(20), commands.recv())
        .await
        .expect("the client's pose in time")
        .unwrap();
    assert_eq!(
        got.value,
        pulicast_examples::Pose {
            x: 1.0,
            y: 2.0,
            heading: 0.5
        }
    );
}

/// One raw HTTP/1.1 WebSocket upgrade to `port`; the status.
async fn upgrade(port: u16, path: &str, headers: &[(&str, &str)]) -> u16 {
    let mut stream = tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .unwrap();
    let mut request = format!(
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
    );
    for (k, v) in headers {
        request += &format!("{k}: {v}\r\n");
    }
    request += "\r\n";
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut answer = vec![0u8; 1024];
    let n = tokio::time::timeout(Duration::from_secs(10), stream.read(&mut answer))
        .await
        .expect("an answer in time")
        .unwrap();
    let answer = String::from_utf8_lossy(&answer[..n]).into_owned();
    answer
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_foxglove_server_needs_the_token_and_refuses_another_sites_page() {
    // No client needed: this is the server's side only.
    let udp = pulicast_tests::free_port();
    let (_server, _, port, token) = puli_foxglove(udp);
    let sdk = ("Sec-WebSocket-Protocol", "foxglove.sdk.v1");
    let with_token = format!("/?token={token}");
    // No token, a wrong one: refused.
    assert_eq!(upgrade(port, "/", &[sdk]).await, 401);
    assert_eq!(upgrade(port, "/?token=0000", &[sdk]).await, 401);
    // A web site open in the operator's browser: refused, with the token.
    let evil = ("Origin", "http://evil.example");
    assert_eq!(upgrade(port, &with_token, &[sdk, evil]).await, 403);
    // Not a Foxglove client.
    assert_eq!(upgrade(port, &with_token, &[]).await, 400);
    // A Foxglove client with the token: switching protocols.
    assert_eq!(upgrade(port, &with_token, &[sdk]).await, 101);
}

/// A Foxglove client of our own (tungstenite), subscribed to `topic`.
async fn subscribed(
    url: &str,
    topic: &str,
) -> tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>> {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::{client::IntoClientRequest, Message};
    let mut request = url.into_client_request().unwrap();
    request
        .headers_mut()
        .insert("Sec-WebSocket-Protocol", "foxglove.sdk.v1".parse().unwrap());
    let (mut socket, _) = tokio_tungstenite::connect_async(request).await.unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        let frame = tokio::time::timeout_at(deadline, socket.next())
            .await
            .unwrap_or_else(|_| panic!("{topic} never advertised"))
            .unwrap()
            .unwrap();
        let Message::Text(text) = frame else { continue };
        let op: serde_json::Value = serde_json::from_str(text.as_str()).unwrap();
        let found = op["channels"]
            .as_array()
            .into_iter()
            .flatten()
            .find(|c| c["topic"] == topic)
            .map(|c| c["id"].clone());
        if let Some(id) = found {
            let subscribe = serde_json::json!({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": id}]});
            socket
                .send(Message::Text(subscribe.to_string().into()))
                .await
                .unwrap();
            return socket;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_foxglove_client_that_never_reads_costs_the_server_bounded_memory_and_the_others_nothing()
{
    use futures_util::StreamExt;
    let udp = pulicast_tests::free_port();
    let fleet = loopback_node("blobs", udp).await;
    let blobs = fleet.channel("fast/blob");
    blobs.publish(&vec![0u8; 2048]).unwrap();
    let (server, url, _, _) = puli_foxglove(udp);
    let _stalled = subscribed(&url, "fast/blob").await;
    let mut reader = subscribed(&url, "fast/blob").await;
    // 2 KiB at about 1 kHz (4 KB of JSON each), for 8 s: 30 MB and more
    // of JSON the stalled client never takes.
    let publishing = tokio::spawn(async move {
        for _ in 0..800 {
            for _ in 0..10 {
                let _ = blobs.publish(&vec![7u8; 2048]);
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    });
    tokio::time::sleep(Duration::from_secs(1)).await;
    let start = server.allocated_bytes().unwrap();
    let mut most = start;
    let mut received = 0u64;
    let until = tokio::time::Instant::now() + Duration::from_secs(7);
    while tokio::time::Instant::now() < until {
        // The reading client keeps getting messages.
        if let Ok(Some(Ok(_))) =
            tokio::time::timeout(Duration::from_millis(100), reader.next()).await
        {
            received += 1;
        }
        most = most.max(server.allocated_bytes().unwrap_or(0));
    }
    publishing.abort();
    assert!(received > 500, "the reading client got {received} frames");
    let grew = most.saturating_sub(start);
    assert!(
        grew < 24 << 20,
        "the server grew by {} MiB while a client read nothing",
        grew >> 20
    );
    eprintln!(
        "server allocated memory: {} MiB at the start, {} MiB at most; the reader got {received} frames",
        start >> 20,
        most >> 20
    );
}

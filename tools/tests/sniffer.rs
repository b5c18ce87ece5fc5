//! `puli-sniffer` against a live fleet on loopback: Rust nodes in this
//! process, a Pulicast 2.x (Python) node in another.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::process::Command;
use std::time::Duration;

use pulicast::{Node, Schema};
use pulicast_tests::{free_port, python_peer};
use serde::{Deserialize, Serialize};
use serde_json::Value;

const SNIFFER: &str = env!("CARGO_BIN_EXE_puli-sniffer");

#[derive(Serialize, Deserialize, Schema, Clone, Copy)]
struct Pose {
    x: f64,
    y: f64,
}

/// Runs the sniffer on loopback, without keys from the environment.
async fn sniff_output(port: u16, args: &[&str]) -> std::process::Output {
    let mut all = vec![
        "--port".to_string(),
        port.to_string(),
        "--interface".into(),
        "127.0.0.1".into(),
    ];
    all.extend(args.iter().map(|a| a.to_string()));
    tokio::task::spawn_blocking(move || {
        let mut command = Command::new(SNIFFER);
        command.args(&all).env_remove(pulicast::KEYS_ENV);
        command.output().unwrap()
    })
    .await
    .unwrap()
}

/// Publishes a `Pose` with this `y` at 20 Hz, for at most 60 s.
fn publish_poses(channel: pulicast::Channel, y: f64) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        for i in 0..1200 {
            let _ = channel.publish(&Pose { x: f64::from(i), y });
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
}

/// Runs the sniffer and returns its stdout, asserting success.
async fn sniff(port: u16, args: &[&str]) -> String {
    let out = sniff_output(port, args).await;
    assert!(
        out.status.success(),
        "puli-sniffer {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

struct Fleet {
    _alpha: Node,
    _beta: Node,
    _sub: pulicast::Subscription<Pose>,
    _python: pulicast_tests::Peer,
    publisher: tokio::task::JoinHandle<()>,
}

impl Drop for Fleet {
    fn drop(&mut self) {
        self.publisher.abort();
    }
}

async fn fleet(port: u16) -> Fleet {
    let node = |name: &str| Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST);
    let alpha = node("alpha").namespace("rover1").start().await.unwrap();
    let beta = node("beta").start().await.unwrap();
    let sub = beta.channel("rover1/pose").subscribe::<Pose>().unwrap();
    let publisher = publish_poses(alpha.channel("pose"), 1.0);
    let p = port.to_string();
    let python = python_peer(&[
        "publish",
        "--port",
        &p,
        "--name",
        "py_status",
        "--channel",
        "py/status",
        "--kind",
        "str",
        "--value",
        "ok {i}",
        "--count",
        "400",
        "--period",
        "0.05",
    ]);
    python.wait_ready(Duration::from_secs(20));
    Fleet {
        _alpha: alpha,
        _beta: beta,
        _sub: sub,
        _python: python,
        publisher,
    }
}

fn by_name<'a>(items: &'a [Value], name: &str) -> &'a Value {
    items
        .iter()
        .find(|n| n["name"] == name)
        .unwrap_or_else(|| panic!("{name} missing in {items:?}"))
}

fn names(v: &Value) -> Vec<&str> {
    v.as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn nodes_channels_and_echo_against_a_known_fleet() {
    let port = free_port();
    let _fleet = fleet(port).await;

    let nodes: Value =
        serde_json::from_str(&sniff(port, &["nodes", "--for", "3", "--json"]).await).unwrap();
    let nodes = nodes.as_array().unwrap();
    let alpha = by_name(nodes, "alpha");
    assert!(
        alpha["session"].as_str().unwrap().len() == 36,
        "a UUID: {alpha}"
    );
    assert!(alpha["address"].as_str().unwrap().starts_with("127.0.0.1:"));
    assert_eq!(names(&alpha["publishes"]), ["rover1/pose"]);
    assert_eq!(alpha["namespace"], "rover1");
    assert_eq!(
        names(&by_name(nodes, "beta")["subscribes"]),
        ["rover1/pose"]
    );
    let python = by_name(nodes, "py_status");
    assert_eq!(python["compat"], true);
    assert!(names(&python["publishes"]).contains(&"py/status"));

    let channels: Value =
        serde_json::from_str(&sniff(port, &["channels", "--for", "3", "--json"]).await).unwrap();
    let channels = channels.as_array().unwrap();
    let pose = by_name(channels, "rover1/pose");
    assert_eq!(names(&pose["publishers"]), ["alpha"]);
    assert_eq!(names(&pose["subscribers"]), ["beta"]);
    assert_eq!(pose["type"], "Pose");
    let rate = pose["rate_hz"].as_f64().unwrap();
    assert!((15.0..25.0).contains(&rate), "{rate}");
    let status = by_name(channels, "py/status");
    assert_eq!(names(&status["publishers"]), ["py_status"]);
    let rate = status["rate_hz"].as_f64().unwrap();
    assert!((15.0..25.0).contains(&rate), "{rate}");

    let echo = sniff(port, &["echo", "rover1/pose", "--count", "3", "--json"]).await;
    let lines: Vec<Value> = echo
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    for l in &lines {
        assert_eq!(l["channel"], "rover1/pose");
        assert_eq!(l["type"], "Pose");
        assert_eq!(l["value"]["y"], 1.0);
        assert!(l["seq"].is_u64() && l["lead"].is_i64() && l["source"].is_string());
    }
    let echo = sniff(
        port,
        &[
            "--namespace",
            "py",
            "echo",
            "status",
            "--count",
            "2",
            "--json",
        ],
    )
    .await;
    for l in echo
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
    {
        assert_eq!(l["type"], "string_msg");
        assert!(l["value"].as_str().unwrap().starts_with("ok "));
    }
    // Plain text too.
    let text = sniff(port, &["echo", "rover1/pose", "--count", "1"]).await;
    assert!(
        text.starts_with("rover1/pose #") && text.contains("Pose: {"),
        "{text}"
    );
    let hz = sniff(port, &["hz", "rover1/pose", "--for", "1.2"]).await;
    assert!(hz.contains("Hz") && hz.contains("jitter"), "{hz}");
    let bw = sniff(port, &["bw", "--for", "1.2"]).await;
    assert!(
        bw.contains("__pulicast_discovery (gossip)") && bw.contains("__nodes"),
        "{bw}"
    );
}

#[test]
fn mistakes_get_clear_errors() {
    let run = |args: &[&str]| Command::new(SNIFFER).args(args).output().unwrap();
    let out = run(&["--peer", "nonsense", "nodes"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("is not host:port"));
    let out = run(&[
        "--interface",
        "127.0.0.1",
        "--port",
        "9",
        "echo",
        "bad\u{1}name",
        "--for",
        "0.1",
    ]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("invalid name"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = run(&["nodes", "--for", "-1"]);
    assert!(!out.status.success());
    // A port held by a program that does not share it.
    let holder = std::net::UdpSocket::bind(("127.0.0.1", 0)).unwrap();
    let port = holder.local_addr().unwrap().port().to_string();
    let out = run(&[
        "--interface",
        "127.0.0.1",
        "--port",
        &port,
        "nodes",
        "--for",
        "0.1",
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(&format!("UDP port {port} is in use")), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sealed_fleet_is_visible_only_with_its_key() {
    let port = free_port();
    let hex = "7a".repeat(32);
    let rover = Node::new("sealed_rover")
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .keys_from_env(false)
        .key("/", pulicast::Key::from_hex(&hex).unwrap())
        .encrypt(true)
        .start()
        .await
        .unwrap();
    let publisher = publish_poses(rover.channel("rover1/pose"), 2.0);
    let key = format!("/={hex}");
    let nodes = sniff(port, &["nodes", "--json", "--key", &key]).await;
    assert!(nodes.contains("sealed_rover"), "{nodes}");
    let echoed = sniff(
        port,
        &[
            "echo",
            "/rover1/pose",
            "--count",
            "2",
            "--json",
            "--key",
            &key,
        ],
    )
    .await;
    assert_eq!(echoed.lines().count(), 2, "{echoed}");
    assert!(echoed.contains("\"y\":2.0"), "{echoed}");

    // Without the key: no members, no messages, and a hint why.
    let nodes = sniff(port, &["nodes", "--json"]).await;
    assert!(!nodes.contains("sealed_rover"), "{nodes}");
    let out = sniff_output(port, &["echo", "/rover1/pose", "--for", "1"]).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && out.stdout.is_empty(), "{stderr}");
    assert!(stderr.contains("--key"), "{stderr}");
    let out = sniff_output(port, &["nodes"]).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("sealed datagrams"), "{stderr}");
    publisher.abort();
}

/// A node on loopback, without keys from the environment.
async fn loopback_node(name: &str, port: u16) -> Node {
    Node::new(name)
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .keys_from_env(false)
        .start()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reader_that_closes_the_pipe_ends_the_sniffer_quietly() {
    let port = free_port();
    let rover = loopback_node("piped_rover", port).await;
    let publisher = publish_poses(rover.channel("rover1/pose"), 3.0);
    // `puli-sniffer echo ... | head -1`: read a line, then close the pipe.
    let out = tokio::task::spawn_blocking(move || {
        use std::io::BufRead;
        let mut child = Command::new(SNIFFER)
            .args(["--port", &port.to_string(), "--interface", "127.0.0.1"])
            .args(["echo", "rover1/pose", "--for", "30"])
            .env_remove(pulicast::KEYS_ENV)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut reader = std::io::BufReader::new(child.stdout.take().unwrap());
        let mut first = String::new();
        reader.read_line(&mut first).unwrap();
        drop(reader);
        (first, child.wait_with_output().unwrap())
    })
    .await
    .unwrap();
    publisher.abort();
    let (first, out) = out;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(first.contains("\"y\":3.0"), "{first}");
    assert!(out.status.success(), "{:?}: {stderr}", out.status);
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_key_says_so_instead_of_showing_an_empty_fleet() {
    let (plain_port, sealed_port) = (free_port(), free_port());
    let fleet_key = "7a".repeat(32);
    let wrong = format!("/={}", "5b".repeat(32));
    let plain = loopback_node("plain_rover", plain_port).await;
    let sealed = Node::new("sealed_rover")
        .port(sealed_port)
        .interface(Ipv4Addr::LOCALHOST)
        .keys_from_env(false)
        .key("/", pulicast::Key::from_hex(&fleet_key).unwrap())
        .start()
        .await
        .unwrap();
    let publishers = [
        publish_poses(plain.channel("rover1/pose"), 4.0),
        publish_poses(sealed.channel("rover1/pose"), 5.0),
    ];

    // A key for a fleet that seals nothing: every datagram is refused.
    let out = sniff_output(plain_port, &["channels", "--for", "1", "--key", &wrong]).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stderr.contains("in namespace / were not sealed") && stderr.contains("leave out its --key"),
        "{stderr}"
    );

    // Another key than the fleet's: nothing opens.
    let out = sniff_output(
        sealed_port,
        &["echo", "/rover1/pose", "--for", "2", "--key", &wrong],
    )
    .await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && out.stdout.is_empty(), "{stderr}");
    assert!(
        stderr.contains(
            "did not open under the key given for it: the fleet seals / with another key"
        ),
        "{stderr}"
    );

    // A key for a namespace nobody uses (a typo, say).
    let typo = format!("rover9={fleet_key}");
    let out = sniff_output(plain_port, &["nodes", "--key", &typo]).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(String::from_utf8_lossy(&out.stdout).contains("plain_rover"));
    assert!(
        stderr.contains("no member of the fleet has a channel in namespace rover9"),
        "{stderr}"
    );
    // The right key: no notes.
    let right = format!("/={fleet_key}");
    let out = sniff_output(sealed_port, &["nodes", "--key", &right]).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(String::from_utf8_lossy(&out.stdout).contains("sealed_rover"));
    assert!(!stderr.contains("note:"), "{stderr}");
    for p in publishers {
        p.abort();
    }
}

#[derive(Serialize, Deserialize, Schema, Clone, Copy)]
struct Twist {
    linear: f64,
    angular: f64,
}

#[derive(Serialize, Deserialize, Schema, Clone, Copy)]
struct Odometry {
    x: f64,
    heading: f64,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn types_that_disagree_rates_per_publisher_and_reserved_channels() {
    let port = free_port();
    let node = |name: &str| Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST);
    let controller = node("controller").start().await.unwrap();
    let _twists = controller
        .channel("rover1/ctrl")
        .subscribe::<Twist>()
        .unwrap();
    let odometer = node("odometer").start().await.unwrap();
    let ctrl = odometer.channel("rover1/ctrl");
    let (alpha, beta) = (
        node("alpha").start().await.unwrap(),
        node("beta").start().await.unwrap(),
    );
    let publishers = [
        publish_poses(alpha.channel("rover1/pose"), 1.0),
        publish_poses(beta.channel("rover1/pose"), 2.0),
        tokio::spawn(async move {
            for _ in 0..1200 {
                let _ = ctrl.publish(&Odometry {
                    x: 1.0,
                    heading: 0.0,
                });
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }),
    ];

    // The channel's type is its publisher's; the disagreement is flagged.
    let rows: Value =
        serde_json::from_str(&sniff(port, &["channels", "--json", "--for", "1.5"]).await).unwrap();
    let ctrl_row = by_name(rows.as_array().unwrap(), "rover1/ctrl");
    assert_eq!(ctrl_row["type"], "Odometry", "{ctrl_row}");
    let conflict = ctrl_row["type_conflict"].as_str().unwrap_or_default();
    assert!(
        conflict.contains("odometer publishes Odometry")
            && conflict.contains("controller subscribes as Twist"),
        "{ctrl_row}"
    );
    assert!(by_name(rows.as_array().unwrap(), "rover1/pose")["type_conflict"].is_null());
    let out = sniff_output(port, &["channels", "--for", "1.5"]).await;
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(stdout.contains("!Odometry"), "{stdout}");
    assert!(
        stderr.contains("members disagree on the type of rover1/ctrl"),
        "{stderr}"
    );

    // Two publishers of one channel: the merged figure, then each one's.
    let hz = sniff(port, &["hz", "rover1/pose", "--for", "2"]).await;
    let last: Vec<&str> = hz.lines().rev().take(3).collect();
    assert!(
        last.iter()
            .any(|l| l.contains("(alpha)") && l.contains("Hz"))
            && last
                .iter()
                .any(|l| l.contains("(beta)") && l.contains("Hz")),
        "{hz}"
    );

    // A reserved channel is nobody's to announce: no "waiting" note.
    let out = sniff_output(port, &["echo", "__nodes", "--count", "1"]).await;
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert_eq!(String::from_utf8_lossy(&out.stdout).lines().count(), 1);
    assert!(!stderr.contains("no member publishes"), "{stderr}");
    for p in publishers {
        p.abort();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_rate_of_a_channel_that_went_quiet_falls_to_zero() {
    let port = free_port();
    let rover = loopback_node("quiet_rover", port).await;
    let publisher = publish_poses(rover.channel("rover1/pose"), 6.0);
    // Tables once a second (stdout is not a terminal), for at most 40 s.
    let mut sniffer = Command::new(SNIFFER)
        .args([
            "--port",
            &port.to_string(),
            "--interface",
            "127.0.0.1",
            "--for",
            "40",
        ])
        .env_remove(pulicast::KEYS_ENV)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = sniffer.stdout.take().unwrap();
    let (tx, mut rates) = tokio::sync::mpsc::unbounded_channel::<f64>();
    let reader = std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            let rate = line
                .strip_prefix("rover1/pose ")
                .and_then(|rest| rest.split_whitespace().next()?.parse().ok());
            if rate.is_some_and(|r| tx.send(r).is_err()) {
                break;
            }
        }
    });
    let next = Duration::from_secs(20);
    // The sniffer measures the channel while it publishes (two tables in
    // a row, so the rate is its own measurement)...
    let mut above = 0;
    while above < 2 {
        let rate = tokio::time::timeout(next, rates.recv())
            .await
            .unwrap()
            .unwrap();
        above = if rate > 5.0 { above + 1 } else { 0 };
    }
    // ... and once it stops publishing (the node stays, announcing its
    // period), the rate falls to 0 within QUIET and a table.
    publisher.abort();
    let stopped = std::time::Instant::now();
    loop {
        let rate = tokio::time::timeout(next, rates.recv())
            .await
            .unwrap()
            .unwrap();
        if rate == 0.0 {
            break;
        }
        assert!(
            stopped.elapsed() < Duration::from_secs(15),
            "still {rate} Hz"
        );
    }
    let _ = sniffer.kill();
    let _ = sniffer.wait();
    let _ = reader.join();
    drop(rover);
}

/// A setting's channels (`rover1/.config/...`) are hidden from `channels`
/// unless `--all`, as 2.x tools hide them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hidden_channels_are_listed_only_with_all() {
    let port = free_port();
    let owner = loopback_node("owner", port).await;
    let _speed = owner
        .make_namespace("rover1")
        .setting("max_speed", 1.5f64)
        .unwrap();
    let pose = owner.channel("rover1/pose");
    let publisher = publish_poses(pose, 1.0);
    let names = |out: String| -> Vec<String> {
        let rows: Value = serde_json::from_str(&out).unwrap();
        rows.as_array()
            .unwrap()
            .iter()
            .map(|r| r["name"].as_str().unwrap().to_string())
            .collect()
    };
    let shown = names(sniff(port, &["channels", "--for", "1", "--json"]).await);
    assert!(shown.contains(&"rover1/pose".to_string()), "{shown:?}");
    assert!(!shown.iter().any(|n| n.contains(".config")), "{shown:?}");
    let all = names(sniff(port, &["channels", "--for", "1", "--json", "--all"]).await);
    assert!(
        all.contains(&"rover1/.config/max_speed".to_string()),
        "{all:?}"
    );
    assert!(
        all.contains(&"rover1/.config/max_speed.r".to_string()),
        "{all:?}"
    );

    // The same everywhere hidden channels could show uninvited: a service
    // beside the setting, the dashboard's plain tables, bw, and echo's
    // note on a name nobody publishes.
    let _serving = owner
        .make_namespace("rover1")
        .serve("distance_to", |(x, y): (f64, f64)| async move {
            Ok::<f64, pulicast::Fault>(x.hypot(y))
        })
        .unwrap();
    let caller = loopback_node("caller", port).await;
    let client = caller
        .client::<(f64, f64), f64>("rover1/distance_to")
        .unwrap();
    let calls = tokio::spawn(async move {
        for _ in 0..100 {
            let _ = client.call(&(3.0, 4.0)).await;
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    let hidden = |text: &str| {
        text.lines()
            .filter(|l| l.contains("/.config/") || l.contains("/.services/"))
            .map(str::to_string)
            .collect::<Vec<_>>()
    };
    let plain = sniff(port, &["--for", "2"]).await;
    assert!(plain.contains("rover1/pose"), "{plain}");
    assert!(hidden(&plain).is_empty(), "{plain}");
    assert!(plain.contains("hidden: --all shows them"), "{plain}");
    let plain = sniff(port, &["--for", "2", "--all"]).await;
    let rows = hidden(&plain);
    assert!(rows.iter().any(|l| l.contains("@reply")), "{plain}");
    // A request is shown as one, not as the bytes of its frame.
    let request = rows
        .iter()
        .find(|l| l.contains("rover1/.services/distance_to ") && l.contains("request"));
    assert!(request.is_some(), "{plain}");
    // Every row of a table keeps its columns: the rate column lines up.
    let columns: Vec<usize> = plain
        .lines()
        .skip_while(|l| !l.starts_with("== ") || !l.contains("channels"))
        .skip(1)
        .take_while(|l| !l.starts_with("== "))
        .filter(|l| !l.starts_with("  "))
        .map(|l| l.find(" Hz ").unwrap_or(0))
        .collect();
    assert!(columns.windows(2).all(|w| w[0] == w[1]), "{plain}");
    let bw = sniff(port, &["bw", "--for", "1"]).await;
    assert!(bw.contains("rover1/pose"), "{bw}");
    assert!(hidden(&bw).is_empty(), "{bw}");
    let out = sniff_output(port, &["echo", "rover1/pos", "--for", "1"]).await;
    let note = String::from_utf8_lossy(&out.stderr);
    assert!(note.contains("did you mean rover1/pose?"), "{note}");
    assert!(
        !note.contains(".config") && !note.contains(".services"),
        "{note}"
    );
    // `--for` is the whole command, the wait for a publisher included.
    let started = std::time::Instant::now();
    let out = sniff_output(port, &["hz", "rover1/nothing", "--for", "1"]).await;
    assert!(out.status.success());
    assert!(
        started.elapsed() < Duration::from_millis(2800),
        "{:?}",
        started.elapsed()
    );
    calls.abort();
    publisher.abort();
}

/// A stranger announces names no tool could subscribe to (one non-ASCII
/// character; a terminal escape) beside a real fleet: every listing still
/// works for every operator, shows the bad names escaped or counts them,
/// and never passes the escape to the terminal.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_bad_name_from_a_stranger_breaks_no_listing() {
    let port = free_port();
    let owner = loopback_node("owner", port).await;
    let publisher = publish_poses(owner.channel("rover1/pose"), 1.0);
    let _stranger =
        pulicast_tests::Stranger::new(port).keep_announcing(Duration::from_secs(60), |s| {
            s.heartbeat(
                "stranger\u{1b}[2J",
                0x5eed,
                &[("/x/é", true, false), ("x/\u{1b}[31mred", true, true)],
            )
        });
    let puli = env!("CARGO_BIN_EXE_puli");
    let file = std::env::temp_dir().join(format!("bad-names-{port}.mcap"));
    let recording = {
        let args = [
            "record".to_string(),
            file.display().to_string(),
            "--for".into(),
            "2".into(),
            "--port".into(),
            port.to_string(),
            "--interface".into(),
            "127.0.0.1".into(),
        ];
        tokio::task::spawn_blocking(move || Command::new(puli).args(args).output().unwrap())
    };
    for args in [
        &["channels", "--for", "1"][..],
        &["channels", "--for", "1", "--all"],
        &["channels", "--for", "1", "--json", "--all"],
        &["nodes", "--for", "1"],
        &["bw", "--for", "1"],
        &["--for", "1"],
    ] {
        let out = sniff_output(port, args).await;
        let stdout = String::from_utf8_lossy(&out.stdout);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{args:?}: {stderr}");
        assert!(
            stdout.contains("rover1/pose") || args[0] == "nodes",
            "{args:?}: {stdout}"
        );
        assert!(
            stdout.contains("stranger") || args[0] != "nodes",
            "{args:?}: {stdout}"
        );
        assert!(
            !stdout.contains('\u{1b}'),
            "{args:?} passed an escape: {stdout:?}"
        );
        if args[0] == "channels" {
            assert!(stdout.contains("/x/é"), "{args:?}: {stdout}");
            assert!(
                stderr.contains("2 announced names are no channel names"),
                "{stderr}"
            );
        }
    }
    let recorded = recording.await.unwrap();
    let stderr = String::from_utf8_lossy(&recorded.stderr);
    assert!(recorded.status.success(), "puli record: {stderr}");
    assert!(stderr.contains("not recording"), "{stderr}");
    assert!(
        String::from_utf8_lossy(&recorded.stdout).contains("rover1/pose"),
        "{}",
        String::from_utf8_lossy(&recorded.stdout)
    );
    let _ = std::fs::remove_file(&file);
    publisher.abort();
}

/// A signal interrupts a command that only waits (`nodes`, `services`)
/// at once, as the shell does, instead of the tool being cut off when
/// its time to end is up; one that runs until stopped (`hz`) ends as at
/// its end.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_signal_interrupts_a_command_that_only_waits() {
    let port = free_port();
    let watcher = Node::new("watcher")
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .start()
        .await
        .unwrap();
    for args in [&["nodes", "--for", "60"][..], &["hz", "nobody/talks"]] {
        let mut all = vec!["--port", "", "--interface", "127.0.0.1"];
        let port_text = port.to_string();
        all[1] = &port_text;
        all.extend_from_slice(args);
        let child = Command::new(SNIFFER)
            .args(&all)
            .env_remove(pulicast::KEYS_ENV)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        // Its node is in the fleet once it started; its signal handler is
        // set up right after.
        let discovery = watcher.discovery();
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        while !discovery
            .live_members()
            .iter()
            .any(|m| m.name == "puli-sniffer")
        {
            assert!(
                std::time::Instant::now() < deadline,
                "no sniffer in the fleet"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
        let pid = child.id().to_string();
        let sent = Command::new("kill").args(["-TERM", &pid]).status().unwrap();
        assert!(sent.success());
        let out = tokio::task::spawn_blocking(move || child.wait_with_output())
            .await
            .unwrap()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!stderr.contains("not ended within"), "{args:?}: {stderr}");
        match args[0] {
            "nodes" => {
                assert_eq!(out.status.code(), Some(1), "{stderr}");
                assert!(stderr.contains("interrupted"), "{stderr}");
            }
            _ => assert!(out.status.success(), "{args:?}: {stderr}"),
        }
    }
    watcher.stop();
}

//! `puli record` and `puli play`: a live channel to an MCAP file and back,
//! byte-identical, and a recorder that keeps up with 10 kHz.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use pulicast::{Node, Schema};
use pulicast_tests::free_port;
use serde::{Deserialize, Serialize};

const PULI: &str = env!("CARGO_BIN_EXE_puli");

#[derive(Serialize, Deserialize, Schema, Clone, Copy, Debug, PartialEq)]
struct Pose {
    x: f64,
    y: f64,
}

fn node(name: &str, port: u16) -> pulicast::NodeBuilder {
    Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST)
}

fn spawn_puli(args: &[String]) -> std::process::Child {
    Command::new(PULI)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn net(port: u16) -> Vec<String> {
    vec![
        "--port".into(),
        port.to_string(),
        "--interface".into(),
        "127.0.0.1".into(),
    ]
}

/// Waits (off the runtime) for a `puli` process to exit and asserts success.
async fn finished(child: std::process::Child) -> std::process::Output {
    let out = tokio::task::spawn_blocking(move || child.wait_with_output().unwrap())
        .await
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Stops a recorder we started, the way a user does (Ctrl-C), once what it
/// should record has had half a second to arrive: a `--for` clock would
/// start at the process's start and race the test's set-up.
async fn stop_recorder(child: std::process::Child) -> std::process::Output {
    tokio::time::sleep(Duration::from_millis(500)).await;
    let status = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success(), "kill -INT {}", child.id());
    finished(child).await
}

/// Waits until a member called `name` subscribes to `channel`.
async fn wait_for_subscriber(node: &Node, channel: &str, name: &str) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while !node
        .channel(channel)
        .subscribers()
        .iter()
        .any(|m| m.name == name)
    {
        assert!(
            Instant::now() < deadline,
            "{name} never subscribed to {channel}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn record_then_play_is_byte_identical_with_original_timing() {
    let port = free_port();
    let file = std::env::temp_dir().join(format!("pulicast-record-{}.mcap", std::process::id()));
    let publisher = node("source", port)
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    let (pose, text) = (publisher.channel("pose"), publisher.channel("status"));
    pose.publish(&Pose { x: -1.0, y: -1.0 }).unwrap();
    text.publish("warm-up").unwrap();

    let mut args = vec![
        "record".to_string(),
        file.display().to_string(),
        "rover1/...".into(),
        "--for".into(),
        "60".into(),
    ];
    args.extend(net(port));
    let recorder = spawn_puli(&args);
    wait_for_subscriber(&publisher, "/rover1/pose", "puli-record").await;
    wait_for_subscriber(&publisher, "/rover1/status", "puli-record").await;

    let mut sent: Vec<(String, Vec<u8>)> = Vec::new();
    for i in 0..40 {
        let p = Pose {
            x: f64::from(i),
            y: 0.5,
        };
        pose.publish(&p).unwrap();
        let mut bytes = Vec::new();
        pulicast_proto::wire::encode_native(&p, &mut bytes).unwrap();
        sent.push(("rover1/pose".into(), bytes));
        let s = format!("status {i}");
        text.publish(s.as_str()).unwrap();
        let mut bytes = Vec::new();
        pulicast_proto::wire::encode_native(s.as_str(), &mut bytes).unwrap();
        sent.push(("rover1/status".into(), bytes));
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let out = stop_recorder(recorder).await;
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(report.contains("80 messages on 2 channels"), "{report}");

    // A standard MCAP file: channels with schemas and our metadata.
    let bytes = std::fs::read(&file).unwrap();
    let messages: Vec<_> = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(Result::unwrap)
        .collect();
    assert_eq!(messages.len(), 80);
    // Byte-identical and in order on each channel (across channels, the
    // file follows arrival, which two subscriptions may interleave).
    let per_channel = |list: &[(String, Vec<u8>)], ch: &str| -> Vec<Vec<u8>> {
        list.iter()
            .filter(|(c, _)| c == ch)
            .map(|(_, b)| b.clone())
            .collect()
    };
    let recorded: Vec<(String, Vec<u8>)> = messages
        .iter()
        .map(|m| (m.channel.topic.clone(), m.data.to_vec()))
        .collect();
    for ch in ["rover1/pose", "rover1/status"] {
        assert!(
            per_channel(&recorded, ch) == per_channel(&sent, ch),
            "{ch} differs"
        );
    }
    // Each channel's log times never go back; across channels, the time is
    // taken as each subscription receives, so a busy machine may write one
    // channel's message a little after another's later one.
    for ch in ["rover1/pose", "rover1/status"] {
        let times: Vec<u64> = messages
            .iter()
            .filter(|m| m.channel.topic == ch)
            .map(|m| m.log_time)
            .collect();
        assert!(times.windows(2).all(|w| w[0] <= w[1]), "{ch}: {times:?}");
    }
    let log_times: Vec<u64> = messages.iter().map(|m| m.log_time).collect();
    assert!(
        log_times.windows(2).all(|w| w[0] <= w[1] + 100_000_000),
        "log times within 100 ms of file order"
    );
    let channel_of = |topic: &str| {
        messages
            .iter()
            .find(|m| m.channel.topic == topic)
            .unwrap()
            .channel
            .clone()
    };
    let pose_channel = channel_of("rover1/pose");
    let schema = pose_channel.schema.as_ref().unwrap();
    assert_eq!(
        (schema.name.as_str(), schema.encoding.as_str()),
        ("Pose", "postcard-schema")
    );
    assert_eq!(pose_channel.message_encoding, "pulicast");
    let status_channel = channel_of("rover1/status");
    let status_schema = status_channel.schema.as_ref().unwrap();
    assert_eq!(
        (status_schema.name.as_str(), status_schema.encoding.as_str()),
        ("string_msg", "zcm")
    );

    // Play it to another fleet: the same bytes, in order, about as spaced.
    let port2 = free_port();
    let listener = node("listener", port2).start().await.unwrap();
    let mut poses = listener.channel("rover1/pose").subscribe_raw().unwrap();
    let mut statuses = listener.channel("rover1/status").subscribe_raw().unwrap();
    // At a fifth of the speed (about a second), so the listener has time
    // to hear the player's type announcement by gossip while it plays.
    let mut args = vec![
        "play".to_string(),
        file.display().to_string(),
        "--speed".into(),
        "0.2".into(),
    ];
    args.extend(net(port2));
    let started = Instant::now();
    let player = spawn_puli(&args);
    let mut got_poses = Vec::new();
    let mut got_statuses = Vec::new();
    let mut announced = None;
    for _ in 0..40 {
        if announced.is_none() {
            // The replay announces the recorded types, so tools decode it.
            announced = pulicast_tools::publish::announced(&listener.channel("rover1/pose"));
        }
        got_poses.push(
            tokio::time::timeout(Duration::from_secs(10), poses.recv())
                .await
                .unwrap()
                .unwrap()
                .value
                .to_vec(),
        );
        got_statuses.push(
            tokio::time::timeout(Duration::from_secs(10), statuses.recv())
                .await
                .unwrap()
                .unwrap()
                .value
                .to_vec(),
        );
    }
    let took = started.elapsed();
    finished(player).await;
    assert!(
        got_poses == per_channel(&sent, "rover1/pose"),
        "replayed poses differ"
    );
    assert!(
        got_statuses == per_channel(&sent, "rover1/status"),
        "replayed statuses differ"
    );
    // 40 messages 5 ms apart take at least ~195 ms to replay at speed 1,
    // so ~975 ms at 0.2.
    assert!(took >= Duration::from_millis(750), "{took:?}");
    assert_eq!(announced.map(|t| t.name).as_deref(), Some("Pose"));
    let _ = std::fs::remove_file(&file);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_recorder_keeps_up_with_ten_kilohertz_for_ten_seconds() {
    let port = free_port();
    let file = std::env::temp_dir().join(format!("pulicast-10khz-{}.mcap", std::process::id()));
    let publisher = node("fast", port).start().await.unwrap();
    let channel = publisher.channel("fast/data");
    channel.publish(&0i64).unwrap();
    let mut args = vec![
        "record".to_string(),
        file.display().to_string(),
        "fast/data".into(),
        "--for".into(),
        "60".into(),
    ];
    args.extend(net(port));
    let recorder = spawn_puli(&args);
    wait_for_subscriber(&publisher, "/fast/data", "puli-record").await;

    // 10 messages every millisecond, for 10 s: 100 000 messages at 10 kHz.
    let sent = tokio::task::spawn_blocking(move || {
        let start = Instant::now();
        let mut sent = 0u64;
        for ms in 0..10_000u64 {
            for _ in 0..10 {
                channel.publish(&(sent as i64)).unwrap();
                sent += 1;
            }
            let due = start + Duration::from_millis(ms + 1);
            if let Some(wait) = due.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
        }
        (sent, start.elapsed())
    })
    .await
    .unwrap();
    let out = stop_recorder(recorder).await;
    let report = String::from_utf8_lossy(&out.stdout).to_string();
    let bytes = std::fs::read(&file).unwrap();
    let in_file = mcap::MessageStream::new(&bytes).unwrap().count() as u64;
    let _ = std::fs::remove_file(&file);
    eprintln!(
        "10 kHz recording: sent {} in {:?}, in the file {in_file}; recorder says: {}",
        sent.0,
        sent.1,
        report.trim()
    );
    // Nothing the recorder received is missing from the file (the command
    // fails otherwise), and on loopback it receives everything.
    assert!(report.contains("dropped by full queues 0"), "{report}");
    assert_eq!(in_file, sent.0, "{report}");
}

#[test]
fn play_explains_bad_files() {
    let run = |file: &str| {
        let out = Command::new(PULI)
            .args(["play", file, "--port", "9", "--interface", "127.0.0.1"])
            .output()
            .unwrap();
        assert!(!out.status.success());
        String::from_utf8_lossy(&out.stderr).to_string()
    };
    assert!(run("/nonexistent/file.mcap").contains("can't read /nonexistent/file.mcap"));
    let not_mcap = std::env::temp_dir().join(format!("pulicast-not-mcap-{}", std::process::id()));
    std::fs::write(&not_mcap, b"hello").unwrap();
    let err = run(not_mcap.to_str().unwrap());
    let _ = std::fs::remove_file(&not_mcap);
    assert!(err.contains("is not an MCAP file"), "{err}");
}

/// Publishes `i64`s on `fast/data` every 10 ms until `stop`, returning them.
async fn publish_until(channel: pulicast::Channel, stop: Instant) -> Vec<(Instant, i64)> {
    let mut sent = Vec::new();
    let mut i = 0i64;
    while Instant::now() < stop {
        channel.publish(&i).unwrap();
        sent.push((Instant::now(), i));
        i += 1;
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    sent
}

/// The `i64` values in an MCAP file's readable part, in file order.
fn recorded_values(bytes: &[u8]) -> Vec<i64> {
    let mut values = Vec::new();
    let stream =
        mcap::MessageStream::new_with_options(bytes, mcap::read::Options::IgnoreEndMagic.into())
            .unwrap();
    for m in stream {
        let Ok(m) = m else { break };
        values.push(pulicast_proto::wire::decode_native::<i64>(&m.data).unwrap());
    }
    values
}

/// Starts a recorder of `fast/data` and a publisher it hears.
async fn recording(
    name: &str,
) -> (
    Node,
    pulicast::Channel,
    std::process::Child,
    std::path::PathBuf,
) {
    let port = free_port();
    let file = std::env::temp_dir().join(format!("pulicast-{name}-{}.mcap", std::process::id()));
    let publisher = node("source", port).start().await.unwrap();
    let channel = publisher.channel("fast/data");
    channel.publish(&-1i64).unwrap();
    let mut args = vec![
        "record".to_string(),
        file.display().to_string(),
        "fast/data".into(),
    ];
    args.extend(net(port));
    let recorder = spawn_puli(&args);
    wait_for_subscriber(&publisher, "/fast/data", "puli-record").await;
    (publisher, channel, recorder, file)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_and_sighup_close_the_recording_like_ctrl_c() {
    for signal in ["-TERM", "-HUP"] {
        let (_publisher, channel, recorder, file) = recording("signal").await;
        let sent = publish_until(channel, Instant::now() + Duration::from_millis(500)).await;
        tokio::time::sleep(Duration::from_millis(300)).await;
        let status = Command::new("kill")
            .args([signal, &recorder.id().to_string()])
            .status()
            .unwrap();
        assert!(status.success());
        let out = finished(recorder).await;
        let report = String::from_utf8_lossy(&out.stdout).to_string();
        let bytes = std::fs::read(&file).unwrap();
        let _ = std::fs::remove_file(&file);
        // A whole file: the strict reader takes it, end magic and all.
        let whole = mcap::MessageStream::new(&bytes)
            .unwrap()
            .collect::<Result<Vec<_>, _>>();
        assert!(whole.is_ok(), "{signal}: {whole:?}; {report}");
        let values: Vec<i64> = sent.iter().map(|(_, v)| *v).collect();
        assert_eq!(recorded_values(&bytes), values, "{signal}: {report}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn under_nohup_a_hangup_does_not_stop_the_recorder() {
    let port = free_port();
    let file = std::env::temp_dir().join(format!("pulicast-nohup-{}.mcap", std::process::id()));
    let publisher = node("source", port).start().await.unwrap();
    let channel = publisher.channel("fast/data");
    channel.publish(&-1i64).unwrap();
    let mut recorder = Command::new("nohup")
        .arg(PULI)
        .args(["record", &file.display().to_string(), "fast/data"])
        .args(net(port))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_for_subscriber(&publisher, "/fast/data", "puli-record").await;
    let signal = |name: &str, pid: u32| {
        let status = Command::new("kill")
            .args([name, &pid.to_string()])
            .status()
            .unwrap();
        assert!(status.success(), "kill {name}");
    };
    signal("-HUP", recorder.id());
    let sent = publish_until(channel, Instant::now() + Duration::from_millis(500)).await;
    assert!(
        recorder.try_wait().unwrap().is_none(),
        "a hangup under nohup stopped it"
    );
    tokio::time::sleep(Duration::from_millis(300)).await;
    signal("-TERM", recorder.id());
    let out = finished(recorder).await;
    let bytes = std::fs::read(&file).unwrap();
    let _ = std::fs::remove_file(&file);
    let values: Vec<i64> = sent.iter().map(|(_, v)| *v).collect();
    assert_eq!(
        recorded_values(&bytes),
        values,
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recorder_killed_outright_loses_at_most_its_last_second() {
    let (_publisher, channel, mut recorder, file) = recording("sigkill").await;
    let sent = publish_until(channel, Instant::now() + Duration::from_secs(3)).await;
    let killed = Instant::now();
    recorder.kill().unwrap(); // SIGKILL: no chance to close the file
    let _ = recorder.wait();
    let bytes = std::fs::read(&file).unwrap();

    // Everything sent more than a second before the kill (and a second of
    // slack for a busy machine's scheduling and fsync) is in the file, in
    // order, and nothing else.
    let got = recorded_values(&bytes);
    let old_enough = sent
        .iter()
        .filter(|(t, _)| killed.duration_since(*t) > Duration::from_secs(2))
        .count();
    let values: Vec<i64> = sent.iter().map(|(_, v)| *v).collect();
    assert!(
        got.len() >= old_enough && values.starts_with(&got),
        "read {} of {} sent, {old_enough} of them over 2 s before the kill",
        got.len(),
        values.len()
    );

    // `puli play` plays that part and says what was lost.
    let mut args = vec![
        "play".to_string(),
        file.display().to_string(),
        "--speed".into(),
        "100".into(),
    ];
    args.extend(net(free_port()));
    let out = finished(spawn_puli(&args)).await;
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(
        stdout.contains(&format!("{} messages published", got.len())),
        "{stdout}"
    );
    assert!(
        stderr.contains("the file was not closed")
            && stderr.contains(&format!("{} messages", got.len()))
            && stderr.contains("are lost")
            && stderr.contains("puli recover"),
        "{stderr}"
    );

    // `puli recover` writes a whole file with the same messages.
    let fixed = file.with_extension("recovered.mcap");
    let out = finished(spawn_puli(&["recover".into(), file.display().to_string()])).await;
    let report = String::from_utf8_lossy(&out.stdout).to_string();
    let recovered = std::fs::read(&fixed).unwrap();
    let _ = (std::fs::remove_file(&file), std::fs::remove_file(&fixed));
    assert!(
        report.contains(&format!("{} messages written", got.len())),
        "{report}"
    );
    let whole: Vec<i64> = mcap::MessageStream::new(&recovered)
        .unwrap()
        .map(|m| pulicast_proto::wire::decode_native::<i64>(&m.unwrap().data).unwrap())
        .collect();
    assert_eq!(whole, got);
}

/// A path that can't be written fails the recorder at once, before it
/// says it records, not after a recording that went nowhere.
#[test]
fn a_path_that_cannot_be_written_fails_at_start() {
    let missing = std::env::temp_dir().join(format!("puli-no-such-dir-{}", std::process::id()));
    assert!(!missing.exists());
    let file = missing.join("x.mcap");
    let mut args = vec!["record".to_string(), file.display().to_string()];
    args.extend(["--for".into(), "30".into()]);
    args.extend(net(free_port()));
    let started = Instant::now();
    let out = spawn_puli(&args).wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("creating") && stderr.contains("x.mcap"),
        "{stderr}"
    );
    assert!(!stderr.contains("recording to"), "{stderr}");
    assert!(
        started.elapsed() < Duration::from_secs(20),
        "it waited out --for"
    );
}

//! `puli pub` against live peers on loopback.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::process::Command;
use std::time::Duration;

use pulicast::{DropReason, Key, Node, Schema};
use pulicast_tests::{free_port, python_peer};
use serde::{Deserialize, Serialize};
use serde_json::Value;

const PULI: &str = env!("CARGO_BIN_EXE_puli");

fn puli(port: u16, args: &[&str]) -> std::process::Output {
    puli_with_keys(port, args, None)
}

/// `puli pub` on loopback, with `keys` as `PULICAST_KEYS` (none: unset).
fn puli_with_keys(port: u16, args: &[&str], keys: Option<&str>) -> std::process::Output {
    let mut all = vec![
        "pub".to_string(),
        "--port".into(),
        port.to_string(),
        "--interface".into(),
        "127.0.0.1".into(),
    ];
    all.extend(args.iter().map(|a| a.to_string()));
    let mut command = Command::new(PULI);
    command.args(&all).env_remove(pulicast::KEYS_ENV);
    if let Some(keys) = keys {
        command.env(pulicast::KEYS_ENV, keys);
    }
    command.output().unwrap()
}

#[test]
fn plain_values_reach_a_python_2x_node() {
    let port = free_port();
    let p = port.to_string();
    let listeners: Vec<_> = [
        ("cli/text", "str"),
        ("cli/number", "int"),
        ("cli/real", "float"),
        ("cli/flag", "bool"),
    ]
    .iter()
    .map(|(ch, as_)| {
        python_peer(&[
            "subscribe",
            "--port",
            &p,
            "--name",
            "py",
            "--channel",
            ch,
            "--as",
            as_,
            "--count",
            "2",
            "--timeout",
            "20",
        ])
    })
    .collect();
    for l in &listeners {
        l.wait_ready(Duration::from_secs(20));
    }
    for (channel, value) in [
        ("cli/text", "Go LEFT!"),
        ("cli/number", "-42"),
        ("cli/real", "2.5"),
        ("cli/flag", "true"),
    ] {
        let out = puli(
            port,
            &[
                channel, value, "--rate", "50", "--count", "2", "--wait", "0",
            ],
        );
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let expect = [
        Value::from("Go LEFT!"),
        Value::from(-42),
        Value::from(2.5),
        Value::from(true),
    ];
    for (l, want) in listeners.into_iter().zip(expect) {
        for got in l.take_json(2, Duration::from_secs(20)) {
            assert_eq!(got["value"], want);
        }
        l.wait_success(Duration::from_secs(10));
    }
}

#[derive(Serialize, Deserialize, Schema, Debug, PartialEq)]
struct Twist {
    linear: f64,
    angular: f64,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn json_is_encoded_into_the_announced_native_type() {
    let port = free_port();
    let node = Node::new("robot")
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .start()
        .await
        .unwrap();
    let mut twists = node.channel("cmd").subscribe::<Twist>().unwrap();
    let out = tokio::task::spawn_blocking(move || {
        puli(
            port,
            &[
                "cmd",
                r#"{"linear": 0.5, "angular": -1}"#,
                "--type",
                "json",
                // At most: it goes on once the subscriber's type is heard.
                "--wait",
                "10",
            ],
        )
    })
    .await
    .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let m = tokio::time::timeout(Duration::from_secs(10), twists.recv())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(
        m.value,
        Twist {
            linear: 0.5,
            angular: -1.0
        }
    );

    // A value that doesn't fit says where.
    let out = tokio::task::spawn_blocking(move || {
        puli(port, &["cmd", r#"{"linear": "fast"}"#, "--type", "json"])
    })
    .await
    .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("value.linear") && err.contains("Twist"),
        "{err}"
    );
    // No type known: a clear error.
    let out = tokio::task::spawn_blocking(move || {
        puli(
            port,
            &["nobody/here", "{}", "--type", "json", "--wait", "0.2"],
        )
    })
    .await
    .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("no member announces a native type"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn keys_come_from_the_flag_a_key_file_or_the_environment() {
    let port = free_port();
    let hex = "3c".repeat(32);
    let node = Node::new("robot")
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .keys_from_env(false)
        .key("rover1", Key::from_hex(&hex).unwrap())
        .start()
        .await
        .unwrap();
    let mut cmds = node.channel("rover1/cmd").subscribe::<String>().unwrap();
    let file = std::env::temp_dir().join(format!("puli-key-{port}"));
    std::fs::write(&file, &hex).unwrap();
    let run = |args: Vec<String>, keys: Option<String>| {
        tokio::task::spawn_blocking(move || {
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            puli_with_keys(port, &args, keys.as_deref())
        })
    };
    let args = |value: &str, extra: &[&str]| {
        let mut a = vec![
            "rover1/cmd".to_string(),
            value.to_string(),
            "--wait".into(),
            "0".into(),
        ];
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let flag = format!("rover1={hex}");
    let from_file = format!("rover1=@{}", file.display());
    for (value, out) in [
        (
            "by flag",
            run(args("by flag", &["--key", &flag]), None).await,
        ),
        (
            "by file",
            run(args("by file", &["--key", &from_file, "--encrypt"]), None).await,
        ),
        (
            "by env",
            run(args("by env", &[]), Some(from_file.clone())).await,
        ),
    ] {
        let out = out.unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let m = tokio::time::timeout(Duration::from_secs(10), cmds.recv())
            .await
            .unwrap()
            .unwrap();
        assert_eq!(m.value, value);
    }
    // Without the key the message goes out unsealed, and is dropped.
    let out = run(args("no key", &[]), None).await.unwrap();
    assert!(out.status.success());
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while node.stats().dropped(DropReason::Unauthenticated) == 0 {
        assert!(
            std::time::Instant::now() < deadline,
            "unsealed message not counted"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(cmds.try_recv().is_none());
    // A bad key is refused without being repeated.
    let short = "3c".repeat(31);
    let out = run(args("x", &["--key", &format!("rover1={short}")]), None)
        .await
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("rover1") && !err.contains(&short),
        "{err}"
    );
    let out = run(args("x", &[]), Some(format!("rover1={short}")))
        .await
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("PULICAST_KEYS") && !err.contains(&short),
        "{err}"
    );
    std::fs::remove_file(&file).unwrap();
}

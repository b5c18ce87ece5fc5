//! `puli call`, `puli serve` and `puli-sniffer services` as separate
//! processes on loopback: servers in two processes, errors a person can
//! read, a server killed mid-call, and one restarted.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::collections::BTreeSet;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use pulicast_tests::{free_port, Peer};
use serde_json::Value;

const PULI: &str = env!("CARGO_BIN_EXE_puli");
const SNIFFER: &str = env!("CARGO_BIN_EXE_puli-sniffer");
const READY: Duration = Duration::from_secs(30);

fn net(port: &str) -> Vec<&str> {
    vec![
        "--port",
        port,
        "--interface",
        "127.0.0.1",
        "--namespace",
        "rover1",
    ]
}

/// A `puli serve` process (killed when dropped).
fn serve(port: u16, name: &str, step_ms: u64) -> Peer {
    let p = port.to_string();
    let step = step_ms.to_string();
    let mut args = vec!["serve"];
    args.extend(net(&p));
    args.extend(["--name", name, "--step-ms", &step, "--for", "120"]);
    let peer = Peer::spawn(PULI, &args);
    peer.wait_ready(READY);
    peer
}

/// `puli call ARGS`, to its end.
fn call(port: u16, args: &[&str]) -> Output {
    let p = port.to_string();
    let mut all = vec!["call"];
    all.extend(net(&p));
    all.extend_from_slice(args);
    Command::new(PULI)
        .args(&all)
        .env_remove(pulicast::KEYS_ENV)
        .output()
        .unwrap()
}

fn lines(out: &Output) -> Vec<Value> {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn puli_call_reaches_servers_in_two_processes_and_says_what_failed() {
    let port = free_port();
    let _a = serve(port, "planner_a", 5);
    let _b = serve(port, "planner_b", 5);

    // Every server (once discovery knows both: --all asks those it knows).
    let deadline = Instant::now() + READY;
    let answers = loop {
        let req = r#"{"goal": [4, 1], "steps": 2}"#;
        let out = call(port, &["plan", req, "--all", "--json", "--timeout", "10"]);
        assert!(out.status.success(), "{}", stderr(&out));
        let answers = lines(&out);
        if answers.len() == 2 || Instant::now() > deadline {
            break answers;
        }
    };
    let nodes: BTreeSet<&str> = answers
        .iter()
        .map(|a| a["node"].as_str().unwrap())
        .collect();
    assert_eq!(nodes, BTreeSet::from(["planner_a", "planner_b"]));
    for a in &answers {
        assert_eq!(a["reply"]["by"], a["node"]);
        assert_eq!(
            a["reply"]["points"],
            serde_json::json!([[0.0, 1.0], [2.0, 1.0]])
        );
    }

    // Progress, in order, then the reply.
    let out = call(port, &["count@planner_a", "3", "--json", "--timeout", "10"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let got = lines(&out);
    let progress: Vec<&Value> = got.iter().filter_map(|l| l.get("progress")).collect();
    assert_eq!(
        progress,
        [&Value::from(0), &Value::from(1), &Value::from(2)]
    );
    assert_eq!(got.last().unwrap()["reply"], "counted 3");

    // 2.x primitive types, typed as a person types them.
    let out = call(port, &["echo", "\"hello\"", "--timeout", "10"]);
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "\"hello\"");
    let out = call(port, &["double", "21", "--timeout", "10"]);
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "42");

    // Failures: non-zero, and why.
    let too_many = r#"{"goal": [1, 1], "steps": 20000}"#;
    let out = call(port, &["plan@planner_b", too_many, "--timeout", "10"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("failed at planner_b: 20000 steps is too many (code 1001)"),
        "{}",
        stderr(&out)
    );
    let out = call(port, &["plan", r#"{"goal": [1, 1]}"#, "--timeout", "10"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("does not fit PlanRequest"),
        "{}",
        stderr(&out)
    );
    let asked = Instant::now();
    let out = call(port, &["nowhere", "1", "--timeout", "0.5"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("no server of rover1/nowhere"),
        "{}",
        stderr(&out)
    );
    assert!(asked.elapsed() < Duration::from_secs(20));

    // The sniffer lists both servers with their types.
    let p = port.to_string();
    let mut args = net(&p);
    args.extend(["services", "--json", "--for", "1"]);
    let out = Command::new(SNIFFER).args(&args).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let services: Value = serde_json::from_slice(&out.stdout).unwrap();
    let plan = services
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "rover1/plan")
        .unwrap();
    assert_eq!(plan["servers"].as_array().unwrap().len(), 2);
    assert_eq!(plan["servers"][0]["request"]["name"], "PlanRequest");
    assert_eq!(plan["servers"][0]["reply"]["name"], "PlanReply");
    // The schema as JSON a program reads, not the announced bytes.
    let schema = &plan["servers"][0]["request"]["schema"];
    assert!(schema.is_object(), "{schema}");
    assert!(schema.to_string().contains("\"goal\""), "{schema}");
    let double = services
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "rover1/double")
        .unwrap();
    assert_eq!(double["servers"][0]["request"]["name"], "i64");
    assert_eq!(double["servers"][0]["request"]["wire_name"], "int64_msg");
    // And the table writes types as a user does.
    let mut args = net(&p);
    args.extend(["services", "--for", "1"]);
    let out = Command::new(SNIFFER).args(&args).output().unwrap();
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(table.contains("i64 -> i64"), "{table}");
    assert!(table.contains("PlanRequest -> PlanReply"), "{table}");
}

/// A `puli serve` process in `namespace` and configuration `config`.
fn serve_in(port: u16, name: &str, namespace: &str, config: &str) -> Peer {
    let p = port.to_string();
    let mut args = vec!["serve", "--port", &p, "--interface", "127.0.0.1"];
    args.extend(["--namespace", namespace, "--config", config]);
    args.extend(["--name", name, "--for", "120"]);
    let peer = Peer::spawn(PULI, &args);
    peer.wait_ready(READY);
    peer
}

#[test]
fn puli_call_nearest_takes_its_configuration_first_and_goes_on_when_that_server_dies() {
    let port = free_port();
    let _anyone = serve_in(port, "anyone_rover1", "rover1", "");
    let alice = serve_in(port, "alice_root", "/", "alice");
    let _bob = serve_in(port, "bob_rover1", "rover1", "bob");
    let nearest = |config: &str| {
        let out = call(
            port,
            &[
                "echo",
                "\"hi\"",
                "--nearest",
                "--config",
                config,
                "--json",
                "--timeout",
                "10",
            ],
        );
        assert!(out.status.success(), "{}", stderr(&out));
        let got = lines(&out);
        assert_eq!(got.len(), 1, "{got:?}");
        assert_eq!(got[0]["reply"], "hi");
        got[0]["node"].as_str().unwrap().to_string()
    };
    // Alice's own server, though it is fleet-wide and another serves
    // rover1 itself; bob's is never called from alice's configuration.
    assert_eq!(nearest("alice"), "alice_root");
    assert_eq!(nearest("bob"), "bob_rover1");
    // Without --nearest, the name is rover1/echo only.
    let out = call(
        port,
        &["echo", "\"hi\"", "--json", "--timeout", "10", "--all"],
    );
    let mut nodes: Vec<String> = lines(&out)
        .iter()
        .map(|l| l["node"].as_str().unwrap().to_string())
        .collect();
    nodes.sort();
    assert_eq!(nodes, ["anyone_rover1", "bob_rover1"]);

    drop(alice); // SIGKILL: the next call finds out and goes on, without an error
    assert_eq!(nearest("alice"), "anyone_rover1");
}

#[test]
fn a_server_killed_mid_call_fails_the_call_soon_and_a_restarted_one_takes_new_calls() {
    let port = free_port();
    let server = serve(port, "counter", 50);
    let p = port.to_string();
    let mut args = vec!["call"];
    args.extend(net(&p));
    args.extend(["count", "1000", "--json", "--timeout", "60"]);
    let mut caller = Peer::spawn(PULI, &args);
    // It runs: progress comes.
    let first = caller.next_json(READY).expect("progress");
    assert_eq!(first["progress"], 0);

    drop(server); // SIGKILL, mid-call
    let killed = Instant::now();
    let status = caller.wait_exit(Duration::from_secs(20));
    assert!(
        status.is_some_and(|s| !s.success()),
        "the caller still runs"
    );
    // Discovery sees a crash within about 400 ms; the call ends soon after,
    // long before its 60 s deadline.
    assert!(killed.elapsed() < Duration::from_secs(5));
    assert!(
        caller
            .stderr()
            .contains("counter left or failed before it answered"),
        "{}",
        caller.stderr()
    );

    // A new server process under the same name takes new calls.
    let _again = serve(port, "counter", 1);
    let out = call(port, &["count", "2", "--timeout", "20"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("\"counted 2\""));
}

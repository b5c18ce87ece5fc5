//! Everything a user runs at once, on loopback: the features whose own
//! tests passed alone and broke together (issue 28).
//!
//! Site A: the demo fleet (two rovers serving `distance_to` and owning
//! `max_speed`, and a controller calling them), a Pulicast 2.x talker and
//! listener (the reference package), the dashboard in its plain mode, a
//! recorder of everything, `puli web` with its Foxglove server, and a
//! bridge. Site B, on a port of its own:
//! a bridge joined to A's over one Zenoh TCP link, and a 2.x talker and
//! listener of its own. With all of that running:
//!
//! - calls to `rover1/distance_to` succeed 20 of 20 from both sites, and
//!   no tool is ever taken for a server (nor the bridge);
//! - `rover1/max_speed` changes twice in a row from both sites, with a
//!   `config list` between, and is never locked;
//! - from rover1's namespace, `distance_to` and `pose` are found as the
//!   nearest server and publisher on both sites (issue 31);
//! - the 2.x channels cross both ways;
//! - the shell's scripted `nodes`, `channels`, `services` and `settings`
//!   list the fleet;
//! - the recording plays back.
//!
//! Every process is one this test starts, stopped by its own handle.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::path::PathBuf;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use pulicast::NearestEvent;
use pulicast_tests::{
    free_port, free_tcp_port, loopback_node, python_listener, python_talker, run_with_stdin,
    workspace_bin, Peer,
};
use serde_json::Value;

/// Any one wait.
const WAIT: Duration = Duration::from_secs(30);

/// How long the long-running processes may run: well past the test.
const RUN_SECS: &str = "240";

fn net(port: u16) -> Vec<String> {
    vec![
        "--port".into(),
        port.to_string(),
        "--interface".into(),
        "127.0.0.1".into(),
    ]
}

fn spawn(program: &PathBuf, args: &[String]) -> Peer {
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    Peer::spawn(program, &args)
}

/// Runs a command to its end (at most [`WAIT`]).
fn run(program: &PathBuf, args: &[String]) -> Output {
    let mut child = Command::new(program)
        .args(args)
        .env_remove(pulicast::KEYS_ENV)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > WAIT {
            // Our own child, by its handle.
            let _ = child.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

fn text(out: &Output) -> String {
    format!(
        "{}\n--- stderr:\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// `puli ARGS` on `port`, which must succeed; its stdout.
fn puli(port: u16, args: &[&str]) -> String {
    let mut all: Vec<String> = args.iter().map(|a| a.to_string()).collect();
    all.extend(net(port));
    let out = run(&workspace_bin("puli"), &all);
    assert!(out.status.success(), "puli {args:?}: {}", text(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn bridge(port: u16, site: &str, link: &[&str]) -> Peer {
    let mut args: Vec<String> = ["--prefix", "fleet", "--site", site, "--lease", "1s"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    args.extend(net(port));
    args.extend(link.iter().map(|s| s.to_string()));
    spawn(&workspace_bin("puli-bridge"), &args)
}

/// Polls `cond` every 100 ms until it holds, at most [`WAIT`].
fn eventually(what: &str, mut cond: impl FnMut() -> bool) {
    let started = Instant::now();
    while !cond() {
        assert!(started.elapsed() < WAIT, "{what}: not within {WAIT:?}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The servers of `service` that `puli-sniffer services --json` lists.
fn servers(port: u16, service: &str) -> Vec<String> {
    let mut args: Vec<String> = vec!["services".into(), "--json".into()];
    args.extend(["--for".into(), "1".into()]);
    args.extend(net(port));
    let out = run(&workspace_bin("puli-sniffer"), &args);
    assert!(out.status.success(), "{}", text(&out));
    let all: Value = serde_json::from_slice(&out.stdout).unwrap();
    all.as_array()
        .unwrap()
        .iter()
        .filter(|s| s["name"] == service)
        .flat_map(|s| s["servers"].as_array().unwrap().clone())
        .map(|e| e["node"].as_str().unwrap().to_string())
        .collect()
}

/// `n` calls to `rover1/distance_to` from a node on `port`; how many
/// got their reply.
fn calls(port: u16, n: usize) -> (usize, Vec<String>) {
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let node = loopback_node("caller", port).await;
        let client = node
            .client::<(f64, f64), f64>("rover1/distance_to")
            .unwrap();
        let (mut ok, mut errors) = (0, Vec::new());
        for _ in 0..n {
            match client
                .call_within(&(0.0, 0.0), Duration::from_secs(5))
                .await
            {
                Ok(d) if d.is_finite() => ok += 1,
                Ok(d) => errors.push(format!("a distance of {d}")),
                Err(e) => errors.push(e.to_string()),
            }
        }
        node.stop();
        (ok, errors)
    })
}

/// Whom a nearest subscription to `pose` from namespace `rover1` on
/// `port` hears, once a message came: (node, channel).
fn rt_nearest_pose(port: u16) -> (String, String) {
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let node = loopback_node("nearest_listener", port).await;
        // Raw bytes: the demo's `Pose` type is the example's own.
        let mut poses = node
            .ns("/rover1")
            .subscribe_nearest::<Vec<u8>>("pose")
            .unwrap();
        // On site B the bridge is the only publisher known until its
        // relays arrive (about 100 ms after a node joins): the
        // subscription may hear it first and then move to the member it
        // carries. What counts is where it settles, with a message heard
        // from there.
        let settled = tokio::time::timeout(WAIT, async {
            loop {
                match poses.recv_event().await {
                    Some(NearestEvent::Message(_)) => {
                        let heard = poses.hearing().cloned();
                        if heard.as_ref().is_some_and(|p| p.node != "puli-bridge") {
                            return heard;
                        }
                    }
                    Some(NearestEvent::Switched { .. }) => {}
                    None => return None,
                }
            }
        })
        .await;
        let heard = settled.ok().flatten();
        let Some(heard) = heard else {
            panic!("no pose but the bridge's: {:?}", poses.hearing());
        };
        node.stop();
        (heard.node, heard.channel)
    })
}

#[test]
fn everything_at_once() {
    let (a, b) = (free_port(), free_port());
    let endpoint = format!("tcp/127.0.0.1:{}", free_tcp_port());
    let dir = std::env::temp_dir().join(format!("pulicast-fleet-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let recording = dir.join("fleet.mcap");

    // Site A: the demo fleet, member by member (each its own process, as
    // the demo starts them), so each is stopped by its own handle.
    let demo = workspace_bin("examples/rover_demo");
    let member = |role: &str, name: &str| {
        let mut args: Vec<String> =
            vec!["--role".into(), role.into(), "--name".into(), name.into()];
        args.extend(["--secs".into(), RUN_SECS.into()]);
        args.extend(net(a));
        spawn(&demo, &args)
    };
    let _rover1 = member("rover", "rover1");
    let _rover2 = member("rover", "rover2");
    let controller = member("controller", "controller");
    // The tools that watch: the plain dashboard and a recorder of all.
    let mut dashboard_args: Vec<String> = vec!["--for".into(), RUN_SECS.into()];
    dashboard_args.extend(net(a));
    let dashboard = spawn(&workspace_bin("puli-sniffer"), &dashboard_args);
    let mut record_args: Vec<String> = vec!["record".into(), recording.display().to_string()];
    record_args.extend(net(a));
    let recorder = spawn(&workspace_bin("puli"), &record_args);
    // The page and the Foxglove server, which watch every channel and
    // follow every setting: taken for no subscriber, server or owner.
    let mut web_args: Vec<String> = [
        "web",
        "--foxglove",
        "--json",
        "--http-port",
        "0",
        "--ws-port",
        "0",
    ]
    .map(String::from)
    .to_vec();
    web_args.extend(net(a));
    let mut web = spawn(&workspace_bin("puli"), &web_args);
    // 2.x nodes on both sites, and the bridges.
    let (pa, pb) = (a.to_string(), b.to_string());
    let listener_a = python_listener(&pa, "py_listener_a", "py/from_b", 5, 60);
    let listener_b = python_listener(&pb, "py_listener_b", "py/from_a", 5, 60);
    let _talker_a = python_talker(&pa, "py_talker_a", "py/from_a", 4000);
    let _talker_b = python_talker(&pb, "py_talker_b", "py/from_b", 4000);
    let bridge_a = bridge(a, "site-a", &["--listen", &endpoint]);
    let bridge_b = bridge(b, "site-b", &["--connect", &endpoint]);
    listener_a.wait_ready(WAIT);
    listener_b.wait_ready(WAIT);

    // The fleet is up on both sites: site B sees rover1's service through
    // its bridge.
    eventually("rover1 serves distance_to on site A", || {
        servers(a, "rover1/distance_to") == ["rover1"]
    });
    eventually("site B sees rover1's service", || {
        servers(b, "rover1/distance_to") == ["rover1"]
    });

    // Calls, 20 of 20 from each site: no watching tool and no bridge is
    // taken for a server.
    for (site, port) in [("A", a), ("B", b)] {
        let (ok, errors) = calls(port, 20);
        assert_eq!(ok, 20, "site {site}: {errors:?}");
    }
    let mut call_args: Vec<String> = vec!["call".into(), "rover1/distance_to".into()];
    call_args.extend(["[0, 0]".into(), "--timeout".into(), "10".into()]);
    for port in [a, b] {
        let args: Vec<&str> = call_args.iter().map(String::as_str).collect();
        let reply = puli(port, &args);
        assert!(reply.trim().parse::<f64>().is_ok(), "{reply}");
    }

    // The nearest server and publisher, from rover1's namespace: found
    // among the tools, the 2.x nodes and the bridge, on both sites (on B,
    // through the bridge).
    for port in [a, b] {
        let args = [
            "call",
            "--nearest",
            "--namespace",
            "rover1",
            "distance_to",
            "[0, 0]",
        ];
        let reply = puli(port, &[&args[..], &["--timeout", "10"]].concat());
        assert!(reply.trim().parse::<f64>().is_ok(), "{reply}");
        let heard = rt_nearest_pose(port);
        assert_eq!(heard, ("rover1".to_string(), "rover1/pose".to_string()));
    }

    // Settings: twice in a row from each site, a listing between; never
    // locked (no tool and no bridge is taken for an owner).
    for (port, values) in [(a, ["0.4", "0.6"]), (b, ["0.7", "0.8"])] {
        let set = |v: &str| puli(port, &["config", "set", "rover1/max_speed", v]);
        assert!(set(values[0]).contains(values[0]));
        let list = puli(port, &["config", "--json", "--quiet", "0.5", "list"]);
        let rows: Value = serde_json::from_str(&list).unwrap();
        let speed = rows
            .as_array()
            .unwrap()
            .iter()
            .find(|r| r["name"] == "rover1/max_speed")
            .unwrap_or_else(|| panic!("{list}"));
        assert_eq!(speed["locked"], false, "{speed}");
        assert_eq!(speed["owners"], serde_json::json!(["rover1"]), "{speed}");
        assert!(set(values[1]).contains(values[1]));
    }
    let got = puli(a, &["config", "get", "rover1/max_speed"]);
    assert!(got.starts_with("0.8"), "{got}");

    // 2.x channels, both ways.
    for (listener, what) in [(&listener_b, "A to B"), (&listener_a, "B to A")] {
        let got = listener.take_json(5, WAIT);
        assert!(
            got.iter()
                .all(|m| m["value"].as_str().is_some_and(|v| v.starts_with("hi "))),
            "{what}: {got:?}"
        );
    }

    // The shell, scripted, sees the fleet at once.
    let mut args = vec!["shell".to_string()];
    args.extend(net(a));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let script = "nodes\nchannels\nservices\nsettings\n";
    let out = run_with_stdin(workspace_bin("puli"), &args, script);
    let listed = text(&out);
    assert!(out.status.success(), "{listed}");
    for name in [
        "rover1",
        "rover2",
        "controller",
        "py_talker_a",
        "puli-sniffer",
        "puli-record",
        "puli-web",
        "rover1/pose",
        "py/from_a",
        "rover1/distance_to",
        "rover1/max_speed",
        "rover2/mode",
    ] {
        assert!(listed.contains(name), "{name} missing: {listed}");
    }

    // The page's server ran through all of that.
    assert!(
        web.wait_exit(Duration::ZERO).is_none(),
        "puli web ended: {}",
        web.stderr()
    );
    // The dashboard ran beside all of that, listing the fleet without its
    // hidden channels; the controller never waited on a tool for an answer.
    dashboard.terminate();
    let shown = dashboard.output(WAIT);
    assert!(shown.contains("rover1/pose"), "{shown}");
    assert!(!shown.contains("/.services/"), "{shown}");
    for line in controller.lines_so_far() {
        assert!(!line.contains("no answer from puli"), "{line}");
    }

    // The recording: stopped as Ctrl-C stops it, then played back onto a
    // port of its own, where rover1's poses arrive again.
    recorder.interrupt();
    let summary = recorder.output(WAIT);
    assert!(summary.contains("rover1/pose"), "{summary}");
    let c = free_port();
    let rt = tokio::runtime::Runtime::new().unwrap();
    let (node, mut poses) = rt.block_on(async {
        let node = loopback_node("replay_watcher", c).await;
        let poses = node.channel("rover1/pose").subscribe_raw().unwrap();
        (node, poses)
    });
    let file = recording.display().to_string();
    let played = puli(
        c,
        &["play", &file, "--speed", "8", "--channels", "rover1/..."],
    );
    assert!(played.contains("messages published"), "{played}");
    let replayed = rt.block_on(async {
        let mut n = 0;
        while let Ok(Some(_)) = tokio::time::timeout(Duration::from_secs(1), poses.recv()).await {
            n += 1;
        }
        n
    });
    assert!(replayed >= 10, "{replayed} poses played back: {played}");
    node.stop();
    // The bridges' logs went to a pipe: no colour codes in them.
    for bridge in [&bridge_a, &bridge_b] {
        let log = bridge.stderr();
        assert!(log.contains("bridge running"), "{log}");
        assert!(
            !log.contains('\u{1b}'),
            "colour codes in a piped log: {log:?}"
        );
    }
    drop((bridge_a, bridge_b));
    let _ = std::fs::remove_dir_all(&dir);
}

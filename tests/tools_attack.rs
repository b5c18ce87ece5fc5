//! The long-running tools under a stranger's flood of fake Pulicast 2.x
//! nodes (200, each from its own socket, 2400 names each, every 2 s): each
//! keeps running, and ends within 2 s of SIGTERM or SIGINT. Most end
//! whole, with their summary; one that can't finish it by then (`channels`
//! listing the stranger's 240 000 published names) exits with status 1 and
//! says so. A test binary of its own: it loads the machine.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::time::{Duration, Instant};

use pulicast_tests::{free_port, workspace_bin, Peer};

#[test]
fn every_long_running_tool_ends_within_two_seconds_of_a_signal_under_a_flood() {
    let port = free_port();
    let p = port.to_string();
    let net = ["--port", p.as_str(), "--interface", "127.0.0.1"];
    let attack = pulicast_tests::fake_2x_flood(port, 200, 2400, Duration::from_secs(2));
    let recording = std::env::temp_dir().join(format!("tools-attack-{port}.mcap"));
    let sniffer = workspace_bin("puli-sniffer");
    let puli = workspace_bin("puli");
    let with_net = |args: &[&str]| -> Vec<String> {
        let mut all: Vec<String> = args.iter().map(|a| a.to_string()).collect();
        all.extend(net.iter().map(|a| a.to_string()));
        all
    };
    let tools: Vec<(&str, std::path::PathBuf, Vec<String>)> = vec![
        ("dashboard", sniffer.clone(), with_net(&["--for", "60"])),
        (
            "channels",
            sniffer.clone(),
            with_net(&["channels", "--for", "60"]),
        ),
        ("bw", sniffer.clone(), with_net(&["bw", "--for", "60"])),
        ("echo", sniffer.clone(), with_net(&["echo", "rover1/pose"])),
        (
            "record",
            puli.clone(),
            with_net(&["record", recording.to_str().unwrap(), "--for", "60"]),
        ),
        (
            "pub",
            puli.clone(),
            with_net(&["pub", "rover1/pose", "1.5", "--rate", "20"]),
        ),
    ];
    // One at a time, as an operator runs them.
    let mut slow = Vec::new();
    for (i, (label, program, args)) in tools.iter().enumerate() {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let mut tool = Peer::spawn(program, &args);
        // The tool runs through the flood for a while.
        std::thread::sleep(Duration::from_secs(4));
        assert!(
            tool.wait_exit(Duration::ZERO).is_none(),
            "{label} ended by itself: {}",
            tool.stderr()
        );
        let asked = Instant::now();
        // Half by SIGTERM, half by SIGINT.
        match i % 2 {
            0 => tool.terminate(),
            _ => tool.interrupt(),
        }
        let status = tool.wait_exit(Duration::from_secs(10));
        let took = asked.elapsed();
        eprintln!("{label}: ended after {took:?} ({status:?})");
        if status.is_none() || took >= Duration::from_secs(2) {
            let stderr = tool.stderr();
            let tail: Vec<&str> = stderr.lines().rev().take(5).collect();
            slow.push(format!("{label} took {took:?}: {tail:?}"));
        }
    }
    drop(attack);
    let _ = std::fs::remove_file(&recording);
    assert!(slow.is_empty(), "{slow:#?}");
}

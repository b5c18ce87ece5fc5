//! `puli bench thr` and `lat` run end to end (small counts): their JSON
//! carries what the docs promise. Figures are not checked here: speed is
//! measured by running the benchmark, never by timed tests.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::process::Command;

use pulicast_tests::free_port;
use serde_json::Value;

const PULI: &str = env!("CARGO_BIN_EXE_puli");

fn bench(args: &[&str]) -> Value {
    let port = free_port().to_string();
    let out = Command::new(PULI)
        .args(["bench"])
        .args(args)
        .args(["--port", &port, "--json"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8(out.stdout).unwrap();
    serde_json::from_str(stdout.lines().last().unwrap()).unwrap()
}

#[test]
fn throughput_reports_every_row_batched_and_fragmented() {
    let report = bench(&[
        "thr",
        "--size",
        "64,100000",
        "--for",
        "0.3",
        "--rounds",
        "1",
        "--batch",
        "1ms",
    ]);
    assert_eq!(report["batch_us"], 1000);
    let results = report["results"].as_array().unwrap();
    assert_eq!(results.len(), 2);
    for r in results {
        let rows = r["rows"].as_object().unwrap();
        let names: Vec<&str> = rows.keys().map(String::as_str).collect();
        // Keys sorted: the default rows, every one of them.
        assert_eq!(
            names,
            ["await", "callback", "many", "raw", "raw-spin", "timeout"],
            "{r}"
        );
        for (name, row) in rows {
            let rate = row["msgs_per_s"].as_f64().unwrap();
            let loss = row["loss"].as_f64().unwrap();
            assert!(rate > 0.0, "{name} {r}");
            assert!((0.0..=1.0).contains(&loss), "{name} {r}");
            assert!(row["vs_raw"].as_f64().unwrap() > 0.0, "{name} {r}");
        }
        assert_eq!(rows["raw"]["vs_raw"], 1.0);
    }
}

#[test]
fn latency_reports_percentiles_of_every_row() {
    let report = bench(&["lat", "--rounds", "200", "--runs", "1", "--batch", "200us"]);
    assert_eq!(report["batch_us"], 200);
    let rows = report["rows_us"].as_object().unwrap();
    assert_eq!(rows.len(), 5);
    for (name, p) in rows {
        let (p50, p99, max) = (
            p["p50"].as_f64().unwrap(),
            p["p99"].as_f64().unwrap(),
            p["max"].as_f64().unwrap(),
        );
        assert!(0.0 < p50 && p50 <= p99 && p99 <= max, "{name}: {p}");
        assert_eq!(p["lost"], 0, "{name}");
    }
    assert_eq!(rows["timeout"]["baseline"], "raw");
    assert_eq!(rows["callback"]["baseline"], "raw-spin");
}

#[test]
fn throughput_over_several_channels_counts_them_all() {
    let report = bench(&[
        "thr",
        "--size",
        "64",
        "--channels",
        "3",
        "--for",
        "0.3",
        "--rounds",
        "1",
        "--rows",
        "raw,raw-spin,await,timeout,many,callback",
    ]);
    assert_eq!(report["channels"], 3);
    let rows = report["results"][0]["rows"].as_object().unwrap();
    assert_eq!(rows.len(), 6);
    for (name, row) in rows {
        assert!(row["msgs_per_s"].as_f64().unwrap() > 0.0, "{name} {row}");
        assert!(row["loss"].as_f64().unwrap() < 1.0, "{name} {row}");
    }
}

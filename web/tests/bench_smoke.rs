//! `puli bench web` runs, briefly, on a small fleet: the benchmark itself
//! (docs/web.md) is run by hand, in a release build.
#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

#[test]
fn the_web_benchmark_measures_both_servers() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_puli-web-bench"))
        .args([
            "--channels",
            "4",
            "--rate",
            "20",
            "--clients",
            "2",
            "--secs",
            "1",
            "--json",
            "--server",
            env!("CARGO_BIN_EXE_puli-web"),
        ])
        .env_remove(pulicast::KEYS_ENV)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    let servers = summary["servers"].as_array().unwrap();
    assert_eq!(servers.len(), 2, "{summary}");
    for s in servers {
        assert!(s["frames"].as_u64().unwrap() > 0, "{s}");
        assert!(s["latency_ms_p50"].as_f64().is_some(), "{s}");
        assert!(s["cpu_percent_of_a_core"].as_f64().is_some(), "{s}");
    }
    assert!(summary["baseline_pulicast_subscriber"]["latency_ms_p50"]
        .as_f64()
        .is_some());
}

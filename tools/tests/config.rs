//! `puli config` and our settings against the real Pulicast 2.x puliconf
//! (`pulicast==2.0.1`'s `Setting`, `SettingDiscoverer`,
//! `pull_configuration`, `push_configuration`, `diff_configuration`, driven
//! by `tests/python/puliconf_peer.py`), both ways, on loopback.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::process::{Command, Output};
use std::time::Duration;

use pulicast::{Check, Node};
use pulicast_tests::{free_port, puliconf_peer, Peer};
use serde_json::Value;

const PULI: &str = env!("CARGO_BIN_EXE_puli");
/// A puliconf command waits 2 s for discovery to settle, plus start-up.
const PY_WAIT: Duration = Duration::from_secs(30);

/// `puli config ARGS` on loopback.
fn puli(port: u16, args: &[&str]) -> Output {
    let p = port.to_string();
    let mut all = vec!["config", "--port", &p, "--interface", "127.0.0.1"];
    all.extend_from_slice(&["--quiet", "1", "--timeout", "20"]);
    all.extend_from_slice(args);
    Command::new(PULI)
        .args(&all)
        .env_remove(pulicast::KEYS_ENV)
        .output()
        .unwrap()
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn node(name: &str, port: u16) -> pulicast::NodeBuilder {
    Node::new(name)
        .port(port)
        .interface(Ipv4Addr::LOCALHOST)
        .heartbeat_period(Duration::from_millis(100))
}

#[test]
fn puli_config_lists_reads_and_changes_a_python_owned_setting() {
    let port = free_port();
    let p = port.to_string();
    let owner = puliconf_peer(&[
        "own",
        "--port",
        &p,
        "--ns",
        "rover1",
        "--for",
        "120",
        "max_speed=float:1.5:0.0,2.0",
        "mode=str:auto",
        "count=int:3",
    ]);
    owner.wait_ready(PY_WAIT);

    let out = puli(port, &["--json", "list"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let rows: Value = serde_json::from_str(&stdout(&out)).unwrap();
    let names: Vec<&str> = rows
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["rover1/count", "rover1/max_speed", "rover1/mode"]);
    assert_eq!(rows[1]["value"], "1.5");
    assert_eq!(rows[1]["type"], "double_msg");
    assert_eq!(rows[1]["owners"][0], "py_owner");
    // The 2.x validator's text, as it answers a poke.
    assert_eq!(rows[1]["about"], "must be in [0.0, 2.0]");

    // Refused with the Python validator's warning; the value stays.
    let out = puli(port, &["set", "rover1/max_speed", "5"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("must be in [0.0, 2.0]"),
        "{}",
        stderr(&out)
    );
    let out = puli(port, &["set", "rover1/max_speed", "0.5"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(stdout(&out).trim(), "0.5");
    let changed = owner.next_json(PY_WAIT).unwrap();
    assert_eq!(changed["name"], "max_speed");
    assert_eq!(changed["value"], 0.5);

    // A value of the wrong type never leaves puli.
    let out = puli(port, &["set", "rover1/count", "2.5"]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("64-bit integer"), "{}", stderr(&out));

    let out = puli(port, &["unset", "rover1/mode"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(stdout(&out).trim(), "unset");
    assert_eq!(owner.next_json(PY_WAIT).unwrap()["value"], Value::Null);
    let out = puli(port, &["get", "rover1/count"]);
    assert_eq!(stdout(&out).trim(), "3");
}

#[test]
fn puliconf_pulls_pushes_and_diffs_rust_owned_settings() {
    let port = free_port();
    let p = port.to_string();
    let owner = node("controller", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let speed = owner
        .setting_builder("max_speed", 1.5f64)
        .describe("top speed")
        .unit("m/s")
        .check(Check::Range(0.0, 2.0))
        .build()
        .unwrap();
    let gain = owner.setting("arm/gain", 3i32).unwrap();
    let mode = owner.setting("mode", "auto".to_string()).unwrap();
    let on = owner.setting("enabled", true).unwrap();

    let pulled = puliconf_peer(&["pull", "--port", &p]).output(PY_WAIT);
    let doc: toml_edit::DocumentMut = pulled.parse().unwrap();
    assert_eq!(doc["rover1/max_speed"].as_float(), Some(1.5));
    assert_eq!(doc["rover1/arm/gain"].as_integer(), Some(3));
    assert_eq!(doc["rover1/mode"].as_str(), Some("auto"));
    assert_eq!(doc["rover1/enabled"].as_bool(), Some(true));
    assert!(
        pulled.contains("# top speed; unit: m/s; must be in [0, 2]"),
        "{pulled}"
    );

    let dir = std::env::temp_dir().join(format!("puli-config-test-{port}"));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("edited.toml");
    std::fs::write(
        &file,
        "\"rover1/max_speed\" = 0.75\n\"rover1/arm/gain\" = -2\n\"rover1/mode\" = \"manual\"\n\"rover1/enabled\" = false\n",
    )
    .unwrap();
    let file = file.to_str().unwrap();
    let pushed = puliconf_peer(&["push", "--port", &p, file]);
    let result = pushed.next_json(PY_WAIT).unwrap();
    assert_eq!(result["failed"], Value::Array(vec![]), "{result}");
    assert_eq!(result["changed"].as_array().unwrap().len(), 4, "{result}");
    assert_eq!(speed.get(), Some(0.75));
    assert_eq!(gain.get(), Some(-2));
    assert_eq!(mode.get().as_deref(), Some("manual"));
    assert_eq!(on.get(), Some(false));

    // Nothing left to change; a value out of range fails with our reason.
    let diff = puliconf_peer(&["diff", "--port", &p, file]).output(PY_WAIT);
    assert_eq!(diff.trim(), "", "diff after push: {diff}");
    let set = puliconf_peer(&["set", "--port", &p, "rover1/max_speed", "7.0"]);
    let answer = set.next_json(PY_WAIT).unwrap();
    assert_eq!(answer["ok"], false);
    assert_eq!(answer["message"], "must be in [0, 2]");
    assert_eq!(speed.get(), Some(0.75));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn files_move_between_puli_config_and_puliconf() {
    let port = free_port();
    let p = port.to_string();
    let rust = node("rust_owner", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let speed = rust
        .setting_checked("max_speed", 1.5f64, vec![Check::Range(0.0, 2.0)])
        .unwrap();
    let python = puliconf_peer(&[
        "own",
        "--port",
        &p,
        "--ns",
        "rover2",
        "--for",
        "120",
        "gain=float:0.5",
        "label=str:left",
    ]);
    python.wait_ready(PY_WAIT);

    // puli pulls both owners' settings; puliconf pushes the file back:
    // nothing to change.
    let dir = std::env::temp_dir().join(format!("puli-config-files-{port}"));
    std::fs::create_dir_all(&dir).unwrap();
    let ours = dir.join("ours.toml");
    let ours_str = ours.to_str().unwrap();
    let out = puli(port, &["pull", ours_str]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&ours).unwrap();
    for key in ["rover1/max_speed", "rover2/gain", "rover2/label"] {
        assert!(text.contains(key), "{key} missing from {text}");
    }
    let pushed = puliconf_peer(&["push", "--port", &p, ours_str]);
    let result = pushed.next_json(PY_WAIT).unwrap();
    assert_eq!(result["changed"], Value::Array(vec![]), "{result}");
    assert_eq!(result["failed"], Value::Array(vec![]), "{result}");
    assert_eq!(result["unchanged"].as_array().unwrap().len(), 3, "{result}");

    // puliconf pulls, the file is edited, puli pushes it and diffs clean.
    let theirs = puliconf_peer(&["pull", "--port", &p]).output(PY_WAIT);
    let edited = theirs
        .replace("= 1.5", "= 0.25")
        .replace("\"left\"", "\"right\"");
    assert_ne!(edited, theirs, "{theirs}");
    let file = dir.join("theirs.toml");
    std::fs::write(&file, edited).unwrap();
    let file = file.to_str().unwrap();
    let out = puli(port, &["push", file]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stdout(&out).contains("# Minimal set of changes:"));
    assert!(
        stderr(&out).contains("2 changed, 1 unchanged, 0 failed"),
        "{}",
        stderr(&out)
    );
    assert_eq!(speed.get(), Some(0.25));
    let out = puli(port, &["diff", file]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(stdout(&out).trim(), "");

    // Unknown names and refused values: reported, the rest applied.
    std::fs::write(
        file,
        "\"rover1/max_speed\" = 9.0\n\"rover9/nothing\" = 1\n\"rover2/gain\" = 0.75\n",
    )
    .unwrap();
    let out = puli(port, &["push", file]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("rover9/nothing: no node owns this setting"),
        "{err}"
    );
    assert!(err.contains("must be in [0, 2]"), "{err}");
    assert!(err.contains("1 changed, 0 unchanged, 2 failed"), "{err}");
    assert_eq!(speed.get(), Some(0.25));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `puli config-owner` processes.
fn owner_process(port: u16, name: &str, ns: &str, count: usize, file: Option<&str>) -> Peer {
    let p = port.to_string();
    let n = count.to_string();
    let mut args = vec![
        "config-owner",
        "--port",
        &p,
        "--interface",
        "127.0.0.1",
        "--name",
        name,
        "--namespace",
        ns,
        "--count",
        &n,
        "--for",
        "120",
    ];
    if let Some(file) = file {
        args.extend_from_slice(&["--settings-file", file]);
    }
    let peer = Peer::spawn(PULI, &args);
    peer.wait_ready(PY_WAIT);
    peer
}

/// Three processes own a dozen settings: pull, edit, push, and diff shows
/// nothing left; a node restarted with the file comes back with the pushed
/// values; an owner that crashed fails its own settings in a push, not
/// the others'.
#[test]
fn a_fleet_of_processes_is_pulled_edited_pushed_and_restarted_from_the_file() {
    let port = free_port();
    let rover1 = owner_process(port, "rover1_ctrl", "rover1", 4, None);
    let rover2 = owner_process(port, "rover2_ctrl", "rover2", 4, None);
    let _base = owner_process(port, "base_ctrl", "base", 4, None);
    let dir = std::env::temp_dir().join(format!("puli-config-fleet-{port}"));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("fleet.toml");
    let file_str = file.to_str().unwrap();

    let out = puli(port, &["pull", file_str]);
    assert!(out.status.success(), "{}", stderr(&out));
    let pulled = std::fs::read_to_string(&file).unwrap();
    let doc: toml_edit::DocumentMut = pulled.parse().unwrap();
    assert_eq!(doc.len(), 12, "{pulled}");
    assert_eq!(doc["rover1/setting_00"].as_float(), Some(0.0));
    assert!(pulled.contains("must be in [0, 100]"), "{pulled}");

    let edited = pulled
        .replace(
            "\"rover1/setting_00\" = 0.0",
            "\"rover1/setting_00\" = 42.5",
        )
        .replace("\"rover1/setting_01\" = 1", "\"rover1/setting_01\" = 7")
        .replace(
            "\"rover2/setting_02\" = false",
            "\"rover2/setting_02\" = true",
        )
        .replace(
            "\"base/setting_03\" = \"v3\"",
            "\"base/setting_03\" = \"edited\"",
        );
    assert_eq!(edited.matches("42.5").count(), 1, "{edited}");
    std::fs::write(&file, &edited).unwrap();
    let out = puli(port, &["push", file_str]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("4 changed, 8 unchanged, 0 failed"),
        "{}",
        stderr(&out)
    );
    let out = puli(port, &["diff", file_str]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(stdout(&out).trim(), "", "left to change after the push");

    // rover1 restarts from the file: the pushed values, not its defaults.
    drop(rover1);
    let _rover1 = owner_process(port, "rover1_ctrl", "rover1", 4, Some(file_str));
    let out = puli(port, &["get", "rover1/setting_00"]);
    assert_eq!(stdout(&out).trim(), "42.5", "{}", stderr(&out));
    let out = puli(port, &["get", "rover1/setting_01"]);
    assert_eq!(stdout(&out).trim(), "7", "{}", stderr(&out));

    // rover2 crashes; a push reports its settings, applies the rest.
    drop(rover2);
    std::fs::write(
        &file,
        "\"rover2/setting_00\" = 5.0\n\"base/setting_00\" = 6.0\n\"rover1/setting_00\" = 7.0\n",
    )
    .unwrap();
    let out = puli(port, &["push", file_str]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(err.contains("rover2/setting_00"), "{err}");
    assert!(err.contains("2 changed, 0 unchanged, 1 failed"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[derive(serde::Serialize, serde::Deserialize, pulicast::Schema, Debug, Clone, PartialEq)]
struct Gains {
    p: f64,
    i: f64,
}

/// A native setting (our extension) next to a primitive one: `puli config`
/// pulls it as a TOML table and pushes an edited one back; 2.x puliconf,
/// which fails on a type it does not know, does not see it and still pulls
/// the primitive setting.
#[test]
fn native_settings_go_through_files_and_stay_out_of_2x_puliconf() {
    use pulicast::Native;
    let port = free_port();
    let p = port.to_string();
    let owner = node("controller", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let gains = owner
        .setting("gains", Native(Gains { p: 1.5, i: 0.25 }))
        .unwrap();
    let _speed = owner.setting("max_speed", 1.5f64).unwrap();

    let dir = std::env::temp_dir().join(format!("puli-config-native-{port}"));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("native.toml");
    let file_str = file.to_str().unwrap();
    let out = puli(port, &["pull", file_str]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&file).unwrap();
    let doc: toml_edit::DocumentMut = text.parse().unwrap();
    let table = doc["rover1/gains"].as_inline_table().unwrap();
    assert_eq!(table.get("p").and_then(|v| v.as_float()), Some(1.5));
    let out = puli(port, &["--json", "get", "rover1/gains"]);
    let row: Value = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(row["type"], "Gains");

    std::fs::write(&file, text.replace("p = 1.5", "p = 2.0")).unwrap();
    let out = puli(port, &["push", file_str]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(gains.get(), Some(Native(Gains { p: 2.0, i: 0.25 })));
    let out = puli(port, &["diff", file_str]);
    assert_eq!(stdout(&out).trim(), "", "{}", stderr(&out));
    let out = puli(port, &["set", "rover1/gains", r#"{"p": 3.0, "i": 0.5}"#]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(gains.get(), Some(Native(Gains { p: 3.0, i: 0.5 })));

    let pulled = puliconf_peer(&["pull", "--port", &p]).output(PY_WAIT);
    assert!(pulled.contains("\"rover1/max_speed\" = 1.5"), "{pulled}");
    assert!(!pulled.contains("gains"), "{pulled}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A typo fails as soon as discovery has settled, naming what was meant,
/// in `puli config`, `puli call` and the shell, instead of waiting out the
/// whole deadline (10 s and 5 s before); `--wait` still waits.
#[test]
fn a_typo_fails_once_the_fleet_is_known_with_the_name_meant() {
    let port = free_port();
    let p = port.to_string();
    let rover = node("rover", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let _speed = rover.setting("max_speed", 0.5f64).unwrap();
    let _distance = rover
        .serve("distance_to", |(x, y): (f64, f64)| async move {
            Ok::<f64, pulicast::Fault>(x.hypot(y))
        })
        .unwrap();
    let quick = |out: &Output, took: Duration, meant: &str| {
        let err = stderr(out);
        assert!(!out.status.success(), "{err}");
        assert!(err.contains(&format!("did you mean {meant}?")), "{err}");
        assert!(took < Duration::from_secs(8), "took {took:?}: {err}");
    };
    let started = std::time::Instant::now();
    let out = puli(port, &["set", "rover1/max_sped", "0.3"]);
    quick(&out, started.elapsed(), "rover1/max_speed");
    let call = |extra: &[&str]| {
        let mut args = vec!["call", "--port", &p, "--interface", "127.0.0.1"];
        args.extend_from_slice(&["rover1/distance", "[3, 4]"]);
        args.extend_from_slice(extra);
        let started = std::time::Instant::now();
        let out = Command::new(PULI).args(&args).output().unwrap();
        (out, started.elapsed())
    };
    let (out, took) = call(&["--timeout", "20"]);
    quick(&out, took, "rover1/distance_to");
    // A node's name after @: the nodes that do serve it.
    let mut args = vec!["call", "--port", &p, "--interface", "127.0.0.1"];
    args.extend_from_slice(&["rover1/distance_to@rovr", "[3, 4]", "--timeout", "20"]);
    let started = std::time::Instant::now();
    let out = Command::new(PULI).args(&args).output().unwrap();
    quick(&out, started.elapsed(), "rover");
    // A request that does not fit names the type as Rust writes it.
    let mut args = vec!["call", "--port", &p, "--interface", "127.0.0.1"];
    args.extend_from_slice(&["rover1/distance_to", "\"far\"", "--timeout", "20"]);
    let out = Command::new(PULI).args(&args).output().unwrap();
    assert!(stderr(&out).contains("(f64, f64)"), "{}", stderr(&out));
    // The names that exist still work.
    let out = puli(port, &["set", "rover1/max_speed", "0.3"]);
    assert!(out.status.success(), "{}", stderr(&out));
    // --wait waits for a server that is not there (yet), up to --timeout.
    let (out, took) = call(&["--wait", "--timeout", "2"]);
    assert!(!out.status.success(), "{}", stderr(&out));
    assert!(took >= Duration::from_secs(2), "{took:?}");
    // And the shell, at its prompt or from a script.
    let script = "set rover1/max_sped 0.2\ncall rover1/distance '[3, 4]'\n";
    let started = std::time::Instant::now();
    let out = pulicast_tests::run_with_stdin(
        PULI,
        &["shell", "--port", &p, "--interface", "127.0.0.1"],
        script,
    );
    let err = stderr(&out);
    assert!(err.contains("did you mean rover1/max_speed?"), "{err}");
    assert!(err.contains("did you mean rover1/distance_to?"), "{err}");
    assert!(started.elapsed() < Duration::from_secs(12), "{err}");
    rover.stop();
}

/// A stranger floods a setting that holds a 30 kB value with pokes (8
/// bytes each, about 60 on the wire) from one socket: every confirmation
/// is multicast to the fleet, so each used to send 30 kB to everyone. The
/// confirmations are paced: over the flood they add up to at most twice
/// the pokes' bytes plus `Pacer`'s rate and capacity, and a real puliconf
/// pull during the flood still reads every setting.
#[test]
fn a_poke_flood_gets_at_most_twice_its_bytes_back_and_a_pull_still_works() {
    use pulicast_proto::setting::Pacer;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;
    let port = free_port();
    let p = port.to_string();
    let owner = node("controller", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let note = "x".repeat(30_000);
    let _note = owner.setting("note", note.clone()).unwrap();
    let _speed = owner.setting("max_speed", 1.5f64).unwrap();
    let observer = node("observer", port).start_blocking().unwrap();
    let out_bytes = Arc::new(AtomicUsize::new(0));
    let counted = Arc::clone(&out_bytes);
    let _watching = observer
        .channel("/rover1/.config/note")
        .watch_raw_with(move |m: pulicast::Message<pulicast::Bytes>| {
            counted.fetch_add(m.value.len(), Ordering::SeqCst);
        })
        .unwrap();

    let mut poke = Vec::new();
    pulicast_proto::wire::setting::Request::Poke.encode(&mut poke);
    let started = std::time::Instant::now();
    let flood = std::thread::spawn(move || {
        let mut stranger = pulicast_tests::Stranger::new(port);
        let mut sent = 0usize;
        // 5000 pokes a second for 4 s.
        while started.elapsed() < Duration::from_secs(4) {
            for _ in 0..50 {
                stranger.send("rover1/.config/note.r", &poke);
                sent += 1;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        sent * poke.len()
    });
    std::thread::sleep(Duration::from_millis(300));
    let pulled = puliconf_peer(&["pull", "--port", &p]).output(PY_WAIT);
    let in_bytes = flood.join().unwrap();
    // What waited goes out once the bucket holds it.
    std::thread::sleep(Duration::from_secs(2));
    let elapsed = started.elapsed().as_secs_f64();
    let out = out_bytes.load(Ordering::SeqCst) as f64;
    let bound = 2.0 * in_bytes as f64 + Pacer::RATE * elapsed + Pacer::CAPACITY;
    eprintln!(
        "{in_bytes} bytes of pokes in {elapsed:.1} s drew {out:.0} bytes of confirmations (bound {bound:.0})"
    );
    assert!(
        out <= bound,
        "{out} bytes of confirmations for {in_bytes} bytes of pokes"
    );
    let doc: toml_edit::DocumentMut = pulled.parse().unwrap();
    assert_eq!(doc["rover1/max_speed"].as_float(), Some(1.5));
    assert_eq!(doc["rover1/note"].as_str(), Some(note.as_str()), "{pulled}");
}

/// A stranger claims a real owner's setting with a fake 2.x heartbeat (one
/// 120-byte datagram every 100 ms): the claim is shown as one that never
/// answered, and locks nothing. Once it also forges confirmations from a
/// second socket it is an owner that answered: the setting is locked for
/// `puli config`, and the owner refuses the stranger's own raw request.
#[test]
fn a_strangers_claim_locks_nothing_until_it_answers_and_then_a_lock_holds_everywhere() {
    use pulicast_proto::wire::setting::RocAck;
    use pulicast_proto::wire::zcm::Primitive;
    let port = free_port();
    let owner = node("controller", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let speed = owner.setting("max_speed", 1.5f64).unwrap();
    let channel = "rover1/.config/max_speed";
    let request = "rover1/.config/max_speed.r";
    let _claim =
        pulicast_tests::Stranger::new(port).keep_announcing(Duration::from_secs(60), move |s| {
            s.heartbeat(
                "stranger",
                0x5eed,
                &[(channel, true, false), (request, false, true)],
            )
        });
    let listed = |port| {
        let out = puli(port, &["list", "--json"]);
        assert!(out.status.success(), "{}", stderr(&out));
        let rows: Value = serde_json::from_str(&stdout(&out)).unwrap();
        rows.as_array()
            .unwrap()
            .iter()
            .find(|r| r["name"] == "rover1/max_speed")
            .cloned()
            .unwrap()
    };
    let row = listed(port);
    assert_eq!(row["locked"], false, "{row}");
    assert_eq!(row["owners"], serde_json::json!(["controller"]), "{row}");
    assert_eq!(
        row["unanswered_claims"],
        serde_json::json!(["stranger"]),
        "{row}"
    );
    let text = puli(port, &["list"]);
    assert!(
        stdout(&text).contains("stranger (claims it, never answered)"),
        "{}",
        stdout(&text)
    );
    for value in ["1.6", "1.7", "1.8"] {
        let out = puli(port, &["set", "rover1/max_speed", value]);
        assert!(out.status.success(), "set {value}: {}", stderr(&out));
    }
    assert_eq!(speed.get(), Some(1.8));

    // Now the stranger answers for its claim, forging confirmations.
    let mut ack = Vec::new();
    RocAck {
        message: "",
        fingerprint: pulicast_proto::wire::zcm::fingerprint::DOUBLE_MSG,
        value: &1.8f64.to_be_bytes(),
    }
    .encode(&mut ack)
    .unwrap();
    let _answers = pulicast_tests::Stranger::new(port)
        .keep_announcing(Duration::from_secs(60), move |s| s.send(channel, &ack));
    std::thread::sleep(Duration::from_millis(500));
    let row = listed(port);
    assert_eq!(row["locked"], true, "{row}");
    let out = puli(port, &["set", "rover1/max_speed", "1.2"]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("locked"), "{}", stderr(&out));
    // The stranger's own raw request reaches the owner, which refuses it.
    let mut raw = pulicast_tests::Stranger::new(port);
    let mut wanted = Vec::new();
    Primitive::Double(0.1).encode(&mut wanted);
    for _ in 0..5 {
        raw.send(request, &wanted);
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(speed.get(), Some(1.8), "a locked setting was written");
}

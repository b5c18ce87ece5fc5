//! Distributed settings between nodes on loopback: a tool's requests are
//! checked and confirmed by the owner, on the 2.x puliconf wire. Every
//! wait is bounded.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod common;

use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use common::{free_port, node, WAIT};
use pulicast::{Bytes, Check, Error, Message};
use pulicast_proto::catalog::request;
use pulicast_proto::wire::setting::{Request, RocAck};
use pulicast_proto::wire::zcm::{fingerprint, Primitive};

/// A tool's side, by hand: sends requests, returns confirmations.
struct Tool {
    requests: pulicast::Channel,
    confirmations: mpsc::Receiver<Vec<u8>>,
    _sub: pulicast::CallbackSubscription,
    _node: pulicast::Node,
}

impl Tool {
    fn new(port: u16, confirmation: &str) -> Self {
        let node = node("tool", port).start_blocking().unwrap();
        let (tx, confirmations) = mpsc::channel();
        let sub = node
            .channel(&format!("/{confirmation}"))
            .subscribe_raw_with(move |m: Message<Bytes>| {
                let _ = tx.send(m.value.to_vec());
            })
            .unwrap();
        let requests = node.channel(&format!("/{confirmation}.r"));
        Self {
            requests,
            confirmations,
            _sub: sub,
            _node: node,
        }
    }

    /// Sends `request` until a confirmation comes (the first may go out
    /// before the owner's subscription is joined), and returns it.
    fn ask(&self, request: &[u8]) -> Vec<u8> {
        let start = Instant::now();
        loop {
            self.requests.publish_bytes(request).unwrap();
            if let Ok(c) = self.confirmations.recv_timeout(Duration::from_millis(200)) {
                return c;
            }
            assert!(start.elapsed() < WAIT, "no confirmation");
        }
    }
}

fn value(p: Primitive) -> Vec<u8> {
    let mut out = Vec::new();
    p.encode(&mut out);
    out
}

#[test]
fn a_tool_reads_and_changes_a_setting_within_its_checks() {
    let port = free_port();
    let owner = node("owner", port)
        .namespace("rover1")
        .start_blocking()
        .unwrap();
    let speed = owner
        .setting_checked("max_speed", 1.5f64, vec![Check::Range(0.0, 2.0)])
        .unwrap();
    assert_eq!(speed.name(), "rover1/max_speed");
    let seen = Arc::new(Mutex::new(Vec::new()));
    let watched = Arc::clone(&seen);
    speed.on_change(move |v| watched.lock().unwrap().push(v.copied()));

    let tool = Tool::new(port, "rover1/.config/max_speed");
    let poked = tool.ask(&request(Request::Poke));
    let ack = RocAck::decode(&poked).unwrap();
    assert_eq!(ack.fingerprint, fingerprint::DOUBLE_MSG);
    assert_eq!(ack.value, 1.5f64.to_be_bytes());
    assert_eq!(ack.message, "must be in [0, 2]");

    let accepted = tool.ask(&value(Primitive::Double(0.5)));
    let ack = RocAck::decode(&accepted).unwrap();
    assert_eq!((ack.message, ack.value), ("", &0.5f64.to_be_bytes()[..]));
    assert_eq!(speed.get(), Some(0.5));

    let refused = tool.ask(&value(Primitive::Double(9.0)));
    let ack = RocAck::decode(&refused).unwrap();
    assert_eq!(
        (ack.message, ack.value),
        ("must be in [0, 2]", &0.5f64.to_be_bytes()[..])
    );
    let wrong = tool.ask(&value(Primitive::String("fast".into())));
    assert!(RocAck::decode(&wrong)
        .unwrap()
        .message
        .contains("double_msg"));
    let garbage = tool.ask(&[1, 2, 3]);
    assert!(!RocAck::decode(&garbage).unwrap().message.is_empty());
    assert_eq!(speed.get(), Some(0.5));

    let reset = tool.ask(&request(Request::Reset));
    assert_eq!(RocAck::decode(&reset).unwrap().value, 1.5f64.to_be_bytes());
    // Watchers run on the owner's receive thread after the confirmation
    // left: the tool may hear it first.
    let start = Instant::now();
    while seen.lock().unwrap().len() < 2 {
        assert!(start.elapsed() < WAIT, "watchers not called");
        std::thread::sleep(Duration::from_millis(5));
    }
    let calls = seen.lock().unwrap().clone();
    assert_eq!(calls, [Some(0.5), Some(1.5)]);

    // The owner's own change is confirmed to the fleet too.
    assert!(speed.set(1.0).unwrap());
    let pushed = tool.confirmations.recv_timeout(WAIT).unwrap();
    assert_eq!(RocAck::decode(&pushed).unwrap().value, 1.0f64.to_be_bytes());
    assert!(matches!(speed.set(5.0), Err(Error::SettingRefused { .. })));
}

#[test]
fn bad_declarations_are_errors() {
    let port = free_port();
    let owner = node("owner", port).start_blocking().unwrap();
    assert!(matches!(
        owner.setting_checked("gain", 20i64, vec![Check::AtMost(10)]),
        Err(Error::SettingRefused { .. })
    ));
    assert!(matches!(
        owner.setting("bad name\n", 1i64),
        Err(Error::InvalidName { .. })
    ));
    let unset = owner.setting("mode", "auto".to_string()).unwrap();
    let tool = Tool::new(port, ".config/mode");
    let ack = tool.ask(&request(Request::Unset));
    assert!(!RocAck::decode(&ack).unwrap().is_set());
    assert_eq!(unset.get(), None);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn changes_can_be_awaited_and_end_with_the_setting() {
    let port = free_port();
    let owner = node("owner", port).start().await.unwrap();
    let gain = owner.setting("gain", 1i64).unwrap();
    let mut changes = gain.changes();
    gain.set(2).unwrap();
    gain.set(2).unwrap(); // no change, nothing to tell
    let got = tokio::time::timeout(WAIT, changes.changed()).await.unwrap();
    assert_eq!(got, Some(Some(2)));
    // A tool's request is a change too.
    let tool = std::thread::spawn(move || {
        let tool = Tool::new(port, ".config/gain");
        tool.ask(&request(Request::Unset))
    });
    let got = tokio::time::timeout(WAIT, changes.changed()).await.unwrap();
    assert_eq!(got, Some(None));
    let _ = tool.join().unwrap();
    drop(gain);
    let got = tokio::time::timeout(WAIT, changes.changed()).await.unwrap();
    assert_eq!(got, None);
}

/// `FleetSettings`: a client node lists the fleet's settings with what
/// they are, reads them and has them changed, unset and reset; refusals
/// come back with the owner's reason, a value of the wrong type never
/// leaves the client, and nothing is written to a setting two nodes own.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_node_lists_reads_and_changes_the_fleets_settings() {
    let port = free_port();
    let owner = node("controller", port)
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    let speed = owner
        .setting_builder("max_speed", 1.5f64)
        .describe("top speed of the base")
        .unit("m/s")
        .check(Check::Range(0.0, 2.0))
        .build()
        .unwrap();
    let _mode = owner
        .setting_checked(
            "mode",
            "auto".to_string(),
            vec![Check::OneOf(vec!["auto".into(), "manual".into()])],
        )
        .unwrap();
    let gain = owner.setting("arm/gain", 3i32).unwrap();
    let ratio = owner.setting("ratio", 0.5f32).unwrap();
    let client = node("tool", port).start().await.unwrap();
    let settings = client.fleet_settings();

    let all = settings.list(Duration::from_millis(500)).await;
    let names: Vec<&str> = all.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "rover1/arm/gain",
            "rover1/max_speed",
            "rover1/mode",
            "rover1/ratio"
        ]
    );
    let max = &all[1];
    assert_eq!(max.value_text().as_deref(), Some("1.5"));
    assert_eq!(max.type_name().as_deref(), Some("double_msg"));
    assert_eq!(
        max.about.as_deref(),
        Some("top speed of the base; unit: m/s; must be in [0, 2]")
    );
    // The same, as a tool builds a slider from it.
    let limits = max.limits();
    assert_eq!((limits.min, limits.max), (Some(0.0), Some(2.0)));
    assert_eq!(
        (limits.unit.as_str(), limits.description.as_str()),
        ("m/s", "top speed of the base")
    );
    assert_eq!(max.owners[0].node, "controller");
    assert!(!max.is_locked() && !max.is_stale());

    // Changes: by value (an integer taken as the setting's float), by text.
    let set = settings
        .set("rover1/max_speed", Primitive::I64(1), WAIT)
        .await
        .unwrap();
    assert_eq!(set.value_text().as_deref(), Some("1.0"));
    assert_eq!(speed.get(), Some(1.0));
    settings
        .set_text("/rover1/max_speed", "0.25", WAIT)
        .await
        .unwrap();
    assert_eq!(speed.get(), Some(0.25));
    // Names as a person types them are the same setting; a name no setting
    // can have fails at once, not after the wait.
    settings
        .set_text("rover1//max_speed", "0.25", WAIT)
        .await
        .unwrap();
    let asked = Instant::now();
    let long = Duration::from_secs(30);
    for bad in ["rover1/max\u{1}speed", "", "rover1/.."] {
        match settings.get(bad, long).await {
            Err(Error::InvalidName { .. }) => {}
            other => panic!("{bad:?}: expected a name error, got {other:?}"),
        }
        match settings.set_text(bad, "1", long).await {
            Err(Error::InvalidName { .. }) => {}
            other => panic!("{bad:?}: expected a name error, got {other:?}"),
        }
    }
    assert!(asked.elapsed() < long);
    settings
        .set_text("rover1/arm/gain", "-4", WAIT)
        .await
        .unwrap();
    settings
        .set_text("rover1/mode", "manual", WAIT)
        .await
        .unwrap();
    // An f32 setting holds the nearest f32: that is what is asked for.
    let set = settings
        .set_text("rover1/ratio", "0.1", WAIT)
        .await
        .unwrap();
    assert_eq!(ratio.get(), Some(0.1f32));
    assert_eq!(
        set.value_text().as_deref(),
        Some(format!("{:?}", f64::from(0.1f32)).as_str())
    );

    // Refusals carry the owner's reason; the value stays.
    match settings.set_text("rover1/max_speed", "9", WAIT).await {
        Err(Error::SettingRefused { name, reason }) => {
            assert_eq!(name, "rover1/max_speed");
            assert_eq!(reason, "must be in [0, 2]");
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    assert_eq!(speed.get(), Some(0.25));
    let wrong = settings.set_text("rover1/arm/gain", "fast", WAIT).await;
    assert!(
        matches!(&wrong, Err(Error::SettingRefused { reason, .. }) if reason.contains("32-bit integer")),
        "{wrong:?}"
    );
    let wrong = settings
        .set("rover1/arm/gain", Primitive::Double(0.5), WAIT)
        .await;
    assert!(
        matches!(wrong, Err(Error::SettingRefused { .. })),
        "{wrong:?}"
    );

    // Unset (which a range refuses: it needs a value) and reset.
    let no_value = settings.unset("rover1/max_speed", WAIT).await;
    assert!(
        matches!(no_value, Err(Error::SettingRefused { .. })),
        "{no_value:?}"
    );
    let unset = settings.unset("rover1/arm/gain", WAIT).await.unwrap();
    assert_eq!(unset.value_text().as_deref(), Some("unset"));
    assert_eq!(gain.get(), None);
    settings.reset("rover1/arm/gain", WAIT).await.unwrap();
    assert_eq!(gain.get(), Some(3));
    settings.reset("rover1/max_speed", WAIT).await.unwrap();
    assert_eq!(speed.get(), Some(1.5));

    // Unknown names end by the deadline with a clear error.
    let short = Duration::from_millis(300);
    let unknown = settings.get("rover1/nothing", short).await;
    assert!(
        matches!(&unknown, Err(Error::SettingUnavailable { reason, .. }) if reason.contains("no node owns it")),
        "{unknown:?}"
    );

    // A second owner of one name locks it: listed with both, not written.
    let twin = node("twin", port)
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    let _twin_mode = twin.setting("mode", "auto".to_string()).unwrap();
    let start = Instant::now();
    loop {
        settings.refresh();
        let snapshot = settings.snapshot();
        let mode = snapshot.iter().find(|s| s.name == "rover1/mode").unwrap();
        if mode.is_locked() {
            break;
        }
        assert!(start.elapsed() < WAIT, "the second owner was not seen");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let locked = settings.set_text("rover1/mode", "auto", WAIT).await;
    assert!(
        matches!(&locked, Err(Error::SettingUnavailable { reason, .. }) if reason.contains("locked")),
        "{locked:?}"
    );

    // The owner gone (its settings still held: it stopped, it did not
    // drop them): they end as unavailable, not as a hang.
    owner.stop();
    let gone = settings
        .get("rover1/max_speed", Duration::from_secs(3))
        .await;
    let start = Instant::now();
    let mut gone = gone;
    while gone.is_ok() {
        assert!(start.elapsed() < WAIT, "the owner's settings stayed");
        tokio::time::sleep(Duration::from_millis(50)).await;
        gone = settings.get("rover1/max_speed", short).await;
    }
    assert!(
        // It left: remembered as gone for a while, so `get` says why.
        matches!(&gone, Err(Error::SettingUnavailable { reason, .. }) if reason == "its owner is gone"),
        "{gone:?}"
    );
    drop((speed, gain, _mode, ratio));
}

/// `NodeBuilder::settings_file`: start-up values in the puliconf format
/// override coded defaults, and go through the same checks as any request:
/// out of range, read-only, another type or a structured value fail the
/// setting's creation, saying which file and why.
#[test]
fn a_settings_file_sets_start_up_values_through_the_checks() {
    let port = free_port();
    let dir = std::env::temp_dir().join(format!("pulicast-settings-file-{port}"));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("fleet.toml");
    std::fs::write(
        &file,
        r#""rover1/max_speed" = 0.8
"rover1/gain" = 7
"rover1/label" = nan
"rover1/too_fast" = 9.0
"rover1/locked" = 2
"rover1/typed" = "fast"
"rover1/structured" = { __msg_type__ = "pose", x = 1.0 }
"rover2/max_speed" = 1.9
"#,
    )
    .unwrap();
    let owner = node("owner", port)
        .namespace("rover1")
        .settings_file(&file)
        .start_blocking()
        .unwrap();
    let speed = owner
        .setting_checked("max_speed", 1.5f64, vec![Check::Range(0.0, 2.0)])
        .unwrap();
    assert_eq!(speed.get(), Some(0.8));
    let gain = owner.setting("gain", 1i16).unwrap();
    assert_eq!(gain.get(), Some(7));
    let label = owner.setting("label", "left".to_string()).unwrap();
    assert_eq!(label.get(), None);
    // Not in the file: the coded default.
    assert_eq!(owner.setting("other", 4i64).unwrap().get(), Some(4));

    let refused = |name: &str, result: pulicast::Result<pulicast::Setting<f64>>| match result {
        Err(Error::SettingRefused { name: n, reason }) => {
            assert_eq!(n, format!("rover1/{name}"));
            assert!(reason.contains("fleet.toml"), "{reason}");
            reason
        }
        other => panic!("{name}: expected a refusal, got {other:?}"),
    };
    let reason = refused(
        "too_fast",
        owner.setting_checked("too_fast", 1.0, vec![Check::Range(0.0, 2.0)]),
    );
    assert!(reason.contains("must be in [0, 2]"), "{reason}");
    let reason = refused(
        "locked",
        owner.setting_checked("locked", 1.0, vec![Check::ReadOnly]),
    );
    assert!(reason.contains("read-only"), "{reason}");
    let reason = refused("typed", owner.setting("typed", 1.0));
    assert!(
        reason.contains("not a value of type double_msg"),
        "{reason}"
    );
    let reason = refused("structured", owner.setting("structured", 1.0));
    assert!(reason.contains("structured message"), "{reason}");

    // A reset goes back to the file's value, not the coded one.
    let tool = Tool::new(port, "rover1/.config/max_speed");
    let ack = tool.ask(&value(Primitive::Double(0.3)));
    assert_eq!(RocAck::decode(&ack).unwrap().message, "");
    tool.ask(&request(Request::Reset));
    assert_eq!(speed.get(), Some(0.8));

    // A file that can't be read, or is not TOML, stops the node's start.
    let missing = node("n", port)
        .settings_file(dir.join("missing.toml"))
        .start_blocking();
    assert!(
        matches!(missing, Err(Error::InvalidConfig { .. })),
        "{missing:?}"
    );
    std::fs::write(dir.join("bad.toml"), "this is = = not toml").unwrap();
    let bad = node("n", port)
        .settings_file(dir.join("bad.toml"))
        .start_blocking();
    assert!(matches!(bad, Err(Error::InvalidConfig { .. })), "{bad:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// As an attacker on the link: garbage and oversized confirmations on a
/// setting's channel are dropped and counted, and the client keeps the
/// last good value; a namespace's key covers its settings, so a node
/// without it can neither read nor change them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_confirmations_are_dropped_and_keys_cover_settings() {
    let port = free_port();
    let owner = node("owner", port)
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    let _speed = owner.setting("max_speed", 1.5f64).unwrap();
    let client = node("tool", port).start().await.unwrap();
    let settings = client.fleet_settings();
    settings.get("rover1/max_speed", WAIT).await.unwrap();
    let drops_before: u64 = client.stats().dropped.iter().sum();

    let attacker = common::raw_sender();
    let channel = "rover1/.config/max_speed";
    let mut huge = Vec::new();
    RocAck {
        message: &"x".repeat(60_000),
        fingerprint: fingerprint::DOUBLE_MSG,
        value: &2.0f64.to_be_bytes(),
    }
    .encode(&mut huge)
    .unwrap();
    for (seq, payload) in [(1000u32, &b"not a roc_ack"[..]), (1001, &huge[..60_000])] {
        common::send_raw(
            &attacker,
            channel,
            port,
            &common::packet(channel, seq, payload),
        );
    }
    let start = Instant::now();
    while client.stats().dropped.iter().sum::<u64>() < drops_before + 2 {
        assert!(
            start.elapsed() < WAIT,
            "the hostile confirmations were not counted"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let now = settings.snapshot();
    let speed = now.iter().find(|s| s.name == "rover1/max_speed").unwrap();
    assert_eq!(speed.value_text().as_deref(), Some("1.5"));

    // A keyed namespace: its settings' channels are sealed like any other.
    let key = pulicast::Key::from_bytes([7; 32]);
    let keyed = node("keyed_owner", port)
        .namespace("rover2")
        .key("rover2", key.clone())
        .start()
        .await
        .unwrap();
    let mode = keyed.setting("mode", "auto".to_string()).unwrap();
    let short = Duration::from_millis(1500);
    let stranger = settings.set_text("rover2/mode", "manual", short).await;
    assert!(
        matches!(stranger, Err(Error::SettingUnavailable { .. })),
        "{stranger:?}"
    );
    assert_eq!(mode.get().as_deref(), Some("auto"));
    let member = node("member_tool", port)
        .key("rover2", key)
        .start()
        .await
        .unwrap();
    member
        .fleet_settings()
        .set_text("rover2/mode", "manual", WAIT)
        .await
        .unwrap();
    assert_eq!(mode.get().as_deref(), Some("manual"));
}

#[derive(serde::Serialize, serde::Deserialize, pulicast::Schema, Debug, Clone, PartialEq)]
struct Limits {
    lo: f64,
    hi: f64,
}

/// Our extension: a native `serde` + `Schema` value as a setting. It lives
/// under `.settings` (not where 2.x tools look), its type is announced on
/// the request channel, and clients read and write it as JSON; checks,
/// start-up files and refusals work as for primitives.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_native_setting_is_read_and_written_as_json() {
    use pulicast::Native;
    let port = free_port();
    let dir = std::env::temp_dir().join(format!("pulicast-native-setting-{port}"));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("start.toml");
    std::fs::write(&file, "\"rover1/limits\" = { lo = -1.0, hi = 1.0 }\n").unwrap();
    let owner = node("owner", port)
        .namespace("rover1")
        .settings_file(&file)
        .start()
        .await
        .unwrap();
    let limits = owner
        .setting_builder("limits", Native(Limits { lo: 0.0, hi: 2.0 }))
        .describe("steering limits")
        .check(Check::Custom(Box::new(|l: &Native<Limits>| {
            if l.0.lo <= l.0.hi {
                Ok(())
            } else {
                Err("lo must not exceed hi".into())
            }
        })))
        .build()
        .unwrap();
    assert_eq!(limits.get(), Some(Native(Limits { lo: -1.0, hi: 1.0 })));

    let client = node("tool", port).start().await.unwrap();
    let settings = client.fleet_settings();
    let seen = settings.get("rover1/limits", WAIT).await.unwrap();
    assert_eq!(seen.channel, "rover1/.settings/limits");
    assert_eq!(seen.type_name().as_deref(), Some("Limits"));
    assert_eq!(
        seen.value_json(),
        Some(serde_json::json!({"lo": -1.0, "hi": 1.0}))
    );

    let set = settings
        .set_text("rover1/limits", r#"{"lo": 0.5, "hi": 3.0}"#, WAIT)
        .await
        .unwrap();
    assert_eq!(
        set.value_json(),
        Some(serde_json::json!({"lo": 0.5, "hi": 3.0}))
    );
    assert_eq!(limits.get(), Some(Native(Limits { lo: 0.5, hi: 3.0 })));
    let refused = settings
        .set_json(
            "rover1/limits",
            serde_json::json!({"lo": 5.0, "hi": 3.0}),
            WAIT,
        )
        .await;
    assert!(
        matches!(&refused, Err(Error::SettingRefused { reason, .. }) if reason == "lo must not exceed hi"),
        "{refused:?}"
    );
    let not_limits = settings
        .set_text("rover1/limits", r#"{"lo": "x"}"#, WAIT)
        .await;
    assert!(
        matches!(&not_limits, Err(Error::SettingRefused { reason, .. }) if reason.contains("Limits")),
        "{not_limits:?}"
    );
    settings.reset("rover1/limits", WAIT).await.unwrap();
    assert_eq!(limits.get(), Some(Native(Limits { lo: -1.0, hi: 1.0 })));

    // Range checks need an order: a native value has none.
    let ranged = owner.setting_checked(
        "ranged",
        Native(Limits { lo: 0.0, hi: 1.0 }),
        vec![Check::AtLeast(Native(Limits { lo: 0.0, hi: 0.0 }))],
    );
    assert!(
        matches!(ranged, Err(Error::SettingRefused { .. })),
        "{ranged:?}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A node's fleet settings don't list the settings it owns itself; asking
/// them for one says so at once instead of "no node owns it" after the
/// whole wait.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nodes_own_setting_through_its_fleet_settings_says_why_at_once() {
    let port = free_port();
    let owner = node("owner", port).start().await.unwrap();
    let _speed = owner.setting("max_speed", 0.5f64).unwrap();
    let started = Instant::now();
    let err = owner
        .fleet_settings()
        .set("max_speed", Primitive::Double(0.3), Duration::from_secs(30))
        .await
        .unwrap_err();
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "waited out the deadline"
    );
    let text = err.to_string();
    assert!(matches!(err, Error::SettingUnavailable { .. }), "{text}");
    assert!(text.contains("this node owns it"), "{text}");
    owner.stop();
}

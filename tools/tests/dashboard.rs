//! The dashboard drawn into ratatui's test backend, from a live fleet.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::net::Ipv4Addr;
use std::time::{Duration, Instant};

use pulicast::{Node, Schema};
use pulicast_tests::free_port;
use pulicast_tools::dashboard::{render, Collector, Model, View};
use ratatui::backend::TestBackend;
use ratatui::crossterm::event::{KeyCode, KeyModifiers};
use ratatui::Terminal;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Schema, Clone, Copy)]
struct Pose {
    x: f64,
    y: f64,
}

fn screen(model: &Model) -> String {
    let mut terminal = Terminal::new(TestBackend::new(140, 30)).unwrap();
    terminal.draw(|f| render(f, model)).unwrap();
    let buffer = terminal.backend().buffer().clone();
    let mut text = String::new();
    for y in 0..buffer.area.height {
        for x in 0..buffer.area.width {
            text.push_str(buffer[(x, y)].symbol());
        }
        text.push('\n');
    }
    text
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_shows_the_fleet_names_rates_and_values() {
    let port = free_port();
    let node = |name: &str| Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST);
    let alpha = node("alpha").namespace("rover1").start().await.unwrap();
    let beta = node("beta").start().await.unwrap();
    let _sub = beta.channel("rover1/pose").subscribe::<Pose>().unwrap();
    let pose = alpha.channel("pose");
    // Until the test ends (it aborts the task), however long a busy
    // machine makes the waits below.
    let publisher = tokio::spawn(async move {
        for i in 0u32.. {
            let _ = pose.publish(&Pose {
                x: f64::from(i),
                y: 7.5,
            });
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    let sniffer = node("puli-sniffer").start().await.unwrap();
    let mut collector = Collector::new(&sniffer);
    let mut model = Model {
        port,
        ..Model::default()
    };
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        collector.refresh(&mut model);
        let rate = model
            .channels
            .iter()
            .find(|c| c.name == "rover1/pose")
            .map(|c| c.rate_hz);
        if rate.is_some_and(|r| r > 15.0)
            && model.last_values.contains_key("rover1/pose")
            && Instant::now() > deadline - Duration::from_secs(8)
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no rate for rover1/pose: {:?}",
            model.channels
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }

    let channels = screen(&model);
    assert!(channels.contains("rover1/pose"), "{channels}");
    assert!(channels.contains("Pose"), "{channels}");
    assert!(
        channels.contains("\"y\":7.5"),
        "last value as text: {channels}"
    );
    let rate = model
        .channels
        .iter()
        .find(|c| c.name == "rover1/pose")
        .unwrap()
        .rate_hz;
    assert!(channels.contains(&format!("{rate:.1}")), "{channels}");
    assert!((15.0..25.0).contains(&rate), "{rate}");

    // Back to the nodes, filter, open a channel.
    assert!(model.key(KeyCode::Left, KeyModifiers::NONE));
    assert_eq!(model.view, View::Nodes);
    let nodes = screen(&model);
    assert!(
        nodes.contains("alpha") && nodes.contains("beta") && nodes.contains("rover1"),
        "{nodes}"
    );
    for c in "alp".chars().chain(std::iter::once('\n')) {
        let code = if c == '\n' {
            KeyCode::Enter
        } else {
            KeyCode::Char(c)
        };
        if c == 'a' {
            model.key(KeyCode::Char('/'), KeyModifiers::NONE);
        }
        model.key(code, KeyModifiers::NONE);
    }
    let filtered = screen(&model);
    assert!(
        filtered.contains("alpha") && !filtered.contains("beta "),
        "{filtered}"
    );
    model.key(KeyCode::Esc, KeyModifiers::NONE);
    model.key(KeyCode::Tab, KeyModifiers::NONE);
    model.selected = model
        .channels
        .iter()
        .position(|c| c.name == "rover1/pose")
        .unwrap();
    model.key(KeyCode::Enter, KeyModifiers::NONE);
    assert_eq!(model.detail.as_deref(), Some("rover1/pose"));
    let deadline = Instant::now() + Duration::from_secs(5);
    while model.detail_lines.len() < 2 {
        assert!(Instant::now() < deadline, "no messages in the channel view");
        tokio::time::sleep(Duration::from_millis(200)).await;
        collector.refresh(&mut model);
    }
    let detail = screen(&model);
    assert!(
        detail.contains("rover1/pose #") && detail.contains("Pose: {"),
        "{detail}"
    );
    assert!(
        !model.key(KeyCode::Char('q'), KeyModifiers::NONE),
        "q quits"
    );
    publisher.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn five_hundred_channels_refresh_and_draw() {
    let port = free_port();
    let node = |name: &str| Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST);
    let busy = node("busy").start().await.unwrap();
    let channels: Vec<_> = (0..500)
        .map(|i| busy.channel(&format!("load/ch{i:03}")))
        .collect();
    let sniffer = node("puli-sniffer").start().await.unwrap();
    let mut collector = Collector::new(&sniffer);
    let mut model = Model::default();
    let deadline = Instant::now() + Duration::from_secs(20);
    while model.channels.len() < 500 || model.last_values.len() < 500 {
        for (i, c) in channels.iter().enumerate() {
            c.publish(&(i as i64)).unwrap();
        }
        collector.refresh(&mut model);
        assert!(
            Instant::now() < deadline,
            "{} channels, {} values",
            model.channels.len(),
            model.last_values.len()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // What one refresh costs with 500 channels (printed, not asserted: a
    // figure, not a timed test).
    let started = Instant::now();
    for _ in 0..10 {
        collector.refresh(&mut model);
        let _ = screen(&model);
    }
    eprintln!(
        "500 channels: refresh + draw {:?} per frame",
        started.elapsed() / 10
    );
    let text = screen(&model);
    assert!(
        text.contains("load/ch000") && text.contains("500 channels"),
        "{text}"
    );
}

/// Anyone can announce channels and send large messages: the sniffer
/// watches a bounded number of channels (and says how many it left out),
/// and keeps at most `LAST_BYTES` of each channel's last payload, so what
/// it holds stays bounded in bytes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_sniffer_watches_a_bounded_number_of_channels_and_keeps_bounded_values() {
    use parking_lot::Mutex;
    use pulicast_tools::sniff::{ChannelWatch, LAST_BYTES};
    use std::collections::HashMap;
    use std::sync::Arc;
    let port = free_port();
    let node = |name: &str| Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST);
    let busy = node("busy").start().await.unwrap();
    let channels: Vec<_> = (0..12)
        .map(|i| busy.channel(&format!("many/ch{i:02}")))
        .collect();
    let sniffer = node("puli-sniffer").start().await.unwrap();
    let last: Arc<Mutex<HashMap<String, pulicast::Bytes>>> = Arc::default();
    let mut watch = ChannelWatch::new(&sniffer).with_limit(8);
    watch.keep_last(Arc::clone(&last));
    let big = vec![7u8; 100_000];
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        for c in &channels {
            c.publish_bytes(&big).unwrap();
        }
        watch.watch_announced();
        let held = last.lock().len();
        if watch.unwatched() == 4 && held == 8 {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "{} unwatched, {held} values",
            watch.unwatched()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(watch.meters().len(), 8);
    for (channel, value) in last.lock().iter() {
        assert_eq!(value.len(), LAST_BYTES, "{channel}");
    }
}

/// The Settings view: every setting of the fleet with its value, type,
/// owner and what it is; hidden channels stay out of the channel view
/// until `h`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_shows_the_fleets_settings() {
    let port = free_port();
    let node = |name: &str| Node::new(name).port(port).interface(Ipv4Addr::LOCALHOST);
    let owner = node("controller")
        .namespace("rover1")
        .start()
        .await
        .unwrap();
    let _speed = owner
        .setting_builder("max_speed", 1.5f64)
        .describe("top speed")
        .unit("m/s")
        .check(pulicast::Check::Range(0.0, 2.0))
        .build()
        .unwrap();
    let sniffer = node("puli-sniffer").start().await.unwrap();
    let mut collector = Collector::new(&sniffer);
    let mut model = Model {
        port,
        ..Model::default()
    };
    let start = Instant::now();
    loop {
        collector.refresh(&mut model);
        let found = model
            .settings
            .iter()
            .any(|s| s.name == "rover1/max_speed" && s.about.is_some());
        if found && !model.channels.is_empty() {
            break;
        }
        assert!(start.elapsed() < Duration::from_secs(10), "no setting seen");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(model.key(KeyCode::Right, KeyModifiers::NONE));
    assert_eq!(model.view, View::Settings);
    let text = screen(&model);
    assert!(text.contains("rover1/max_speed"), "{text}");
    assert!(text.contains("1.5"), "{text}");
    assert!(text.contains("double_msg"), "{text}");
    assert!(text.contains("controller"), "{text}");
    assert!(
        text.contains("top speed; unit: m/s; must be in [0, 2]"),
        "{text}"
    );

    model.key(KeyCode::Left, KeyModifiers::NONE);
    assert_eq!(model.view, View::Channels);
    assert!(!screen(&model).contains(".config"));
    model.key(KeyCode::Char('h'), KeyModifiers::NONE);
    assert!(screen(&model).contains("rover1/.config/max_speed"));
}

//! `puli web` in a real browser (headless Chromium, see
//! [`harness`]), against a fleet the test starts: what an operator sees,
//! and what a node's name can't do to the page.
#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod harness;

use std::time::Duration;

use harness::Browser;
use pulicast_tests::{loopback_node, Peer};

const XSS: &str = "<img src=x onerror=alert(1)>";

/// One browser at a time: the machine may have two cores.
static ONE_BROWSER: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// `puli web` (the subcommand, which runs `puli-web`) on a fleet's port,
/// on any free TCP port; the address with the token it prints.
fn puli_web(udp: u16) -> (Peer, String) {
    let puli = pulicast_tests::workspace_bin("puli");
    let udp = udp.to_string();
    let web = Peer::spawn(
        &puli,
        &[
            "web",
            "--json",
            "--http-port",
            "0",
            "--port",
            &udp,
            "--interface",
            "127.0.0.1",
        ],
    );
    let printed = web
        .next_json(Duration::from_secs(30))
        .unwrap_or_else(|| panic!("puli web printed no address; stderr:\n{}", web.stderr()));
    let url = printed["url"].as_str().unwrap().to_string();
    assert!(url.starts_with("http://127.0.0.1:"), "{url}");
    (web, url)
}

/// A JavaScript string literal of `text`.
fn js(text: &str) -> String {
    serde_json::Value::from(text).to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_shows_the_fleet_live_and_a_name_made_of_markup_runs_nothing() {
    let _one = ONE_BROWSER.lock().await;
    let Some(browser) = Browser::start().await else {
        return;
    };
    let udp = pulicast_tests::free_port();
    let rover = loopback_node("rover1", udp).await;
    let controller = loopback_node("controller", udp).await;
    let _poses = controller
        .channel("rover1/pose")
        .subscribe::<f64>()
        .unwrap();
    let pose = rover.channel("rover1/pose");
    // 50 Hz, for at most a minute.
    let publishing = tokio::spawn(async move {
        for i in 0..3000 {
            let _ = pose.publish(&f64::from(i));
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    let (_web, url) = puli_web(udp);

    browser.client.goto(&url).await.unwrap();
    // The token swapped for a cookie: the address bar shows none.
    let shown = browser.client.current_url().await.unwrap();
    assert!(!shown.as_str().contains("token"), "{shown}");
    browser
        .wait_until(
            "rover1 and controller among the members",
            "const names = [...document.querySelectorAll('#members td.name')].map(e => e.textContent);
             return names.includes('rover1') && names.includes('controller');",
        )
        .await;
    browser
        .wait_until(
            "rover1/pose's rate, its publisher and subscriber",
            "const row = document.querySelector('#channels tr[data-channel=\"rover1/pose\"]');
             if (!row) return false;
             const rate = parseFloat(row.querySelector('td.rate').textContent);
             const cells = [...row.querySelectorAll('td')].map(e => e.textContent);
             return rate > 20 && rate < 80 && cells.includes('rover1') && cells.includes('controller');",
        )
        .await;
    // The graph links them: a member, a channel, a line of each kind.
    browser
        .wait_until(
            "the connection graph",
            "const labels = [...document.querySelectorAll('#graph text')].map(e => e.textContent);
             return labels.includes('rover1') && labels.includes('controller')
                 && labels.includes('rover1/pose')
                 && document.querySelectorAll('#graph path.pub').length >= 1
                 && document.querySelectorAll('#graph path.sub').length >= 1;",
        )
        .await;
    assert_eq!(
        browser
            .eval("return document.querySelector('#status').textContent")
            .await,
        "live"
    );

    // Anything that would run, were a name taken for markup, is caught:
    // an alert as a call, an error, an image.
    browser
        .eval(
            "window.__alerts = [];
             window.alert = (m) => window.__alerts.push(String(m));
             return true;",
        )
        .await;
    let markup = loopback_node(XSS, udp).await;
    let _markup_pose = markup.channel("elsewhere/pose");
    markup.channel("elsewhere/pose").publish(&0.5f64).unwrap();
    browser
        .wait_until(
            "the member named as markup, as text",
            &format!(
                "return [...document.querySelectorAll('#members td.name')]
                     .some(e => e.textContent === {xss});",
                xss = js(XSS)
            ),
        )
        .await;
    // In the graph too, as a text node's characters.
    browser
        .wait_until(
            "the member named as markup in the graph",
            &format!(
                "return [...document.querySelectorAll('#graph text')].some(e => e.textContent === {});",
                js(XSS)
            ),
        )
        .await;
    // Give an image's error, were there one, time to fire.
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        browser
            .eval("return document.querySelectorAll('img').length")
            .await,
        0
    );
    assert_eq!(
        browser.eval("return window.__alerts.length").await,
        0,
        "alert was called"
    );
    match browser.client.get_alert_text().await {
        Err(e) if e.is_no_such_alert() => {}
        other => panic!("an alert is open: {other:?}"),
    }

    let shot = browser.shot("fleet").await;
    let png = std::fs::read(&shot).unwrap();
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "{}",
        shot.display()
    );
    eprintln!("screenshot: {}", shot.display());

    publishing.abort();
    browser.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_channels_tab_plots_fields_and_a_field_named_as_markup_runs_nothing() {
    let _one = ONE_BROWSER.lock().await;
    let Some(browser) = Browser::start().await else {
        return;
    };
    let udp = pulicast_tests::free_port();
    let rover = loopback_node("rover1", udp).await;
    let markup = loopback_node("markup", udp).await;
    let pose = rover.channel("rover1/pose");
    let fields = markup.channel("markup/fields");
    // A map's keys are field names too: anyone may send any.
    let odd = std::collections::BTreeMap::from([(XSS.to_string(), 1.0f64), ("ok".into(), 2.0)]);
    // 50 Hz, for at most a minute.
    let publishing = tokio::spawn(async move {
        for i in 0..3000 {
            let t = f64::from(i) / 50.0;
            let p = pulicast_examples::Pose {
                x: t.cos(),
                y: t.sin(),
                heading: t,
            };
            let _ = pose.publish(&p);
            let _ = fields.publish(&odd);
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    let (_web, url) = puli_web(udp);
    browser.client.goto(&url).await.unwrap();
    browser
        .eval("document.querySelector('nav .tab[data-tab=channels]').click(); return true;")
        .await;
    browser
        .eval(
            "window.__alerts = [];
             window.alert = (m) => window.__alerts.push(String(m));
             return true;",
        )
        .await;
    for channel in ["rover1/pose", "markup/fields"] {
        let pick = format!(
            "const pick = document.getElementById('channel-pick');
             if (![...pick.options].some(o => o.value === {c})) return false;
             pick.value = {c};
             document.getElementById('watch-add').click();
             return true;",
            c = js(channel)
        );
        browser
            .wait_until(&format!("{channel} offered and watched"), &pick)
            .await;
        browser
            .wait_until(
                &format!("{channel}'s card"),
                &format!(
                    "return [...document.querySelectorAll('#watched .card')].some(c => c.dataset.channel === {});",
                    js(channel)
                ),
            )
            .await;
    }
    // Tick rover1/pose's x and y, and the map's field named as markup.
    let tick = |channel: &str, field: &str| {
        format!(
            "const card = [...document.querySelectorAll('#watched .card')].find(c => c.dataset.channel === {c});
             const box = card && [...card.querySelectorAll('input[type=checkbox]')].find(b => b.dataset.field === {f});
             if (!box) return false;
             if (!box.checked) box.click();
             return box.checked;",
            c = js(channel),
            f = js(field)
        )
    };
    for (channel, field) in [
        ("rover1/pose", "x"),
        ("rover1/pose", "y"),
        ("markup/fields", XSS),
    ] {
        browser
            .wait_until(
                &format!("{channel}'s field {field} ticked"),
                &tick(channel, field),
            )
            .await;
    }
    browser
        .wait_until(
            "60 points plotted",
            "return Number(document.getElementById('plot').dataset.points) > 60;",
        )
        .await;
    browser
        .wait_until(
            "the plot's legend, the markup as text",
            &format!(
                "const labels = [...document.querySelectorAll('#plot .u-legend .u-label')].map(e => e.textContent);
                 return labels.includes('rover1/pose x') && labels.includes('rover1/pose y')
                     && labels.includes('markup/fields ' + {});",
                js(XSS)
            ),
        )
        .await;
    // The newest message, as JSON text.
    browser
        .wait_until(
            "rover1/pose's latest message",
            "const card = [...document.querySelectorAll('#watched .card')].find(c => c.dataset.channel === 'rover1/pose');
             const last = JSON.parse(card.querySelector('pre.last').textContent || 'null');
             return last !== null && typeof last.heading === 'number';",
        )
        .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        browser
            .eval("return document.querySelectorAll('img').length")
            .await,
        0
    );
    assert_eq!(
        browser.eval("return window.__alerts.length").await,
        0,
        "alert was called"
    );
    match browser.client.get_alert_text().await {
        Err(e) if e.is_no_such_alert() => {}
        other => panic!("an alert is open: {other:?}"),
    }
    let shot = browser.shot("channels").await;
    eprintln!("screenshot: {}", shot.display());

    // Paused, the plot holds still while the data keeps coming.
    browser
        .eval("document.getElementById('pause').click(); return true;")
        .await;
    let held = browser
        .eval("return document.getElementById('plot').dataset.points")
        .await;
    tokio::time::sleep(Duration::from_millis(600)).await;
    assert_eq!(
        browser
            .eval("return document.getElementById('plot').dataset.points")
            .await,
        held
    );
    browser
        .eval("document.getElementById('pause').click(); return true;")
        .await;
    browser
        .wait_until(
            "the plot moving again",
            &format!(
                "return document.getElementById('plot').dataset.points !== {};",
                held
            ),
        )
        .await;

    publishing.abort();
    browser.close().await;
}

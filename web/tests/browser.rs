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

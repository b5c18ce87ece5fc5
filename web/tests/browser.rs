//! `puli web` in a real browser (headless Chromium, see
//! [`harness`]), against a fleet the test starts: what an operator sees,
//! and what a node's name can't do to the page.
#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

mod harness;

use std::time::Duration;

use fantoccini::actions::{InputSource, MouseActions, PointerAction, MOUSE_BUTTON_LEFT};
use harness::{demo_member, puli_config, puli_serving, Browser};
use pulicast_tests::{loopback_node, Peer};

const XSS: &str = "<img src=x onerror=alert(1)>";

/// One browser at a time: the machine may have two cores.
static ONE_BROWSER: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// `puli web` (the subcommand, which runs `puli-web`) on a fleet's port,
/// on any free TCP port; the address with the token it prints.
fn puli_web(udp: u16) -> (Peer, String) {
    let (web, printed) = puli_serving("web", udp, &["--http-port", "0"]);
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
    browser.nothing_ran().await;

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
    browser.nothing_ran().await;
    let shot = browser.shot("channels").await;
    eprintln!("screenshot: {}", shot.display());

    // Paused, the plot holds still while the data keeps coming.
    let drawn = "return [plot.data[0].length, plot.scales.x.max];";
    browser
        .eval("document.getElementById('pause').click(); return true;")
        .await;
    let held = browser.eval(drawn).await;
    tokio::time::sleep(Duration::from_millis(600)).await;
    assert_eq!(
        browser.eval(drawn).await,
        held,
        "the plot moved while paused"
    );
    browser
        .eval("document.getElementById('pause').click(); return true;")
        .await;
    browser
        .wait_until(
            "the plot moving again",
            &format!("return plot.scales.x.max > {};", held[1]),
        )
        .await;
    // A drag on the plot zooms in and pauses, so the zoom stays.
    let before = browser
        .eval("return plot.scales.x.max - plot.scales.x.min;")
        .await;
    let over = browser
        .client
        .find(fantoccini::Locator::Css("#plot .u-over"))
        .await
        .unwrap();
    let drag = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: over.clone(),
            duration: None,
            x: -100.0,
            y: 0.0,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_LEFT,
        })
        .then(PointerAction::MoveToElement {
            element: over,
            duration: Some(Duration::from_millis(200)),
            x: 100.0,
            y: 0.0,
        })
        .then(PointerAction::Up {
            button: MOUSE_BUTTON_LEFT,
        });
    browser.client.perform_actions(drag).await.unwrap();
    assert_eq!(
        browser
            .eval("return document.getElementById('pause').textContent")
            .await,
        "resume"
    );
    let zoomed = browser
        .eval("return plot.scales.x.max - plot.scales.x.min;")
        .await;
    assert!(
        zoomed.as_f64().unwrap() < before.as_f64().unwrap() / 2.0,
        "zoomed to {zoomed} of {before}"
    );
    tokio::time::sleep(Duration::from_millis(600)).await;
    assert_eq!(
        browser
            .eval("return plot.scales.x.max - plot.scales.x.min;")
            .await,
        zoomed,
        "the zoom held"
    );

    publishing.abort();
    browser.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_settings_tab_drives_the_demo_rovers_settings_and_shows_refusals_and_changes_made_elsewhere(
) {
    let _one = ONE_BROWSER.lock().await;
    let Some(browser) = Browser::start().await else {
        return;
    };
    let udp = pulicast_tests::free_port();
    let _rover = demo_member("rover", "rover1", udp);
    let (_web, url) = puli_web(udp);
    browser.client.goto(&url).await.unwrap();
    browser
        .eval("document.querySelector('nav .tab[data-tab=settings]').click(); return true;")
        .await;
    let row = |name: &str| {
        format!(
            "const row = [...document.querySelectorAll('#settings tbody tr')].find(r => r.dataset.setting === {});",
            js(name)
        )
    };
    // max_speed: a slider from its check's range, with its unit and what
    // it is, as the rover says.
    browser
        .wait_until(
            "rover1/max_speed as a slider over [0, 2] m/s",
            &format!(
                "{} if (!row) return false;
                 const r = row.querySelector('input[type=range]');
                 return !!r && r.min === '0' && r.max === '2'
                     && row.querySelector('td.unit').textContent === 'm/s'
                     && row.querySelector('td.about').textContent.includes('top speed')
                     && row.querySelector('td.owner').textContent === 'rover1'
                     && row.querySelector('td.value').dataset.value === '0.5';",
                row("rover1/max_speed")
            ),
        )
        .await;
    // Moved as an operator moves it (the change comes when it is let go).
    browser
        .eval(&format!(
            "{} const r = row.querySelector('input[type=range]');
             r.value = '1.5';
             r.dispatchEvent(new Event('input'));
             r.dispatchEvent(new Event('change'));
             return true;",
            row("rover1/max_speed")
        ))
        .await;
    browser
        .wait_until(
            "the owner's confirmation of 1.5",
            &format!(
                "{} return row.querySelector('td.status-cell').textContent === 'set: 1.5';",
                row("rover1/max_speed")
            ),
        )
        .await;
    let got = puli_config(udp, &["get", "rover1/max_speed"]).await;
    assert_eq!(got["value"], "1.5", "{got}");

    // A value its check refuses: the owner's reason, and the owner's value
    // kept on the slider.
    browser
        .eval("askSetting('rover1/max_speed', 'set', { text: '5' }); return true;")
        .await;
    browser
        .wait_until(
            "the owner's refusal of 5",
            &format!(
                "{} const status = row.querySelector('td.status-cell');
                 return status.classList.contains('refused') && status.textContent.startsWith('refused: ')
                     && status.textContent.includes('2');",
                row("rover1/max_speed")
            ),
        )
        .await;
    let got = puli_config(udp, &["get", "rover1/max_speed"]).await;
    assert_eq!(got["value"], "1.5", "{got}");

    // mode: a choice of its one-of, changed from the page...
    browser
        .wait_until(
            "rover1/mode as a choice of drive and stop",
            &format!(
                "{} if (!row) return false;
                 const s = row.querySelector('select');
                 return !!s && [...s.options].map(o => o.value).join() === 'drive,stop' && s.value === 'drive';",
                row("rover1/mode")
            ),
        )
        .await;
    browser
        .eval(&format!(
            "{} const s = row.querySelector('select'); s.value = 'stop'; s.dispatchEvent(new Event('change')); return true;",
            row("rover1/mode")
        ))
        .await;
    browser
        .wait_until(
            "mode set to stop",
            &format!(
                "{} return row.querySelector('td.status-cell').textContent === 'set: stop';",
                row("rover1/mode")
            ),
        )
        .await;
    assert_eq!(
        puli_config(udp, &["get", "rover1/mode"]).await["value"],
        "stop"
    );
    // ...and from elsewhere: `puli config set` shows on the page.
    puli_config(udp, &["set", "rover1/mode", "drive"]).await;
    let started = std::time::Instant::now();
    browser
        .wait_until(
            "mode back to drive, changed elsewhere",
            &format!(
                "{} return row.querySelector('select').value === 'drive'
                     && row.querySelector('td.value').dataset.value === 'drive';",
                row("rover1/mode")
            ),
        )
        .await;
    eprintln!(
        "a change made elsewhere showed {:?} after `puli config set` returned",
        started.elapsed()
    );
    let shot = browser.shot("settings").await;
    eprintln!("screenshot: {}", shot.display());
    browser.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_services_tab_calls_streams_progress_cancels_shows_faults_keeps_buttons_and_publishes()
{
    let _one = ONE_BROWSER.lock().await;
    let Some(browser) = Browser::start().await else {
        return;
    };
    let udp = pulicast_tests::free_port();
    let _rover = demo_member("rover", "rover1", udp);
    let port = udp.to_string();
    let server = Peer::spawn(
        pulicast_tests::workspace_bin("puli"),
        &[
            "serve",
            "--name",
            "srv",
            "--namespace",
            "srv",
            "--step-ms",
            "100",
            "--for",
            "120",
            "--port",
            &port,
            "--interface",
            "127.0.0.1",
        ],
    );
    server.wait_ready(Duration::from_secs(30));
    // A subscriber of commands, for the page to publish to.
    let listener = loopback_node("listener", udp).await;
    let mut commands = listener
        .channel("rover1/cmd_pose")
        .subscribe::<pulicast_examples::Pose>()
        .unwrap();
    let (_web, url) = puli_web(udp);
    browser.client.goto(&url).await.unwrap();
    browser
        .eval(
            "window.__alerts = [];
             window.alert = (m) => window.__alerts.push(String(m));
             document.querySelector('nav .tab[data-tab=services]').click();
             return true;",
        )
        .await;
    let card = |name: &str| {
        format!(
            "const card = [...document.querySelectorAll('#service-cards .card')].find(c => c.dataset.service === {});",
            js(name)
        )
    };
    let out = |name: &str| {
        format!(
            "{} if (!card) return false; const out = [...card.querySelectorAll('.call-out div')].map(d => d.textContent);",
            card(name)
        )
    };
    // distance_to: a form of its request (f64, f64), a call, the reply.
    browser
        .wait_until(
            "rover1/distance_to's form of two numbers",
            &format!(
                "{} if (!card) return false;
                 const inputs = card.querySelectorAll('.form input[type=number]');
                 return inputs.length === 2 && card.querySelector('.note').textContent === '(f64, f64) → f64';",
                card("rover1/distance_to")
            ),
        )
        .await;
    browser
        .eval(&format!(
            "{} const inputs = card.querySelectorAll('.form input[type=number]');
             inputs[0].value = '3'; inputs[1].value = '4';
             card.querySelector('button.call').click();
             return true;",
            card("rover1/distance_to")
        ))
        .await;
    browser
        .wait_until(
            "distance_to's reply",
            &format!(
                "{} return out.includes('reply 5');",
                out("rover1/distance_to")
            ),
        )
        .await;

    // count: progress streams in; cancel stops it.
    browser
        .wait_until(
            "srv/count's form",
            &format!(
                "{} return !!card && !!card.querySelector('.form input[type=number]');",
                card("srv/count")
            ),
        )
        .await;
    browser
        .eval(&format!(
            "{} card.querySelector('.form input[type=number]').value = '1000';
             card.querySelector('button.call').click();
             return true;",
            card("srv/count")
        ))
        .await;
    browser
        .wait_until(
            "three progress messages of count",
            &format!(
                "{} return out.filter(l => l.startsWith('progress ')).length >= 3;",
                out("srv/count")
            ),
        )
        .await;
    browser
        .eval(&format!(
            "{} card.querySelector('button.cancel').click(); return true;",
            card("srv/count")
        ))
        .await;
    browser
        .wait_until(
            "count cancelled",
            &format!("{} return out.includes('cancelled');", out("srv/count")),
        )
        .await;
    let lines = format!("{} return out;", out("srv/count"));
    let after_cancel = browser.eval(&lines).await;
    tokio::time::sleep(Duration::from_millis(600)).await;
    assert_eq!(
        browser.eval(&lines).await,
        after_cancel,
        "progress after the cancel"
    );

    // plan: a fault shows its code and message.
    browser
        .wait_until(
            "srv/plan's form",
            &format!(
                "{} return !!card && !!card.querySelector('.form input[data-field=steps]');",
                card("srv/plan")
            ),
        )
        .await;
    browser
        .eval(&format!(
            "{} card.querySelector('.form textarea[data-field=goal]').value = '[1, 2]';
             card.querySelector('.form input[data-field=steps]').value = '20000';
             card.querySelector('button.call').click();
             return true;",
            card("srv/plan")
        ))
        .await;
    browser
        .wait_until(
            "plan's fault, code and message",
            &format!(
                "{} return out.some(l => l.startsWith('fault 1001: 20000 steps is too many (at srv)'));",
                out("srv/plan")
            ),
        )
        .await;

    // echo: a reply made of markup is text.
    browser
        .wait_until(
            "srv/echo's form",
            &format!(
                "{} return !!card && !!card.querySelector('.form input[type=text]');",
                card("srv/echo")
            ),
        )
        .await;
    browser
        .eval(&format!(
            "{} card.querySelector('.form input[type=text]').value = {};
             card.querySelector('button.call').click();
             return true;",
            card("srv/echo"),
            js(XSS)
        ))
        .await;
    browser
        .wait_until(
            "echo's reply, as text",
            &format!(
                "{} return out.includes('reply ' + {});",
                out("srv/echo"),
                js(&serde_json::Value::from(XSS).to_string())
            ),
        )
        .await;

    // A saved button outlives the page, and calls.
    browser
        .eval(&format!(
            "{} card.querySelector('button.save').click(); return true;",
            card("rover1/distance_to")
        ))
        .await;
    browser.client.goto(&url).await.unwrap();
    browser
        .eval(
            "window.__alerts = [];
             window.alert = (m) => window.__alerts.push(String(m));
             document.querySelector('nav .tab[data-tab=services]').click();
             return true;",
        )
        .await;
    browser
        .wait_until(
            "the saved button, after a reload",
            "const run = document.querySelector('#buttons .saved button.run');
             if (!run) return false;
             run.click();
             return run.textContent === 'rover1/distance_to [3,4]';",
        )
        .await;
    browser
        .wait_until(
            "the saved button's reply",
            "return [...document.querySelectorAll('#buttons .saved .call-out div')].some(d => d.textContent === 'reply 5');",
        )
        .await;
    let shot = browser.shot("services").await;
    eprintln!("screenshot: {}", shot.display());

    // Publish: JSON into the channel's announced type, received typed.
    browser
        .eval("document.querySelector('nav .tab[data-tab=channels]').click(); return true;")
        .await;
    browser
        .wait_until(
            "rover1/cmd_pose's form",
            "const pick = document.getElementById('publish-pick');
             if (![...pick.options].some(o => o.value === 'rover1/cmd_pose')) return false;
             if (pick.value !== 'rover1/cmd_pose') {
                 pick.value = 'rover1/cmd_pose';
                 pick.dispatchEvent(new Event('change'));
             }
             return !!document.querySelector('#publish-form input[data-field=heading]');",
        )
        .await;
    browser
        .eval(
            "const form = document.getElementById('publish-form');
             form.querySelector('input[data-field=x]').value = '1.5';
             form.querySelector('input[data-field=y]').value = '-2';
             form.querySelector('input[data-field=heading]').value = '0.25';
             document.getElementById('publish-send').click();
             return true;",
        )
        .await;
    let got = tokio::time::timeout(Duration::from_secs(30), commands.recv())
        .await
        .expect("the page's pose in time")
        .expect("a pose");
    assert_eq!(
        got.value,
        pulicast_examples::Pose {
            x: 1.5,
            y: -2.0,
            heading: 0.25
        }
    );
    browser
        .wait_until(
            "the page saying it published",
            "return document.getElementById('publish-status').textContent === 'published on rover1/cmd_pose';",
        )
        .await;
    browser.nothing_ran().await;
    browser.close().await;
}

/// A web site of the test's own on loopback: any page it is asked for is
/// a blank one, with no policy of its own (so its script may open any
/// WebSocket the browser allows). Its address.
async fn a_site() -> String {
    let listener = tokio::net::TcpListener::bind(("127.0.0.1", 0))
        .await
        .unwrap();
    let port = listener.local_addr().unwrap().port();
    tokio::spawn(async move {
        while let Ok((mut stream, _)) = listener.accept().await {
            tokio::spawn(async move {
                use tokio::io::{AsyncReadExt, AsyncWriteExt};
                let mut request = [0u8; 4096];
                let _ = stream.read(&mut request).await;
                let page = "<!doctype html><title>another site</title><p>another site";
                let answer = format!(
                    "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{page}",
                    page.len()
                );
                let _ = stream.write_all(answer.as_bytes()).await;
            });
        }
    });
    format!("http://127.0.0.1:{port}")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_page_reaches_the_foxglove_gate_only_from_an_allowed_origin_and_never_the_server_behind_it(
) {
    let _one = ONE_BROWSER.lock().await;
    let Some(browser) = Browser::start().await else {
        return;
    };
    let (allowed, other) = (a_site().await, a_site().await);
    let (_server, said) = puli_serving(
        "foxglove",
        pulicast_tests::free_port(),
        &["--ws-port", "0", "--allow-origin", &allowed],
    );
    let inner = said["foxglove_inner_port"].as_u64().unwrap();
    assert!(
        puli_web::foxglove_server::BROWSERS_REFUSE.contains(&u16::try_from(inner).unwrap()),
        "{said}"
    );
    let token = said["foxglove_token"].as_str().unwrap();
    let gate = said["foxglove_url"].as_str().unwrap().to_string();
    // From a page of `site` in a real browser: whether a WebSocket to
    // `url` opens.
    let attempt = |site: String, url: String| {
        let browser = &browser;
        async move {
            browser.client.goto(&site).await.unwrap();
            browser
                .client
                .execute_async(
                    "const [url, done] = arguments;
                     const ws = new WebSocket(url, ['foxglove.sdk.v1']);
                     ws.onopen = () => { ws.close(); done('open'); };
                     ws.onerror = () => done('refused');
                     setTimeout(() => done('no answer'), 10000);",
                    vec![serde_json::Value::from(url)],
                )
                .await
                .unwrap()
        }
    };
    // The gate, with the token, from the allowed site: open.
    assert_eq!(attempt(allowed.clone(), gate.clone()).await, "open");
    // The server behind it, even with the token, from the same page: the
    // browser won't (a bad port), so no page goes round the gate...
    let behind = format!("ws://127.0.0.1:{inner}/?token={token}");
    assert_eq!(attempt(allowed.clone(), behind).await, "refused");
    // ...for the port alone: the same server, forwarded from an ordinary
    // port, is open to the same page (what the bad port keeps out).
    let forward = tokio::net::TcpListener::bind(("127.0.0.1", 0))
        .await
        .unwrap();
    let ordinary = forward.local_addr().unwrap().port();
    let forwarding = tokio::spawn(async move {
        while let Ok((mut from, _)) = forward.accept().await {
            let inner = u16::try_from(inner).unwrap();
            tokio::spawn(async move {
                if let Ok(mut to) = tokio::net::TcpStream::connect(("127.0.0.1", inner)).await {
                    let _ = tokio::io::copy_bidirectional(&mut from, &mut to).await;
                }
            });
        }
    });
    let around = format!("ws://127.0.0.1:{ordinary}/");
    assert_eq!(attempt(allowed, around).await, "open");
    forwarding.abort();
    // The gate from another site's page: refused, token or not.
    assert_eq!(attempt(other, gate).await, "refused");
    browser.close().await;
}

//! What the web tests share: the demo fleet's members, `puli config`, and
//! a real browser.
//!
//! The browser is Debian's `chromium`, driven through
//! `chromedriver` over WebDriver (fantoccini). `.ci/run` installs both and
//! sets `PULICAST_REQUIRE_BROWSER`, so there a missing browser fails the
//! test; elsewhere it is skipped, saying so.
//!
//! The browser is held to loopback: host names resolve to nothing but
//! `localhost`, and whatever it would fetch elsewhere goes to a proxy on
//! loopback that isn't there. Chromium's own background traffic
//! (updates, sync, metrics) is turned off besides.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::{Client, ClientBuilder};
use pulicast_tests::Peer;
use serde_json::{json, Value};

/// How long the page may take to show what the test waits for.
pub const WAIT: Duration = Duration::from_secs(30);

/// Where screenshots go: `target/tmp/web/` (the artifacts of a run).
pub fn artifacts() -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web");
    std::fs::create_dir_all(&dir).expect("the artifacts directory");
    dir
}

pub fn found(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(program))
        .find(|p| p.is_file())
}

/// A chromedriver of ours and a browser session through it; both end with
/// [`Browser::close`] (or, on a panic, when dropped: chromedriver is
/// killed by its handle, and takes its browser along).
pub struct Browser {
    driver: Child,
    home: PathBuf,
    pub client: Client,
}

impl Browser {
    /// A headless Chromium, or `None` (skipped) where none is installed.
    pub async fn start() -> Option<Browser> {
        // Debian's `chromium` is a wrapper script; the binary is beside it.
        let chromium = [Path::new("/usr/lib/chromium/chromium").to_path_buf()]
            .into_iter()
            .find(|p| p.is_file())
            .or_else(|| found("chromium"));
        let driver = found("chromedriver");
        let (Some(chromium), Some(driver)) = (chromium, driver) else {
            assert!(
                std::env::var_os("PULICAST_REQUIRE_BROWSER").is_none(),
                "chromium and chromedriver are required here (PULICAST_REQUIRE_BROWSER) \
                 and not installed"
            );
            eprintln!("skipped: chromium or chromedriver is not installed (.ci/run installs them)");
            return None;
        };
        let port = pulicast_tests::free_tcp_port();
        let home = artifacts().join(format!("home-{port}"));
        std::fs::create_dir_all(&home).expect("the browser's home");
        let log = home.join("chromedriver.log");
        let mut driver = Command::new(driver);
        // A process group of its own, which the browser's processes join:
        // all of them are stopped together, however the test ends.
        std::os::unix::process::CommandExt::process_group(&mut driver, 0);
        let mut driver = driver
            // Nothing written to the machine's own home (profile, crash
            // reports, caches): all of it under target/.
            .env("HOME", &home)
            .env("XDG_CONFIG_HOME", home.join(".config"))
            .env("XDG_CACHE_HOME", home.join(".cache"))
            .arg(format!("--port={port}"))
            .arg(format!("--log-path={}", log.display()))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let profile = home.join("profile");
        let mut capabilities = serde_json::Map::new();
        capabilities.insert(
            "goog:chromeOptions".into(),
            json!({
                "binary": chromium,
                "args": [
                    "--headless=new",
                    "--no-sandbox",
                    "--disable-gpu",
                    "--disable-dev-shm-usage",
                    "--no-first-run",
                    "--no-default-browser-check",
                    "--disable-background-networking",
                    "--disable-component-update",
                    "--disable-sync",
                    "--disable-extensions",
                    "--disable-default-apps",
                    "--disable-domain-reliability",
                    "--no-pings",
                    "--disable-breakpad",
                    "--disable-crash-reporter",
                    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1",
                    "--proxy-server=127.0.0.1:9",
                    format!("--user-data-dir={}", profile.display()),
                    "--window-size=1280,1000",
                ],
            }),
        );
        // An alert left open must not answer the test's next command: the
        // test asks for it itself.
        capabilities.insert("unhandledPromptBehavior".into(), json!("ignore"));
        let url = format!("http://127.0.0.1:{port}");
        let started = Instant::now();
        let client = loop {
            let connector = hyper_util::client::legacy::connect::HttpConnector::new();
            match ClientBuilder::new(connector)
                .capabilities(capabilities.clone())
                .connect(&url)
                .await
            {
                Ok(client) => break client,
                Err(e) if started.elapsed() < WAIT => {
                    let _ = e;
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
                Err(e) => {
                    let _ = driver.kill();
                    panic!(
                        "no browser session through chromedriver in {WAIT:?}: {e}; its log: {}",
                        log.display()
                    );
                }
            }
        };
        Some(Browser {
            driver,
            home,
            client,
        })
    }

    /// Evaluates `script` (a function body: `return ...`) in the page.
    pub async fn eval(&self, script: &str) -> Value {
        self.client
            .execute(script, vec![])
            .await
            .unwrap_or_else(|e| panic!("running {script:?} in the page: {e}"))
    }

    /// Asserts that nothing the network sent ran as markup or script: no
    /// `img` element in the page, `alert` never called (the page's hook
    /// counts calls) and no dialog open. Waits half a second first, for
    /// an image's error to fire were there one.
    pub async fn nothing_ran(&self) {
        tokio::time::sleep(Duration::from_millis(500)).await;
        assert_eq!(
            self.eval("return document.querySelectorAll('img').length")
                .await,
            0,
            "an img element in the page"
        );
        assert_eq!(
            self.eval("return window.__alerts.length").await,
            0,
            "alert was called"
        );
        match self.client.get_alert_text().await {
            Err(e) if e.is_no_such_alert() => {}
            other => panic!("an alert is open: {other:?}"),
        }
    }

    /// Waits until `script` returns true, or panics after [`WAIT`], naming
    /// `what` and taking a screenshot of how the page looked.
    pub async fn wait_until(&self, what: &str, script: &str) {
        let started = Instant::now();
        while started.elapsed() < WAIT {
            if self.eval(script).await == Value::Bool(true) {
                return;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let shot = self.shot("failed").await;
        panic!(
            "the page did not show {what} in {WAIT:?} (screenshot: {})",
            shot.display()
        );
    }

    /// A screenshot of the page, kept as `target/tmp/web/<name>.png`.
    pub async fn shot(&self, name: &str) -> PathBuf {
        let png = self.client.screenshot().await.expect("a screenshot");
        let path = artifacts().join(format!("{name}.png"));
        std::fs::write(&path, &png).expect("the screenshot written");
        path
    }

    /// Ends the session (the browser goes), then chromedriver.
    pub async fn close(self) {
        let client = self.client.clone();
        let _ = tokio::time::timeout(Duration::from_secs(10), client.close()).await;
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // The process group chromedriver leads (ours: made for it, and
        // the browser's processes are in it), by its ID.
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", self.driver.id())])
            .status();
        let _ = self.driver.wait();
        // Kept after a failure, for chromedriver's log.
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.home);
        }
    }
}

/// `puli SUBCOMMAND --json ARGS...` on the fleet at `udp` (loopback),
/// and the JSON line it prints once it serves; panics with its stderr if
/// it prints none within 30 s.
pub fn puli_serving(subcommand: &str, udp: u16, args: &[&str]) -> (Peer, Value) {
    let udp = udp.to_string();
    let mut all = vec![
        subcommand,
        "--json",
        "--port",
        &udp,
        "--interface",
        "127.0.0.1",
    ];
    all.extend_from_slice(args);
    let served = Peer::spawn(pulicast_tests::workspace_bin("puli"), &all);
    let said = served
        .next_json(Duration::from_secs(30))
        .unwrap_or_else(|| {
            panic!(
                "puli {subcommand} printed no address; stderr:\n{}",
                served.stderr()
            )
        });
    (served, said)
}

/// `puli config ARGS --json` on the fleet at `udp`, its JSON.
pub async fn puli_config(udp: u16, args: &[&str]) -> serde_json::Value {
    let mut all: Vec<String> = vec!["config".into(), "--json".into(), "--wait".into()];
    all.extend(args.iter().map(|a| a.to_string()));
    all.extend([
        "--port".into(),
        udp.to_string(),
        "--interface".into(),
        "127.0.0.1".into(),
    ]);
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new(pulicast_tests::workspace_bin("puli"))
            .args(&all)
            .env_remove(pulicast::KEYS_ENV)
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    assert!(
        out.status.success(),
        "puli config {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// A member of the demo fleet (`examples/rover_demo --role ROLE`), on
/// loopback at `udp`, for two minutes at most.
pub fn demo_member(role: &str, name: &str, udp: u16) -> Peer {
    let udp = udp.to_string();
    Peer::spawn(
        pulicast_tests::workspace_bin("examples/rover_demo"),
        &[
            "--role",
            role,
            "--name",
            name,
            "--secs",
            "120",
            "--port",
            &udp,
            "--interface",
            "127.0.0.1",
        ],
    )
}

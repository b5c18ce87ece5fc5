//! Helpers for tests that run nodes in other processes: free ports, child
//! processes that announce readiness, and the Pulicast 2.x reference peer.
//!
//! Children are started with piped output and killed (by their own handle) when
//! the [`Peer`] that owns them is dropped, so a failing test leaves nothing
//! running.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// A UDP port that is free right now and outside the ephemeral range, so
/// parallel tests don't hear each other and no socket takes it by chance.
pub fn free_port() -> u16 {
    pulicast::unused_port().expect("an unused port")
}

/// A node of ours pinned to loopback, started: what most tests here run
/// beside the processes they start.
pub async fn loopback_node(name: &str, port: u16) -> pulicast::Node {
    pulicast::Node::new(name)
        .port(port)
        .interface(std::net::Ipv4Addr::LOCALHOST)
        .start()
        .await
        .expect("node starts")
}

/// A TCP port on loopback that is free right now (for a Zenoh link).
pub fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind((std::net::Ipv4Addr::LOCALHOST, 0))
        .and_then(|l| l.local_addr())
        .expect("a free TCP port")
        .port()
}

/// Runs `program` with `args` and `input` on its standard input (then
/// closed), without keys from the environment, and waits for its end.
pub fn run_with_stdin(
    program: impl AsRef<std::ffi::OsStr>,
    args: &[&str],
    input: &str,
) -> std::process::Output {
    use std::io::Write;
    let mut child = Command::new(program)
        .args(args)
        .env_remove(pulicast::KEYS_ENV)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawning");
    let mut stdin = child.stdin.take().expect("piped stdin");
    stdin.write_all(input.as_bytes()).expect("writing stdin");
    drop(stdin);
    child.wait_with_output().expect("waiting")
}

/// The repository's root directory.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ lives in the repository")
        .to_path_buf()
}

/// A binary of another package of this workspace (`puli`,
/// `examples/rover_demo`), from the target directory this test was built
/// into. `cargo test --workspace` builds every package's binaries and
/// examples before it runs any test; a test run of one package alone does
/// not, which the panic says.
pub fn workspace_bin(relative: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    // target/<profile>/deps/<test>: the binaries are in target/<profile>.
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("a test runs from target/<profile>/deps");
    let path = dir.join(relative);
    assert!(
        path.exists(),
        "{} is not built: `cargo test --workspace` builds it, as does \
         `cargo build --workspace --bins --examples`",
        path.display()
    );
    path
}

/// A child process whose stdout lines and `READY` line are collected.
pub struct Peer {
    child: Child,
    lines: Receiver<String>,
    ready: Receiver<String>,
    stderr_tail: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    label: String,
}

impl Peer {
    /// Starts `program` with `args`.
    pub fn spawn(program: impl AsRef<std::ffi::OsStr>, args: &[&str]) -> Peer {
        let label = format!("{} {}", program.as_ref().to_string_lossy(), args.join(" "));
        let mut child = Command::new(program)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap_or_else(|e| panic!("spawning {label}: {e}"));
        let (line_tx, lines) = mpsc::channel();
        let stdout = child.stdout.take().expect("piped stdout");
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if line_tx.send(line).is_err() {
                    break;
                }
            }
        });
        let (ready_tx, ready) = mpsc::channel();
        let stderr = child.stderr.take().expect("piped stderr");
        let stderr_tail = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let tail = std::sync::Arc::clone(&stderr_tail);
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(info) = line.strip_prefix("READY ") {
                    let _ = ready_tx.send(info.to_string());
                }
                if let Ok(mut tail) = tail.lock() {
                    tail.push(line);
                }
            }
        });
        Peer {
            child,
            lines,
            ready,
            stderr_tail,
            label,
        }
    }

    /// Waits for the `READY` line and returns its JSON.
    pub fn wait_ready(&self, timeout: Duration) -> serde_json::Value {
        match self.ready.recv_timeout(timeout) {
            Ok(info) => serde_json::from_str(&info).expect("READY carries JSON"),
            Err(_) => panic!(
                "{} not ready in {timeout:?}; stderr:\n{}",
                self.label,
                self.stderr()
            ),
        }
    }

    /// The next stdout line parsed as JSON, or `None` after `timeout` or EOF.
    pub fn next_json(&self, timeout: Duration) -> Option<serde_json::Value> {
        match self.lines.recv_timeout(timeout) {
            Ok(line) => Some(serde_json::from_str(&line).unwrap_or_else(|e| {
                panic!("{}: stdout line {line:?} is not JSON: {e}", self.label)
            })),
            Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => None,
        }
    }

    /// The next stdout line that is a JSON object, other lines skipped
    /// (a test binary run as a peer prints libtest's lines too); `None`
    /// after `timeout` or EOF.
    pub fn next_json_object(&self, timeout: Duration) -> Option<serde_json::Value> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let line = self.lines.recv_timeout(left).ok()?;
            if line.starts_with('{') {
                if let Ok(value) = serde_json::from_str(&line) {
                    return Some(value);
                }
            }
        }
    }

    /// Its resident memory now, in bytes (Linux; `None` once it ended).
    pub fn resident_bytes(&self) -> Option<u64> {
        self.status_bytes("VmRSS:")
    }

    /// Its resident memory that is its own, not a mapped file: what it
    /// allocated (heap, stacks), without its code, whose size is the
    /// build's (a debug build maps tens of megabytes more than a release
    /// one). Linux; `None` once it ended.
    pub fn allocated_bytes(&self) -> Option<u64> {
        self.status_bytes("RssAnon:")
    }

    fn status_bytes(&self, field: &str) -> Option<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).ok()?;
        let kb: u64 = status
            .lines()
            .find_map(|l| l.strip_prefix(field))?
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()
            .ok()?;
        Some(kb * 1024)
    }

    /// Asks the process to stop with SIGTERM (by its PID), as a service
    /// manager would; [`Peer::wait_exit`] then waits for it.
    pub fn terminate(&self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
    }

    /// Asks the process to stop with SIGINT (by its PID), as Ctrl-C does.
    pub fn interrupt(&self) {
        let _ = Command::new("kill")
            .args(["-INT", &self.child.id().to_string()])
            .status();
    }

    /// Every stdout line that has arrived so far (taken: the next call
    /// returns only newer ones).
    pub fn lines_so_far(&self) -> Vec<String> {
        self.lines.try_iter().collect()
    }

    /// `n` JSON lines, panicking with the child's stderr if they don't come.
    pub fn take_json(&self, n: usize, timeout: Duration) -> Vec<serde_json::Value> {
        let deadline = Instant::now() + timeout;
        (0..n)
            .map(|i| {
                let left = deadline.saturating_duration_since(Instant::now());
                self.next_json(left).unwrap_or_else(|| {
                    panic!(
                        "{}: got {i} of {n} lines; stderr:\n{}",
                        self.label,
                        self.stderr()
                    )
                })
            })
            .collect()
    }

    /// Waits for the process to exit successfully and returns what it
    /// wrote to stdout, lines joined.
    pub fn output(mut self, timeout: Duration) -> String {
        let lines = std::mem::replace(&mut self.lines, mpsc::channel().1);
        self.wait_success(timeout);
        // The reader thread ends at EOF, after the process has exited.
        let mut out = Vec::new();
        while let Ok(line) = lines.recv_timeout(Duration::from_secs(2)) {
            out.push(line);
        }
        out.join("\n")
    }

    /// Waits for the process to exit and asserts success.
    pub fn wait_success(mut self, timeout: Duration) {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                assert!(
                    status.success(),
                    "{} exited with {status}; stderr:\n{}",
                    self.label,
                    self.stderr()
                );
                return;
            }
            assert!(
                Instant::now() < deadline,
                "{} still running after {timeout:?}",
                self.label
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits up to `timeout` for the process to exit, and returns how it
    /// ended; `None` if it still runs.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<std::process::ExitStatus> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(status) = self.child.try_wait().expect("try_wait") {
                return Some(status);
            }
            if Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// What the child wrote to stderr so far.
    pub fn stderr(&self) -> String {
        self.stderr_tail
            .lock()
            .map(|t| t.join("\n"))
            .unwrap_or_default()
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        // Our own child only, by its handle.
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The venv's python with `pulicast==2.0.1`, set up on first use by
/// `tests/python/setup_venv.sh` (idempotent).
pub fn reference_python() -> &'static Path {
    static PYTHON: OnceLock<PathBuf> = OnceLock::new();
    PYTHON.get_or_init(|| {
        let root = repo_root();
        let venv = root.join("target/pyvenv");
        let out = Command::new("bash")
            .arg(root.join("tests/python/setup_venv.sh"))
            .arg(&venv)
            .stderr(Stdio::inherit())
            .output()
            .expect("running setup_venv.sh");
        assert!(out.status.success(), "setup_venv.sh failed");
        let python = venv.join("bin/python");
        assert!(python.exists(), "no python in {}", venv.display());
        python
    })
}

/// Starts `tests/python/puliconf_peer.py` (2.x distributed settings through
/// `pulicast_tools.puliconf`) with `args` under the reference venv.
pub fn puliconf_peer(args: &[&str]) -> Peer {
    let script = repo_root().join("tests/python/puliconf_peer.py");
    let script = script.to_str().expect("UTF-8 path");
    let mut all = vec!["-u", script];
    all.extend_from_slice(args);
    Peer::spawn(reference_python(), &all)
}

/// Starts `tests/python/peer.py` with `args` under the reference venv.
pub fn python_peer(args: &[&str]) -> Peer {
    let script = repo_root().join("tests/python/peer.py");
    let script = script.to_str().expect("UTF-8 path");
    let mut all = vec!["-u", script];
    all.extend_from_slice(args);
    Peer::spawn(reference_python(), &all)
}

/// A 2.x talker (the reference package): `"hi {i}"` as text on `channel`,
/// every 50 ms, `count` times.
pub fn python_talker(port: &str, name: &str, channel: &str, count: usize) -> Peer {
    let count = count.to_string();
    python_peer(&[
        "publish",
        "--port",
        port,
        "--name",
        name,
        "--channel",
        channel,
        "--kind",
        "str",
        "--value",
        "hi {i}",
        "--count",
        &count,
        "--period",
        "0.05",
    ])
}

/// A 2.x listener (the reference package) that prints the first `count`
/// messages of `channel` as JSON lines and waits at most `timeout_secs`.
pub fn python_listener(
    port: &str,
    name: &str,
    channel: &str,
    count: usize,
    timeout_secs: u32,
) -> Peer {
    let (count, timeout) = (count.to_string(), timeout_secs.to_string());
    python_peer(&[
        "subscribe",
        "--port",
        port,
        "--name",
        name,
        "--channel",
        channel,
        "--count",
        &count,
        "--timeout",
        &timeout,
    ])
}

/// Several hosts on one machine: network namespaces on a bridge, made and
/// removed by the tests that use them (`tests/netns/netns.sh`). They need
/// root and `iptables`, as CI has (`.ci/run` installs it); elsewhere
/// [`netns::Net::up`] says why and returns `None`, unless
/// `PULICAST_REQUIRE_NETNS=1` (set by `.ci/run`) makes a missing
/// prerequisite a failure. Traffic stays inside the namespaces: they have
/// no link to the real network.
pub mod netns {
    use std::io::Write;
    use std::net::Ipv4Addr;
    use std::process::Command;
    use std::sync::{Mutex, MutexGuard};
    use std::time::Instant;

    use crate::{repo_root, Peer};

    /// Held by the test whose network exists: the tests of one process
    /// build their hosts one at a time. A test that panicked poisons it
    /// harmlessly.
    static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

    /// A test network; removed on drop, also when the test panics.
    pub struct Net {
        /// The network's tag (its namespaces are `TAG-h1`.., `TAG-br`).
        pub tag: String,
        hosts: Vec<Ipv4Addr>,
        started: Instant,
        // Declared last: released after the network is gone (fields drop in
        // order, after `Drop::drop` has run `down`).
        _turn: MutexGuard<'static, ()>,
    }

    /// A line on the test's stderr that `cargo test` shows at once: libtest
    /// captures `eprintln!`, not writes to the stream itself.
    pub fn say(line: &str) {
        let _ = writeln!(std::io::stderr().lock(), "netns: {line}");
    }

    /// Why this machine can't run the tests, or `None` when it can.
    fn unusable() -> Option<String> {
        let uid = Command::new("id").arg("-u").output().ok()?;
        if String::from_utf8_lossy(&uid.stdout).trim() != "0" {
            return Some("network namespaces need root".into());
        }
        let out = Command::new("bash")
            .arg(netns_sh())
            .arg("check")
            .output()
            .expect("running netns.sh");
        if out.status.success() {
            return None;
        }
        Some(String::from_utf8_lossy(&out.stderr).trim().to_owned())
    }

    /// The path of `netns.sh`.
    pub fn netns_sh() -> String {
        repo_root()
            .join("tests/netns/netns.sh")
            .display()
            .to_string()
    }

    /// Runs `netns.sh ARGS`, asserting it succeeds; returns its stdout.
    pub fn run(args: &[&str]) -> String {
        let out = Command::new("bash")
            .arg(netns_sh())
            .args(args)
            .output()
            .expect("running netns.sh");
        assert!(
            out.status.success(),
            "netns.sh {args:?} failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    impl Net {
        /// Waits for the other tests' networks (of this process) to be
        /// gone, then builds `n` hosts. `None` (saying why) where
        /// namespaces can't be made, unless the environment requires them.
        pub fn up(name: &str, n: usize) -> Option<Net> {
            // libtest names each test's thread after the test.
            let test = std::thread::current().name().unwrap_or(name).to_owned();
            let turn = ONE_AT_A_TIME
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            if let Some(why) = unusable() {
                let required = std::env::var("PULICAST_REQUIRE_NETNS").is_ok_and(|v| v == "1");
                assert!(!required, "PULICAST_REQUIRE_NETNS=1 but: {why}");
                say(&format!("skipping {test}: {why}"));
                return None;
            }
            let tag = format!("{name}{}", std::process::id() % 100_000);
            let mut net = Net {
                tag: tag.clone(),
                hosts: Vec::new(),
                started: Instant::now(),
                _turn: turn,
            };
            say(&format!("{test}: {n} hosts in namespaces {tag}-h1.."));
            let out = run(&["up", &tag, &n.to_string()]);
            net.hosts = out
                .lines()
                .filter_map(|l| l.split_whitespace().nth(1)?.parse().ok())
                .collect();
            assert_eq!(net.hosts.len(), n, "{out}");
            Some(net)
        }

        /// Host `host`'s address (1-based).
        pub fn ip(&self, host: usize) -> Ipv4Addr {
            self.hosts[host - 1]
        }

        /// Starts `program args` inside `host` (1-based).
        pub fn spawn(&self, host: usize, program: &str, args: &[&str]) -> Peer {
            let sh = netns_sh();
            let host = host.to_string();
            let mut all = vec![
                sh.as_str(),
                "exec",
                self.tag.as_str(),
                host.as_str(),
                program,
            ];
            all.extend_from_slice(args);
            Peer::spawn("bash", &all)
        }

        /// Runs `program args` inside `host` to its end, asserting success.
        pub fn exec(&self, host: usize, program: &str, args: &[&str]) -> String {
            let host = host.to_string();
            let mut all = vec!["exec", self.tag.as_str(), host.as_str(), program];
            all.extend_from_slice(args);
            run(&all)
        }
    }

    impl Drop for Net {
        fn drop(&mut self) {
            let _ = Command::new("bash")
                .arg(netns_sh())
                .args(["down", &self.tag])
                .status();
            say(&format!(
                "{}: removed after {:.1} s",
                self.tag,
                self.started.elapsed().as_secs_f64()
            ));
        }
    }
}

/// A stranger on the link: one plain UDP socket on loopback (TTL 0) that
/// sends hand-made datagrams, as anyone who read docs/wire.md could.
pub struct Stranger {
    socket: std::net::UdpSocket,
    port: u16,
    seq: u32,
}

impl Stranger {
    /// A stranger sending to the groups of `port`.
    pub fn new(port: u16) -> Stranger {
        let socket = std::net::UdpSocket::bind((std::net::Ipv4Addr::LOCALHOST, 0)).expect("bind");
        socket.set_multicast_ttl_v4(0).expect("ttl");
        socket.set_multicast_loop_v4(true).expect("loop");
        socket2::SockRef::from(&socket)
            .set_multicast_if_v4(&std::net::Ipv4Addr::LOCALHOST)
            .expect("interface");
        Stranger {
            socket,
            port,
            seq: 0,
        }
    }

    /// Its address, as receivers see it.
    pub fn address(&self) -> std::net::SocketAddr {
        self.socket.local_addr().expect("bound")
    }

    /// Sends `payload` as a packet on `channel`'s group (the next sequence
    /// number of this socket).
    pub fn send(&mut self, channel: &str, payload: &[u8]) {
        let mut datagram = Vec::new();
        pulicast_proto::wire::Packet {
            channel,
            seq: self.seq,
            payload,
        }
        .encode(&mut datagram);
        self.seq = self.seq.wrapping_add(1);
        let group = std::net::SocketAddr::from((pulicast::group_for(channel), self.port));
        // A full send buffer loses a datagram, as the link would.
        let _ = self.socket.send_to(&datagram, group);
    }

    /// Sends a Pulicast 2.x heartbeat of a node `name` with `session_id`,
    /// announcing `channels` as (name, published, subscribed).
    pub fn heartbeat(&mut self, name: &str, session_id: i64, channels: &[(&str, bool, bool)]) {
        let mut announced = vec![pulicast::ChannelAnnouncement {
            name: "__nodes".into(),
            period_ns: 100_000_000,
            is_published: true,
            is_subscribed: true,
        }];
        announced.extend(channels.iter().map(|&(channel, published, subscribed)| {
            pulicast::ChannelAnnouncement {
                name: channel.into(),
                period_ns: 0,
                is_published: published,
                is_subscribed: subscribed,
            }
        }));
        let heartbeat = pulicast_discovery::compat::Heartbeat {
            name: name.into(),
            session_id,
            channels: announced,
        };
        let mut payload = Vec::new();
        pulicast_proto::wire::zcm::encode_heartbeat(&heartbeat, &mut payload);
        self.send("__nodes", &payload);
    }

    /// Sends `heartbeat` every 100 ms on a thread until the returned flag
    /// is dropped, for at most `limit`.
    pub fn keep_announcing(
        mut self,
        limit: Duration,
        heartbeat: impl Fn(&mut Stranger) + Send + 'static,
    ) -> Announcing {
        let on = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
        let running = std::sync::Arc::clone(&on);
        let thread = std::thread::spawn(move || {
            let end = Instant::now() + limit;
            while running.load(std::sync::atomic::Ordering::SeqCst) && Instant::now() < end {
                heartbeat(&mut self);
                std::thread::sleep(Duration::from_millis(100));
            }
        });
        Announcing {
            on,
            thread: Some(thread),
        }
    }
}

/// A stranger announcing on a thread: dropping it stops the thread.
pub struct Announcing {
    on: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Drop for Announcing {
    fn drop(&mut self) {
        self.on.store(false, std::sync::atomic::Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// The Pulicast 2.x heartbeat of fake node `i` of a stranger's flood:
/// `names` channel names of about 10 bytes (2400 fill a datagram),
/// published by the even nodes and subscribed by the odd ones, announcing
/// `period`.
pub fn fake_2x_heartbeat(i: usize, names: usize, period: Duration) -> Vec<u8> {
    fake_2x_heartbeat_of_round(i, names, period, None)
}

/// [`fake_2x_heartbeat`] whose names differ in every `round` (none: the
/// names of [`fake_2x_heartbeat`]).
pub fn fake_2x_heartbeat_of_round(
    i: usize,
    names: usize,
    period: Duration,
    round: Option<u64>,
) -> Vec<u8> {
    let publishes = i % 2 == 0;
    let round = round.map(|r| format!("r{r}/")).unwrap_or_default();
    let mut channels = vec![pulicast::ChannelAnnouncement {
        name: "__nodes".into(),
        period_ns: i64::try_from(period.as_nanos()).unwrap_or(i64::MAX),
        is_published: true,
        is_subscribed: true,
    }];
    channels.extend((0..names).map(|c| pulicast::ChannelAnnouncement {
        name: format!("f{i:03}/{round}c{c:04}"),
        period_ns: 0,
        is_published: publishes,
        is_subscribed: !publishes,
    }));
    let heartbeat = pulicast_discovery::compat::Heartbeat {
        name: format!("fake{i}"),
        session_id: 0x0bad_0000 + i as i64,
        channels,
    };
    let mut payload = Vec::new();
    pulicast_proto::wire::zcm::encode_heartbeat(&heartbeat, &mut payload);
    assert!(payload.len() < 65_000, "{} bytes", payload.len());
    payload
}

/// A stranger's flood of `nodes` fake 2.x nodes on `port`, each from a
/// socket of its own (one address speaks for one 2.x session), each
/// announcing `names` names ([`fake_2x_heartbeat`]) every `every` (and a
/// period twice that, so none expires), until dropped or for at most 11
/// minutes.
pub fn fake_2x_flood(port: u16, nodes: usize, names: usize, every: Duration) -> Announcing {
    fake_2x_flood_announcing(port, nodes, names, every, every * 2)
}

/// [`fake_2x_flood`] with the heartbeat period the fakes announce: below a
/// third of `every`, each fake expires between two heartbeats and joins
/// again with the next (churn).
pub fn fake_2x_flood_announcing(
    port: u16,
    nodes: usize,
    names: usize,
    every: Duration,
    period: Duration,
) -> Announcing {
    fake_2x_flood_of(port, nodes, names, every, period, false)
}

/// [`fake_2x_flood`] whose fakes announce new names with every heartbeat:
/// every name is one the bridges never saw.
pub fn fake_2x_flood_of_fresh_names(
    port: u16,
    nodes: usize,
    names: usize,
    every: Duration,
) -> Announcing {
    fake_2x_flood_of(port, nodes, names, every, every * 2, true)
}

fn fake_2x_flood_of(
    port: u16,
    nodes: usize,
    names: usize,
    every: Duration,
    period: Duration,
    fresh: bool,
) -> Announcing {
    let on = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let running = std::sync::Arc::clone(&on);
    let thread = std::thread::spawn(move || {
        let mut strangers: Vec<Stranger> = (0..nodes).map(|_| Stranger::new(port)).collect();
        let heartbeats = |round: Option<u64>| -> Vec<Vec<u8>> {
            (0..nodes)
                .map(|i| fake_2x_heartbeat_of_round(i, names, period, round))
                .collect()
        };
        let mut payloads = heartbeats(None);
        let end = Instant::now() + Duration::from_secs(660);
        let mut round = 0;
        while running.load(std::sync::atomic::Ordering::SeqCst) && Instant::now() < end {
            if fresh {
                round += 1;
                payloads = heartbeats(Some(round));
            }
            for (stranger, payload) in strangers.iter_mut().zip(&payloads) {
                stranger.send("__nodes", payload);
            }
            std::thread::sleep(every);
        }
    });
    Announcing {
        on,
        thread: Some(thread),
    }
}

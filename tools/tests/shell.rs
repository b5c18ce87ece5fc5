//! `puli shell` as a user drives it: scripts through standard input and
//! from a file (the same output), stopping at the first error when told
//! to, and a terminal session under tmux: Tab completes a live service's
//! name, Ctrl-C ends a command and not the shell, history outlives it.
//! Loopback only; every process is one this test started.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use pulicast_tests::{free_port, Peer};

const PULI: &str = env!("CARGO_BIN_EXE_puli");
const READY: Duration = Duration::from_secs(30);

fn net(port: &str) -> Vec<&str> {
    vec!["--port", port, "--interface", "127.0.0.1"]
}

/// A `puli serve` process in `namespace` (killed when dropped).
fn serve(port: u16, namespace: &str, name: &str) -> Peer {
    let p = port.to_string();
    let mut args = vec!["serve"];
    args.extend(net(&p));
    args.extend(["--namespace", namespace, "--name", name, "--for", "120"]);
    let peer = Peer::spawn(PULI, &args);
    peer.wait_ready(READY);
    peer
}

/// A temporary directory of this test, removed when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("puli-shell-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// `puli shell ARGS`, its three streams piped (no terminal).
fn spawn_shell(port: u16, extra: &[&str]) -> std::process::Child {
    let p = port.to_string();
    let mut args = vec!["shell"];
    args.extend(net(&p));
    args.extend_from_slice(extra);
    Command::new(PULI)
        .args(&args)
        .env_remove(pulicast::KEYS_ENV)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// `puli shell` with `script` on standard input.
fn shell_stdin(port: u16, extra: &[&str], script: &str) -> Output {
    let mut child = spawn_shell(port, extra);
    child
        .stdin
        .take()
        .unwrap()
        .write_all(script.as_bytes())
        .unwrap();
    child.wait_with_output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

#[test]
fn a_script_runs_through_stdin_or_a_file_with_the_same_output() {
    let port = free_port();
    let _server = serve(port, "rover1", "planner_a");
    let p = port.to_string();
    let mut owner_args = vec!["config-owner"];
    owner_args.extend(net(&p));
    owner_args.extend(["--namespace", "rover1", "--name", "owner", "--count", "2"]);
    let owner = Peer::spawn(PULI, &owner_args);
    owner.wait_ready(READY);
    let mut pub_args = vec!["pub"];
    pub_args.extend(net(&p));
    pub_args.extend(["rover1/pose", "1.5", "--rate", "50", "--count", "5000"]);
    let _publisher = Peer::spawn(PULI, &pub_args);

    let dir = TempDir::new("script");
    let pulled = dir.0.join("pulled.toml");
    // Everything a session does, as a user types it: the view, a call,
    // settings read and changed (a refused value too), messages, a file.
    let script = format!(
        "# a comment, then a blank line\n\
         \n\
         services\n\
         call rover1/double 21\n\
         call rover1/plan '{{\"goal\": [4, 1], \"steps\": 2}}' --json\n\
         get rover1/setting_01\n\
         set rover1/setting_01 7\n\
         set rover1/setting_01 -3\n\
         echo rover1/pose --count 2 --json\n\
         hz rover1/pose --for 1.2\n\
         pull {}\n\
         nodes planner_a\n\
         bogus\n\
         channels\n",
        pulled.display()
    );
    let out = shell_stdin(port, &["--echo"], &script);
    let stdout = text(&out.stdout);
    let stderr = text(&out.stderr);
    // One command failed (the refused value) and one is no command: the
    // script went on past both, and its status says so.
    assert_eq!(out.status.code(), Some(1), "{stdout}\n{stderr}");
    assert!(
        stderr.contains("error: line 8: setting rover1/setting_01: must be at least 0"),
        "{stderr}"
    );
    assert!(
        stderr.contains("error: line 13: unrecognized subcommand 'bogus'"),
        "{stderr}"
    );
    let lines: Vec<&str> = stdout.lines().collect();
    // Each command's output follows its prompt line, as at a terminal.
    let after = |command: &str| -> Vec<&str> {
        let at = lines
            .iter()
            .position(|l| *l == format!("puli> {command}"))
            .unwrap_or_else(|| panic!("{command:?} not echoed in\n{stdout}"));
        lines[at + 1..]
            .iter()
            .take_while(|l| !l.starts_with("puli> "))
            .copied()
            .collect()
    };
    assert!(
        after("services")
            .iter()
            .any(|l| l.starts_with("rover1/plan") && l.contains("PlanRequest -> PlanReply")),
        "{stdout}"
    );
    assert_eq!(after("call rover1/double 21"), ["42"]);
    let plan: serde_json::Value =
        serde_json::from_str(after(r#"call rover1/plan '{"goal": [4, 1], "steps": 2}' --json"#)[0])
            .unwrap();
    assert_eq!(
        plan["reply"]["points"],
        serde_json::json!([[0.0, 1.0], [2.0, 1.0]])
    );
    assert_eq!(after("get rover1/setting_01"), ["1"]);
    assert_eq!(after("set rover1/setting_01 7"), ["7"]);
    assert!(after("set rover1/setting_01 -3").is_empty());
    let echoed = after("echo rover1/pose --count 2 --json");
    assert_eq!(echoed.len(), 2, "{stdout}");
    for l in echoed {
        let m: serde_json::Value = serde_json::from_str(l).unwrap();
        assert_eq!(m["value"], 1.5);
    }
    let hz = after("hz rover1/pose --for 1.2");
    assert!(
        hz.iter().any(|l| l.contains("Hz") && l.contains("jitter")),
        "{stdout}"
    );
    let file = std::fs::read_to_string(&pulled).unwrap();
    assert!(file.contains("\"rover1/setting_01\" = 7"), "{file}");
    let node = after("nodes planner_a");
    assert!(node.iter().any(|l| l.starts_with("planner_a ")), "{stdout}");
    assert!(
        node.iter().any(|l| l.contains("rover1/.services/plan")),
        "{stdout}"
    );
    assert!(
        after("channels")
            .iter()
            .any(|l| l.starts_with("rover1/pose") && l.contains(" f64 ")),
        "{stdout}"
    );

    // The same commands from a file: the same output, line for line (the
    // commands whose output does not change from run to run).
    let steady = "call rover1/double 21\nget rover1/setting_01\nnodes planner_a\n";
    let script_file = dir.0.join("steady.puli");
    std::fs::write(&script_file, steady).unwrap();
    let from_stdin = shell_stdin(port, &["--echo"], steady);
    let file_arg = script_file.to_str().unwrap();
    let from_file = shell_stdin(port, &["--echo", "--script", file_arg], "");
    assert!(from_stdin.status.success(), "{}", text(&from_stdin.stderr));
    assert!(from_file.status.success(), "{}", text(&from_file.stderr));
    // Node lines carry the session's address: the same processes, so the
    // same text.
    assert_eq!(text(&from_stdin.stdout), text(&from_file.stdout));
    assert!(text(&from_file.stdout).contains("puli> get rover1/setting_01\n7\n"));
}

#[test]
fn exit_on_error_stops_at_the_first_failure() {
    let port = free_port();
    let _server = serve(port, "arm", "arm_server");
    let script = "call arm/double 1\ncall arm/double 'not a number'\ncall arm/double 2\n";

    let out = shell_stdin(port, &["--exit-on-error"], script);
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(text(&out.stdout), "2\n", "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("error: line 2:"),
        "{}",
        text(&out.stderr)
    );

    // Without it, the rest runs; the status still says one failed.
    let out = shell_stdin(port, &[], script);
    assert_eq!(out.status.code(), Some(1));
    assert_eq!(text(&out.stdout), "2\n4\n");

    // `exit` ends a script early; all went well, so the status is 0.
    let out = shell_stdin(port, &[], "call arm/double 5\nexit\ncall arm/double 6\n");
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(text(&out.stdout), "10\n");
}

/// A tmux server of this test's own (its own socket), killed when dropped.
struct Tmux {
    socket: String,
}

impl Tmux {
    fn cmd(&self, args: &[&str]) -> Output {
        Command::new("tmux")
            .args(["-L", &self.socket, "-f", "/dev/null"])
            .env_remove(pulicast::KEYS_ENV)
            .args(args)
            .output()
            .unwrap()
    }

    fn keys(&self, keys: &[&str]) {
        let mut args = vec!["send-keys", "-t", "shell"];
        args.extend_from_slice(keys);
        assert!(self.cmd(&args).status.success());
    }

    fn screen(&self) -> String {
        text(&self.cmd(&["capture-pane", "-p", "-t", "shell"]).stdout)
    }

    /// The screen, once `ok` holds for it (within `within`).
    fn wait_for(&self, within: Duration, ok: impl Fn(&str) -> bool) -> String {
        let deadline = Instant::now() + within;
        loop {
            let screen = self.screen();
            if ok(&screen) {
                return screen;
            }
            assert!(
                Instant::now() < deadline,
                "timed out; the screen:\n{screen}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The last line with a prompt on the screen.
    fn prompt_line(&self) -> String {
        self.screen()
            .lines()
            // capture-pane drops the spaces that end a line.
            .rfind(|l| l.starts_with("puli>"))
            .unwrap_or_default()
            .trim_end()
            .to_string()
    }

    /// Starts `puli shell ARGS` in a new session named `shell`.
    fn start_shell(&self, args: &[&str]) {
        let mut command = vec![PULI.to_string(), "shell".into()];
        command.extend(args.iter().map(|a| a.to_string()));
        let line = command.join(" ");
        let out = self.cmd(&[
            "new-session",
            "-d",
            "-s",
            "shell",
            "-x",
            "160",
            "-y",
            "50",
            &line,
        ]);
        assert!(out.status.success(), "{}", text(&out.stderr));
        self.wait_for(READY, |s| s.lines().any(|l| l.starts_with("puli>")));
    }
}

impl Drop for Tmux {
    fn drop(&mut self) {
        let _ = self.cmd(&["kill-server"]);
    }
}

fn tmux_available() -> bool {
    let found = Command::new("tmux")
        .arg("-V")
        .output()
        .is_ok_and(|o| o.status.success());
    if !found && std::env::var_os("PULICAST_REQUIRE_TMUX").is_some() {
        panic!("tmux is required here (PULICAST_REQUIRE_TMUX) and not installed");
    }
    if !found {
        eprintln!("skipped: tmux is not installed (.ci/run installs it)");
    }
    found
}

#[test]
fn at_a_terminal_tab_completes_a_live_service_and_history_outlives_the_session() {
    if !tmux_available() {
        return;
    }
    let port = free_port();
    // A namespace no other test uses, so what completes is this test's.
    let ns = format!("tmux{port}");
    let _server = serve(port, &ns, "tmux_planner");
    let dir = TempDir::new("tmux");
    let history = dir.0.join("history");
    let p = port.to_string();
    let history_arg = history.to_str().unwrap();
    let mut args = net(&p);
    args.extend(["--history", history_arg]);
    let tmux = Tmux {
        socket: format!("puli-shell-test-{}-{port}", std::process::id()),
    };
    tmux.start_shell(&args);

    // Tab completes the namespace (every service of it shares that much)
    // once the shell's warm view has the service; nothing waits per key.
    let deadline = Instant::now() + READY;
    loop {
        tmux.keys(&["C-u", "call tmux", "Tab"]);
        std::thread::sleep(Duration::from_millis(200));
        if tmux.prompt_line() == format!("puli> call {ns}/") {
            break;
        }
        assert!(Instant::now() < deadline, "{}", tmux.screen());
    }
    // A second Tab lists the services; `pl` and Tab take the one.
    tmux.keys(&["Tab"]);
    tmux.wait_for(Duration::from_secs(5), |s| {
        s.contains(&format!("{ns}/plan")) && s.contains(&format!("{ns}/count"))
    });
    tmux.keys(&["pl", "Tab"]);
    tmux.wait_for(Duration::from_secs(5), |_| {
        tmux.prompt_line() == format!("puli> call {ns}/plan")
    });
    // `@` and Tab: the node that serves it.
    tmux.keys(&["BSpace", "@", "Tab"]);
    tmux.wait_for(Duration::from_secs(5), |_| {
        tmux.prompt_line() == format!("puli> call {ns}/plan@tmux_planner")
    });
    tmux.keys(&[r#"'{"goal": [2, 2], "steps": 1}'"#, "Enter"]);
    tmux.wait_for(Duration::from_secs(10), |s| {
        s.contains(r#"{"by":"tmux_planner","points":[[0.0,2.0]]}"#)
    });

    // Ctrl-C ends a command that would run for a minute, not the shell.
    // (Once it runs: its note that nobody publishes comes after 2 s.)
    tmux.keys(&["echo nobody/talks --for 60", "Enter"]);
    tmux.wait_for(READY, |s| {
        s.contains("no member publishes \"nobody/talks\"")
    });
    tmux.keys(&["C-c"]);
    tmux.keys(&["services", "Enter"]);
    tmux.wait_for(Duration::from_secs(10), |s| {
        s.lines().any(|l| l.starts_with(&format!("{ns}/plan ")))
    });

    // A line that starts with a space stays out of the history.
    tmux.keys(&[" nodes tmux_planner", "Enter"]);
    tmux.wait_for(Duration::from_secs(10), |s| {
        s.lines().any(|l| l.starts_with("tmux_planner "))
    });

    // Ctrl-D leaves; the history has the session's commands, and a new
    // session brings them back with the up arrow.
    tmux.keys(&["C-d"]);
    let kept = wait_for_file(&history, "services");
    assert!(!kept.contains("nodes tmux_planner"), "{kept}");
    assert!(
        kept.contains(&format!("call {ns}/plan@tmux_planner")),
        "{kept}"
    );
    tmux.wait_for(Duration::from_secs(10), |_| {
        tmux.cmd(&["has-session", "-t", "shell"]).status.code() != Some(0)
    });
    tmux.start_shell(&args);
    tmux.keys(&["Up"]);
    tmux.wait_for(Duration::from_secs(5), |_| {
        tmux.prompt_line() == "puli> services"
    });
    tmux.keys(&["Up"]);
    tmux.wait_for(Duration::from_secs(5), |_| {
        tmux.prompt_line() == "puli> echo nobody/talks --for 60"
    });
}

/// The file's text once it contains `wanted` (within 10 s).
fn wait_for_file(path: &Path, wanted: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let text = std::fs::read_to_string(path).unwrap_or_default();
        if text.contains(wanted) || Instant::now() > deadline {
            return text;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn names_and_faults_from_the_network_cannot_drive_the_terminal() {
    // An attacker joins with a name that, printed raw, retitles the
    // operator's terminal, and a service whose fault clears the screen.
    let port = free_port();
    let evil = pulicast::Node::new("evil\u{1b}]0;owned\u{7}\nforged row")
        .port(port)
        .interface(std::net::Ipv4Addr::LOCALHOST)
        .heartbeat_period(Duration::from_millis(100))
        .start_blocking()
        .unwrap();
    let _trap = evil
        .serve_blocking("trap", |_: i64| {
            Err::<i64, _>(pulicast::Fault::msg("\u{1b}[2Jscreen cleared"))
        })
        .unwrap();
    let out = shell_stdin(port, &["--echo"], "call trap 1\nnodes\nservices\n");
    for stream in [&out.stdout, &out.stderr] {
        assert!(!stream.contains(&0x1b), "{}", text(stream));
        assert!(!stream.contains(&0x07), "{}", text(stream));
    }
    let (stdout, stderr) = (text(&out.stdout), text(&out.stderr));
    assert!(
        stdout.contains("evil\\u{1b}]0;owned\\u{7}\\nforged row"),
        "{stdout}"
    );
    // A newline in a name can't forge a row of a table either.
    assert!(!stdout.lines().any(|l| l.starts_with("forged")), "{stdout}");
    assert!(stderr.contains("\\u{1b}[2Jscreen cleared"), "{stderr}");
    evil.stop();
}

/// Sends SIGTERM to a process this test started.
fn terminate(child: &std::process::Child) {
    let pid = child.id().to_string();
    let sent = Command::new("kill").args(["-TERM", &pid]).status().unwrap();
    assert!(sent.success());
}

/// The lines of a child's stdout, read on a thread of their own, so the
/// test waits for each with a time limit.
fn lines_of(stdout: std::process::ChildStdout) -> std::sync::mpsc::Receiver<String> {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::BufRead::lines(std::io::BufReader::new(stdout)) {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

#[test]
fn a_signal_ends_a_scripts_command_as_its_end_would_and_then_the_script() {
    let port = free_port();
    // `hz` without --for runs until stopped: SIGTERM ends it with its
    // last report, and the lines after it do not run.
    let mut child = spawn_shell(port, &["--echo"]);
    let mut stdin = child.stdin.take().unwrap();
    stdin
        .write_all(b"hz nobody/talks\ncall never/runs 1\n")
        .unwrap();
    let lines = lines_of(child.stdout.take().unwrap());
    let first = |wanted: &str| loop {
        let line = lines.recv_timeout(READY).expect("a line in time");
        if line.contains(wanted) {
            break line;
        }
    };
    // It reports every second: once it has, it runs.
    first("nobody/talks: 0 messages so far");
    terminate(&child);
    let rest: Vec<String> = lines.iter().collect();
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    // Its report at the end, and no prompt of the next command.
    assert!(
        rest.last()
            .is_some_and(|l| l.contains("nobody/talks: 0 messages so far")),
        "{rest:?}"
    );
    assert!(!rest.iter().any(|l| l.contains("never/runs")), "{rest:?}");
    let stderr = text(&out.stderr);
    assert!(
        stderr.contains("stopped by a signal after line 1"),
        "{stderr}"
    );
    drop(stdin);

    // Waiting for the next line of a pipe that stays open: SIGTERM ends
    // the shell at once.
    let mut child = spawn_shell(port, &["--echo"]);
    let mut stdin = child.stdin.take().unwrap();
    stdin.write_all(b"sleep 0.1\n# slept\n").unwrap();
    let lines = lines_of(child.stdout.take().unwrap());
    loop {
        let line = lines.recv_timeout(READY).expect("a line in time");
        if line == "puli> # slept" {
            break;
        }
    }
    terminate(&child);
    let started = Instant::now();
    let out = child.wait_with_output().unwrap();
    assert!(started.elapsed() < Duration::from_secs(10));
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("puli shell: stopped by a signal"));
    drop(stdin);
}

/// A script's `nodes`, run right after the shell starts, lists a live
/// Pulicast 2.x node every time: the shell waits until discovery had a
/// fair chance (a 2.x node is listed only a grace period after its first
/// heartbeat), not until an empty view has not changed for a moment (it
/// listed the node in 3 runs of 6 that way).
#[test]
fn a_scripted_nodes_lists_a_live_2x_node_every_time() {
    let port = free_port();
    let p = port.to_string();
    let peer = pulicast_tests::python_peer(&[
        "publish",
        "--port",
        &p,
        "--name",
        "old_timer",
        "--channel",
        "chatter",
        "--kind",
        "int",
        "--value",
        "{i}",
        "--count",
        "2000",
        "--period",
        "0.05",
    ]);
    peer.wait_ready(READY);
    for run in 0..3 {
        let out = shell_stdin(port, &[], "nodes\n");
        let stdout = text(&out.stdout);
        assert!(out.status.success(), "run {run}: {}", text(&out.stderr));
        assert!(stdout.contains("old_timer"), "run {run}: {stdout}");
    }
}

//! The `puli` command-line tools for pulicast fleets.
//!
//! The binaries stay thin: everything they do lives here, so it can be tested
//! and reused: the shared flags ([`flags`]), what `puli-sniffer` does
//! ([`sniff`]), what `puli pub` does ([`publish`]), recording and playback
//! ([`record`]) and the benchmarks ([`mod@bench`]).

pub mod bench;
pub mod call;
pub mod config;
pub mod dashboard;
pub mod flags;
pub mod inspect;
pub mod publish;
pub mod record;
pub mod shell;
pub mod sniff;
pub mod suggest;

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Whether `channel` is one of the fleet's own (`__nodes`, the discovery
/// channel): every node uses them and no member announces them, and the
/// tools leave them out unless asked for by name.
pub fn is_internal(channel: &str) -> bool {
    channel.starts_with("__")
}

/// Nanoseconds since the Unix epoch: one clock that every process on this
/// host shares, so events reported by different processes can be compared.
pub fn unix_ns() -> u128 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0)
}

/// Asks `f` every 20 ms until it answers or `within` has passed: how the
/// tools wait for something discovery will tell them (a channel's type).
pub async fn poll_for<T>(within: Duration, mut f: impl FnMut() -> Option<T>) -> Option<T> {
    let deadline = Instant::now() + within;
    loop {
        if let Some(found) = f() {
            return Some(found);
        }
        if Instant::now() >= deadline {
            return None;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Resolves when the process is asked to stop: Ctrl-C (SIGINT), SIGTERM (as
/// `timeout`, systemd and `docker stop` send) or SIGHUP (a closed terminal;
/// not under `nohup`, which asks for SIGHUP to be ignored).
/// Every tool ends the same way on each, closing its files and printing its
/// summary. Create it once per run and keep it pinned: a signal that
/// arrives after it was made and before it is awaited is kept, not lost.
///
/// The signals are heard on a thread of their own, so a tool whose runtime
/// is busy (a fleet of thousands of names to list) still hears them; and a
/// tool that has not ended [`END_WITHIN`] after the first one exits then,
/// with status 1 (unless [`keep_running_after_signals`] was called).
pub fn stop_requested() -> impl std::future::Future<Output = ()> {
    let mut heard = signals();
    let seen = *heard.borrow_and_update();
    async move {
        let _ = heard.wait_for(|n| *n > seen).await;
    }
}

/// How long a tool may take to end after a stop signal (see
/// [`stop_requested`]).
pub const END_WITHIN: Duration = Duration::from_millis(1500);

/// Whether a stop signal ends the process after [`END_WITHIN`].
static EXIT_AFTER_SIGNAL: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(true);

/// For a tool whose signals stop what it is doing rather than the process
/// (`puli shell`): signals no longer end the process after
/// [`END_WITHIN`].
pub fn keep_running_after_signals() {
    EXIT_AFTER_SIGNAL.store(false, std::sync::atomic::Ordering::SeqCst);
}

/// The count of stop signals heard, from the signal thread (started on
/// first use).
fn signals() -> tokio::sync::watch::Receiver<u64> {
    static HEARD: std::sync::OnceLock<tokio::sync::watch::Receiver<u64>> =
        std::sync::OnceLock::new();
    HEARD
        .get_or_init(|| {
            let (tx, rx) = tokio::sync::watch::channel(0u64);
            let listening = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build();
            match listening {
                Ok(runtime) => {
                    let spawned = std::thread::Builder::new()
                        .name("signals".into())
                        .spawn(move || runtime.block_on(listen(tx)));
                    if let Err(e) = spawned {
                        errln!("warning: signals can't be heard: {e}");
                    }
                }
                Err(e) => errln!("warning: signals can't be heard: {e}"),
            }
            rx
        })
        .clone()
}

/// Counts the stop signals into `heard`; from the first, ends the process
/// after [`END_WITHIN`] unless told not to.
#[cfg(unix)]
async fn listen(heard: tokio::sync::watch::Sender<u64>) {
    use tokio::signal::unix::{signal, SignalKind};
    // Under `nohup` SIGHUP is ignored, and must stay so: listening for it
    // would replace the ignoring.
    let mut hup = match hangup_ignored() {
        true => None,
        false => signal(SignalKind::hangup()).ok(),
    };
    let (Ok(mut term), Ok(mut int)) = (
        signal(SignalKind::terminate()),
        signal(SignalKind::interrupt()),
    ) else {
        errln!("warning: SIGTERM and SIGINT can't be heard");
        return;
    };
    let mut deadline: Option<tokio::time::Instant> = None;
    loop {
        let exit = async {
            match deadline {
                Some(at) => tokio::time::sleep_until(at).await,
                None => std::future::pending().await,
            }
        };
        let hangup = async {
            match &mut hup {
                Some(hup) => hup.recv().await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            _ = int.recv() => {}
            _ = term.recv() => {}
            _ = hangup => {}
            _ = exit => {
                errln!("stopped: not ended within {END_WITHIN:?} of the signal");
                std::process::exit(1);
            }
        }
        heard.send_modify(|n| *n += 1);
        if deadline.is_none() && EXIT_AFTER_SIGNAL.load(std::sync::atomic::Ordering::SeqCst) {
            deadline = Some(tokio::time::Instant::now() + END_WITHIN);
        }
    }
}

/// Counts Ctrl-C into `heard` (where there are no Unix signals).
#[cfg(not(unix))]
async fn listen(heard: tokio::sync::watch::Sender<u64>) {
    while tokio::signal::ctrl_c().await.is_ok() {
        heard.send_modify(|n| *n += 1);
    }
}

/// Whether this process was started ignoring SIGHUP (`nohup`), as the
/// kernel reports it in `/proc/self/status` (`SigIgn`, a hex mask whose
/// bit 0 is signal 1, SIGHUP). Elsewhere: false.
fn hangup_ignored() -> bool {
    let Ok(status) = std::fs::read_to_string("/proc/self/status") else {
        return false;
    };
    status
        .lines()
        .find_map(|l| l.strip_prefix("SigIgn:"))
        .and_then(|mask| u64::from_str_radix(mask.trim(), 16).ok())
        .is_some_and(|mask| mask & 1 != 0)
}

/// Whether `c` changes what a terminal shows beyond itself: a control
/// character (escape sequences start with one) or a bidirectional
/// override, which reorders the text after it.
pub fn steers_terminal(c: char) -> bool {
    c.is_control() || matches!(c, '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}')
}

/// `text` safe to show on a terminal: every control character but newline
/// and tab, and every bidirectional override, written as its escape
/// (`\u{1b}`). Names, fault messages and values come from the network,
/// and anyone on the link can put an escape sequence in them that would
/// retitle, clear or reprogram the operator's terminal.
pub fn printable(text: &str) -> std::borrow::Cow<'_, str> {
    escaped(text, |c| steers_terminal(c) && c != '\n' && c != '\t')
}

/// Like [`printable`], for one field of a line (a name in a table): a
/// newline or a tab is escaped too, so it can't forge rows or columns.
pub fn one_line(text: &str) -> std::borrow::Cow<'_, str> {
    escaped(text, steers_terminal)
}

fn escaped(text: &str, unsafe_char: impl Fn(char) -> bool) -> std::borrow::Cow<'_, str> {
    if !text.contains(&unsafe_char) {
        return std::borrow::Cow::Borrowed(text);
    }
    let mut out = String::with_capacity(text.len() + 16);
    for c in text.chars() {
        match unsafe_char(c) {
            true => out.extend(c.escape_default()),
            false => out.push(c),
        }
    }
    std::borrow::Cow::Owned(out)
}

/// Writes a line to stderr, made [`printable`]. A failure to write is
/// ignored, where `eprintln!` would panic.
pub fn eprint_line(line: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let text = line.to_string();
    let _ = writeln!(std::io::stderr().lock(), "{}", printable(&text));
}

/// `eprintln!` for the tools: see [`eprint_line`].
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {
        $crate::eprint_line(format_args!($($arg)*))
    };
}

/// Writes a line to stdout, made [`printable`]. A reader that closed the
/// pipe (`| head -1`) has all it wanted, so the process ends quietly, with
/// success, where `println!` would panic; any other failure to write ends
/// it with an error.
pub fn print_line(line: std::fmt::Arguments<'_>) {
    use std::io::Write;
    let text = line.to_string();
    let mut out = std::io::stdout().lock();
    let written = out
        .write_all(printable(&text).as_bytes())
        .and_then(|()| out.write_all(b"\n"));
    if let Err(e) = written {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(0);
        }
        eprintln!("can't write to stdout: {e}");
        std::process::exit(1);
    }
}

/// `println!` for the tools: see [`print_line`].
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::print_line(format_args!($($arg)*))
    };
}

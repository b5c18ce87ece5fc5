//! `puli shell`: an interactive inspector of the fleet, in the spirit of
//! SORMA's `scott`. One node for the whole session keeps a view of the
//! fleet warm (nodes, channels, services, settings), so completing a name
//! never waits on the network, and `settings` answers at once once the
//! fleet has been quiet. It reads commands from a terminal (line editing,
//! completion, history kept across sessions), from a script file, or from
//! standard input, with the same output in each case.
//!
//! Every command is also a `puli` or `puli-sniffer` command, run by the
//! same code: `call` is `puli call`, `echo` is `puli-sniffer echo`, `get`
//! is `puli config get`.

use std::collections::BTreeMap;
use std::io::{BufRead, IsTerminal};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context as _, Result};
use clap::{CommandFactory, Parser, Subcommand};
use parking_lot::Mutex;
use pulicast::{resolve_name, FleetSettings, Node};
use rustyline::completion::{Completer, FilenameCompleter, Pair};
use rustyline::error::ReadlineError;
use rustyline::history::FileHistory;
use rustyline::{CompletionType, Config, Editor, Helper, Highlighter, Hinter, Validator};

use crate::call::CallOpts;
use crate::config::{self, SettingCommand};
use crate::flags::NetArgs;
use crate::inspect::{Inspect, Listening};
use crate::publish::{self, PubOpts};

/// The prompt.
pub const PROMPT: &str = "puli> ";

/// How often the background task reads discovery and the settings again.
const REFRESH: Duration = Duration::from_millis(200);

/// The longest wait for the fleet view to settle at start: a fleet that
/// keeps changing (nodes starting) does not hold the first command longer.
const SETTLE_MAX: Duration = Duration::from_secs(3);

/// How long no new setting must have appeared before `settings`, `pull`,
/// `push` and `diff` list them (as `puli config --quiet`, and puliconf).
const SETTINGS_QUIET: Duration = Duration::from_secs(2);

/// How long a settings command may take in all.
const SETTINGS_TIMEOUT: Duration = Duration::from_secs(10);

/// Most lines of history kept.
const HISTORY_LINES: usize = 1000;

/// `puli shell`'s arguments.
#[derive(clap::Args, Debug)]
pub struct ShellArgs {
    #[command(flatten)]
    net: NetArgs,
    /// Run the commands in FILE (one per line, `#` starts a comment), then
    /// exit; `-` is standard input. Without it, a standard input that is
    /// not a terminal is read as a script too.
    #[arg(long)]
    pub script: Option<PathBuf>,
    /// In a script, stop at the first command that fails (exit status 1).
    /// Without it the script goes on, and the status is 1 if any failed.
    #[arg(long)]
    pub exit_on_error: bool,
    /// In a script, print each command after the prompt before its
    /// output, as a terminal session shows it.
    #[arg(long)]
    pub echo: bool,
    /// Where the history is kept (default:
    /// $XDG_STATE_HOME/puli/shell_history, or
    /// ~/.local/state/puli/shell_history).
    #[arg(long)]
    pub history: Option<PathBuf>,
}

/// One line typed at the prompt.
#[derive(Parser, Debug)]
#[command(
    multicall = true,
    disable_help_flag = false,
    help_template = "Commands (`help COMMAND` for one, Tab completes names):\n{subcommands}"
)]
struct Line {
    #[command(subcommand)]
    command: ShellCommand,
}

#[derive(Subcommand, Debug)]
enum ShellCommand {
    #[command(flatten)]
    Inspect(Inspect),
    /// Every setting: value, type, owner, and what it is.
    Settings {
        /// One JSON array instead of a table.
        #[arg(long)]
        json: bool,
    },
    #[command(flatten)]
    Setting(SettingCommand),
    /// Call a service with a JSON request (`NAME@NODE`: that node's only).
    Call(CallOpts),
    /// Publish a value on a channel.
    Pub(PubOpts),
    /// Wait, in a script, for the fleet to change.
    Sleep {
        /// Seconds.
        secs: f64,
    },
    /// Leave the shell (Ctrl-D does too).
    #[command(alias = "quit")]
    Exit,
}

/// What the background task last read of the fleet: the names that Tab
/// completes, by kind.
#[derive(Debug, Default, Clone)]
pub struct Names {
    /// Node names.
    pub nodes: Vec<String>,
    /// Channels some live member announces (full names; none hidden).
    pub channels: Vec<String>,
    /// Services with at least one server, and the nodes serving each.
    pub services: BTreeMap<String, Vec<String>>,
    /// Setting names.
    pub settings: Vec<String>,
}

impl Names {
    /// Reads them off `node`'s discovery and `settings`.
    pub fn read(node: &Node, settings: &FleetSettings) -> Self {
        let members = node.discovery().live_members();
        let own = node.session_id();
        let mut names = Names::default();
        for m in &members {
            if m.session != Some(own) {
                names.nodes.push(m.name.clone());
            }
            for c in &m.channels {
                if !crate::is_internal(&c.name) && !pulicast::is_hidden_channel(&c.name) {
                    names.channels.push(c.name.clone());
                }
            }
        }
        for s in node.discovery().services() {
            if !s.servers.is_empty() {
                let servers = s.servers.iter().map(|e| e.node.clone()).collect();
                names.services.insert(s.name.clone(), servers);
            }
        }
        names.settings = settings.snapshot().into_iter().map(|s| s.name).collect();
        for list in [&mut names.nodes, &mut names.channels, &mut names.settings] {
            // What no one can type as one word is not offered: a name
            // with control characters would be printed raw in the list of
            // completions, escape sequences and all.
            list.retain(|n| typeable(n));
            list.sort();
            list.dedup();
        }
        names.services.retain(|name, servers| {
            servers.retain(|n| typeable(n));
            typeable(name)
        });
        names
    }
}

/// Whether `name` can be typed as one word at the prompt (and shown in
/// the list of completions as it is).
fn typeable(name: &str) -> bool {
    !name.is_empty() && !name.contains(|c: char| crate::steers_terminal(c) || c.is_whitespace())
}

/// The fleet view the background task keeps warm.
#[derive(Debug)]
struct Warm {
    names: Names,
    /// When a setting was last found for the first time.
    last_new_setting: Instant,
}

type Shared = Arc<Mutex<Warm>>;

/// The shell's session: its node, the settings it follows, and the view.
struct Session {
    node: Node,
    settings: Arc<FleetSettings>,
    warm: Shared,
    net: NetArgs,
    refresher: tokio::task::JoinHandle<()>,
}

impl Session {
    async fn start(net: &NetArgs) -> Result<Self> {
        let node = net
            .node("puli-shell")?
            .start()
            .await
            .with_context(|| format!("starting a node on port {}", net.port))?;
        let settings = Arc::new(node.fleet_settings());
        let warm = Arc::new(Mutex::new(Warm {
            names: Names::default(),
            last_new_setting: Instant::now(),
        }));
        let refresher = {
            let (node, settings, warm) = (node.clone(), Arc::clone(&settings), Arc::clone(&warm));
            tokio::spawn(async move {
                let mut said_spent = false;
                loop {
                    // Keeps the settings' values current and pokes new ones.
                    let found = settings.refresh();
                    // A long session in a fleet whose settings keep coming
                    // under new names spends its client. A new client on
                    // this node would grow the node's channel table past
                    // the bound the client's own limit keeps, so the user
                    // is told instead.
                    if settings.is_spent() && !said_spent {
                        said_spent = true;
                        crate::errln!(
                            "note: this session has asked as many settings as one client may; \
                             settings found from now on are listed without values (start a \
                             new puli shell to ask them)"
                        );
                    }
                    let names = Names::read(&node, &settings);
                    {
                        let mut warm = warm.lock();
                        if found > 0 {
                            warm.last_new_setting = Instant::now();
                        }
                        warm.names = names;
                    }
                    tokio::time::sleep(REFRESH).await;
                }
            })
        };
        Ok(Self {
            node,
            settings,
            warm,
            net: net.clone(),
            refresher,
        })
    }

    /// Waits until discovery has had a fair chance to show the fleet
    /// ([`pulicast::Discovery::settle`]), at most [`SETTLE_MAX`], so a
    /// script's first `nodes` sees the fleet: an empty view that has not
    /// changed yet only means nothing was heard yet.
    async fn settle(&self) {
        self.node.discovery().settle(SETTLE_MAX).await;
    }

    /// The settings commands' waits: listing waits only for what is left
    /// of the quiet time since a setting was last found.
    fn settings_how(&self, json: bool) -> config::How {
        let quiet = SETTINGS_QUIET.saturating_sub(self.warm.lock().last_new_setting.elapsed());
        config::How {
            timeout: SETTINGS_TIMEOUT,
            quiet,
            json,
            wait: false,
        }
    }

    /// Runs one command; `stop` ends a command that runs until told to.
    async fn run(&self, command: ShellCommand, stop: Stop) -> Result<()> {
        // Commands that end on a stop as at their end (echo's messages,
        // hz's last report) take it; the others end as interrupted.
        let interruptible = |stop: Stop| async move {
            stop.wait().await;
            Err(anyhow!("interrupted"))
        };
        tokio::select! {
            result = self.run_until(command, stop.clone()) => result,
            result = interruptible(stop), if !command_takes_stop(&command) => result,
        }
    }

    async fn run_until(&self, command: ShellCommand, stop: Stop) -> Result<()> {
        let node = &self.node;
        let ns = self.net.namespace.as_str();
        let settings = Arc::clone(&self.settings);
        let stop = stop.wait();
        match command {
            ShellCommand::Inspect(command) => command.run(node, ns, Listening::Long, stop).await,
            ShellCommand::Settings { json } => {
                config::run(&settings, &node.discovery(), None, &self.settings_how(json)).await
            }
            ShellCommand::Setting(command) => {
                let how = self.settings_how(false);
                config::run(&settings, &node.discovery(), Some(&command), &how).await
            }
            ShellCommand::Call(opts) => crate::call::call(node, &opts).await,
            ShellCommand::Pub(opts) => {
                // From a node of its own, as `puli pub`: the shell's node
                // would stay a publisher of the channel, with the type its
                // first value was read as, and that type would decide how
                // the next value is read.
                let publisher = self.net.node("puli-pub")?.start().await?;
                let sent = publish::run_on(&publisher, &opts, stop).await;
                if let Ok(sent) = &sent {
                    let name = resolve_name(&opts.channel, ns)?;
                    crate::errln!("published {sent} message(s) on {name}");
                }
                // Let the last datagrams leave before the node goes.
                tokio::time::sleep(Duration::from_millis(20)).await;
                publisher.stop();
                sent.map(|_| ())
            }
            ShellCommand::Sleep { secs } => {
                let wait = crate::flags::seconds("sleep", secs)?;
                tokio::select! {
                    _ = tokio::time::sleep(wait) => {}
                    _ = stop => {}
                }
                Ok(())
            }
            // The loops handle it before a command runs.
            ShellCommand::Exit => Ok(()),
        }
    }
}

/// Whether `command` ends by itself, as at its end, when told to stop.
fn command_takes_stop(command: &ShellCommand) -> bool {
    match command {
        ShellCommand::Inspect(command) => command.ends_on_stop(),
        ShellCommand::Pub(_) | ShellCommand::Sleep { .. } => true,
        _ => false,
    }
}

/// Tells a running command to stop: Ctrl-C at the prompt, a signal in a
/// script. One listener of the signal sets it, so the command and the
/// shell never race for the same signal.
/// It counts the signals of the session; a command stops at the first
/// one after it began.
#[derive(Clone)]
struct Stop {
    signals: tokio::sync::watch::Receiver<u64>,
    since: u64,
}

impl Stop {
    /// Stops at the next signal that `signals` counts.
    fn from_now(signals: tokio::sync::watch::Receiver<u64>) -> Self {
        let since = *signals.borrow();
        Self { signals, since }
    }

    /// Resolves once told to stop (never, if no one can tell it any more).
    async fn wait(mut self) {
        let since = self.since;
        if self.signals.wait_for(|n| *n > since).await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        self.refresher.abort();
        self.node.stop();
    }
}

/// What one line asks for.
enum Parsed {
    /// Nothing: blank, a comment, or help (printed).
    Nothing,
    /// Leave the shell.
    Exit,
    /// A command to run.
    Run(ShellCommand),
}

/// Parses a line as a command. Help is printed here; a line that is no
/// command is an error that says why (and what was meant, if it can).
fn parse(line: &str) -> Result<Parsed> {
    let trimmed = line.trim();
    if trimmed.is_empty() || trimmed.starts_with('#') {
        return Ok(Parsed::Nothing);
    }
    let words = shlex::split(trimmed).ok_or_else(|| anyhow!("unbalanced quotes"))?;
    match Line::try_parse_from(words) {
        Ok(Line {
            command: ShellCommand::Exit,
        }) => Ok(Parsed::Exit),
        Ok(line) => Ok(Parsed::Run(line.command)),
        Err(e) => match e.kind() {
            clap::error::ErrorKind::DisplayHelp
            | clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
            | clap::error::ErrorKind::DisplayVersion => {
                crate::inspect::print_text(&e.render().to_string());
                Ok(Parsed::Nothing)
            }
            // clap's message, without its "error: " (the shell says it)
            // and its usage lines (`help` has them).
            _ => {
                let text = e.render().to_string();
                let kept: Vec<&str> = text
                    .lines()
                    .filter(|l| !l.is_empty())
                    .filter(|l| !l.starts_with("Usage:") && !l.starts_with("For more information"))
                    .collect();
                Err(anyhow!("{}", kept.join("\n").trim_start_matches("error: ")))
            }
        },
    }
}

/// The history file: `--history`, or in the XDG state directory.
fn history_path(args: &ShellArgs) -> Option<PathBuf> {
    if let Some(p) = &args.history {
        return Some(p.clone());
    }
    let state = std::env::var_os("XDG_STATE_HOME")
        .filter(|d| !d.is_empty())
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".local/state")))?;
    Some(state.join("puli").join("shell_history"))
}

/// Runs `puli shell`; returns whether every command of a script
/// succeeded (at a terminal: true, the person saw each error).
pub fn run(args: ShellArgs) -> Result<bool> {
    // A script that can't be read fails before a node starts.
    let script: Option<Box<dyn BufRead>> = match &args.script {
        Some(p) if p.as_os_str() == "-" => Some(Box::new(std::io::stdin().lock())),
        Some(p) => {
            let file =
                std::fs::File::open(p).with_context(|| format!("opening {}", p.display()))?;
            Some(Box::new(std::io::BufReader::new(file)))
        }
        None if !std::io::stdin().is_terminal() => Some(Box::new(std::io::stdin().lock())),
        None => None,
    };
    let runtime = tokio::runtime::Runtime::new()?;
    let session = runtime.block_on(Session::start(&args.net))?;
    runtime.block_on(session.settle());
    let ok = match script {
        Some(lines) => run_script(&runtime, &session, lines, &args),
        None => interactive(&runtime, &session, &args)?,
    };
    drop(session);
    Ok(ok)
}

/// Reports a command's failure as the shell does.
fn report(e: &anyhow::Error) {
    crate::errln!("error: {e:#}");
}

/// Runs the lines of a script; stops early at `exit`, or at the first
/// failure with `--exit-on-error`. Ctrl-C, SIGTERM or SIGHUP end the
/// command that runs as its end would (`hz` prints its summary) and the
/// script with it; between commands (waiting for the next line of a
/// pipe) they end the shell at once.
fn run_script(
    runtime: &tokio::runtime::Runtime,
    session: &Session,
    lines: Box<dyn BufRead>,
    args: &ShellArgs,
) -> bool {
    // A signal stops the command running, not the shell.
    crate::keep_running_after_signals();
    let (stopped, _) = tokio::sync::watch::channel(0u64);
    let stopped = Arc::new(stopped);
    // Whether a command runs: the signal's task decides under this lock
    // whether to end the process or the command.
    let running = Arc::new(Mutex::new(false));
    let watcher = {
        let (stopped, running, node) = (
            Arc::clone(&stopped),
            Arc::clone(&running),
            session.node.clone(),
        );
        runtime.spawn(async move {
            crate::stop_requested().await;
            let running = running.lock();
            if !*running {
                crate::errln!("puli shell: stopped by a signal");
                node.stop();
                std::process::exit(1);
            }
            stopped.send_replace(1);
        })
    };
    let stop = || Stop::from_now(stopped.subscribe());
    let mut ok = true;
    for (number, line) in lines.lines().enumerate() {
        let line = match line {
            Ok(line) => line,
            Err(e) => {
                report(&anyhow!("reading the script: {e}"));
                return false;
            }
        };
        if args.echo && !line.trim().is_empty() {
            crate::outln!("{PROMPT}{line}");
        }
        let result = match parse(&line) {
            Ok(Parsed::Nothing) => Ok(()),
            Ok(Parsed::Exit) => break,
            Ok(Parsed::Run(command)) => {
                *running.lock() = true;
                let result = runtime.block_on(session.run(command, stop()));
                *running.lock() = false;
                result
            }
            Err(e) => Err(e),
        };
        if let Err(e) = result {
            ok = false;
            report(&e.context(format!("line {}", number + 1)));
            if args.exit_on_error {
                break;
            }
        }
        if *stopped.borrow() > 0 {
            report(&anyhow!("stopped by a signal after line {}", number + 1));
            ok = false;
            break;
        }
    }
    watcher.abort();
    ok
}

/// The terminal session: prompt, editing, completion and history.
fn interactive(
    runtime: &tokio::runtime::Runtime,
    session: &Session,
    args: &ShellArgs,
) -> Result<bool> {
    let config = Config::builder()
        .completion_type(CompletionType::List)
        .max_history_size(HISTORY_LINES)?
        .history_ignore_dups(true)?
        .history_ignore_space(true)
        .build();
    let mut editor: Editor<ShellHelper, FileHistory> = Editor::with_config(config)?;
    editor.set_helper(Some(ShellHelper::new(
        Arc::clone(&session.warm),
        &session.net.namespace,
    )));
    let history = history_path(args);
    if let Some(path) = &history {
        // None yet is the first session; another failure only costs the
        // history, which is said once.
        if path.exists() {
            if let Err(e) = editor.load_history(path) {
                crate::errln!("note: history not read from {}: {e}", path.display());
            }
        }
    }
    let mut history_failed = false;
    // One listener of Ctrl-C for the session, from before the first
    // command, counting: a command stops at the first Ctrl-C after it
    // began (at the prompt the terminal is raw, and Ctrl-C is a key).
    let (interrupts, _) = tokio::sync::watch::channel(0u64);
    let interrupts = Arc::new(interrupts);
    let listener = {
        let interrupts = Arc::clone(&interrupts);
        runtime.spawn(async move {
            while tokio::signal::ctrl_c().await.is_ok() {
                interrupts.send_modify(|n| *n += 1);
            }
        })
    };
    crate::errln!("puli shell: `help` lists the commands; Tab completes; Ctrl-D leaves.");
    loop {
        let line = match editor.readline(PROMPT) {
            Ok(line) => line,
            // Ctrl-C at the prompt drops the line, as in bash.
            Err(ReadlineError::Interrupted) => continue,
            Err(ReadlineError::Eof) => break,
            Err(e) => return Err(e.into()),
        };
        if !line.trim().is_empty() {
            let _ = editor.add_history_entry(line.as_str());
            if let Some(path) = &history {
                if let Err(e) = save_history(&mut editor, path) {
                    if !history_failed {
                        crate::errln!("note: history not kept in {}: {e}", path.display());
                        history_failed = true;
                    }
                }
            }
        }
        let result = match parse(&line) {
            Ok(Parsed::Nothing) => Ok(()),
            Ok(Parsed::Exit) => break,
            // Ctrl-C ends the command, not the shell.
            Ok(Parsed::Run(command)) => {
                let stop = Stop::from_now(interrupts.subscribe());
                runtime.block_on(session.run(command, stop))
            }
            Err(e) => Err(e),
        };
        if let Err(e) = result {
            report(&e);
        }
    }
    listener.abort();
    Ok(true)
}

/// Appends the new history to `path`, making its directory first.
fn save_history(editor: &mut Editor<ShellHelper, FileHistory>, path: &Path) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    editor.append_history(path)?;
    Ok(())
}

/// Completion for the shell's line editor, from the warm view.
#[derive(Helper, Hinter, Validator, Highlighter)]
pub struct ShellHelper {
    warm: Shared,
    namespace: String,
    /// Each command's long flags, and which of them take a value.
    commands: BTreeMap<String, Vec<(String, bool)>>,
    files: FilenameCompleter,
}

impl ShellHelper {
    fn new(warm: Shared, namespace: &str) -> Self {
        let mut commands = BTreeMap::new();
        let line = Line::command();
        for sub in line.get_subcommands() {
            let flags = sub
                .get_arguments()
                .filter_map(|a| {
                    let takes = a.get_action().takes_values();
                    a.get_long().map(|l| (format!("--{l}"), takes))
                })
                .collect();
            commands.insert(sub.get_name().to_string(), flags);
        }
        commands.insert("help".into(), Vec::new());
        commands.insert("quit".into(), Vec::new());
        Self {
            warm,
            namespace: namespace.to_string(),
            commands,
            files: FilenameCompleter::new(),
        }
    }

    /// The completions of the word that ends `before` (the line up to the
    /// cursor): where the word starts, and the words it may become.
    pub fn candidates(&self, before: &str) -> Completion {
        let start = before.rfind(char::is_whitespace).map_or(0, |i| {
            i + before[i..].chars().next().map_or(1, char::len_utf8)
        });
        let word = &before[start..];
        let mut earlier = before[..start].split_whitespace();
        let nearest = before[..start].split_whitespace().any(|w| w == "--nearest");
        let Some(command) = earlier.next() else {
            let all = self.commands.keys().cloned();
            return Completion::Words(start, matching(all, word));
        };
        let Some(flags) = self.commands.get(command) else {
            return Completion::Words(start, Vec::new());
        };
        // Which positional argument the word is, skipping flags and the
        // values of those that take one.
        let mut position = 0;
        let mut value_next = false;
        for w in earlier {
            if value_next {
                value_next = false;
            } else if w.starts_with("--") {
                value_next = flags.iter().any(|(f, takes)| f == w && *takes);
            } else {
                position += 1;
            }
        }
        if value_next {
            return Completion::Words(start, Vec::new());
        }
        if word.starts_with('-') {
            let all = flags.iter().map(|(f, _)| f.clone());
            return Completion::Words(start, matching(all, word));
        }
        let names = self.warm.lock().names.clone();
        let shown = |full: &String| shown_name(full, &self.namespace);
        let words: Vec<String> = match (command, position) {
            ("help", 0) => self.commands.keys().cloned().collect(),
            ("nodes", 0) => names.nodes,
            ("echo" | "hz" | "bw" | "pub", 0) => names.channels.iter().map(shown).collect(),
            ("get" | "set" | "unset" | "reset", 0) => names.settings,
            // A search from the shell's namespace out to the root: each
            // service as named from the namespace it is found in.
            ("call", 0) if nearest => names
                .services
                .keys()
                .filter_map(|full| searched_name(full, &self.namespace))
                .collect(),
            ("call", 0) => match word.split_once('@') {
                // `NAME@` completes the nodes that serve NAME.
                Some((service, _)) => names
                    .services
                    .iter()
                    .filter(|(full, _)| shown(full) == service)
                    .flat_map(|(_, servers)| servers.iter().map(|n| format!("{service}@{n}")))
                    .collect(),
                None => names.services.keys().map(shown).collect(),
            },
            ("pull" | "push" | "diff", 0) => return Completion::Files,
            _ => Vec::new(),
        };
        Completion::Words(start, matching(words.into_iter(), word))
    }
}

/// What Tab offers.
#[derive(Debug, PartialEq, Eq)]
pub enum Completion {
    /// Where the word starts, and what it may become.
    Words(usize, Vec<String>),
    /// A file name.
    Files,
}

/// `full` as typed in the shell's namespace: relative inside it,
/// absolute (a leading `/`) outside it.
fn shown_name(full: &str, namespace: &str) -> String {
    let ns = namespace.trim_matches('/');
    if ns.is_empty() {
        return full.to_string();
    }
    match full.strip_prefix(ns).and_then(|r| r.strip_prefix('/')) {
        Some(relative) => relative.to_string(),
        None => format!("/{full}"),
    }
}

/// The name `call --nearest` finds `full` by from `namespace`: relative to
/// the innermost of the namespace and its ancestors that holds it (from
/// `rover1/arm`, `rover1/laser` is `laser`); `None` if none does.
fn searched_name(full: &str, namespace: &str) -> Option<String> {
    let mut ns = namespace.trim_matches('/');
    loop {
        if ns.is_empty() {
            return Some(full.to_string());
        }
        if let Some(relative) = full.strip_prefix(ns).and_then(|r| r.strip_prefix('/')) {
            return Some(relative.to_string());
        }
        ns = ns.rsplit_once('/').map_or("", |(parent, _)| parent);
    }
}

fn matching(all: impl Iterator<Item = String>, prefix: &str) -> Vec<String> {
    let mut found: Vec<String> = all.filter(|w| w.starts_with(prefix)).collect();
    found.sort();
    found.dedup();
    found
}

impl Completer for ShellHelper {
    type Candidate = Pair;

    fn complete(
        &self,
        line: &str,
        pos: usize,
        ctx: &rustyline::Context<'_>,
    ) -> rustyline::Result<(usize, Vec<Pair>)> {
        match self.candidates(&line[..pos]) {
            Completion::Files => self.files.complete(line, pos, ctx),
            Completion::Words(start, words) => {
                // A single match is taken whole, with the space after it.
                let single = words.len() == 1;
                // A single match is quoted where the line's parser would
                // read it otherwise (a node named `it's`). Several are not:
                // the editor inserts what they have in common, and an
                // opening quote there would match nothing at the next Tab.
                let pairs = words
                    .into_iter()
                    .map(|w| {
                        let typed = match single {
                            true => shlex::try_quote(&w).map_or_else(|_| w.clone(), |q| q.into()),
                            false => w.clone(),
                        };
                        Pair {
                            replacement: match single && !w.ends_with('@') {
                                true => format!("{typed} "),
                                false => typed,
                            },
                            display: w,
                        }
                    })
                    .collect();
                Ok((start, pairs))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn helper(namespace: &str) -> ShellHelper {
        let names = Names {
            nodes: vec!["planner_a".into(), "planner_b".into(), "rover1".into()],
            channels: vec!["rover1/pose".into(), "rover1/status".into()],
            services: BTreeMap::from([
                (
                    "plan".to_string(),
                    vec!["planner_a".into(), "planner_b".into()],
                ),
                ("rover1/distance_to".to_string(), vec!["rover1".into()]),
            ]),
            settings: vec!["rover1/max_speed".into(), "rover1/mode".into()],
        };
        let warm = Arc::new(Mutex::new(Warm {
            names,
            last_new_setting: Instant::now(),
        }));
        ShellHelper::new(warm, namespace)
    }

    fn words(h: &ShellHelper, before: &str) -> Vec<String> {
        match h.candidates(before) {
            Completion::Words(_, w) => w,
            Completion::Files => vec!["<files>".into()],
        }
    }

    /// The shell takes every fleet command puli-sniffer takes, with the
    /// same arguments: both flatten [`Inspect`] (a flag added to
    /// `puli-sniffer channels` is in the shell's `channels` too).
    #[test]
    fn the_shell_takes_the_sniffers_commands_with_the_same_flags() {
        let shell = Line::command();
        let inspect = <Inspect as clap::Subcommand>::augment_subcommands(clap::Command::new("x"));
        let args = |c: &clap::Command| -> Vec<String> {
            c.get_arguments().map(|a| a.get_id().to_string()).collect()
        };
        let mut checked = 0;
        for command in inspect.get_subcommands() {
            let name = command.get_name();
            let in_shell = shell
                .find_subcommand(name)
                .unwrap_or_else(|| panic!("the shell has no {name}"));
            assert_eq!(args(in_shell), args(command), "{name}");
            checked += 1;
        }
        assert_eq!(checked, 6);
        // And a line parses into it, flags and all.
        match parse("channels --for 0.5 --all --json").unwrap() {
            Parsed::Run(ShellCommand::Inspect(Inspect::Channels(a))) => {
                assert_eq!((a.for_secs, a.all, a.json), (Some(0.5), true, true));
            }
            _ => panic!("channels parsed as something else"),
        }
    }

    #[test]
    fn commands_then_names_by_what_each_command_takes() {
        let h = helper("");
        assert_eq!(words(&h, "ca"), ["call"]);
        assert_eq!(words(&h, "se"), ["services", "set", "settings"]);
        assert_eq!(words(&h, "call "), ["plan", "rover1/distance_to"]);
        assert_eq!(words(&h, "call rover1/d"), ["rover1/distance_to"]);
        assert_eq!(
            words(&h, "call plan@"),
            ["plan@planner_a", "plan@planner_b"]
        );
        assert_eq!(words(&h, "call plan@planner_b"), ["plan@planner_b"]);
        assert_eq!(words(&h, "echo rover1/p"), ["rover1/pose"]);
        assert_eq!(words(&h, "hz --for 2 rover1/s"), ["rover1/status"]);
        assert_eq!(
            words(&h, "get rover1/m"),
            ["rover1/max_speed", "rover1/mode"]
        );
        assert_eq!(words(&h, "nodes pl"), ["planner_a", "planner_b"]);
        assert_eq!(words(&h, "help ec"), ["echo"]);
        assert_eq!(words(&h, "push "), ["<files>"]);
        // Flags, and nothing where a flag's value or a JSON value goes.
        assert_eq!(words(&h, "echo --c"), ["--count"]);
        assert!(words(&h, "echo --count ").is_empty());
        assert!(words(&h, "call plan ").is_empty());
        assert!(words(&h, "bogus x").is_empty());
        // Where the word starts, after several spaces.
        assert_eq!(
            h.candidates("call   rov"),
            Completion::Words(7, vec!["rover1/distance_to".into()])
        );
    }

    #[test]
    fn names_are_offered_as_typed_in_the_shells_namespace() {
        let h = helper("rover1");
        assert_eq!(words(&h, "echo "), ["pose", "status"]);
        assert_eq!(words(&h, "call "), ["/plan", "distance_to"]);
        assert_eq!(
            words(&h, "call /plan@"),
            ["/plan@planner_a", "/plan@planner_b"]
        );
        assert_eq!(shown_name("rover10/x", "rover1"), "/rover10/x");
    }

    #[test]
    fn call_nearest_completes_names_as_the_search_finds_them() {
        // From rover1/arm, the root's `plan` is `plan` and rover1's
        // `distance_to` is `distance_to`: the search walks out to both.
        let h = helper("rover1/arm");
        assert_eq!(words(&h, "call --nearest "), ["distance_to", "plan"]);
        assert_eq!(words(&h, "call --nearest d"), ["distance_to"]);
        assert_eq!(words(&h, "call --n"), ["--nearest"]);
        // Without --nearest, names are as typed in the namespace.
        assert_eq!(words(&h, "call "), ["/plan", "/rover1/distance_to"]);
        assert_eq!(
            searched_name("rover10/x", "rover1"),
            Some("rover10/x".into())
        );
    }

    #[test]
    fn lines_parse_as_commands_with_clear_errors() {
        assert!(matches!(parse("  # a comment").unwrap(), Parsed::Nothing));
        assert!(matches!(parse("").unwrap(), Parsed::Nothing));
        assert!(matches!(parse("quit").unwrap(), Parsed::Exit));
        assert!(matches!(
            parse(r#"call plan '{"goal": [1, 2], "steps": 3}' --timeout 2"#).unwrap(),
            Parsed::Run(ShellCommand::Call(_))
        ));
        let e = parse("cal plan 1").err().unwrap().to_string();
        assert!(e.contains("unrecognized subcommand 'cal'"), "{e}");
        let e = parse("echo").err().unwrap().to_string();
        assert!(e.contains("<CHANNEL>"), "{e}");
        let e = parse("call plan '{").err().unwrap().to_string();
        assert_eq!(e, "unbalanced quotes");
    }
}

//! `puli config`: the fleet's distributed settings from the command line,
//! in the Pulicast 2.x `puliconf` file format (TOML: one key per setting,
//! `nan` for an unset value), so files move between the two tools.

use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use pulicast::{FileValue, FleetSettings, SettingInfo, SettingsFile};
use serde_json::json;

/// One row of `puli config list`.
pub fn row(s: &SettingInfo) -> serde_json::Value {
    let owners: Vec<&str> = s
        .owners
        .iter()
        .filter(|o| o.answered || !o.live)
        .map(|o| o.node.as_str())
        .collect();
    let claims: Vec<&str> = s.unanswered_claims().map(|o| o.node.as_str()).collect();
    json!({
        "name": s.name,
        "value": s.value_text(),
        "type": s.type_name(),
        "owners": owners,
        "unanswered_claims": claims,
        "locked": s.is_locked(),
        "stale": s.is_stale(),
        "about": s.about,
        "message": s.confirmed.as_ref().map(|c| c.message.clone()),
    })
}

/// Who owns a setting, marked when locked (two owners that answered) or
/// gone; a claim no confirmation came from is marked as one.
pub fn owner_text(s: &SettingInfo) -> String {
    let owners: Vec<String> = s
        .owners
        .iter()
        .map(|o| match o.live && !o.answered {
            true => format!("{} (claims it, never answered)", o.node),
            false => o.node.clone(),
        })
        .collect();
    let mark = if s.is_locked() {
        " (locked)"
    } else if s.is_stale() {
        " (gone)"
    } else {
        ""
    };
    owners.join(",") + mark
}

/// `puli config list` as a table.
pub fn table(settings: &[SettingInfo]) -> String {
    let mut rows = vec![[
        "NAME".to_string(),
        "VALUE".into(),
        "TYPE".into(),
        "OWNER".into(),
        "ABOUT".into(),
    ]];
    for s in settings {
        // Every cell comes from the network: none may break its row.
        let cell = |text: &str| crate::one_line(text).into_owned();
        rows.push([
            cell(&s.name),
            cell(&s.value_text().unwrap_or_else(|| "?".into())),
            cell(&s.type_name().unwrap_or_else(|| "?".into())),
            cell(&owner_text(s)),
            cell(s.about.as_deref().unwrap_or_default()),
        ]);
    }
    let widths: Vec<usize> = (0..4)
        .map(|i| rows.iter().map(|r| r[i].chars().count()).max().unwrap_or(0))
        .collect();
    let mut out = String::new();
    for r in rows {
        for (i, cell) in r.iter().enumerate() {
            match widths.get(i) {
                Some(w) => out += &format!("{cell:<w$}  ", w = *w),
                None => out += cell,
            }
        }
        out = out.trim_end().to_string() + "\n";
    }
    out
}

/// A command on settings: `puli config`'s and `puli shell`'s.
#[derive(clap::Subcommand, Debug, Clone)]
pub enum SettingCommand {
    /// One setting's value.
    Get {
        /// Its name (`rover1/max_speed`).
        name: String,
    },
    /// Ask a setting's owner to take a value (read as the setting's type).
    Set {
        /// Its name.
        name: String,
        /// The value.
        #[arg(allow_hyphen_values = true)]
        value: String,
    },
    /// Ask a setting's owner to drop its value.
    Unset {
        /// Its name.
        name: String,
    },
    /// Ask a setting's owner to go back to its default.
    Reset {
        /// Its name.
        name: String,
    },
    /// Write every setting to FILE (or standard output) as puliconf does.
    Pull {
        /// Where to write.
        file: Option<std::path::PathBuf>,
    },
    /// Apply FILE; print the changes made (as TOML).
    Push {
        /// The file.
        file: std::path::PathBuf,
        /// Reset each setting to its default first.
        #[arg(long, conflicts_with = "unset_first")]
        reset_first: bool,
        /// Unset each setting first.
        #[arg(long)]
        unset_first: bool,
    },
    /// Print what in FILE differs from the fleet (what push would change).
    Diff {
        /// The file.
        file: std::path::PathBuf,
    },
}

/// How a settings command waits and prints.
#[derive(Debug, Clone)]
pub struct How {
    /// The whole command ends within this long.
    pub timeout: Duration,
    /// Listing waits until no new setting has appeared for this long.
    pub quiet: Duration,
    /// JSON instead of text (list, get, set, unset, reset).
    pub json: bool,
    /// `get`, `set`, `unset` and `reset` wait for an owner up to the
    /// timeout; without it, a setting no node owns once discovery has
    /// settled fails then, naming the nearest setting that exists.
    pub wait: bool,
}

/// Runs `op` on setting `name`, and fails it as soon as discovery has
/// settled with no owner of `name` (unless `how.wait`): a typo fails in
/// about half a second, with the name meant, not after the whole wait.
async fn owned<T>(
    settings: &FleetSettings,
    fleet: &pulicast::Discovery,
    name: &str,
    how: &How,
    left: Duration,
    op: impl std::future::Future<Output = pulicast::Result<T>>,
) -> Result<T> {
    let started = Instant::now();
    let unknown = async {
        if how.wait {
            return std::future::pending().await;
        }
        fleet.settle(left).await;
        settings.refresh();
        let name = pulicast::resolve_name(name, "").unwrap_or_else(|_| name.to_string());
        let known = settings.snapshot();
        if known.iter().any(|s| s.name == name) {
            return std::future::pending().await;
        }
        let names = known.iter().map(|s| s.name.as_str());
        anyhow!(
            "{name}: no node owns it{} (none found in {:?}, once discovery settled; --wait waits for an owner)",
            crate::suggest::did_you_mean(&name, names),
            Duration::from_millis(u64::try_from(started.elapsed().as_millis()).unwrap_or(0)),
        )
    };
    tokio::select! {
        biased;
        done = op => Ok(done?),
        e = unknown => Err(e),
    }
}

/// Runs `command` (`None`: list every setting), printing its result.
pub async fn run(
    settings: &FleetSettings,
    fleet: &pulicast::Discovery,
    command: Option<&SettingCommand>,
    how: &How,
) -> Result<()> {
    let deadline = Instant::now() + how.timeout;
    let left = || deadline.saturating_duration_since(Instant::now());
    let list = || async {
        let listed = async {
            let all = settings.list(how.quiet).await;
            if all.is_empty() {
                crate::errln!("puli: no settings found");
            }
            all
        };
        tokio::time::timeout(left(), listed).await.map_err(|_| {
            anyhow!(
                "the fleet did not settle within --timeout {:?}",
                how.timeout
            )
        })
    };
    let show = |s: &SettingInfo| match how.json {
        true => crate::outln!("{}", row(s)),
        false => crate::outln!("{}", describe(s)),
    };
    let Some(command) = command else {
        let all = list().await?;
        match how.json {
            true => {
                let rows: Vec<_> = all.iter().map(row).collect();
                crate::outln!("{}", serde_json::Value::Array(rows));
            }
            false => crate::inspect::print_text(&table(&all)),
        }
        return Ok(());
    };
    match command {
        SettingCommand::Get { name } => {
            let op = settings.get(name, left());
            show(&owned(settings, fleet, name, how, left(), op).await?);
        }
        SettingCommand::Set { name, value } => {
            let op = settings.set_text(name, value, left());
            show(&owned(settings, fleet, name, how, left(), op).await?);
        }
        SettingCommand::Unset { name } => {
            let op = settings.unset(name, left());
            show(&owned(settings, fleet, name, how, left(), op).await?);
        }
        SettingCommand::Reset { name } => {
            let op = settings.reset(name, left());
            show(&owned(settings, fleet, name, how, left(), op).await?);
        }
        SettingCommand::Pull { file } => {
            let all = list().await?;
            let (doc, left_out) = SettingsFile::pull(&all);
            for skipped in left_out {
                crate::errln!("puli: left out {}: {}", skipped.name, skipped.reason);
            }
            match file {
                Some(path) => std::fs::write(path, doc.to_string())
                    .map_err(|e| anyhow!("writing {}: {e}", path.display()))?,
                None => crate::inspect::print_text(&doc.to_string()),
            }
        }
        SettingCommand::Push {
            file,
            reset_first,
            unset_first,
        } => {
            let doc = read_file(file)?;
            let all = list().await?;
            let pushed = push(settings, &all, &doc, *reset_first, *unset_first, deadline).await;
            let (changes, _) = SettingsFile::pull(&pushed.changed);
            if !pushed.changed.is_empty() {
                crate::outln!("# Minimal set of changes:");
                crate::inspect::print_text(&changes.to_string());
            }
            for (name, why) in &pushed.failed {
                crate::errln!("puli: {name}: {why}");
            }
            crate::errln!(
                "{} changed, {} unchanged, {} failed",
                pushed.changed.len(),
                pushed.unchanged.len(),
                pushed.failed.len()
            );
            if !pushed.failed.is_empty() {
                anyhow::bail!("{} settings were not set", pushed.failed.len());
            }
        }
        SettingCommand::Diff { file } => {
            let doc = read_file(file)?;
            let all = list().await?;
            let (diff, errors) = doc.differing(&all);
            for skipped in &errors {
                crate::errln!("puli: {}: {}", skipped.name, skipped.reason);
            }
            crate::inspect::print_text(&diff.to_string());
        }
    }
    Ok(())
}

/// What pushing a file did.
#[derive(Debug, Default)]
pub struct Pushed {
    /// Changed, with the value confirmed.
    pub changed: Vec<SettingInfo>,
    /// Already as the file says.
    pub unchanged: Vec<String>,
    /// Refused or unanswered, with why.
    pub failed: Vec<(String, String)>,
}

/// How long one setting's owner has to confirm a push's request before
/// that setting counts as failed and the push goes on (puliconf: 0.5 s).
pub const REQUEST_WAIT: Duration = Duration::from_secs(1);

/// Pushes `doc` as puliconf does: each key is a setting; optionally reset
/// or unset first; a setting already holding its value is left alone.
/// Each request waits at most [`REQUEST_WAIT`] (an owner that crashed
/// fails its settings, not the rest), and all end by `deadline`.
pub async fn push(
    settings: &FleetSettings,
    known: &[SettingInfo],
    doc: &SettingsFile,
    reset_first: bool,
    unset_first: bool,
    deadline: Instant,
) -> Pushed {
    let mut pushed = Pushed::default();
    for entry in doc.entries() {
        let left = || {
            deadline
                .saturating_duration_since(Instant::now())
                .min(REQUEST_WAIT)
        };
        let name = entry.name.as_str();
        let Some(setting) = known.iter().find(|s| s.name == name) else {
            pushed
                .failed
                .push((name.to_string(), "no node owns this setting".into()));
            continue;
        };
        let target = match entry.value {
            Ok(t) => t,
            Err(why) => {
                pushed.failed.push((name.to_string(), why));
                continue;
            }
        };
        let mut current = setting.clone();
        let first = match (reset_first, unset_first) {
            (true, _) => Some(settings.reset(name, left()).await),
            (false, true) => Some(settings.unset(name, left()).await),
            _ => None,
        };
        match first {
            Some(Ok(now)) => current = now,
            Some(Err(e)) => {
                pushed.failed.push((name.to_string(), e.to_string()));
                continue;
            }
            None => {}
        }
        if current.holds(&target) {
            pushed.unchanged.push(name.to_string());
            continue;
        }
        let result = match target {
            FileValue::Unset => settings.unset(name, left()).await,
            FileValue::Value(v) => settings.set(name, v, left()).await,
            FileValue::Structured(j) => settings.set_json(name, j, left()).await,
        };
        match result {
            Ok(now) => pushed.changed.push(now),
            Err(e) => pushed.failed.push((name.to_string(), e.to_string())),
        }
    }
    pushed
}

/// Reads a puliconf file.
pub fn read_file(path: &std::path::Path) -> Result<SettingsFile> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    text.parse::<SettingsFile>()
        .map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// A setting's value, and its owner's warning if it gave one (other than
/// what the setting is, which answers a poke), for `get` and `set`.
pub fn describe(s: &SettingInfo) -> String {
    let value = s.value_text().unwrap_or_else(|| "?".into());
    match s.confirmed.as_ref().map(|c| c.message.as_str()) {
        Some(m) if !m.is_empty() && Some(m) != s.about.as_deref() => format!("{value}  ({m})"),
        _ => value,
    }
}

/// The hidden `puli config-owner` role: a node owning `count` settings
/// (`setting_00`, ... in its namespace, cycling through a checked `f64`,
/// an `i32`, a `bool` and a `String`), optionally started from a settings
/// file, until killed or `for_secs` ends. For multi-process tests.
#[derive(clap::Args, Debug)]
pub struct OwnerArgs {
    #[command(flatten)]
    net: crate::flags::NetArgs,
    /// The node's name.
    #[arg(long)]
    name: String,
    /// How many settings.
    #[arg(long, default_value_t = 4)]
    count: usize,
    /// Start-up values (`NodeBuilder::settings_file`).
    #[arg(long)]
    settings_file: Option<std::path::PathBuf>,
    /// Stop after this many seconds.
    #[arg(long = "for", default_value_t = 60.0)]
    for_secs: f64,
}

/// Runs the `config-owner` role.
pub async fn own(args: OwnerArgs) -> Result<()> {
    use pulicast::Check;
    let mut builder = args.net.node(&args.name)?;
    if let Some(file) = &args.settings_file {
        builder = builder.settings_file(file);
    }
    let node = builder.start().await?;
    let mut held: Vec<Box<dyn std::any::Any + Send>> = Vec::new();
    for i in 0..args.count {
        let name = format!("setting_{i:02}");
        let n = i32::try_from(i)?;
        match i % 4 {
            0 => held.push(Box::new(node.setting_checked(
                &name,
                f64::from(n),
                vec![Check::Range(0.0, 100.0)],
            )?)),
            1 => held.push(Box::new(node.setting_checked(
                &name,
                n,
                vec![Check::AtLeast(0)],
            )?)),
            2 => held.push(Box::new(node.setting(&name, false)?)),
            _ => held.push(Box::new(node.setting(&name, format!("v{i}"))?)),
        }
    }
    crate::errln!("READY {}", json!({"settings": args.count}));
    let stop = crate::stop_requested();
    tokio::select! {
        _ = tokio::time::sleep(crate::flags::seconds("--for", args.for_secs)?) => {}
        _ = stop => {}
    }
    drop(held);
    node.stop();
    Ok(())
}

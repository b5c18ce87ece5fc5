//! The live dashboard `puli-sniffer` shows without arguments: the fleet's
//! nodes, channels and settings, refreshed five times a second, with the
//! last value of every channel as text, and one channel's messages on
//! demand. Hidden channels (`.config/...`, see
//! [`pulicast::is_hidden_channel`]) are left out unless asked for (`h`).
//!
//! [`Model`] holds what is shown and [`render`] draws it; both are free of the
//! terminal, so tests draw into ratatui's test backend. [`run`] is the
//! terminal loop; [`print_tables`] is what happens when stdout is not a
//! terminal.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::io::IsTerminal;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Result;
use parking_lot::Mutex;
use pulicast::{Bytes, FleetSettings, MemberView, Node, SettingInfo, TypeEncoding, TypeInfo};
use ratatui::crossterm::event::{self, Event, KeyCode, KeyEventKind, KeyModifiers};
use ratatui::layout::{Constraint, Layout};
use ratatui::style::{Color, Modifier, Style, Stylize};
use ratatui::text::Line;
use ratatui::widgets::{Block, Borders, Paragraph, Row, Table, TableState, Tabs};
use ratatui::Frame;

use crate::sniff::{channel_rows, ChannelRow, ChannelWatch};

/// How often the screen is redrawn.
pub const REFRESH: Duration = Duration::from_millis(200);

/// Messages kept for the channel view.
const DETAIL_LINES: usize = 200;

/// Which table is shown.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum View {
    /// The nodes.
    Nodes,
    /// The channels.
    #[default]
    Channels,
    /// The distributed settings.
    Settings,
}

impl View {
    const ALL: [View; 3] = [View::Nodes, View::Channels, View::Settings];

    fn index(self) -> usize {
        Self::ALL.iter().position(|v| *v == self).unwrap_or(0)
    }

    fn step(self, forward: bool) -> View {
        let n = Self::ALL.len();
        let i = if forward {
            self.index() + 1
        } else {
            self.index() + n - 1
        };
        Self::ALL[i % n]
    }
}

/// Everything on screen, refreshed from the fleet.
#[derive(Debug, Default)]
pub struct Model {
    /// Nodes, sorted by name.
    pub nodes: Vec<MemberView>,
    /// Channels, sorted by name.
    pub channels: Vec<ChannelRow>,
    /// The fleet's settings, sorted by name.
    pub settings: Vec<SettingInfo>,
    /// Show hidden channels (settings' and `__nodes`) too.
    pub show_hidden: bool,
    /// The last value seen on each channel, as text.
    pub last_values: HashMap<String, String>,
    /// Which table is shown.
    pub view: View,
    /// Only rows whose name contains this.
    pub filter: String,
    /// Typing into the filter.
    pub editing_filter: bool,
    /// The channel whose messages are shown, if one is open.
    pub detail: Option<String>,
    /// Its latest messages, newest last.
    pub detail_lines: VecDeque<String>,
    /// Selected row.
    pub selected: usize,
    /// The port, for the title.
    pub port: u16,
}

impl Model {
    fn visible_nodes(&self) -> Vec<&MemberView> {
        self.nodes
            .iter()
            .filter(|m| m.name.contains(&self.filter) || m.namespace.contains(&self.filter))
            .collect()
    }

    fn visible_channels(&self) -> Vec<&ChannelRow> {
        self.channels
            .iter()
            .filter(|c| c.name.contains(&self.filter))
            .filter(|c| self.show_hidden || !pulicast::is_hidden_channel(&c.name))
            .collect()
    }

    fn visible_settings(&self) -> Vec<&SettingInfo> {
        self.settings
            .iter()
            .filter(|s| s.name.contains(&self.filter))
            .collect()
    }

    fn rows(&self) -> usize {
        match self.view {
            View::Nodes => self.visible_nodes().len(),
            View::Channels => self.visible_channels().len(),
            View::Settings => self.visible_settings().len(),
        }
    }

    /// Applies a key; false when the user asked to quit.
    pub fn key(&mut self, code: KeyCode, modifiers: KeyModifiers) -> bool {
        if modifiers.contains(KeyModifiers::CONTROL) && code == KeyCode::Char('c') {
            return false;
        }
        if self.editing_filter {
            match code {
                KeyCode::Enter => self.editing_filter = false,
                KeyCode::Esc => {
                    self.editing_filter = false;
                    self.filter.clear();
                }
                KeyCode::Backspace => {
                    self.filter.pop();
                }
                KeyCode::Char(c) => self.filter.push(c),
                _ => {}
            }
            self.selected = 0;
            return true;
        }
        let rows = self.rows();
        match code {
            KeyCode::Char('q') => return false,
            KeyCode::Esc | KeyCode::Backspace if self.detail.is_some() => self.detail = None,
            KeyCode::Esc => self.filter.clear(),
            KeyCode::Tab | KeyCode::Right | KeyCode::BackTab | KeyCode::Left => {
                let forward = matches!(code, KeyCode::Tab | KeyCode::Right);
                self.view = self.view.step(forward);
                self.selected = 0;
            }
            KeyCode::Char('h') => {
                self.show_hidden = !self.show_hidden;
                self.selected = 0;
            }
            KeyCode::Char('/') => self.editing_filter = true,
            KeyCode::Up | KeyCode::Char('k') => self.selected = self.selected.saturating_sub(1),
            KeyCode::Down | KeyCode::Char('j') => {
                self.selected = (self.selected + 1).min(rows.saturating_sub(1))
            }
            KeyCode::PageUp => self.selected = self.selected.saturating_sub(20),
            KeyCode::PageDown => self.selected = (self.selected + 20).min(rows.saturating_sub(1)),
            KeyCode::Home => self.selected = 0,
            KeyCode::End => self.selected = rows.saturating_sub(1),
            KeyCode::Enter if self.view == View::Channels => {
                if let Some(c) = self.visible_channels().get(self.selected) {
                    self.detail = Some(c.name.clone());
                    self.detail_lines.clear();
                }
            }
            _ => {}
        }
        true
    }
}

/// Draws the model.
pub fn render(frame: &mut Frame<'_>, model: &Model) {
    let [top, body, bottom] = Layout::vertical([
        Constraint::Length(3),
        Constraint::Min(3),
        Constraint::Length(1),
    ])
    .areas(frame.area());
    let live = model.nodes.iter().filter(|m| m.is_live()).count();
    let title = format!(
        " puli-sniffer  port {}  {} nodes ({} live)  {} channels  {} settings ",
        model.port,
        model.nodes.len(),
        live,
        model
            .channels
            .iter()
            .filter(|c| model.show_hidden || !pulicast::is_hidden_channel(&c.name))
            .count(),
        model.settings.len()
    );
    let tabs = Tabs::new(vec!["Nodes", "Channels", "Settings"])
        .select(model.view.index())
        .block(Block::default().borders(Borders::ALL).title(title))
        .highlight_style(Style::default().add_modifier(Modifier::REVERSED));
    frame.render_widget(tabs, top);

    let mut state = TableState::default().with_selected(Some(model.selected));
    if let Some(channel) = &model.detail {
        let lines: Vec<Line<'_>> = model
            .detail_lines
            .iter()
            .map(|l| Line::raw(l.as_str()))
            .collect();
        let height = usize::from(body.height.saturating_sub(2));
        let skip = lines.len().saturating_sub(height);
        let paragraph = Paragraph::new(lines[skip..].to_vec()).block(
            Block::default()
                .borders(Borders::ALL)
                .title(format!(" {channel} (Esc: back) ")),
        );
        frame.render_widget(paragraph, body);
    } else {
        match model.view {
            View::Nodes => {
                let rows = model.visible_nodes().into_iter().map(|m| {
                    let session = m
                        .session
                        .map(|s| s.to_string()[..8].to_string())
                        .unwrap_or_else(|| "2.x".into());
                    Row::new(vec![
                        m.name.clone(),
                        session,
                        m.host.clone(),
                        m.address.to_string(),
                        format!("{:?}", m.state).to_lowercase(),
                        m.channels
                            .iter()
                            .filter(|c| c.publishes)
                            .count()
                            .to_string(),
                        m.channels
                            .iter()
                            .filter(|c| c.subscribes)
                            .count()
                            .to_string(),
                        m.namespace.clone(),
                    ])
                });
                let table = Table::new(
                    rows,
                    [
                        Constraint::Min(16),
                        Constraint::Length(9),
                        Constraint::Length(12),
                        Constraint::Length(22),
                        Constraint::Length(8),
                        Constraint::Length(4),
                        Constraint::Length(4),
                        Constraint::Min(10),
                    ],
                )
                .header(
                    Row::new(vec![
                        "NAME",
                        "SESSION",
                        "HOST",
                        "ADDRESS",
                        "STATE",
                        "PUB",
                        "SUB",
                        "NAMESPACE",
                    ])
                    .bold(),
                )
                .row_highlight_style(Style::default().add_modifier(Modifier::REVERSED))
                .block(Block::default().borders(Borders::ALL));
                frame.render_stateful_widget(table, body, &mut state);
            }
            View::Channels => {
                let rows = model.visible_channels().into_iter().map(|c| {
                    let row = Row::new(vec![
                        c.name.clone(),
                        format!("{:.1}", c.rate_hz),
                        human_bytes(c.bandwidth),
                        format!("{:.1}%", c.loss * 100.0),
                        format!("{}/{}", c.publishers.len(), c.subscribers.len()),
                        type_cell(c),
                        match &c.type_conflict {
                            // What disagrees matters more than the last value.
                            Some(conflict) => conflict.clone(),
                            None => model.last_values.get(&c.name).cloned().unwrap_or_default(),
                        },
                    ]);
                    match c.type_conflict {
                        Some(_) => row.style(Style::default().fg(Color::Red)),
                        None => row,
                    }
                });
                let table = Table::new(
                    rows,
                    [
                        Constraint::Min(20),
                        Constraint::Length(8),
                        Constraint::Length(9),
                        Constraint::Length(6),
                        Constraint::Length(7),
                        Constraint::Length(14),
                        Constraint::Min(20),
                    ],
                )
                .header(
                    Row::new(vec![
                        "CHANNEL",
                        "HZ",
                        "BW",
                        "LOSS",
                        "PUB/SUB",
                        "TYPE",
                        "LAST VALUE",
                    ])
                    .bold(),
                )
                .row_highlight_style(Style::default().add_modifier(Modifier::REVERSED))
                .block(Block::default().borders(Borders::ALL));
                frame.render_stateful_widget(table, body, &mut state);
            }
            View::Settings => {
                let rows = model.visible_settings().into_iter().map(|s| {
                    let row = Row::new(setting_cells(s));
                    if s.is_locked() || s.is_stale() {
                        row.style(Style::default().fg(Color::Red))
                    } else {
                        row
                    }
                });
                let table = Table::new(
                    rows,
                    [
                        Constraint::Min(18),
                        Constraint::Length(10),
                        Constraint::Length(11),
                        Constraint::Length(14),
                        Constraint::Fill(2),
                        Constraint::Fill(1),
                    ],
                )
                .header(
                    Row::new(vec![
                        "SETTING",
                        "VALUE",
                        "TYPE",
                        "OWNER",
                        "ABOUT",
                        "LAST MESSAGE",
                    ])
                    .bold(),
                )
                .row_highlight_style(Style::default().add_modifier(Modifier::REVERSED))
                .block(Block::default().borders(Borders::ALL));
                frame.render_stateful_widget(table, body, &mut state);
            }
        }
    }
    let help = if model.editing_filter {
        format!(" filter: {}_   (Enter: keep, Esc: clear)", model.filter)
    } else {
        let filter = if model.filter.is_empty() {
            String::new()
        } else {
            format!("  [filter: {}]", model.filter)
        };
        let hidden = if model.show_hidden {
            "h: hide hidden"
        } else {
            "h: show hidden"
        };
        format!(" Tab: nodes/channels/settings  ↑↓: move  /: filter  Enter: messages  {hidden}  Esc: back  q: quit{filter}")
    };
    frame.render_widget(Paragraph::new(help), bottom);
}

/// A setting's row: name, value, type, owner (marked when locked or
/// gone), what it is, and the owner's last message when it says more than
/// that (a refusal, a warning).
fn setting_cells(s: &SettingInfo) -> Vec<String> {
    vec![
        s.name.clone(),
        s.value_text().unwrap_or_else(|| "?".into()),
        s.type_name().unwrap_or_else(|| "?".into()),
        crate::config::owner_text(s),
        s.about.clone().unwrap_or_default(),
        s.confirmed
            .as_ref()
            .map(|c| c.message.clone())
            .filter(|m| Some(m) != s.about.as_ref())
            .unwrap_or_default(),
    ]
}

fn human_bytes(bytes_per_s: f64) -> String {
    match bytes_per_s {
        b if b >= 1e6 => format!("{:.1} MB/s", b / 1e6),
        b if b >= 1e3 => format!("{:.1} kB/s", b / 1e3),
        b => format!("{b:.0} B/s"),
    }
}

/// Keeps the model current: what discovery knows, what the channels carry.
pub struct Collector {
    node: Node,
    settings: FleetSettings,
    watch: ChannelWatch,
    last: Arc<Mutex<HashMap<String, Bytes>>>,
    detail: Option<(String, pulicast::Subscription<Bytes>)>,
}

impl Collector {
    /// Starts collecting through `node`.
    pub fn new(node: &Node) -> Self {
        let last: Arc<Mutex<HashMap<String, Bytes>>> = Arc::default();
        let mut watch = ChannelWatch::new(node);
        watch.keep_last(Arc::clone(&last));
        Self {
            node: node.clone(),
            settings: node.fleet_settings(),
            watch,
            last,
            detail: None,
        }
    }

    /// Refreshes `model` from the fleet.
    pub fn refresh(&mut self, model: &mut Model) {
        self.watch.watch_announced();
        let mut nodes = self.node.discovery().members();
        nodes.sort_by(|a, b| (&a.name, a.key).cmp(&(&b.name, b.key)));
        let types = announced_types(&nodes);
        model.channels = channel_rows(&nodes, &self.watch.meters(), self.watch.elapsed());
        model.nodes = nodes;
        // Pokes settings not yet heard: a read that changes nothing.
        self.settings.refresh();
        model.settings = self.settings.snapshot();
        let last = self.last.lock();
        model.last_values = last
            .iter()
            .map(|(channel, payload)| {
                let text = crate::sniff::value_text(channel, payload, types.get(channel));
                let text: String = text.chars().take(120).collect();
                (channel.clone(), text)
            })
            .collect();
        drop(last);
        model.selected = model.selected.min(model.rows().saturating_sub(1));
        // The open channel's messages.
        if model.detail.as_ref() != self.detail.as_ref().map(|(c, _)| c) {
            self.detail = model.detail.as_ref().and_then(|c| {
                let sub = self.node.channel(&format!("/{c}")).subscribe_raw().ok()?;
                Some((c.clone(), sub))
            });
        }
        if let Some((channel, sub)) = self.detail.as_mut() {
            while let Some(m) = sub.try_recv() {
                model.detail_lines.push_back(crate::sniff::echo_line(
                    channel,
                    &m,
                    types.get(channel.as_str()),
                ));
                if model.detail_lines.len() > DETAIL_LINES {
                    model.detail_lines.pop_front();
                }
            }
        }
    }
}

/// The native type each channel's members announce.
fn announced_types(nodes: &[MemberView]) -> BTreeMap<String, TypeInfo> {
    let mut types = BTreeMap::new();
    for m in nodes {
        for c in &m.channels {
            if let Some(t) = c
                .message_type
                .as_ref()
                .filter(|t| t.encoding == TypeEncoding::Native)
            {
                types.entry(c.name.clone()).or_insert_with(|| t.clone());
            }
        }
    }
    types
}

/// Runs the dashboard until the user quits; plain tables every second when
/// stdout is not a terminal.
pub async fn run(node: &Node, port: u16, for_secs: Option<f64>, all: bool) -> Result<()> {
    let end = for_secs.map(|s| Instant::now() + Duration::from_secs_f64(s.clamp(0.0, 86_400.0)));
    let mut collector = Collector::new(node);
    let mut model = Model {
        port,
        show_hidden: all,
        ..Model::default()
    };
    if !std::io::stdout().is_terminal() {
        // One listener for the whole run: no Ctrl-C falls between waits.
        let ctrl_c = crate::stop_requested();
        tokio::pin!(ctrl_c);
        loop {
            tokio::select! {
                _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                _ = &mut ctrl_c => return Ok(()),
            }
            collector.refresh(&mut model);
            print_tables(&model);
            if end.is_some_and(|e| Instant::now() >= e) {
                return Ok(());
            }
        }
    }
    // SIGTERM or SIGHUP end it like `q`, so the terminal is restored.
    let stopped = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flag = Arc::clone(&stopped);
    let watcher = tokio::spawn(async move {
        crate::stop_requested().await;
        flag.store(true, std::sync::atomic::Ordering::Relaxed);
    });
    let mut terminal = ratatui::init();
    let result = (|| -> Result<()> {
        loop {
            collector.refresh(&mut model);
            terminal.draw(|f| render(f, &model))?;
            if end.is_some_and(|e| Instant::now() >= e)
                || stopped.load(std::sync::atomic::Ordering::Relaxed)
            {
                return Ok(());
            }
            // Keys are read on this thread between refreshes; the node's
            // tasks run on the runtime's workers meanwhile.
            if event::poll(REFRESH)? {
                if let Event::Key(key) = event::read()? {
                    if key.kind == KeyEventKind::Press && !model.key(key.code, key.modifiers) {
                        return Ok(());
                    }
                }
            }
        }
    })();
    ratatui::restore();
    watcher.abort();
    result
}

/// A channel's type as the tables show it: marked `!` when members
/// disagree on it.
fn type_cell(c: &ChannelRow) -> String {
    let name = c.type_name.as_deref().unwrap_or("-");
    match c.type_conflict {
        Some(_) => format!("!{name}"),
        None => name.to_string(),
    }
}

/// The plain-text form of the dashboard, for logs and pipes.
pub fn print_tables(model: &Model) {
    crate::outln!("== {} nodes", model.nodes.len());
    for m in &model.nodes {
        crate::outln!(
            "{:<20} {:<8} {:<22} pub {:>3} sub {:>3} {}",
            m.name,
            format!("{:?}", m.state).to_lowercase(),
            m.address,
            m.channels.iter().filter(|c| c.publishes).count(),
            m.channels.iter().filter(|c| c.subscribes).count(),
            m.host
        );
    }
    let shown: Vec<&ChannelRow> = model
        .channels
        .iter()
        .filter(|c| model.show_hidden || !pulicast::is_hidden_channel(&c.name))
        .collect();
    let hidden = model.channels.len() - shown.len();
    match hidden {
        0 => crate::outln!("== {} channels", shown.len()),
        n => crate::outln!("== {} channels ({n} hidden: --all shows them)", shown.len()),
    }
    // As wide as the longest name, so a long one keeps its row's columns.
    let width = shown
        .iter()
        .map(|c| c.name.chars().count())
        .max()
        .unwrap_or(0)
        .clamp(32, 96);
    for c in shown {
        crate::outln!(
            "{:<width$} {:>8.1} Hz {:>10} {:>5.1}% {:<14} {}",
            crate::one_line(&c.name),
            c.rate_hz,
            human_bytes(c.bandwidth),
            c.loss * 100.0,
            type_cell(c),
            model
                .last_values
                .get(&c.name)
                .map(String::as_str)
                .unwrap_or("")
        );
        if let Some(conflict) = &c.type_conflict {
            crate::outln!("  types disagree: {conflict}");
        }
    }
    crate::outln!("== {} settings", model.settings.len());
    for s in &model.settings {
        crate::outln!("{}", setting_cells(s).join("  ").trim_end());
    }
}

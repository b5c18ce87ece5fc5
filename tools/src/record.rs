//! What `puli record` and `puli play` do: channels to an MCAP file and back,
//! payloads byte-identical.
//!
//! The file is standard MCAP, so any MCAP reader opens it and lists its
//! channels and schemas. Each channel's message encoding is `pulicast` (the
//! payload exactly as it was on the wire, type fingerprint included); its
//! schema is the type discovery announced: for native types a
//! `postcard-schema` description as JSON, for Pulicast 2.x messages the ZCM
//! definition as text. Channel metadata carries the fingerprint.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use pulicast::text::{hex, schema_of};
use pulicast::{Bytes, Node, TypeEncoding, TypeInfo};
use pulicast_proto::wire::zcm_types::{self, Dim, ZcmType};

use crate::unix_ns;

/// The message encoding we write: the raw pulicast payload.
pub const MESSAGE_ENCODING: &str = "pulicast";

/// Which channels to record or play: exact names, or `prefix/...` for a
/// whole namespace. No patterns: every channel except the internal `__` ones.
#[derive(Debug, Clone, Default)]
pub struct Selection {
    exact: Vec<String>,
    prefixes: Vec<String>,
}

impl Selection {
    /// Patterns resolved against `namespace`.
    pub fn new(patterns: &[String], namespace: &str) -> Result<Self> {
        let mut selection = Selection::default();
        for p in patterns {
            match p.strip_suffix("/...") {
                Some(prefix) => {
                    let resolved = pulicast::resolve_name(prefix, namespace)
                        .with_context(|| format!("bad namespace pattern {p:?}"))?;
                    selection.prefixes.push(format!("{resolved}/"));
                }
                None => selection.exact.push(
                    pulicast::resolve_name(p, namespace)
                        .with_context(|| format!("bad channel name {p:?}"))?,
                ),
            }
        }
        Ok(selection)
    }

    /// Whether `channel` is selected.
    pub fn matches(&self, channel: &str) -> bool {
        if self.exact.is_empty() && self.prefixes.is_empty() {
            return !crate::is_internal(channel);
        }
        self.exact.iter().any(|e| e == channel)
            || self
                .prefixes
                .iter()
                .any(|p| channel.starts_with(p.as_str()))
    }

    /// The exact names given (they are recorded even before anyone announces them).
    pub fn exact(&self) -> &[String] {
        &self.exact
    }
}

/// One received message on its way to the file.
struct Record {
    channel: String,
    ty: Option<TypeInfo>,
    seq: u32,
    log_time: u64,
    payload: Bytes,
}

/// Counts of one recording.
#[derive(Debug, Clone, Default)]
pub struct RecordStats {
    /// Messages the recorder's subscriptions received, per channel.
    pub received: BTreeMap<String, u64>,
    /// Messages written to the file, per channel.
    pub written: BTreeMap<String, u64>,
    /// Messages dropped by full subscription queues before the recorder saw them.
    pub queue_drops: u64,
    /// Size of the file.
    pub bytes: u64,
    /// Announced names not recorded because they are no channel names
    /// (anyone may announce one); past [`MAX_RECORDED`] channels, the
    /// others are not recorded either, which is said once.
    pub skipped: usize,
}

/// The most channels one recording subscribes to: a stranger announcing
/// thousands of names gets no more subscriptions than this.
pub const MAX_RECORDED: usize = 4096;

/// The ZCM definition of a 2.x message as text, for the MCAP schema record.
fn zcm_definition(name: &str) -> Option<String> {
    let def = zcm_types::KNOWN.iter().find(|s| s.name == name)?;
    let members: Vec<String> = def
        .members
        .iter()
        .map(|m| {
            let ty = match m.ty {
                ZcmType::Primitive(p) => p.to_string(),
                ZcmType::Struct(s) => s.name.to_string(),
            };
            let dims: String = m
                .dims
                .iter()
                .map(|d| match d {
                    Dim::Fixed(n) => format!("[{n}]"),
                    Dim::Variable(by) => format!("[{by}]"),
                })
                .collect();
            format!("    {ty} {}{dims};", m.name)
        })
        .collect();
    Some(format!(
        "struct {} {{\n{}\n}}\n",
        def.name,
        members.join("\n")
    ))
}

/// How often the recorder ends its chunk and makes the file durable: a
/// recorder killed outright (SIGKILL, power loss) loses at most this much.
pub const SYNC_PERIOD: Duration = Duration::from_secs(1);

/// Writes records to an MCAP file until the channel closes. Every
/// [`SYNC_PERIOD`] in which something arrived, the open chunk is closed and
/// written, and the file synced to disk, so all but the last moments
/// survive a crash ([`readable`] reads such a file).
fn write_file(
    path: &Path,
    file: File,
    rx: mpsc::Receiver<Record>,
) -> Result<(BTreeMap<String, u64>, u64)> {
    let syncer = Syncer::start(&file).with_context(|| format!("opening {}", path.display()))?;
    let mut writer = mcap::WriteOptions::new()
        .library(concat!("pulicast-tools ", env!("CARGO_PKG_VERSION")))
        .profile("")
        .create(BufWriter::new(file))
        .context("starting the MCAP file")?;
    let mut ids: HashMap<String, u16> = HashMap::new();
    let mut written: BTreeMap<String, u64> = BTreeMap::new();
    let mut synced = Instant::now();
    let mut unsynced = false;
    loop {
        let record = match rx.recv_timeout(SYNC_PERIOD.saturating_sub(synced.elapsed())) {
            Ok(record) => Some(record),
            Err(mpsc::RecvTimeoutError::Timeout) => None,
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        };
        if unsynced && synced.elapsed() >= SYNC_PERIOD {
            writer.flush().context("writing the MCAP file")?;
            syncer.request();
            unsynced = false;
        }
        if !unsynced {
            synced = Instant::now();
        }
        let Some(record) = record else { continue };
        unsynced = true;
        let Record {
            channel,
            ty,
            seq,
            log_time,
            payload,
        } = record;
        let id = match ids.get(&channel) {
            Some(id) => *id,
            None => {
                let schema_id = match &ty {
                    Some(t) if t.encoding == TypeEncoding::Native => match schema_of(t) {
                        Some(schema) => writer.add_schema(
                            &t.name,
                            "postcard-schema",
                            &serde_json::to_vec(&schema)?,
                        )?,
                        None => 0,
                    },
                    Some(t) => match zcm_definition(&t.name) {
                        Some(text) => writer.add_schema(&t.name, "zcm", text.as_bytes())?,
                        None => 0,
                    },
                    None => 0,
                };
                let mut metadata = BTreeMap::new();
                if let Some(t) = &ty {
                    metadata.insert("pulicast.type".into(), t.name.clone());
                    metadata.insert("pulicast.fingerprint".into(), hex(&t.fingerprint));
                }
                let id = writer.add_channel(schema_id, &channel, MESSAGE_ENCODING, &metadata)?;
                ids.insert(channel.clone(), id);
                id
            }
        };
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: seq,
            log_time,
            publish_time: log_time,
        };
        writer.write_to_known_channel(&header, &payload)?;
        *written.entry(channel).or_default() += 1;
    }
    writer.finish().context("finishing the MCAP file")?;
    drop(writer);
    syncer
        .finish()
        .with_context(|| format!("syncing {}", path.display()))?;
    let bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    Ok((written, bytes))
}

/// Syncs a file to disk on a thread of its own when asked, so that a slow
/// disk (an SD card) never holds up writing.
struct Syncer {
    ask: mpsc::SyncSender<()>,
    thread: std::thread::JoinHandle<std::io::Result<File>>,
}

impl Syncer {
    /// Starts syncing (a second handle on) `file`.
    fn start(file: &File) -> std::io::Result<Self> {
        let file = file.try_clone()?;
        let (ask, asked) = mpsc::sync_channel::<()>(1);
        let thread = std::thread::spawn(move || {
            for () in asked {
                file.sync_data()?;
            }
            Ok(file)
        });
        Ok(Self { ask, thread })
    }

    /// Asks for a sync of what was written so far; one already pending
    /// covers it.
    fn request(&self) {
        let _ = self.ask.try_send(());
    }

    /// Waits for pending syncs, then syncs the file whole; the first error.
    fn finish(self) -> std::io::Result<()> {
        drop(self.ask);
        let file = self
            .thread
            .join()
            .map_err(|_| std::io::Error::other("the sync thread failed"))??;
        file.sync_all()
    }
}

/// A recording's file, created before anything is recorded: a path that
/// can't be written fails the command at its start, not at its end.
#[derive(Debug)]
pub struct Output {
    path: PathBuf,
    file: File,
}

impl Output {
    /// Creates (or truncates) the file at `path`.
    pub fn create(path: &Path) -> Result<Self> {
        let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
        })
    }

    /// Where it is written.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Records the selected channels of the fleet `node` sees into `output`
/// for `duration` (or until Ctrl-C).
pub async fn record(
    node: &Node,
    output: Output,
    selection: &Selection,
    duration: Option<Duration>,
) -> Result<RecordStats> {
    let (tx, rx) = mpsc::channel::<Record>();
    // The file is written on a thread of its own, so compression never holds
    // up the subscriptions.
    let writer = std::thread::spawn(move || write_file(&output.path, output.file, rx));
    let received: Counts = Counts::default();
    let mut tasks: HashMap<String, tokio::task::JoinHandle<()>> = HashMap::new();
    let end = duration.map(|d| Instant::now() + d);
    let subscribe = |tasks: &mut HashMap<_, _>, channel: &str| -> Result<()> {
        if !tasks.contains_key(channel) {
            let task = record_channel(node, channel, tx.clone(), Counts::clone(&received))?;
            tasks.insert(channel.to_string(), task);
        }
        Ok(())
    };
    // Names heard that are no channel names, kept to count them once each
    // (bounded: past it, more are not counted).
    let mut skipped: HashSet<String> = HashSet::new();
    let mut full = false;
    for channel in selection.exact() {
        subscribe(&mut tasks, channel)?;
    }
    // One listener for the whole recording: a Ctrl-C that arrives while the
    // loop is busy is kept for the next wait, not lost.
    let ctrl_c = crate::stop_requested();
    tokio::pin!(ctrl_c);
    loop {
        // Once it records all it may, the fleet is not read again: a
        // stranger's thousands of names cost nothing more.
        if !full {
            for member in node.discovery().live_members() {
                for channel in member.channels.iter().filter(|c| c.publishes) {
                    let name = &channel.name;
                    if !selection.matches(name)
                        || tasks.contains_key(name)
                        || skipped.contains(name)
                    {
                        continue;
                    }
                    if tasks.len() >= MAX_RECORDED {
                        crate::errln!(
                            "puli: {MAX_RECORDED} channels are recorded already: the fleet's \
                             other channels are not recorded"
                        );
                        full = true;
                        break;
                    }
                    if let Err(e) = subscribe(&mut tasks, name) {
                        if skipped.len() < MAX_RECORDED {
                            if skipped.len() < 16 {
                                crate::errln!("puli: not recording {}: {e}", crate::one_line(name));
                            }
                            skipped.insert(name.clone());
                        }
                    }
                }
                if full {
                    break;
                }
            }
        }
        let left = end.map(|e| e.saturating_duration_since(Instant::now()));
        if left.is_some_and(|l| l.is_zero()) {
            break;
        }
        let nap = left
            .unwrap_or(Duration::from_millis(100))
            .min(Duration::from_millis(100));
        tokio::select! {
            _ = tokio::time::sleep(nap) => {}
            _ = &mut ctrl_c => break,
        }
    }
    let queue_drops = node.stats().dropped(pulicast::DropReason::QueueOverflow);
    // Stop receiving, then let the writer drain what was received.
    for task in tasks.values() {
        task.abort();
    }
    for (_, task) in tasks {
        let _ = task.await;
    }
    drop(tx);
    let (written, bytes) = writer
        .join()
        .map_err(|_| anyhow::anyhow!("the MCAP writer thread failed"))??;
    let received = received.lock().clone();
    Ok(RecordStats {
        received,
        written,
        queue_drops,
        bytes,
        skipped: skipped.len(),
    })
}

type Counts = std::sync::Arc<parking_lot::Mutex<BTreeMap<String, u64>>>;

/// Subscribes to `channel` and forwards what arrives to the writer.
fn record_channel(
    node: &Node,
    channel: &str,
    tx: mpsc::Sender<Record>,
    received: Counts,
) -> Result<tokio::task::JoinHandle<()>> {
    let handle = node.channel(&format!("/{channel}"));
    let mut sub = handle.subscribe_raw()?;
    let name = channel.to_string();
    Ok(tokio::spawn(async move {
        let mut ty = crate::publish::announced(&handle);
        let mut checked = Instant::now();
        while let Some(m) = sub.recv().await {
            if ty.is_none() && checked.elapsed() > Duration::from_millis(200) {
                ty = crate::publish::announced(&handle);
                checked = Instant::now();
            }
            *received.lock().entry(name.clone()).or_default() += 1;
            let record = Record {
                channel: name.clone(),
                ty: ty.clone(),
                seq: m.seq,
                log_time: unix_ns() as u64,
                payload: m.value,
            };
            if tx.send(record).is_err() {
                break;
            }
        }
    }))
}

/// The type a recorded channel carried, from its schema and metadata.
fn recorded_type(channel: &mcap::Channel<'_>) -> Option<TypeInfo> {
    let fingerprint: [u8; 8] =
        pulicast::text::unhex(channel.metadata.get("pulicast.fingerprint")?)?
            .try_into()
            .ok()?;
    let schema = channel.schema.as_ref()?;
    let (encoding, description) = match schema.encoding.as_str() {
        "postcard-schema" => {
            let owned: postcard_schema::schema::owned::OwnedNamedType =
                serde_json::from_slice(&schema.data).ok()?;
            (TypeEncoding::Native, postcard::to_stdvec(&owned).ok()?)
        }
        "zcm" => (TypeEncoding::Zcm, Vec::new()),
        _ => return None,
    };
    Some(TypeInfo {
        encoding,
        name: schema.name.clone(),
        fingerprint,
        schema: description,
    })
}

/// Counts of one playback.
#[derive(Debug, Clone, Default)]
pub struct PlayStats {
    /// Messages published, per channel.
    pub published: BTreeMap<String, u64>,
    /// Messages skipped (reserved channels).
    pub skipped: u64,
}

/// Reads an MCAP file, with errors a person understands.
pub fn read_file(path: &Path) -> Result<Vec<u8>> {
    let bytes = std::fs::read(path).with_context(|| format!("can't read {}", path.display()))?;
    if !bytes.starts_with(mcap::MAGIC) {
        bail!("{} is not an MCAP file", path.display());
    }
    Ok(bytes)
}

/// How much of a recording can be read: all of it, or (for a file whose
/// recorder was killed before it could close it) everything up to the first
/// record that is not whole.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Readable {
    /// Messages that can be read, from the start of the file.
    pub messages: u64,
    /// Log times (ns since the Unix epoch) of the first and last of them.
    pub span: Option<(u64, u64)>,
    /// Why the rest can't be read; `None` for a whole file.
    pub damage: Option<String>,
    /// Bytes after the last whole chunk, lost with the damage (0 for a whole file).
    pub lost_bytes: u64,
}

impl Readable {
    /// What a person reads about a damaged file, or `None` for a whole one.
    pub fn describe(&self) -> Option<String> {
        let damage = self.damage.as_ref()?;
        let span = match self.span {
            Some((first, last)) => format!(
                ", {:.1} s of recording",
                last.saturating_sub(first) as f64 / 1e9
            ),
            None => String::new(),
        };
        Some(format!(
            "the file was not closed ({damage}): {} messages{span} can be read; the last {} bytes, \
             after the last whole chunk, are lost",
            self.messages, self.lost_bytes
        ))
    }
}

/// The messages of `bytes` that can be read, in file order: every message of
/// a whole file, or, of a file that ends mid-record, those before the damage.
fn messages(
    bytes: &[u8],
) -> Result<impl Iterator<Item = mcap::McapResult<mcap::Message<'static>>> + '_> {
    // A file that was never closed has no summary and no closing magic.
    mcap::read::MessageStream::new_with_options(bytes, mcap::read::Options::IgnoreEndMagic.into())
        .context("reading the MCAP file")
}

/// Reads `bytes` through to the end or to the first record that is not
/// whole, and says how much can be read.
pub fn readable(bytes: &[u8]) -> Result<Readable> {
    let mut found = Readable {
        messages: 0,
        span: None,
        damage: None,
        lost_bytes: 0,
    };
    for message in messages(bytes)? {
        match message {
            Ok(m) => {
                found.messages += 1;
                let (first, _) = found.span.unwrap_or((m.log_time, m.log_time));
                found.span = Some((first, m.log_time));
            }
            Err(e) => {
                found.damage = Some(e.to_string());
                break;
            }
        }
    }
    // A recorder killed just after a chunk leaves a file that reads cleanly
    // but has no summary and no closing magic.
    if found.damage.is_none()
        && !(bytes.len() >= 2 * mcap::MAGIC.len() && bytes.ends_with(mcap::MAGIC))
    {
        found.damage = Some("it ends without its footer".into());
    }
    if found.damage.is_some() {
        found.lost_bytes = (bytes.len() - whole_chunks_end(bytes)) as u64;
    }
    Ok(found)
}

/// Where the last whole chunk of `bytes` ends (the end of the header when
/// there is none): what follows it holds no message that can be read.
fn whole_chunks_end(bytes: &[u8]) -> usize {
    use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_skip_end_magic(true)
            .with_emit_chunks(true)
            .with_record_length_limit(bytes.len()),
    );
    let (mut fed, mut at, mut end) = (0, mcap::MAGIC.len(), mcap::MAGIC.len());
    while let Some(event) = reader.next_event() {
        match event {
            Ok(LinearReadEvent::ReadRequest(want)) => {
                let n = want.min(bytes.len() - fed);
                reader.insert(n).copy_from_slice(&bytes[fed..fed + n]);
                reader.notify_read(n);
                fed += n;
            }
            // Records follow each other: an opcode, a u64 length, the body.
            Ok(LinearReadEvent::Record { data, opcode }) => {
                at += 1 + 8 + data.len();
                if opcode == mcap::records::op::CHUNK {
                    end = at;
                }
            }
            Err(_) => break,
        }
    }
    end.min(bytes.len())
}

/// Writes the readable part of the recording `bytes` to `path` as a whole
/// MCAP file (channels, schemas and payloads as they were). What
/// `puli recover` does.
pub fn recover(bytes: &[u8], path: &Path) -> Result<Readable> {
    let found = readable(bytes)?;
    let file = File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut writer = mcap::WriteOptions::new()
        .library(concat!("pulicast-tools ", env!("CARGO_PKG_VERSION")))
        .profile("")
        .create(BufWriter::new(file))
        .context("starting the MCAP file")?;
    for message in messages(bytes)?.take(found.messages as usize) {
        writer
            .write(&message.context("reading the MCAP file")?)
            .context("writing the MCAP file")?;
    }
    writer.finish().context("finishing the MCAP file")?;
    Ok(found)
}

/// Publishes the selected channels of a recording with their original
/// timing divided by `speed`, payloads byte-identical; `loops` times (None:
/// until Ctrl-C). Only the first `readable` messages are played: what
/// [`readable`] found, for a file that was never closed.
pub async fn play(
    node: &Node,
    bytes: &[u8],
    readable: &Readable,
    selection: &Selection,
    speed: f64,
    loops: Option<u64>,
) -> Result<PlayStats> {
    if !(speed > 0.0 && speed.is_finite()) {
        bail!("--speed must be a positive number");
    }
    let readable = readable.messages as usize;
    let mut stats = PlayStats::default();
    let mut round = 0u64;
    // One listener for the whole replay, so no Ctrl-C falls between waits.
    let ctrl_c = crate::stop_requested();
    tokio::pin!(ctrl_c);
    while loops.is_none_or(|n| round < n) {
        round += 1;
        let start = tokio::time::Instant::now();
        let mut first: Option<u64> = None;
        let mut channels: HashMap<String, pulicast::Channel> = HashMap::new();
        for message in messages(bytes)?.take(readable) {
            let message = message.context("reading the MCAP file")?;
            let topic = &message.channel.topic;
            if !selection.matches(topic) {
                continue;
            }
            let t0 = *first.get_or_insert(message.log_time);
            let offset = Duration::from_nanos(message.log_time.saturating_sub(t0)).div_f64(speed);
            tokio::select! {
                _ = tokio::time::sleep_until(start + offset) => {}
                _ = &mut ctrl_c => return Ok(stats),
            }
            let channel = channels.entry(topic.clone()).or_insert_with(|| {
                let channel = node.channel(&format!("/{topic}"));
                // Re-announce the recorded type, so tools decode the replay.
                if let Some(ty) = recorded_type(&message.channel) {
                    let _ = channel.declare_type(ty);
                }
                channel
            });
            match channel.publish_bytes(&message.data) {
                Ok(()) => *stats.published.entry(topic.clone()).or_default() += 1,
                Err(pulicast::Error::InvalidName { .. }) => stats.skipped += 1,
                Err(e) => return Err(e.into()),
            }
        }
    }
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selections() {
        let s = Selection::new(&["rover1/...".into(), "/fleet/status".into()], "").unwrap();
        assert!(
            s.matches("rover1/pose") && s.matches("rover1/arm/pose") && s.matches("fleet/status")
        );
        assert!(!s.matches("rover10/pose") && !s.matches("fleet/other"));
        let all = Selection::new(&[], "").unwrap();
        assert!(all.matches("x") && !all.matches("__nodes"));
        let relative = Selection::new(&["pose".into()], "rover2").unwrap();
        assert!(relative.matches("rover2/pose"));
        assert!(Selection::new(&["bad\u{1}".into()], "").is_err());
    }

    /// A recording of `n` messages in chunks of ten, as the recorder writes
    /// them (each flush ends a chunk), left unclosed or closed.
    fn recording(n: u32, close: bool) -> Vec<u8> {
        let mut out = std::io::Cursor::new(Vec::new());
        let mut writer = mcap::WriteOptions::new().create(&mut out).unwrap();
        let id = writer
            .add_channel(0, "rover1/pose", MESSAGE_ENCODING, &BTreeMap::new())
            .unwrap();
        for i in 0..n {
            let header = mcap::records::MessageHeader {
                channel_id: id,
                sequence: i,
                log_time: u64::from(i) * 1_000_000,
                publish_time: 0,
            };
            writer
                .write_to_known_channel(&header, &i.to_le_bytes())
                .unwrap();
            if i % 10 == 9 {
                writer.flush().unwrap();
            }
        }
        if close {
            writer.finish().unwrap();
            drop(writer);
        } else {
            writer.flush().unwrap();
            // Dropping it would close the file, as a killed recorder can't.
            std::mem::forget(writer);
        }
        out.into_inner()
    }

    #[test]
    fn a_whole_file_reads_whole() {
        let whole = readable(&recording(25, true)).unwrap();
        assert_eq!(
            (whole.messages, whole.lost_bytes, whole.damage),
            (25, 0, None)
        );
        assert_eq!(whole.span, Some((0, 24_000_000)));
    }

    #[test]
    fn a_file_cut_anywhere_reads_up_to_its_last_whole_chunk() {
        let bytes = recording(25, false);
        let unclosed = readable(&bytes).unwrap();
        assert_eq!(unclosed.messages, 25);
        assert!(unclosed.describe().unwrap().contains("without its footer"));
        let (mut last, mut chunk_end) = (0, mcap::MAGIC.len());
        for cut in mcap::MAGIC.len()..=bytes.len() {
            let found = readable(&bytes[..cut]).unwrap();
            // Only whole chunks are read: 0, 10, 20 or 25 messages, growing
            // with the cut...
            assert!(
                [0, 10, 20, 25].contains(&found.messages),
                "cut {cut}: {found:?}"
            );
            assert!(found.messages >= last, "cut {cut}");
            // ... each from the cut where its chunk ends, and what is lost
            // is what follows the last whole chunk.
            if found.messages > last {
                chunk_end = cut;
            }
            last = found.messages;
            assert!(found.damage.is_some(), "cut {cut}");
            assert_eq!(found.lost_bytes, (cut - chunk_end) as u64, "cut {cut}");
        }
    }

    #[test]
    fn zcm_definitions_as_text() {
        assert_eq!(
            zcm_definition("string_msg").unwrap(),
            "struct string_msg {\n    string value;\n}\n"
        );
        assert!(zcm_definition("roc_ack")
            .unwrap()
            .contains("byte fingerprint[8];"));
        assert!(zcm_definition("nope").is_none());
    }
}

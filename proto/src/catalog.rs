//! The fleet's settings as a client sees them, sans-IO: which members own
//! which setting (from discovery), the last confirmation of each (from its
//! confirmation channel), and the values a person types, read as the
//! setting's type. The node's runtime subscribes, pokes and sends; nothing
//! here touches a socket or a clock.
//!
//! A member claims setting `X` when it publishes `X` (a confirmation
//! channel, see [`crate::wire::setting`]) and subscribes `X.r`, as 2.x
//! `puliconf` tells. Anyone can announce that (a 2.x heartbeat is one
//! datagram), so a claimant counts as an owner that answered
//! ([`OwnerRef::answered`]) once a confirmation is heard from where its
//! messages come from: its data address, or for a 2.x node (which sends
//! each channel from a socket of its own) a socket of its host that no
//! other claimant answered from. Confirmations from anywhere else are not
//! taken ([`Catalog::unowned`]). Two live owners that answered lock a
//! setting: both are shown, neither is written to.
//!
//! ```
//! use pulicast_proto::catalog::{Catalog, Member};
//! use pulicast_proto::wire::setting::RocAck;
//! use pulicast_proto::wire::zcm::fingerprint;
//! use pulicast_discovery::wire::ChannelInfo;
//!
//! let channel = |name: &str, publishes, subscribes| ChannelInfo {
//!     name: name.into(), publishes, subscribes, period_ns: 0, message_type: None,
//! };
//! let channels = [
//!     channel("rover1/.config/max_speed", true, false),
//!     channel("rover1/.config/max_speed.r", false, true),
//! ];
//! let mut catalog = Catalog::default();
//! let at: std::net::SocketAddr = "127.0.0.1:4000".parse()?;
//! let controller = Member { key: 7, node: "controller", live: true, channels: &channels, address: at, data_address: Some(at) };
//! let found = catalog.update([controller]);
//! assert_eq!(found, ["rover1/.config/max_speed"]);
//!
//! let mut ack = Vec::new();
//! RocAck { message: "", fingerprint: fingerprint::DOUBLE_MSG, value: &1.5f64.to_be_bytes() }.encode(&mut ack)?;
//! catalog.hear("rover1/.config/max_speed", &ack, at, std::time::Instant::now())?;
//! let speed = catalog.get("rover1/max_speed").expect("known");
//! assert_eq!(speed.value_text().as_deref(), Some("1.5"));
//! assert!(speed.owners[0].answered);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::net::{IpAddr, SocketAddr};
use std::time::{Duration, Instant};

use pulicast_discovery::wire::{ChannelInfo, TypeEncoding, TypeInfo};

use crate::setting::FileValue;
use crate::wire::setting::{self as wire, Request, RocAck};
use crate::wire::zcm::{Primitive, PrimitiveKind};
use crate::wire::{DecodeError, Fingerprint};

/// Settings a catalog tracks at most by default; more are counted in
/// [`Catalog::left_out`] and left out. Each one tracked is a subscription
/// (a multicast group joined), so a fleet announcing fake settings in
/// discovery costs a client at most this many.
pub const DEFAULT_MAX_SETTINGS: usize = 1024;

/// The largest confirmation a catalog keeps, in bytes: a `roc_ack` value
/// is at most 32 KiB, and the message is a line of text. Larger ones are
/// refused, so the catalog holds at most this times its setting count.
pub const MAX_CONFIRMATION: usize = 40 * 1024;

/// A member that owns a setting.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OwnerRef {
    /// Its session key (as in discovery).
    pub key: i64,
    /// Its node name.
    pub node: String,
    /// Whether it is live (alive or suspected).
    pub live: bool,
    /// Whether a confirmation was heard from where its messages come
    /// from: a claim nobody answered for is no owner that locks.
    pub answered: bool,
}

/// A member as the catalog reads it from discovery.
#[derive(Debug, Clone, Copy)]
pub struct Member<'a> {
    /// Its session key.
    pub key: i64,
    /// Its node name.
    pub node: &'a str,
    /// Alive or suspected (not dead, not left).
    pub live: bool,
    /// The channels it announces.
    pub channels: &'a [ChannelInfo],
    /// Where it announces itself from (for a 2.x node, its heartbeats'
    /// socket).
    pub address: SocketAddr,
    /// Where its messages come from, if known (not for 2.x nodes).
    pub data_address: Option<SocketAddr>,
}

/// Where a claimant's confirmations come from, as far as can be told.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Sender {
    /// This socket (our nodes, and other sites' through their bridge).
    At(SocketAddr),
    /// Some socket of this host (2.x nodes).
    Host(IpAddr),
}

impl Member<'_> {
    fn sender(&self) -> Sender {
        match self.data_address {
            Some(at) => Sender::At(at),
            None => Sender::Host(self.address.ip()),
        }
    }
}

/// A setting's last confirmation.
#[derive(Debug, Clone, PartialEq)]
pub struct Confirmed {
    /// The fingerprint of the setting's type.
    pub fingerprint: Fingerprint,
    /// The value, when its type is a 2.x primitive and it is set.
    pub value: Option<Primitive>,
    /// The value's encoding without the fingerprint (empty: unset).
    pub encoded: Vec<u8>,
    /// The owner's message: why a request was refused, a warning, or (the
    /// answer to a poke) what the setting accepts. Empty if none.
    pub message: String,
}

impl Confirmed {
    /// The type, when it is a 2.x primitive.
    pub fn kind(&self) -> Option<PrimitiveKind> {
        PrimitiveKind::from_fingerprint(self.fingerprint)
    }

    /// Whether the setting has a value.
    pub fn is_set(&self) -> bool {
        !self.encoded.is_empty()
    }
}

/// One setting of the fleet.
#[derive(Debug, Clone, PartialEq)]
pub struct SettingInfo {
    /// Its fleet-wide name (`rover1/max_speed`).
    pub name: String,
    /// Its confirmation channel (`rover1/.config/max_speed`).
    pub channel: String,
    /// The members that own it, live or recently gone; more than one live
    /// owner locks it.
    pub owners: Vec<OwnerRef>,
    /// The last confirmation heard; `None` until one is.
    pub confirmed: Option<Confirmed>,
    /// What its owner answered a poke with: for our owners the
    /// description, unit and checks; for 2.x ones their validator's text.
    pub about: Option<String>,
    /// How many confirmations were heard, so that a waiter tells a new one.
    pub heard: u64,
    /// The last refusal or warning heard (a message other than
    /// [`SettingInfo::about`]), with the value of [`SettingInfo::heard`]
    /// when it came: a waiter tells whether its request was refused even
    /// if other confirmations came after.
    pub last_refusal: Option<(u64, String)>,
    /// The type its owner announces for its values (native settings).
    pub type_info: Option<TypeInfo>,
}

impl SettingInfo {
    /// Whether the setting already holds what a file's `value` asks (read
    /// as the setting's type): pushing it would change nothing.
    pub fn holds(&self, value: &FileValue) -> bool {
        let wanted = match value {
            FileValue::Unset => Wanted::Unset,
            FileValue::Value(v) => Wanted::Value(v.clone()),
            FileValue::Structured(j) => Wanted::Json(j.clone()),
        };
        request_for(self, &wanted).is_ok_and(|(_, asked)| shows(self, &asked))
    }

    /// Its description, unit and checks, read from what its owner answered
    /// a poke with ([`SettingInfo::about`]); empty until it answered.
    pub fn limits(&self) -> crate::setting::SettingLimits {
        self.about
            .as_deref()
            .map(crate::setting::SettingLimits::parse)
            .unwrap_or_default()
    }

    /// Two live owners answered for it: nobody should write to it.
    pub fn is_locked(&self) -> bool {
        self.owners.iter().filter(|o| o.live && o.answered).count() > 1
    }

    /// The live claimants no confirmation was heard from: a claim anyone
    /// can make, shown as what it is rather than as an owner.
    pub fn unanswered_claims(&self) -> impl Iterator<Item = &OwnerRef> {
        self.owners.iter().filter(|o| o.live && !o.answered)
    }

    /// No owner is live any more: its value is the last one known.
    pub fn is_stale(&self) -> bool {
        !self.owners.iter().any(|o| o.live)
    }

    /// Its request-of-change channel.
    pub fn request_channel(&self) -> String {
        self.channel.clone() + wire::REQUEST_SUFFIX
    }

    /// The type's name (`double_msg`, a native type's name), or its
    /// fingerprint for a type nobody announced.
    pub fn type_name(&self) -> Option<String> {
        let confirmed = self.confirmed.as_ref()?;
        Some(match (confirmed.kind(), self.native_type()) {
            (Some(kind), _) => kind.type_name().to_string(),
            (None, Some(ty)) => ty.name.clone(),
            (None, None) => confirmed.fingerprint.to_string(),
        })
    }

    /// The announced native type of its values, if it matches the
    /// confirmed one.
    pub fn native_type(&self) -> Option<&TypeInfo> {
        let confirmed = self.confirmed.as_ref()?;
        self.type_info.as_ref().filter(|t| {
            t.encoding == TypeEncoding::Native && t.fingerprint == confirmed.fingerprint.0
        })
    }

    /// A native setting's value as JSON, decoded from its announced type;
    /// `None` for other settings, an unset value, or bytes that don't decode.
    pub fn value_json(&self) -> Option<serde_json::Value> {
        let confirmed = self.confirmed.as_ref()?;
        let ty = self.native_type().filter(|_| confirmed.is_set())?;
        let mut whole = confirmed.fingerprint.0.to_vec();
        whole.extend_from_slice(&confirmed.encoded);
        let decoded = crate::text::decode_payload(&whole, Some(ty));
        (decoded.type_name == ty.name).then_some(decoded.value)
    }

    /// The value as a person reads it: `None` until confirmed, `"unset"`
    /// for no value, JSON for a native value, the bytes' count for a type
    /// that is neither a primitive nor announced.
    pub fn value_text(&self) -> Option<String> {
        let confirmed = self.confirmed.as_ref()?;
        Some(match (&confirmed.value, confirmed.is_set()) {
            (Some(value), _) => primitive_text(value),
            (None, false) => "unset".to_string(),
            (None, true) => match self.value_json() {
                Some(json) => json.to_string(),
                None => format!("<{} bytes>", confirmed.encoded.len()),
            },
        })
    }
}

/// A primitive value as a person types it (strings as they are; floats
/// always with a point or exponent, so `1.0` reads as a float).
pub fn primitive_text(value: &Primitive) -> String {
    match value {
        Primitive::Bool(v) => v.to_string(),
        Primitive::Byte(v) => v.to_string(),
        Primitive::I8(v) => v.to_string(),
        Primitive::I16(v) => v.to_string(),
        Primitive::I32(v) => v.to_string(),
        Primitive::I64(v) => v.to_string(),
        Primitive::Float(v) | Primitive::Double(v) => format!("{v:?}"),
        Primitive::String(v) => v.clone(),
    }
}

/// A primitive value as JSON (a float that JSON can't hold, as `null`).
pub fn primitive_json(value: &Primitive) -> serde_json::Value {
    match value {
        Primitive::Bool(v) => (*v).into(),
        Primitive::Byte(v) => (*v).into(),
        Primitive::I8(v) => (*v).into(),
        Primitive::I16(v) => (*v).into(),
        Primitive::I32(v) => (*v).into(),
        Primitive::I64(v) => (*v).into(),
        Primitive::Float(v) | Primitive::Double(v) => serde_json::Number::from_f64(*v)
            .map_or(serde_json::Value::Null, serde_json::Value::Number),
        Primitive::String(v) => v.clone().into(),
    }
}

/// Reads `text` as a value of `kind`, or says why it can't be one.
pub fn parse_value(kind: PrimitiveKind, text: &str) -> Result<Primitive, String> {
    let t = text.trim();
    let bad = |what: &str| format!("{text:?} is not {what}");
    Ok(match kind {
        PrimitiveKind::Bool => match t {
            "true" | "True" | "1" | "on" => Primitive::Bool(true),
            "false" | "False" | "0" | "off" => Primitive::Bool(false),
            _ => return Err(bad("true or false")),
        },
        PrimitiveKind::Byte => {
            Primitive::Byte(t.parse().map_err(|_| bad("an integer in 0..=255"))?)
        }
        PrimitiveKind::I8 => Primitive::I8(t.parse().map_err(|_| bad("an 8-bit integer"))?),
        PrimitiveKind::I16 => Primitive::I16(t.parse().map_err(|_| bad("a 16-bit integer"))?),
        PrimitiveKind::I32 => Primitive::I32(t.parse().map_err(|_| bad("a 32-bit integer"))?),
        PrimitiveKind::I64 => Primitive::I64(t.parse().map_err(|_| bad("a 64-bit integer"))?),
        PrimitiveKind::Float => {
            let v: f32 = t.parse().map_err(|_| bad("a number"))?;
            Primitive::Float(f64::from(v))
        }
        PrimitiveKind::Double => Primitive::Double(t.parse().map_err(|_| bad("a number"))?),
        PrimitiveKind::String => Primitive::String(text.to_string()),
    })
}

/// Converts `value` to a value of `kind` as puliconf reads a TOML value by
/// the setting's type: an integer to a smaller integer that holds it, an
/// integer or a float to the float type (rounded to an `f32` for
/// `float_msg`, which its owner holds); says why not otherwise (a float to
/// an integer, a string to a number, ...).
pub fn convert(kind: PrimitiveKind, value: Primitive) -> Result<Primitive, String> {
    if let (PrimitiveKind::Float, Primitive::Float(v) | Primitive::Double(v)) = (kind, &value) {
        // The owner holds an f32: ask for the value it will hold.
        let narrowed = *v as f32;
        if v.is_finite() && !narrowed.is_finite() {
            return Err(format!("{v} is beyond the range of float_msg (an f32)"));
        }
        return Ok(Primitive::Float(f64::from(narrowed)));
    }
    if value.kind() == kind {
        return Ok(value);
    }
    let integer = match &value {
        Primitive::Byte(v) => Some(i64::from(*v)),
        Primitive::I8(v) => Some(i64::from(*v)),
        Primitive::I16(v) => Some(i64::from(*v)),
        Primitive::I32(v) => Some(i64::from(*v)),
        Primitive::I64(v) => Some(*v),
        _ => None,
    };
    let float = match &value {
        Primitive::Float(v) | Primitive::Double(v) => Some(*v),
        _ => None,
    };
    let refused = || {
        format!(
            "{} is not a value of type {}",
            primitive_text(&value),
            kind.type_name()
        )
    };
    let out = match (kind, integer, float) {
        (PrimitiveKind::Byte, Some(i), _) => u8::try_from(i).ok().map(Primitive::Byte),
        (PrimitiveKind::I8, Some(i), _) => i8::try_from(i).ok().map(Primitive::I8),
        (PrimitiveKind::I16, Some(i), _) => i16::try_from(i).ok().map(Primitive::I16),
        (PrimitiveKind::I32, Some(i), _) => i32::try_from(i).ok().map(Primitive::I32),
        (PrimitiveKind::I64, Some(i), _) => Some(Primitive::I64(i)),
        // Precision beyond 2^53 is the one loss puliconf accepts too.
        (PrimitiveKind::Double, Some(i), _) => Some(Primitive::Double(i as f64)),
        (PrimitiveKind::Float, Some(i), _) => Some(Primitive::Float(f64::from(i as f32))),
        (PrimitiveKind::Double, _, Some(f)) => Some(Primitive::Double(f)),
        _ => None,
    };
    out.ok_or_else(refused)
}

#[derive(Debug)]
struct Entry {
    info: SettingInfo,
    /// Where each claimant's confirmations come from.
    senders: Vec<(i64, Sender)>,
    /// The claimants a confirmation was heard from.
    answered: BTreeSet<i64>,
    /// The sockets 2.x claimants answered from (one claimant each).
    sources: HashMap<SocketAddr, i64>,
    /// Sources of confirmations nobody answered for yet, most recent last
    /// (at most [`MAX_UNOWNED`]): a claimant heard of later may be theirs.
    unowned: VecDeque<SocketAddr>,
    /// When this client's pokes still unanswered were sent, oldest first
    /// (at most [`MAX_POKES_OUT`]): a confirmation that answers one is
    /// what the setting is, not a refusal of anything.
    pokes_out: VecDeque<Instant>,
}

/// Pokes a catalog counts as unanswered at most, per setting.
const MAX_POKES_OUT: usize = 16;

/// Sources of confirmations no claimant answers for, kept per setting.
const MAX_UNOWNED: usize = 8;

impl Entry {
    /// The claimant that confirmations from `from` answer for, if any.
    fn attribute(&mut self, from: SocketAddr) -> Option<i64> {
        if let Some(&(key, _)) = self.senders.iter().find(|(_, s)| *s == Sender::At(from)) {
            self.answered.insert(key);
            return Some(key);
        }
        if let Some(&key) = self.sources.get(&from) {
            return Some(key);
        }
        // A 2.x claimant of that host that has not answered yet: a second
        // socket of one host is a second node.
        let key = self
            .senders
            .iter()
            .filter(|(k, s)| *s == Sender::Host(from.ip()) && !self.answered.contains(k))
            .map(|(k, _)| *k)
            .min()?;
        self.answered.insert(key);
        self.sources.insert(from, key);
        Some(key)
    }

    /// The claimants now: who answered is kept for those still claiming,
    /// and sources nobody answered for are tried again.
    fn claimants(&mut self, owners: Vec<OwnerRef>, senders: Vec<(i64, Sender)>) {
        self.senders = senders;
        let claiming: BTreeSet<i64> = self.senders.iter().map(|(k, _)| *k).collect();
        self.answered.retain(|k| claiming.contains(k));
        self.sources.retain(|_, k| claiming.contains(k));
        for from in std::mem::take(&mut self.unowned) {
            if self.attribute(from).is_none() {
                self.unowned.push_back(from);
            }
        }
        self.info.owners = owners;
        self.mark_answered();
    }

    fn mark_answered(&mut self) {
        for owner in &mut self.info.owners {
            owner.answered = self.answered.contains(&owner.key);
        }
    }
}

/// How long a poke may stay unanswered before it counts as lost.
const POKE_ANSWER_WAIT: Duration = Duration::from_secs(1);

/// The settings of the fleet: see the module.
#[derive(Debug)]
pub struct Catalog {
    /// By confirmation channel.
    entries: BTreeMap<String, Entry>,
    max: usize,
    left_out: usize,
    unowned: u64,
}

impl Default for Catalog {
    fn default() -> Self {
        Self::new(DEFAULT_MAX_SETTINGS)
    }
}

impl Catalog {
    /// A catalog of at most `max_settings` settings.
    pub fn new(max_settings: usize) -> Self {
        Self {
            entries: BTreeMap::new(),
            max: max_settings,
            left_out: 0,
            unowned: 0,
        }
    }

    /// Reads who owns what from discovery's `members` (every member it
    /// knows, recently gone ones included) and returns the confirmation
    /// channels of settings found for the first time, to subscribe and
    /// poke. A setting no member announces any more is forgotten.
    pub fn update<'a>(&mut self, members: impl IntoIterator<Item = Member<'a>>) -> Vec<String> {
        let mut owners: BTreeMap<&str, Vec<(OwnerRef, Sender)>> = BTreeMap::new();
        // The type a native setting's live owner announces on its request
        // channel.
        let mut types: BTreeMap<&str, &TypeInfo> = BTreeMap::new();
        for member in members {
            // The member's subscribed request channels, by the confirmation
            // channel they belong to: one pass, however many channels.
            let requests: HashMap<&str, &ChannelInfo> = member
                .channels
                .iter()
                .filter(|c| c.subscribes)
                .filter_map(|c| Some((c.name.strip_suffix(wire::REQUEST_SUFFIX)?, c)))
                .collect();
            for channel in member.channels.iter().filter(|c| c.publishes) {
                let Some(request) = requests.get(channel.name.as_str()) else {
                    continue;
                };
                if wire::name_of_any_confirmation(&channel.name).is_none() {
                    continue;
                }
                let owner = OwnerRef {
                    key: member.key,
                    node: member.node.to_string(),
                    live: member.live,
                    answered: false,
                };
                owners
                    .entry(&channel.name)
                    .or_default()
                    .push((owner, member.sender()));
                if let Some(ty) = request.message_type.as_ref().filter(|_| member.live) {
                    types.insert(&channel.name, ty);
                }
            }
        }
        // One name under both parts (`.config`, `.settings`) is one
        // setting claimed twice: each entry shows every claimant, and so
        // is locked, rather than one hiding the other.
        let mut by_name: HashMap<String, Vec<OwnerRef>> = HashMap::new();
        for (channel, owned) in &owners {
            if let Some(name) = wire::name_of_any_confirmation(channel) {
                by_name
                    .entry(name)
                    .or_default()
                    .extend(owned.iter().map(|(o, _)| o.clone()));
            }
        }
        self.entries
            .retain(|channel, _| owners.contains_key(channel.as_str()));
        let mut found = Vec::new();
        let mut left_out = 0;
        for (channel, claims) in &owners {
            let Some(name) = wire::name_of_any_confirmation(channel) else {
                continue;
            };
            let mut owned = by_name.get(&name).cloned().unwrap_or_default();
            owned.sort_by_key(|o| (!o.live, o.key));
            owned.dedup();
            let senders: Vec<(i64, Sender)> = claims.iter().map(|(o, s)| (o.key, *s)).collect();
            let ty = types.get(channel).map(|t| (*t).clone());
            if let Some(entry) = self.entries.get_mut(*channel) {
                entry.claimants(owned, senders);
                entry.info.type_info = ty;
                continue;
            }
            if self.entries.len() >= self.max {
                left_out += 1;
                continue;
            }
            let info = SettingInfo {
                name,
                channel: channel.to_string(),
                owners: Vec::new(),
                confirmed: None,
                about: None,
                heard: 0,
                last_refusal: None,
                type_info: ty,
            };
            let mut entry = Entry {
                info,
                pokes_out: VecDeque::new(),
                senders: Vec::new(),
                answered: BTreeSet::new(),
                sources: HashMap::new(),
                unowned: VecDeque::new(),
            };
            entry.claimants(owned, senders);
            self.entries.insert(channel.to_string(), entry);
            found.push(channel.to_string());
        }
        self.left_out = left_out;
        self.share_answers();
        found
    }

    /// One name under both parts is one setting: a claimant that answered
    /// on either channel answered for it.
    fn share_answers(&mut self) {
        let mut by_name: HashMap<&str, BTreeSet<i64>> = HashMap::new();
        let mut shared = false;
        for entry in self.entries.values() {
            let answered = by_name.entry(&entry.info.name).or_default();
            shared |= !answered.is_empty() && !entry.answered.is_empty();
            answered.extend(&entry.answered);
        }
        if !shared {
            return;
        }
        let by_name: HashMap<String, BTreeSet<i64>> = by_name
            .into_iter()
            .map(|(name, keys)| (name.to_string(), keys))
            .collect();
        for entry in self.entries.values_mut() {
            if let Some(keys) = by_name.get(&entry.info.name) {
                for owner in &mut entry.info.owners {
                    owner.answered |= keys.contains(&owner.key);
                }
            }
        }
    }

    /// Takes a message heard on confirmation channel `channel`; returns the
    /// setting it updated (`None` for a channel of no known setting).
    /// One larger than [`MAX_CONFIRMATION`] is malformed.
    ///
    /// A confirmation is taken as the answer to one of this client's pokes
    /// (sent within the last second) if its message is what the setting
    /// is (or that is not known yet); otherwise a message is a refusal or
    /// a warning ([`SettingInfo::last_refusal`]). Another client's poke
    /// answered meanwhile can't be told apart: it reads as a refusal of
    /// whatever was asked just before.
    ///
    /// `from` is where it came from: one that no claimant answers for (see
    /// the module) is not taken, and counted in [`Catalog::unowned`].
    pub fn hear(
        &mut self,
        channel: &str,
        payload: &[u8],
        from: SocketAddr,
        now: Instant,
    ) -> Result<Option<&SettingInfo>, DecodeError> {
        let Some(entry) = self.entries.get_mut(channel) else {
            return Ok(None);
        };
        if payload.len() > MAX_CONFIRMATION {
            return Err(DecodeError::Malformed(format!(
                "a confirmation of {} bytes, more than a setting's",
                payload.len()
            )));
        }
        let ack = RocAck::decode(payload)?;
        let answered_before = entry.answered.len();
        if entry.attribute(from).is_none() {
            if !entry.unowned.contains(&from) {
                if entry.unowned.len() >= MAX_UNOWNED {
                    entry.unowned.pop_front();
                }
                entry.unowned.push_back(from);
            }
            self.unowned += 1;
            return Ok(None);
        }
        if entry.answered.len() != answered_before {
            entry.mark_answered();
            self.share_answers();
        }
        let Some(entry) = self.entries.get_mut(channel) else {
            return Ok(None);
        };
        let value = match PrimitiveKind::from_fingerprint(ack.fingerprint) {
            Some(kind) if ack.is_set() => {
                let mut whole = ack.fingerprint.0.to_vec();
                whole.extend_from_slice(ack.value);
                Some(Primitive::decode_as(kind, &whole)?)
            }
            _ => None,
        };
        let info = &mut entry.info;
        let pokes = &mut entry.pokes_out;
        while pokes
            .front()
            .is_some_and(|sent| now.saturating_duration_since(*sent) > POKE_ANSWER_WAIT)
        {
            pokes.pop_front();
        }
        let describes = info
            .about
            .as_deref()
            .is_none_or(|about| about == ack.message);
        info.heard += 1;
        if describes && pokes.pop_front().is_some() {
            info.about.get_or_insert_with(|| ack.message.to_string());
        } else if !ack.message.is_empty() {
            info.last_refusal = Some((info.heard, ack.message.to_string()));
        }
        info.confirmed = Some(Confirmed {
            fingerprint: ack.fingerprint,
            value,
            encoded: ack.value.to_vec(),
            message: ack.message.to_string(),
        });
        Ok(Some(info))
    }

    /// A poke for the setting of confirmation channel `channel`, to send
    /// on its request channel: its answer is taken as the setting's
    /// description ([`SettingInfo::about`]).
    pub fn poke(&mut self, channel: &str, now: Instant) -> Vec<u8> {
        if let Some(entry) = self.entries.get_mut(channel) {
            if entry.pokes_out.len() >= MAX_POKES_OUT {
                entry.pokes_out.pop_front();
            }
            entry.pokes_out.push_back(now);
        }
        let mut out = Vec::new();
        Request::Poke.encode(&mut out);
        out
    }

    /// The setting called `name` (`rover1/max_speed`; a leading `/` is
    /// ignored).
    pub fn get(&self, name: &str) -> Option<&SettingInfo> {
        let name = name.trim_start_matches('/');
        self.entries
            .values()
            .map(|e| &e.info)
            .find(|info| info.name == name)
    }

    /// Every setting, by name.
    pub fn settings(&self) -> Vec<SettingInfo> {
        let mut all: Vec<SettingInfo> = self.entries.values().map(|e| e.info.clone()).collect();
        all.sort_by(|a, b| a.name.cmp(&b.name));
        all
    }

    /// Confirmations heard from where no claimant of their setting sends
    /// from (a stranger's, or an owner's before it was announced), not
    /// taken.
    pub fn unowned(&self) -> u64 {
        self.unowned
    }

    /// How many settings the last [`Catalog::update`] left out, the
    /// catalog being full.
    pub fn left_out(&self) -> usize {
        self.left_out
    }

    /// The settings that are live and have not answered a poke yet, as
    /// (confirmation channel, request channel): what to poke.
    pub fn unanswered(&self) -> Vec<(String, String)> {
        self.entries
            .values()
            .filter(|e| !e.info.is_stale() && e.info.about.is_none())
            .map(|e| (e.info.channel.clone(), e.info.request_channel()))
            .collect()
    }

    /// The confirmation channels of every setting tracked.
    pub fn channels(&self) -> impl Iterator<Item = &str> {
        self.entries.keys().map(String::as_str)
    }
}

/// The request that asks for `value`, of the setting's confirmed type
/// `kind` (converted as [`convert`] does).
pub fn set_request(kind: PrimitiveKind, value: Primitive) -> Result<Vec<u8>, String> {
    let value = convert(kind, value)?;
    let mut out = Vec::new();
    value.encode(&mut out);
    Ok(out)
}

/// A request without a value (poke, unset, reset).
pub fn request(request: Request<'_>) -> Vec<u8> {
    let mut out = Vec::new();
    request.encode(&mut out);
    out
}

/// What a client asks a setting to become.
#[derive(Debug, Clone, PartialEq)]
pub enum Wanted {
    /// This value, converted to the setting's type where nothing is lost.
    Value(Primitive),
    /// A value as a person types it: read as the setting's primitive type,
    /// or as JSON for a native setting.
    Text(String),
    /// A JSON value: a native setting's, or a primitive's (number, boolean,
    /// string).
    Json(serde_json::Value),
    /// No value.
    Unset,
    /// Its default.
    Reset,
}

/// What a confirmation must show for a request to count as granted.
#[derive(Debug, Clone, PartialEq)]
pub enum Target {
    /// This primitive value.
    Value(Primitive),
    /// This encoding (a native value, without its fingerprint).
    Encoded(Vec<u8>),
    /// No value.
    Unset,
    /// The default, which the client does not know: any answer without a
    /// refusal (a reset).
    Default,
}

/// Why a request can't be made.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Unaskable {
    /// The value is not one of the setting's type.
    #[error("{0}")]
    NotOfType(String),
    /// The setting can't be written by a client: not confirmed yet, or of
    /// a type that is neither a 2.x primitive nor announced.
    #[error("{0}")]
    Unwritable(String),
}

/// The request payload for `wanted` on `setting`, as confirmed so far, and
/// what its confirmation must show; or why it can't be asked.
pub fn request_for(setting: &SettingInfo, wanted: &Wanted) -> Result<(Vec<u8>, Target), Unaskable> {
    use Unaskable::{NotOfType, Unwritable};
    match wanted {
        Wanted::Unset => return Ok((request(Request::Unset), Target::Unset)),
        Wanted::Reset => return Ok((request(Request::Reset), Target::Default)),
        _ => {}
    }
    let confirmed = setting
        .confirmed
        .as_ref()
        .ok_or_else(|| Unwritable("not confirmed by its owner yet".into()))?;
    let no_value = || NotOfType("no value asked for".into());
    if let Some(kind) = confirmed.kind() {
        let value = match wanted {
            Wanted::Value(v) => convert(kind, v.clone()),
            Wanted::Text(t) => parse_value(kind, t),
            Wanted::Json(j) => json_primitive(j).and_then(|p| convert(kind, p)),
            Wanted::Unset | Wanted::Reset => return Err(no_value()),
        }
        .map_err(NotOfType)?;
        let payload = set_request(kind, value.clone()).map_err(NotOfType)?;
        return Ok((payload, Target::Value(value)));
    }
    let ty = setting.native_type().ok_or_else(|| {
        Unwritable(
            "its type is neither a 2.x primitive nor announced, so it can't be written".into(),
        )
    })?;
    let json = match wanted {
        Wanted::Json(j) => j.clone(),
        Wanted::Text(t) => serde_json::from_str(t).map_err(|e| {
            NotOfType(format!(
                "{t:?} is not JSON, which a {} value is written as: {e}",
                ty.name
            ))
        })?,
        Wanted::Value(p) => primitive_json(p),
        Wanted::Unset | Wanted::Reset => return Err(no_value()),
    };
    let schema = crate::text::schema_of(ty)
        .ok_or_else(|| Unwritable("its announced type can't be read".into()))?;
    let payload = crate::text::encode_native_value(&schema, ty.fingerprint, &json)
        .map_err(|e| NotOfType(format!("not a {} value: {e}", ty.name)))?;
    let encoded = payload.get(8..).unwrap_or_default().to_vec();
    Ok((payload, Target::Encoded(encoded)))
}

/// A JSON scalar as the primitive it reads as.
fn json_primitive(json: &serde_json::Value) -> Result<Primitive, String> {
    use serde_json::Value as J;
    Ok(match json {
        J::Bool(b) => Primitive::Bool(*b),
        J::Number(n) => match n.as_i64() {
            Some(i) => Primitive::I64(i),
            None => Primitive::Double(n.as_f64().ok_or("a number out of range")?),
        },
        J::String(s) => Primitive::String(s.clone()),
        other => return Err(format!("{other} is not a value of a 2.x primitive type")),
    })
}

/// Where a request stands, judged from the setting as last heard.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Verdict {
    /// A confirmation shows what was asked.
    Granted,
    /// The owner refused (or warned), saying this, after the request.
    Refused(String),
    /// Nothing that answers it yet.
    Waiting,
}

/// Judges a request for `target` sent when the setting had heard `sent_at`
/// confirmations. Other confirmations may come between (another tool's
/// poke answered, the late answer to an earlier request, the owner's own
/// change): a refusal after the request counts, a value that is not the
/// target does not, so the waiter waits on for the answer or its deadline.
pub fn judge(now: &SettingInfo, target: &Target, sent_at: u64) -> Verdict {
    if now.heard <= sent_at {
        return Verdict::Waiting;
    }
    if let Some((at, why)) = &now.last_refusal {
        if *at > sent_at {
            return Verdict::Refused(why.clone());
        }
    }
    if shows(now, target) {
        Verdict::Granted
    } else {
        Verdict::Waiting
    }
}

/// Whether the setting's last confirmation shows `target`.
pub fn shows(now: &SettingInfo, target: &Target) -> bool {
    let Some(confirmed) = now.confirmed.as_ref() else {
        return false;
    };
    match target {
        Target::Value(v) => confirmed.value.as_ref().is_some_and(|c| same(c, v)),
        Target::Encoded(bytes) => confirmed.is_set() && &confirmed.encoded == bytes,
        Target::Unset => !confirmed.is_set(),
        // The client does not know the default: an answer without a
        // refusal is all it can see (puliconf takes any answer).
        Target::Default => true,
    }
}

/// Whether two primitives hold the same value; floats by their bits, so
/// that NaN is NaN.
fn same(a: &Primitive, b: &Primitive) -> bool {
    match (a, b) {
        (Primitive::Double(x), Primitive::Double(y))
        | (Primitive::Float(x), Primitive::Float(y)) => {
            x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan())
        }
        _ => a == b,
    }
}

/// Why a request that confirmations came for, none granting it, counts
/// as refused: what the owner kept.
pub fn kept(now: &SettingInfo) -> String {
    match now.value_text() {
        Some(kept) => format!("the owner kept {kept}"),
        None => "the owner kept its value".into(),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::wire::zcm::fingerprint;

    /// Where member `key` sends from, in these tests.
    fn at(key: i64) -> SocketAddr {
        SocketAddr::from(([127, 0, 0, 1], 4000 + key as u16))
    }

    fn channel(name: &str, publishes: bool, subscribes: bool) -> ChannelInfo {
        ChannelInfo {
            name: name.into(),
            publishes,
            subscribes,
            period_ns: 0,
            message_type: None,
        }
    }

    fn owning(name: &str) -> Vec<ChannelInfo> {
        vec![
            channel(&format!("rover1/.config/{name}"), true, false),
            channel(&format!("rover1/.config/{name}.r"), false, true),
        ]
    }

    fn ack(message: &str, value: Option<f64>) -> Vec<u8> {
        let bytes = value.map(f64::to_be_bytes);
        let mut out = Vec::new();
        RocAck {
            message,
            fingerprint: fingerprint::DOUBLE_MSG,
            value: bytes.as_ref().map_or(&[][..], |b| &b[..]),
        }
        .encode(&mut out)
        .unwrap();
        out
    }

    #[test]
    fn owners_need_both_channels_and_two_lock_a_setting() {
        let mut catalog = Catalog::default();
        let owner = owning("gain");
        // A tool: it publishes requests and subscribes confirmations.
        let tool = [
            channel("rover1/.config/gain", false, true),
            channel("rover1/.config/gain.r", true, false),
        ];
        let only_publishes = [channel("rover1/.config/other", true, false)];
        fn m(key: i64, channels: &[ChannelInfo]) -> Member<'_> {
            Member {
                key,
                node: "n",
                live: true,
                channels,
                address: at(key),
                data_address: Some(at(key)),
            }
        }
        let (owner, tool, only) = (&owner[..], &tool[..], &only_publishes[..]);
        assert_eq!(
            catalog.update([m(1, owner), m(2, tool), m(3, only)]).len(),
            1
        );
        let gain = catalog.get("/rover1/gain").unwrap();
        assert_eq!(gain.owners.len(), 1);
        assert!(!gain.is_locked() && !gain.is_stale());
        // A second claimant: found already; locked once both answered.
        assert!(catalog.update([m(1, owner), m(4, owner)]).is_empty());
        assert!(!catalog.get("rover1/gain").unwrap().is_locked());
        let now = Instant::now();
        let ch = "rover1/.config/gain";
        catalog.hear(ch, &ack("", Some(1.0)), at(1), now).unwrap();
        assert!(!catalog.get("rover1/gain").unwrap().is_locked());
        catalog.hear(ch, &ack("", Some(1.0)), at(4), now).unwrap();
        assert!(catalog.get("rover1/gain").unwrap().is_locked());
        // One gone: not locked; both gone: stale; unannounced: forgotten.
        let mut gone = m(4, owner);
        gone.live = false;
        catalog.update([m(1, owner), gone]);
        assert!(!catalog.get("rover1/gain").unwrap().is_locked());
        let mut gone_too = m(1, owner);
        gone_too.live = false;
        catalog.update([gone_too]);
        assert!(catalog.get("rover1/gain").unwrap().is_stale());
        catalog.update([]);
        assert!(catalog.get("rover1/gain").is_none());
    }

    #[test]
    fn a_claim_counts_as_an_owner_only_once_answered_from_where_it_sends() {
        let mut catalog = Catalog::default();
        let owner = owning("gain");
        let ch = "rover1/.config/gain";
        let now = Instant::now();
        let ours = Member {
            key: 1,
            node: "controller",
            live: true,
            channels: &owner,
            address: at(1),
            data_address: Some(at(1)),
        };
        // A 2.x heartbeat claiming the setting, from a stranger's socket.
        let claim = |key, port| Member {
            key,
            node: "stranger",
            live: true,
            channels: &owner,
            address: SocketAddr::from(([127, 0, 0, 1], port)),
            data_address: None,
        };
        catalog.update([ours, claim(9, 9000)]);
        catalog.hear(ch, &ack("", Some(1.5)), at(1), now).unwrap();
        let gain = catalog.get("rover1/gain").unwrap();
        assert!(
            !gain.is_locked(),
            "a claim nobody answered for locks nothing"
        );
        let claims: Vec<&str> = gain.unanswered_claims().map(|o| o.node.as_str()).collect();
        assert_eq!(claims, ["stranger"]);
        // A confirmation from a socket no claimant sends from (another
        // host) is not taken.
        let elsewhere = SocketAddr::from(([10, 0, 0, 9], 1234));
        assert!(catalog
            .hear(ch, &ack("", Some(0.1)), elsewhere, now)
            .unwrap()
            .is_none());
        assert_eq!(catalog.unowned(), 1);
        let gain = catalog.get("rover1/gain").unwrap();
        assert_eq!(gain.value_text().as_deref(), Some("1.5"));
        // Forged confirmations from a second socket of the claim's host:
        // then it is an owner that answered, and the setting is locked.
        let forged = SocketAddr::from(([127, 0, 0, 1], 9001));
        catalog.hear(ch, &ack("", Some(1.5)), forged, now).unwrap();
        assert!(catalog.get("rover1/gain").unwrap().is_locked());
        // Our owners send from their data address only: one of theirs
        // from another socket is no answer of theirs.
        let mut catalog = Catalog::default();
        catalog.update([ours, Member { key: 2, ..ours }]);
        let other = SocketAddr::from(([127, 0, 0, 1], 9002));
        catalog.hear(ch, &ack("", Some(1.5)), at(1), now).unwrap();
        catalog.hear(ch, &ack("", Some(1.5)), other, now).unwrap();
        assert!(!catalog.get("rover1/gain").unwrap().is_locked());
        // An early confirmation waits for the claim it answers for.
        let mut catalog = Catalog::default();
        catalog.update([ours]);
        catalog.hear(ch, &ack("", Some(1.5)), at(1), now).unwrap();
        catalog.hear(ch, &ack("", Some(1.5)), at(3), now).unwrap();
        let third = Member {
            key: 3,
            data_address: Some(at(3)),
            address: at(3),
            ..ours
        };
        catalog.update([ours, third]);
        assert!(catalog.get("rover1/gain").unwrap().is_locked());
    }

    /// A catalog that knows one owner of `rover1/gain`.
    fn with_gain() -> Catalog {
        let mut catalog = Catalog::default();
        let owner = owning("gain");
        catalog.update([Member {
            key: 1,
            node: "n",
            live: true,
            channels: &owner,
            address: at(1),
            data_address: Some(at(1)),
        }]);
        catalog
    }

    #[test]
    fn confirmations_fill_values_and_the_poke_answer_is_the_description() {
        let mut catalog = with_gain();
        let ch = "rover1/.config/gain";
        let now = Instant::now();
        assert_eq!(catalog.poke(ch, now), request(Request::Poke));
        let info = catalog.hear(ch, &ack("must be in [0, 2]", Some(1.5)), at(1), now);
        let info = info.unwrap().unwrap();
        assert_eq!(info.about.as_deref(), Some("must be in [0, 2]"));
        assert_eq!(info.last_refusal, None);
        assert_eq!(info.value_text().as_deref(), Some("1.5"));
        assert_eq!(info.type_name().as_deref(), Some("double_msg"));
        let info = catalog
            .hear(ch, &ack("", None), at(1), now)
            .unwrap()
            .unwrap();
        assert_eq!(info.value_text().as_deref(), Some("unset"));
        assert_eq!(info.about.as_deref(), Some("must be in [0, 2]"));
        assert_eq!(info.heard, 2);
        // Bad bytes change nothing; an unknown channel is no setting.
        assert!(catalog.hear(ch, b"garbage", at(1), now).is_err());
        let huge = vec![0; MAX_CONFIRMATION + 1];
        assert!(catalog.hear(ch, &huge, at(1), now).is_err());
        let none = catalog.hear("rover1/.config/none", &ack("", None), at(1), now);
        assert!(none.unwrap().is_none());
        assert_eq!(catalog.get("rover1/gain").unwrap().heard, 2);
    }

    #[test]
    fn poke_answers_are_told_from_refusals_and_requests_judged() {
        let mut catalog = with_gain();
        let ch = "rover1/.config/gain";
        let t0 = Instant::now();
        // Two pokes out; the text of a refusal is the same as the answer
        // to a poke (as 2.x validators and checks without a description
        // give), so only the pokes out tell them apart.
        catalog.poke(ch, t0);
        catalog.poke(ch, t0);
        catalog
            .hear(ch, &ack("must be in [0, 2]", Some(1.5)), at(1), t0)
            .unwrap();
        let sent_at = catalog.get("rover1/gain").unwrap().heard;
        let want = Target::Value(Primitive::Double(0.5));
        // The second poke's answer comes after the request: not a refusal.
        let late = catalog
            .hear(ch, &ack("must be in [0, 2]", Some(1.5)), at(1), t0)
            .unwrap()
            .unwrap();
        assert_eq!(judge(late, &want, sent_at), Verdict::Waiting);
        // The owner's own change meanwhile: not the answer either.
        let other = catalog
            .hear(ch, &ack("", Some(1.0)), at(1), t0)
            .unwrap()
            .unwrap();
        assert_eq!(judge(other, &want, sent_at), Verdict::Waiting);
        let granted = catalog
            .hear(ch, &ack("", Some(0.5)), at(1), t0)
            .unwrap()
            .unwrap();
        assert_eq!(judge(granted, &want, sent_at), Verdict::Granted);
        // No poke out: the same text is a refusal, and stays one for a
        // waiter even when a later confirmation came.
        let sent_at = catalog.get("rover1/gain").unwrap().heard;
        let want = Target::Value(Primitive::Double(9.0));
        catalog
            .hear(ch, &ack("must be in [0, 2]", Some(0.5)), at(1), t0)
            .unwrap();
        let after = catalog
            .hear(ch, &ack("", Some(0.5)), at(1), t0)
            .unwrap()
            .unwrap();
        let refused = Verdict::Refused("must be in [0, 2]".into());
        assert_eq!(judge(after, &want, sent_at), refused);
        assert_eq!(kept(after), "the owner kept 0.5");
        // A poke unanswered for over a second counts as lost.
        catalog.poke(ch, t0);
        let later = t0 + Duration::from_secs(2);
        let sent_at = catalog.get("rover1/gain").unwrap().heard;
        let info = catalog
            .hear(ch, &ack("must be in [0, 2]", Some(0.5)), at(1), later)
            .unwrap()
            .unwrap();
        assert!(matches!(judge(info, &want, sent_at), Verdict::Refused(_)));
        // Floats are compared by their bits; f32 settings by their f32.
        let f = convert(PrimitiveKind::Float, Primitive::Double(0.1)).unwrap();
        assert_eq!(f, Primitive::Float(f64::from(0.1f32)));
        assert!(same(
            &Primitive::Double(f64::NAN),
            &Primitive::Double(f64::NAN)
        ));
    }

    #[test]
    fn the_catalog_is_bounded() {
        let mut catalog = Catalog::new(2);
        let channels: Vec<ChannelInfo> = (0..5).flat_map(|i| owning(&format!("s{i}"))).collect();
        let found = catalog.update([Member {
            key: 1,
            node: "n",
            live: true,
            channels: &channels,
            address: at(1),
            data_address: Some(at(1)),
        }]);
        assert_eq!(found.len(), 2);
        assert_eq!(catalog.left_out(), 3);
    }

    #[test]
    fn typed_text_and_toml_values_are_read_as_the_settings_type() {
        assert_eq!(
            parse_value(PrimitiveKind::Double, " 2.5 "),
            Ok(Primitive::Double(2.5))
        );
        assert_eq!(
            parse_value(PrimitiveKind::Bool, "on"),
            Ok(Primitive::Bool(true))
        );
        assert!(parse_value(PrimitiveKind::I8, "300").is_err());
        assert_eq!(
            parse_value(PrimitiveKind::String, " a b"),
            Ok(Primitive::String(" a b".into()))
        );
        assert_eq!(
            convert(PrimitiveKind::I16, Primitive::I64(-7)),
            Ok(Primitive::I16(-7))
        );
        assert!(convert(PrimitiveKind::Byte, Primitive::I64(256)).is_err());
        assert_eq!(
            convert(PrimitiveKind::Double, Primitive::I64(2)),
            Ok(Primitive::Double(2.0))
        );
        assert!(convert(PrimitiveKind::I64, Primitive::Double(2.0)).is_err());
        assert!(convert(PrimitiveKind::Bool, Primitive::String("x".into())).is_err());
        assert_eq!(primitive_json(&Primitive::I8(-3)), serde_json::json!(-3));
        let req = set_request(PrimitiveKind::I32, Primitive::I64(5)).unwrap();
        assert_eq!(Primitive::decode(&req).unwrap(), Primitive::I32(5));
    }
}

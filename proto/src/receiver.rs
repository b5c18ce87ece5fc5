//! What a node does with the datagrams it receives, as a state machine
//! without sockets, tasks or clocks: the one receive path of every node,
//! and what the simulation tests and the fuzzers drive.
//!
//! A [`Receiver`] owns the dispatch table (channel -> subscribers), each
//! channel's [`LeadTracker`], the [`Reassembler`] and the [`Opener`]. It
//! takes every kind of datagram on the wire (2.x packet, batch, fragment,
//! sealed, discovery), delivers complete messages into its subscribers'
//! [`Sink`]s, and hands out what it does not keep: gossip for the
//! discovery layer ([`Receiver::poll_gossip`]) and the details of what it
//! dropped ([`Receiver::poll_drop`]). It counts every datagram under
//! exactly one [`Fate`] and every drop under one [`DropReason`]
//! ([`Receiver::counts`]).
//!
//! # Call order
//!
//! 1. [`Receiver::subscribe`] / [`Receiver::unsubscribe`] at any time.
//! 2. For each datagram read: [`Receiver::handle_datagram`]. When it
//!    returns a [`Loan`], the next datagram of that socket may be received
//!    straight into the message buffer ([`Loan::land`]); give the loan back
//!    with [`Receiver::repay`] either way.
//! 3. After each call: [`Receiver::poll_gossip`] and [`Receiver::poll_drop`]
//!    until `None` (one datagram adds at most one gossip datagram; drop
//!    details past [`MAX_DROP_DETAILS`] are counted but not kept).
//! 4. [`Receiver::poll_timeout`] says when to call
//!    [`Receiver::handle_timeout`] (fragmented messages that stopped).
//!
//! Gossip received by unicast, on the discovery socket rather than a
//! receive socket, is opened by [`Receiver::open_gossip`].
//!
//! # Several receivers
//!
//! A node with several receive sockets runs one receiver per socket
//! ([`Receiver::sibling`]), each for the channels whose groups its socket
//! joined, so that sockets are read in parallel. Siblings share one
//! reassembly, so the memory limits of [`ReassemblyLimits`] hold for all of them
//! together; each has its own dispatch, leads, replay windows and counts
//! (add them up with [`ReceiveCounts::add`]). A receiver's lock is taken before
//! the shared reassembly's, which is held only while a fragment is stored
//! or a loan is taken back.

use std::collections::{HashMap, VecDeque};
use std::net::{Ipv4Addr, SocketAddr};
use std::ops::Range;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use bytes::{Bytes, BytesMut};

use super::fragment::{Header, Loan, Outcome, Reassembler, ReassemblyLimits};
use super::secure::{self, OpenError, Opener};
use super::{Lead, LeadTracker};
use crate::wire::batch::Layout;
use crate::wire::{self, Datagram, DecodeError, DropReason, Fingerprint, Kind, DISCOVERY_CHANNEL};

/// Most senders whose leads one channel tracks (the oldest are forgotten).
pub const MAX_SOURCES_PER_CHANNEL: usize = 1024;

/// Most drop details kept between two [`Receiver::poll_drop`] drains.
pub const MAX_DROP_DETAILS: usize = 64;

/// One received message, on its way to a subscriber: not yet decoded.
#[derive(Debug, Clone)]
pub struct RawMessage {
    /// The payload: a view into the datagram (or the reassembled message).
    pub payload: Bytes,
    /// Where it came from.
    pub source: SocketAddr,
    /// The sender's sequence number for the channel.
    pub seq: u32,
    /// Its lead (see [`LeadTracker`]).
    pub lead: Lead,
}

/// The messages of one batch datagram, not yet taken apart: a view of
/// the datagram and where its messages are. Cheap to clone (one reference
/// count), so a sink may keep it whole and take the messages out one by
/// one later ([`RawBatch::pop`]).
#[derive(Debug, Clone)]
pub struct RawBatch {
    datagram: Bytes,
    /// The messages not yet taken.
    layout: Layout,
    source: SocketAddr,
    first_lead: Lead,
    /// Messages taken (or skipped) from the front so far.
    taken: usize,
}

impl RawBatch {
    /// How many messages it holds.
    pub fn len(&self) -> usize {
        usize::from(self.layout.count())
    }

    /// Whether it holds none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Its messages, in order, each a view of the datagram.
    pub fn messages(&self) -> impl Iterator<Item = RawMessage> + '_ {
        let (datagram, source, first_lead) = (&self.datagram, self.source, self.first_lead);
        let taken = self.taken;
        self.layout
            .entries(datagram)
            .enumerate()
            .map(move |(i, (seq, range))| RawMessage {
                payload: datagram.slice(range),
                source,
                seq,
                lead: LeadTracker::lead_in_run(first_lead, taken + i),
            })
    }

    /// Takes the first message out.
    pub fn pop(&mut self) -> Option<RawMessage> {
        let ((seq, range), rest) = self.layout.split_first(&self.datagram)?;
        let lead = LeadTracker::lead_in_run(self.first_lead, self.taken);
        self.layout = rest;
        self.taken += 1;
        Some(RawMessage {
            payload: self.datagram.slice(range),
            source: self.source,
            seq,
            lead,
        })
    }
}

/// Where a subscriber's messages go: its queue, in a node.
pub trait Sink {
    /// Queues `messages`; returns how many of them (or of those queued
    /// before) the queue's policy dropped to make room.
    fn push_many(&mut self, messages: impl Iterator<Item = RawMessage>) -> usize;

    /// Queues every message of `batch`, as [`Sink::push_many`] does; a
    /// sink that can keep the batch whole (one entry, not one per message)
    /// does so.
    fn push_batch(&mut self, batch: &RawBatch) -> usize {
        self.push_many(batch.messages())
    }
}

/// The type a typed subscription accepts, checked before a message is
/// queued so that payloads of other types never take a place in its queue.
#[derive(Debug, Clone, Copy)]
pub struct Expected {
    /// The fingerprint payloads must start with.
    pub fingerprint: Fingerprint,
    /// The type's name, for the log.
    pub type_name: &'static str,
}

impl Expected {
    /// Whether `payload` starts with the expected fingerprint.
    pub fn check(&self, payload: &[u8]) -> Result<(), DecodeError> {
        match Fingerprint::of_payload(payload) {
            Some(found) if found == self.fingerprint => Ok(()),
            Some(found) => Err(DecodeError::WrongType {
                expected: self.fingerprint,
                expected_name: self.type_name,
                found,
            }),
            None => Err(DecodeError::Truncated {
                offset: payload.len(),
                needed: 8 - payload.len(),
            }),
        }
    }
}

/// One subscription as the receiver sees it.
#[derive(Debug)]
pub struct Subscriber<S> {
    /// Unique within the receiver; [`Receiver::unsubscribe`] takes it.
    pub id: u64,
    /// Skip messages whose lead is below 1 (late or duplicate).
    pub ordered: bool,
    /// Refuse payloads of another type.
    pub expected: Option<Expected>,
    /// Where accepted messages go.
    pub sink: S,
}

/// What became of one datagram: each datagram read has exactly one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fate {
    /// A packet or batch whose messages went to the channel's subscribers.
    Delivered,
    /// A fragment taken by reassembly (pending, completing, duplicate, or
    /// refused by the memory limits: see [`DropReason::IncompleteMessage`]).
    Fragment,
    /// Gossip handed to discovery ([`Receiver::poll_gossip`]).
    Gossip,
    /// For a channel nobody here subscribes (it shares a group), or gossip
    /// while discovery is off: not ours to count as dropped.
    NotOurs,
    /// Dropped, counted under one [`DropReason`].
    Dropped,
}

impl Fate {
    /// Every fate, in the order [`ReceiveCounts::fates`] stores them.
    pub const ALL: [Fate; 5] = [
        Fate::Delivered,
        Fate::Fragment,
        Fate::Gossip,
        Fate::NotOurs,
        Fate::Dropped,
    ];
}

/// What a receiver did so far. Every count only grows.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct ReceiveCounts {
    /// Datagrams handled (a fragment received in place included).
    pub datagrams: u64,
    /// Per [`Fate`], in the order of [`Fate::ALL`]; they add up to `datagrams`.
    pub fates: [u64; Fate::ALL.len()],
    /// Complete messages on subscribed channels (a batch's each count).
    pub messages: u64,
    /// (message, subscriber) pairs offered to subscribers; each is
    /// `queued`, `out_of_order_skipped`, `refused` or `overflowed`.
    pub offered: u64,
    /// Offers a sink took.
    pub queued: u64,
    /// Offers an ordered subscriber skipped (lead below 1).
    pub out_of_order_skipped: u64,
    /// Offers a typed subscriber refused (another type, or too short to
    /// carry one).
    pub refused: u64,
    /// Messages a full queue dropped by its policy.
    pub overflowed: u64,
    /// Drops per reason, in the order of [`DropReason::ALL`]: dropped
    /// datagrams, refused and overflowed offers, and incomplete messages.
    pub dropped: [u64; DropReason::ALL.len()],
}

impl ReceiveCounts {
    /// Adds `other`'s counts to these (a node's receivers, summed).
    pub fn add(&mut self, other: &ReceiveCounts) {
        self.datagrams += other.datagrams;
        for (sum, more) in self.fates.iter_mut().zip(other.fates) {
            *sum += more;
        }
        self.messages += other.messages;
        self.offered += other.offered;
        self.queued += other.queued;
        self.out_of_order_skipped += other.out_of_order_skipped;
        self.refused += other.refused;
        self.overflowed += other.overflowed;
        for (sum, more) in self.dropped.iter_mut().zip(other.dropped) {
            *sum += more;
        }
    }

    /// Datagrams that met `fate`.
    pub fn fate(&self, fate: Fate) -> u64 {
        self.fates[fate as usize]
    }

    /// Drops for `reason`.
    pub fn dropped(&self, reason: DropReason) -> u64 {
        self.dropped[reason.index()]
    }
}

/// Why something was dropped, in detail, for the log.
#[derive(Debug, Clone)]
pub enum Cause {
    /// It did not decode, or a subscriber refused its type.
    Decode(DecodeError),
    /// A sealed datagram that did not open.
    Open(OpenError),
    /// Not sealed, on a channel with a key.
    Unsealed,
    /// A fragmented message that did not complete.
    Incomplete,
    /// A full queue dropped a message.
    Overflow,
    /// A sealed datagram of another channel, sent to the discovery socket.
    Misdirected,
}

/// One drop, in detail: what [`Receiver::poll_drop`] gives.
#[derive(Debug, Clone)]
pub struct Dropped {
    /// The counter it went to.
    pub reason: DropReason,
    /// Its channel, when known.
    pub channel: Option<Arc<str>>,
    /// Its sender, when known.
    pub source: Option<SocketAddr>,
    /// Why.
    pub cause: Cause,
    /// How many drops for `reason` the receiver had counted with this one:
    /// 1 for the first.
    pub nth: u64,
}

/// How one namespace's keys fared with what this node received: from
/// `pulicast::Node::key_uses`. It tells a key that opens nothing (another
/// key than the fleet's) from a namespace the fleet does not seal.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
#[non_exhaustive]
pub struct KeyUse {
    /// The namespace the keys are for (`""` is the root: every channel
    /// without a more specific key).
    pub namespace: String,
    /// Sealed datagrams in the namespace that opened under its keys.
    pub opened: u64,
    /// Sealed datagrams in the namespace whose tag did not match its keys:
    /// sealed with another key (or tampered with). Counted as
    /// [`DropReason::Forged`] too.
    pub not_opened: u64,
    /// Datagrams in the namespace that were not sealed, refused because it
    /// has a key. Counted as [`DropReason::Unauthenticated`] too.
    pub unsealed: u64,
}

/// How a [`Receiver`] is set up.
#[derive(Debug)]
pub struct ReceiverConfig {
    /// Memory and time limits of reassembly.
    pub limits: ReassemblyLimits,
    /// The node's keys, if it has any.
    pub opener: Option<Opener>,
    /// Whether gossip is taken (discovery is on).
    pub gossip: bool,
    /// Whether gossip must be sealed (a key covers the discovery channel);
    /// unsealed gossip is then refused, counted, even with discovery off.
    pub gossip_sealed: bool,
    /// The address the node's own datagrams come from, and its ports:
    /// heard back, they do not count in [`KeyUse`].
    pub own_ip: Ipv4Addr,
    /// See `own_ip`.
    pub own_ports: Vec<u16>,
}

impl Default for ReceiverConfig {
    fn default() -> Self {
        Self {
            limits: ReassemblyLimits::default(),
            opener: None,
            gossip: false,
            gossip_sealed: false,
            own_ip: Ipv4Addr::UNSPECIFIED,
            own_ports: Vec::new(),
        }
    }
}

/// The subscribers of one channel and the lead state they share.
struct Channel<S> {
    leads: LeadTracker,
    subscribers: Vec<Subscriber<S>>,
    /// Whether a key covers the channel: only sealed datagrams count.
    sealed: bool,
}

/// The receive side of a node. See the [module docs](self) for the call
/// order.
pub struct Receiver<S> {
    channels: HashMap<Arc<str>, Channel<S>>,
    /// Shared with the siblings (see the module docs).
    reassembler: Arc<Mutex<Reassembler>>,
    opener: Option<Opener>,
    /// Per namespace with a key, what its keys met.
    uses: Vec<KeyUse>,
    gossip_on: bool,
    gossip_sealed: bool,
    own_ip: Ipv4Addr,
    own_ports: Vec<u16>,
    counts: ReceiveCounts,
    gossip: VecDeque<(SocketAddr, Bytes)>,
    drops: VecDeque<Dropped>,
}

impl<S: Sink> Receiver<S> {
    /// A receiver without subscribers.
    pub fn new(config: ReceiverConfig) -> Self {
        let uses = config
            .opener
            .as_ref()
            .map(|o| {
                let namespaces = o.namespaces().into_iter();
                namespaces
                    .map(|namespace| KeyUse {
                        namespace: namespace.to_owned(),
                        ..KeyUse::default()
                    })
                    .collect()
            })
            .unwrap_or_default();
        Self {
            channels: HashMap::new(),
            reassembler: Arc::new(Mutex::new(Reassembler::new(config.limits))),
            opener: config.opener,
            uses,
            gossip_on: config.gossip,
            gossip_sealed: config.gossip_sealed,
            own_ip: config.own_ip,
            own_ports: config.own_ports,
            counts: ReceiveCounts::default(),
            gossip: VecDeque::new(),
            drops: VecDeque::new(),
        }
    }

    /// A receiver for another socket: the same keys, settings and
    /// reassembly (its memory limits shared), no subscribers, counts at 0,
    /// and no gossip taken: only the receiver of the socket that carries
    /// the discovery group takes it ([`Receiver::set_gossip`]), so a
    /// sender's sealed gossip meets one replay window, wherever a copy is
    /// sent.
    #[must_use]
    pub fn sibling(&self) -> Self {
        Self {
            channels: HashMap::new(),
            reassembler: Arc::clone(&self.reassembler),
            opener: self.opener.as_ref().map(Opener::with_same_keys),
            uses: self
                .uses
                .iter()
                .map(|u| KeyUse {
                    namespace: u.namespace.clone(),
                    ..KeyUse::default()
                })
                .collect(),
            gossip_on: false,
            gossip_sealed: self.gossip_sealed,
            own_ip: self.own_ip,
            own_ports: self.own_ports.clone(),
            counts: ReceiveCounts::default(),
            gossip: VecDeque::new(),
            drops: VecDeque::new(),
        }
    }

    /// Takes out `channel`'s replay windows, for the receiver that
    /// handles it from now on ([`Receiver::put_windows`]).
    pub fn take_windows(&mut self, channel: &str) -> secure::ChannelWindows {
        self.opener
            .as_mut()
            .map(|o| o.take_windows(channel))
            .unwrap_or_default()
    }

    /// Adds `channel`'s replay windows taken from a sibling: a channel
    /// whose group moved to this receiver's socket refuses what it refused
    /// there.
    pub fn put_windows(&mut self, channel: &str, windows: secure::ChannelWindows) {
        if let Some(opener) = self.opener.as_mut() {
            opener.put_windows(channel, windows);
        }
    }

    /// ReceiveCounts `port` (on the node's address) among the node's own sockets,
    /// whose datagrams heard back are not counted in the key uses: a
    /// socket opened after the start, such as the service socket.
    pub fn add_own_port(&mut self, port: u16) {
        if !self.own_ports.contains(&port) {
            self.own_ports.push(port);
        }
    }

    /// Whether this receiver takes gossip (with discovery on: the receiver
    /// of the socket that carries the discovery group). Without it, gossip
    /// is not ours, and sealed gossip is not opened.
    pub fn set_gossip(&mut self, on: bool) {
        self.gossip_on = on;
    }

    /// The shared reassembly. A panic elsewhere while it was held leaves
    /// its tables consistent (every change is made whole), so a poisoned
    /// lock is taken over.
    fn reassembly(&self) -> MutexGuard<'_, Reassembler> {
        self.reassembler
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Adds a subscriber to `channel`; true if it is the channel's first
    /// (its group is to be joined). `sealed`: only sealed datagrams count
    /// on the channel (taken from its first subscriber).
    pub fn subscribe(&mut self, channel: &Arc<str>, sealed: bool, sub: Subscriber<S>) -> bool {
        let first = !self.channels.contains_key(channel);
        let entry = self
            .channels
            .entry(Arc::clone(channel))
            .or_insert_with(|| Channel {
                leads: LeadTracker::new(MAX_SOURCES_PER_CHANNEL),
                subscribers: Vec::new(),
                sealed,
            });
        entry.subscribers.push(sub);
        first
    }

    /// Removes the subscriber `id` of `channel`, and returns it; `last`
    /// is true if the channel has no subscriber left (its group may be
    /// left).
    #[must_use]
    pub fn unsubscribe(&mut self, channel: &str, id: u64) -> Option<Unsubscribed<S>> {
        let entry = self.channels.get_mut(channel)?;
        let at = entry.subscribers.iter().position(|s| s.id == id)?;
        let subscriber = entry.subscribers.remove(at);
        let last = entry.subscribers.is_empty();
        if last {
            self.channels.remove(channel);
        }
        Some(Unsubscribed { subscriber, last })
    }

    /// Drops every subscriber (the node stops).
    pub fn clear(&mut self) {
        self.channels.clear();
    }

    /// Whether anyone here subscribes `channel`.
    pub fn subscribes(&self, channel: &str) -> bool {
        self.channels.contains_key(channel)
    }

    /// What the receiver did so far.
    pub fn counts(&self) -> &ReceiveCounts {
        &self.counts
    }

    /// Bytes of incomplete messages held.
    pub fn reassembly_bytes(&self) -> usize {
        self.reassembly().bytes()
    }

    /// What each namespace's keys met so far (empty without keys).
    pub fn key_uses(&self) -> Vec<KeyUse> {
        self.uses.clone()
    }

    /// The next gossip datagram received, with its sender.
    #[must_use]
    pub fn poll_gossip(&mut self) -> Option<(SocketAddr, Bytes)> {
        self.gossip.pop_front()
    }

    /// The next drop's details.
    #[must_use]
    pub fn poll_drop(&mut self) -> Option<Dropped> {
        self.drops.pop_front()
    }

    /// When [`Receiver::handle_timeout`] is next due.
    #[must_use]
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.reassembly().poll_timeout()
    }

    /// Gives up on fragmented messages past their deadline.
    pub fn handle_timeout(&mut self, now: Instant) {
        self.reassembly().expire(now);
        self.count_lost();
    }

    /// Handles the datagram in `buf`, received from `source` at `now`
    /// (`unix_ms` by the wall clock, for sealed datagrams' age). Only a
    /// datagram that is delivered is taken out of `buf` (without
    /// copying); otherwise its space is reused.
    ///
    /// A fragment of a message still incomplete returns the loan of its
    /// buffer, to receive the next fragment into (see [`Loan`]).
    #[must_use]
    pub fn handle_datagram(
        &mut self,
        now: Instant,
        unix_ms: u64,
        source: SocketAddr,
        buf: &mut BytesMut,
    ) -> Option<Loan> {
        self.counts.datagrams += 1;
        match Kind::of(buf) {
            Kind::Sealed => self.handle_sealed(now, unix_ms, source, buf),
            Kind::Discovery => {
                if self.gossip_sealed {
                    self.drop_unsealed(DISCOVERY_CHANNEL, source);
                } else if !self.gossip_on {
                    self.fate(Fate::NotOurs);
                } else {
                    self.fate(Fate::Gossip);
                    self.gossip.push_back((source, buf.split().freeze()));
                }
                None
            }
            _ => self.handle_inner(now, source, buf, false),
        }
    }

    /// Takes back a loan whose fragment did (`received`: it is counted as
    /// a datagram) or did not come; delivers the message if that
    /// completed it, or lends it out again for the fragment after.
    #[must_use]
    pub fn repay(&mut self, loan: Loan, received: bool) -> Option<Loan> {
        if received {
            self.counts.datagrams += 1;
            self.fate(Fate::Fragment);
        }
        let channel = Arc::clone(loan.channel());
        let (source, seq) = (loan.source(), loan.seq);
        let mut reassembly = self.reassembly();
        let outcome = reassembly.repay(loan, received);
        let next = match (&outcome, received) {
            (Outcome::Pending, true) => reassembly.lend(&channel, source, seq),
            _ => None,
        };
        drop(reassembly);
        self.count_lost();
        self.conclude(&channel, source, outcome);
        next
    }

    /// Opens a gossip datagram received by unicast, where it lies, and
    /// returns where the gossip in it is: sealed ones are opened, unsealed
    /// ones pass only while gossip need not be sealed. Not counted among
    /// [`ReceiveCounts::datagrams`] (they are not read from a receive socket);
    /// what it refuses is counted as dropped.
    #[must_use]
    pub fn open_gossip(
        &mut self,
        unix_ms: u64,
        source: SocketAddr,
        datagram: &mut [u8],
    ) -> Option<Range<usize>> {
        if Kind::of(datagram) != Kind::Sealed {
            if self.gossip_sealed {
                self.count_unsealed(DISCOVERY_CHANNEL, source);
                return None;
            }
            return Some(0..datagram.len());
        }
        // Only the discovery channel is opened here: sealed datagrams of
        // made-up channels cost no key derivation.
        let named = wire::split_name(datagram, &secure::MAGIC).map(|(name, _)| name);
        if named != Ok(DISCOVERY_CHANNEL) {
            let channel = named.ok().map(Arc::from);
            self.record_drop(DropReason::Forged, channel, Some(source), || {
                Cause::Misdirected
            });
            return None;
        }
        match self.open(unix_ms, source, datagram) {
            Ok(inner) => Some(inner),
            Err(e) => {
                self.count_unopened(e, datagram, source);
                None
            }
        }
    }

    fn fate(&mut self, fate: Fate) {
        self.counts.fates[fate as usize] += 1;
    }

    /// Opens a sealed datagram and handles what it carries, or counts why
    /// not. Only channels this node listens to are opened: sealed traffic
    /// of others sharing a group costs no cryptography.
    fn handle_sealed(
        &mut self,
        now: Instant,
        unix_ms: u64,
        source: SocketAddr,
        buf: &mut BytesMut,
    ) -> Option<Loan> {
        let discovery = match wire::split_name(buf, &secure::MAGIC) {
            Ok((channel, _)) => {
                let discovery = channel == DISCOVERY_CHANNEL;
                let ours = match discovery {
                    true => self.gossip_on,
                    false => self.channels.contains_key(channel),
                };
                if !ours {
                    self.fate(Fate::NotOurs);
                    return None;
                }
                discovery
            }
            Err(e) => {
                self.drop_datagram(e, source);
                return None;
            }
        };
        let inner = match self.open(unix_ms, source, buf) {
            Ok(inner) => inner,
            Err(e) => {
                self.count_unopened(e, buf, source);
                self.fate(Fate::Dropped);
                return None;
            }
        };
        // The inner datagram stays where it was received: no copy.
        buf.truncate(inner.end);
        let _header = buf.split_to(inner.start);
        if discovery {
            self.fate(Fate::Gossip);
            self.gossip.push_back((source, buf.split().freeze()));
            return None;
        }
        self.handle_inner(now, source, buf, true)
    }

    /// Checks and opens a sealed datagram in place; counts, unless it is
    /// the node's own heard back, what its namespace's keys made of it.
    fn open(
        &mut self,
        unix_ms: u64,
        source: SocketAddr,
        datagram: &mut [u8],
    ) -> Result<Range<usize>, OpenError> {
        let own = self.is_own(source);
        let Some(opener) = self.opener.as_mut() else {
            return Err(OpenError::UnknownKey);
        };
        // Looked up before opening, which may decrypt the datagram in place.
        let uses = match own {
            true => None,
            false => wire::split_name(datagram, &secure::MAGIC)
                .ok()
                .and_then(|(channel, _)| uses_of(&self.uses, channel)),
        };
        let opened = opener.open_in_place(datagram, source, unix_ms);
        if let Some(i) = uses {
            match &opened {
                Ok(_) => self.uses[i].opened += 1,
                // Only a tag that did not match says "another key".
                Err(OpenError::Forged) => self.uses[i].not_opened += 1,
                Err(_) => {}
            }
        }
        opened.map(|o| o.inner)
    }

    /// Whether `source` is one of this node's own sockets, heard back.
    fn is_own(&self, source: SocketAddr) -> bool {
        source.ip() == self.own_ip && self.own_ports.contains(&source.port())
    }

    /// Handles a packet, batch or fragment (`sealed` if it came out of a
    /// sealed datagram): one [`Datagram::decode`], then the channel's
    /// checks (not ours, not sealed), then delivery or reassembly.
    fn handle_inner(
        &mut self,
        now: Instant,
        source: SocketAddr,
        buf: &mut BytesMut,
        sealed: bool,
    ) -> Option<Loan> {
        let (channel, inner) = match Datagram::decode(buf) {
            Ok(view) => {
                let inner = match &view {
                    Datagram::Packet(p) => Kept::Packet {
                        seq: p.seq,
                        payload_len: p.payload.len(),
                    },
                    Datagram::Batch(b) => Kept::Batch(b.layout()),
                    Datagram::Fragment(f) => Kept::Fragment {
                        header: f.header(),
                        chunk_len: f.chunk.len(),
                    },
                    // Never inside a sealed one (`check_inner`), and taken
                    // before this otherwise.
                    Datagram::Sealed(_) | Datagram::Discovery(_) => {
                        self.drop_datagram(DecodeError::BadMagic, source);
                        return None;
                    }
                };
                let name = view.channel().unwrap_or_default();
                match self.channels.get_key_value(name) {
                    // Another channel may share the group; it is not ours
                    // to count, and nothing is buffered for it.
                    None => {
                        self.fate(Fate::NotOurs);
                        return None;
                    }
                    Some((_, c)) if c.sealed && !sealed => {
                        self.drop_unsealed(name, source);
                        return None;
                    }
                    Some((name, _)) => (Arc::clone(name), inner),
                }
            }
            Err(e) => {
                self.drop_datagram(e, source);
                return None;
            }
        };
        match inner {
            Kept::Packet { seq, payload_len } => {
                self.fate(Fate::Delivered);
                let datagram = buf.split().freeze();
                // The payload is the datagram's tail: a view, not a copy.
                let payload = datagram.slice(datagram.len() - payload_len..);
                self.deliver(&channel, source, seq, payload);
                None
            }
            Kept::Batch(layout) => {
                // All of its messages, or none if it was malformed.
                self.fate(Fate::Delivered);
                let datagram = buf.split().freeze();
                self.deliver_batch(&channel, source, layout, &datagram);
                None
            }
            Kept::Fragment { header, chunk_len } => {
                self.handle_fragment(now, source, buf, sealed, channel, header, chunk_len)
            }
        }
    }

    /// Adds a fragment to its message; delivers the message when complete.
    /// While it is not, lends out its buffer for the next fragment (unless
    /// fragments come sealed, and so can't be received in place).
    #[allow(clippy::too_many_arguments)]
    fn handle_fragment(
        &mut self,
        now: Instant,
        source: SocketAddr,
        buf: &BytesMut,
        sealed: bool,
        channel: Arc<str>,
        header: Header,
        chunk_len: usize,
    ) -> Option<Loan> {
        self.fate(Fate::Fragment);
        let chunk = &buf[buf.len() - chunk_len..];
        let mut reassembly = self.reassembly();
        let outcome = reassembly.push(now, &channel, source, header, chunk);
        let loan = match outcome {
            Outcome::Pending if !sealed => reassembly.lend(&channel, source, header.seq),
            _ => None,
        };
        drop(reassembly);
        self.count_lost();
        self.conclude(&channel, source, outcome);
        loan
    }

    /// Delivers a message that reassembly completed, or counts one it gave up.
    fn conclude(&mut self, channel: &Arc<str>, source: SocketAddr, outcome: Outcome) {
        match outcome {
            Outcome::Complete { seq, message } => self.deliver(channel, source, seq, message),
            Outcome::OverBudget => self.count_incomplete(Some(channel), Some(source), 1),
            Outcome::Pending | Outcome::Duplicate => {}
        }
    }

    /// Hands a complete message (a packet's or a reassembled one) to every
    /// subscriber of `channel`, with its lead.
    fn deliver(&mut self, channel: &Arc<str>, source: SocketAddr, seq: u32, payload: Bytes) {
        let Some(entry) = self.channels.get_mut(channel) else {
            return;
        };
        let message = RawMessage {
            payload,
            source,
            seq,
            lead: entry.leads.observe(source, seq),
        };
        let mut offers = Offers::new(channel, &mut self.counts, &mut self.drops);
        for sub in &mut entry.subscribers {
            offers.offer(sub, std::iter::once(message.clone()));
        }
        self.counts.messages += 1;
    }

    /// Hands every message of a checked batch to every subscriber: one lead
    /// lookup for the batch, one sink call per subscriber, and views into
    /// the datagram rather than copies.
    fn deliver_batch(
        &mut self,
        channel: &Arc<str>,
        source: SocketAddr,
        layout: Layout,
        datagram: &Bytes,
    ) {
        let Some(entry) = self.channels.get_mut(channel) else {
            return;
        };
        let count = layout.count();
        let first_lead = entry.leads.observe_run(source, layout.first_seq(), count);
        let batch = RawBatch {
            datagram: datagram.clone(),
            layout,
            source,
            first_lead,
            taken: 0,
        };
        let mut offers = Offers::new(channel, &mut self.counts, &mut self.drops);
        for sub in &mut entry.subscribers {
            offers.offer_batch(sub, &batch);
        }
        self.counts.messages += u64::from(count);
    }

    /// ReceiveCounts a datagram that did not decode.
    fn drop_datagram(&mut self, error: DecodeError, source: SocketAddr) {
        self.fate(Fate::Dropped);
        self.record_drop(error.reason(), None, Some(source), || Cause::Decode(error));
    }

    /// ReceiveCounts a datagram that should have been sealed and was not.
    fn drop_unsealed(&mut self, channel: &str, source: SocketAddr) {
        self.fate(Fate::Dropped);
        self.count_unsealed(channel, source);
    }

    fn count_unsealed(&mut self, channel: &str, source: SocketAddr) {
        if let Some(i) = uses_of(&self.uses, channel) {
            self.uses[i].unsealed += 1;
        }
        let reason = DropReason::Unauthenticated;
        self.record_drop(reason, Some(channel.into()), Some(source), || {
            Cause::Unsealed
        });
    }

    /// ReceiveCounts a sealed datagram that did not open.
    fn count_unopened(&mut self, error: OpenError, datagram: &[u8], source: SocketAddr) {
        // Opening never changes the header, which names the channel.
        let channel = wire::split_name(datagram, &secure::MAGIC)
            .ok()
            .map(|(c, _)| Arc::from(c));
        let reason = error.reason();
        self.record_drop(reason, channel, Some(source), || Cause::Open(error));
    }

    /// ReceiveCounts the messages reassembly gave up since last asked.
    fn count_lost(&mut self) {
        let lost = self.reassembly().take_lost();
        self.count_incomplete(None, None, lost);
    }

    fn count_incomplete(&mut self, channel: Option<&Arc<str>>, source: Option<SocketAddr>, n: u64) {
        for _ in 0..n {
            let channel = channel.map(Arc::clone);
            let reason = DropReason::IncompleteMessage;
            self.record_drop(reason, channel, source, || Cause::Incomplete);
        }
    }

    fn record_drop(
        &mut self,
        reason: DropReason,
        channel: Option<Arc<str>>,
        source: Option<SocketAddr>,
        cause: impl FnOnce() -> Cause,
    ) {
        record(&mut self.counts, &mut self.drops, reason, || Dropped {
            reason,
            channel,
            source,
            cause: cause(),
            nth: 0,
        });
    }
}

/// What [`Receiver::unsubscribe`] removed.
#[derive(Debug)]
#[must_use]
pub struct Unsubscribed<S> {
    /// The subscriber, with its sink.
    pub subscriber: Subscriber<S>,
    /// Whether its channel has no subscriber left.
    pub last: bool,
}

/// What [`Receiver`] keeps of a decoded packet, batch or fragment once
/// the datagram's borrow ends.
enum Kept {
    Packet { seq: u32, payload_len: usize },
    Batch(Layout),
    Fragment { header: Header, chunk_len: usize },
}

/// ReceiveCounts one drop and keeps its details while there is room.
fn record(
    counts: &mut ReceiveCounts,
    drops: &mut VecDeque<Dropped>,
    reason: DropReason,
    detail: impl FnOnce() -> Dropped,
) {
    record_many(counts, drops, reason, 1, detail);
}

/// ReceiveCounts `n` drops of one cause and keeps one detail while there is room.
fn record_many(
    counts: &mut ReceiveCounts,
    drops: &mut VecDeque<Dropped>,
    reason: DropReason,
    n: u64,
    detail: impl FnOnce() -> Dropped,
) {
    counts.dropped[reason.index()] += n;
    if drops.len() < MAX_DROP_DETAILS {
        drops.push_back(Dropped {
            nth: counts.dropped[reason.index()],
            ..detail()
        });
    }
}

/// The index in `uses` of the most specific namespace covering `channel`.
fn uses_of(uses: &[KeyUse], channel: &str) -> Option<usize> {
    uses.iter()
        .enumerate()
        .filter(|(_, u)| crate::name::in_namespace(&u.namespace, channel))
        .max_by_key(|(_, u)| u.namespace.len())
        .map(|(i, _)| i)
}

/// Offers messages of one channel to its subscribers and counts what each
/// did with them.
struct Offers<'a> {
    channel: &'a Arc<str>,
    counts: &'a mut ReceiveCounts,
    drops: &'a mut VecDeque<Dropped>,
}

impl<'a> Offers<'a> {
    fn new(
        channel: &'a Arc<str>,
        counts: &'a mut ReceiveCounts,
        drops: &'a mut VecDeque<Dropped>,
    ) -> Self {
        Self {
            channel,
            counts,
            drops,
        }
    }

    /// Filters `messages` for `sub` (order, type) and queues the rest.
    fn offer<S: Sink>(
        &mut self,
        sub: &mut Subscriber<S>,
        messages: impl Iterator<Item = RawMessage>,
    ) {
        let (ordered, expected) = (sub.ordered, sub.expected);
        let mut source = None;
        let counts = &mut *self.counts;
        let drops = &mut *self.drops;
        let channel = self.channel;
        let mut queued = 0u64;
        let accepted = messages.filter(|message| {
            counts.offered += 1;
            source = Some(message.source);
            if ordered && message.lead < 1 {
                counts.out_of_order_skipped += 1;
                return false;
            }
            if let Some(Err(e)) = expected.map(|x| x.check(&message.payload)) {
                counts.refused += 1;
                let from = Some(message.source);
                record(counts, drops, e.reason(), || Dropped {
                    reason: e.reason(),
                    channel: Some(Arc::clone(channel)),
                    source: from,
                    cause: Cause::Decode(e),
                    nth: 0,
                });
                return false;
            }
            queued += 1;
            true
        });
        let overflowed = sub.sink.push_many(accepted) as u64;
        self.account(queued, overflowed, source);
    }

    /// Hands a whole batch to `sub` when every message passes its filters
    /// (the usual case: all in order, all of its type), so the sink may
    /// keep it as one entry; otherwise message by message.
    fn offer_batch<S: Sink>(&mut self, sub: &mut Subscriber<S>, batch: &RawBatch) {
        let in_order = !sub.ordered || batch.first_lead >= 1;
        let typed = |x: &Expected| {
            batch
                .layout
                .entries(&batch.datagram)
                .all(|(_, range)| x.check(&batch.datagram[range]).is_ok())
        };
        if !(in_order && sub.expected.as_ref().is_none_or(typed)) {
            return self.offer(sub, batch.messages());
        }
        let n = batch.len() as u64;
        self.counts.offered += n;
        let overflowed = sub.sink.push_batch(batch) as u64;
        self.account(n, overflowed, Some(batch.source));
    }

    /// ReceiveCounts what a sink took of `queued` messages, and what its policy
    /// dropped.
    fn account(&mut self, queued: u64, overflowed: u64, source: Option<SocketAddr>) {
        let channel = self.channel;
        self.counts.queued += queued;
        // A policy may drop what was queued before: those count as well.
        self.counts.overflowed += overflowed;
        self.counts.queued -= overflowed.min(queued);
        if overflowed > 0 {
            // One detail for what one push dropped: an old batch may hold
            // thousands of messages, counted at once.
            let reason = DropReason::QueueOverflow;
            record_many(self.counts, self.drops, reason, overflowed, || Dropped {
                reason,
                channel: Some(Arc::clone(channel)),
                source,
                cause: Cause::Overflow,
                nth: 0,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::secure::{Key, Sealer};
    use crate::wire::Packet;

    /// A queue that keeps everything.
    #[derive(Default)]
    struct Keep(Vec<RawMessage>);

    impl Sink for Keep {
        fn push_many(&mut self, messages: impl Iterator<Item = RawMessage>) -> usize {
            self.0.extend(messages);
            0
        }
    }

    const FROM: SocketAddr = SocketAddr::V4(std::net::SocketAddrV4::new(
        Ipv4Addr::new(10, 0, 0, 1),
        4000,
    ));

    fn packet(channel: &str, seq: u32, payload: &[u8]) -> Vec<u8> {
        let mut d = Vec::new();
        Packet {
            channel,
            seq,
            payload,
        }
        .encode(&mut d);
        d
    }

    fn handle(rx: &mut Receiver<Keep>, datagram: &[u8]) -> Option<Loan> {
        rx.handle_datagram(Instant::now(), 0, FROM, &mut BytesMut::from(datagram))
    }

    fn subscriber(id: u64) -> Subscriber<Keep> {
        Subscriber {
            id,
            ordered: false,
            expected: None,
            sink: Keep::default(),
        }
    }

    /// A sink that keeps batches whole, as a node's queue does.
    #[derive(Default)]
    struct KeepBatches(Vec<RawBatch>, Vec<RawMessage>);

    impl Sink for KeepBatches {
        fn push_many(&mut self, messages: impl Iterator<Item = RawMessage>) -> usize {
            self.1.extend(messages);
            0
        }
        fn push_batch(&mut self, batch: &RawBatch) -> usize {
            self.0.push(batch.clone());
            0
        }
    }

    fn batch_datagram(channel: &str, first_seq: u32, payloads: &[&[u8]]) -> Vec<u8> {
        let mut builder = crate::wire::batch::BatchBuilder::new();
        builder.start(channel, first_seq);
        for p in payloads {
            assert!(builder.push(p));
        }
        builder.finish().to_vec()
    }

    /// A batch kept whole gives the same messages, seqs and leads whether
    /// taken all at once or one by one (or partly);
    /// one that a subscriber's filter would split is offered message by
    /// message.
    #[test]
    fn batches_kept_whole_are_taken_apart_like_the_messages_they_hold() {
        let mut rx: Receiver<KeepBatches> = Receiver::new(ReceiverConfig::default());
        let sub = |id, ordered| Subscriber {
            id,
            ordered,
            expected: None,
            sink: KeepBatches::default(),
        };
        let _first = rx.subscribe(&"b".into(), false, sub(0, false));
        let _second = rx.subscribe(&"b".into(), false, sub(1, true));
        let payloads: [&[u8]; 5] = [b"a", b"bb", b"", b"dddd", b"e"];
        let _ = rx.handle_datagram(
            Instant::now(),
            0,
            FROM,
            &mut BytesMut::from(&batch_datagram("b", 10, &payloads)[..]),
        );
        // Late: seqs 7..=9, before the 10..=14 already seen.
        let _ = rx.handle_datagram(
            Instant::now(),
            0,
            FROM,
            &mut BytesMut::from(&batch_datagram("b", 7, &payloads[..3])[..]),
        );
        let removed = rx.unsubscribe("b", 0).unwrap().subscriber.sink;
        let ordered = rx.unsubscribe("b", 1).unwrap().subscriber.sink;
        assert_eq!((removed.0.len(), removed.1.len()), (2, 0));
        // The ordered subscriber took the first whole, the late one split
        // (its messages skipped, all of them late).
        assert_eq!((ordered.0.len(), ordered.1.len()), (1, 0));

        let all: Vec<RawMessage> = removed.0[0].messages().collect();
        let got = |m: &RawMessage| (m.seq, m.lead, m.payload.to_vec());
        assert_eq!(
            all.iter().map(|m| m.seq).collect::<Vec<_>>(),
            [10, 11, 12, 13, 14]
        );
        let mut one_by_one = removed.0[0].clone();
        let popped: Vec<RawMessage> = std::iter::from_fn(|| one_by_one.pop()).collect();
        assert_eq!(
            popped.iter().map(got).collect::<Vec<_>>(),
            all.iter().map(got).collect::<Vec<_>>()
        );
        assert!(one_by_one.is_empty());

        // Partly taken, the rest is what is left.
        let mut part = removed.0[0].clone();
        let _ = part.pop();
        assert_eq!(part.len(), 4);
        let rest: Vec<_> = part.messages().map(|m| got(&m)).collect();
        assert_eq!(rest, all[1..].iter().map(got).collect::<Vec<_>>());
        let _ = part.pop();
        assert_eq!(part.pop().map(|m| got(&m)), Some(got(&all[2])));

        // The late batch: leads below 1, catching up one by one.
        let late: Vec<_> = removed.0[1].messages().map(|m| (m.seq, m.lead)).collect();
        let mut popped = removed.0[1].clone();
        let late_popped: Vec<_> = std::iter::from_fn(|| popped.pop())
            .map(|m| (m.seq, m.lead))
            .collect();
        assert_eq!(late, late_popped);
        assert!(late.iter().all(|&(_, lead)| lead < 1), "{late:?}");
    }

    #[test]
    fn each_namespace_counts_what_its_keys_opened_and_refused() {
        let mut opener = Opener::new(None);
        opener.add_key("rover1", &Key::from_bytes([1; 32])).unwrap();
        opener.add_key("/", &Key::from_bytes([2; 32])).unwrap();
        let mut rx: Receiver<Keep> = Receiver::new(ReceiverConfig {
            opener: Some(opener),
            ..ReceiverConfig::default()
        });
        for channel in ["rover1/pose", "rover2/pose"] {
            let _first = rx.subscribe(&channel.into(), true, subscriber(0));
        }
        let seal = |key: u8, channel: &str| {
            Sealer::new(&Key::from_bytes([key; 32]), channel, false)
                .seal(&packet(channel, 0, b""), 0)
                .to_vec()
        };
        assert!(handle(&mut rx, &seal(1, "rover1/pose")).is_none());
        let _ = handle(&mut rx, &seal(9, "rover1/pose"));
        let _ = handle(&mut rx, &seal(9, "rover1/pose"));
        let _ = handle(&mut rx, &seal(9, "rover2/pose"));
        let _ = handle(&mut rx, &packet("rover2/pose", 0, b""));
        let uses = rx.key_uses();
        let of = |ns: &str| uses.iter().find(|u| u.namespace == ns).unwrap().clone();
        let rover1 = of("rover1");
        assert_eq!(
            (rover1.opened, rover1.not_opened, rover1.unsealed),
            (1, 2, 0)
        );
        let root = of("");
        assert_eq!((root.opened, root.not_opened, root.unsealed), (0, 1, 1));
        let counts = rx.counts();
        assert_eq!(counts.dropped(DropReason::Forged), 3);
        assert_eq!(counts.dropped(DropReason::Unauthenticated), 1);
        assert_eq!(counts.fate(Fate::Delivered), 1);
        assert_eq!(counts.fate(Fate::Dropped), 4);
    }

    #[test]
    fn every_datagram_has_one_fate_and_every_drop_its_details() {
        let mut rx: Receiver<Keep> = Receiver::new(ReceiverConfig {
            gossip: true,
            ..ReceiverConfig::default()
        });
        let _first = rx.subscribe(&"a".into(), false, subscriber(0));
        let _ = handle(&mut rx, &packet("a", 1, b"x"));
        let _ = handle(&mut rx, &packet("other", 1, b"x"));
        let _ = handle(&mut rx, b"PULI\xffshort");
        let _ = handle(&mut rx, b"PDSC gossip");
        let _ = handle(&mut rx, b"?");
        let counts = rx.counts().clone();
        assert_eq!(counts.datagrams, 5);
        let fates: Vec<u64> = Fate::ALL.iter().map(|&f| counts.fate(f)).collect();
        // Delivered, Fragment, Gossip, NotOurs, Dropped.
        assert_eq!(fates, [1, 0, 1, 1, 2]);
        assert_eq!(counts.dropped(DropReason::NamePastEnd), 1);
        assert_eq!(counts.dropped(DropReason::TooShort), 1);
        let (source, gossip) = rx.poll_gossip().unwrap();
        assert_eq!((source, &gossip[..]), (FROM, &b"PDSC gossip"[..]));
        let reasons: Vec<DropReason> = std::iter::from_fn(|| rx.poll_drop())
            .map(|d| d.reason)
            .collect();
        assert_eq!(reasons, [DropReason::NamePastEnd, DropReason::TooShort]);
    }

    #[test]
    fn unsealed_gossip_is_refused_where_a_key_covers_discovery_even_with_discovery_off() {
        let mut opener = Opener::new(None);
        opener.add_key("/", &Key::from_bytes([1; 32])).unwrap();
        let mut rx: Receiver<Keep> = Receiver::new(ReceiverConfig {
            opener: Some(opener),
            gossip: false,
            gossip_sealed: true,
            ..ReceiverConfig::default()
        });
        let _ = handle(&mut rx, b"PDSC gossip");
        assert_eq!(rx.counts().dropped(DropReason::Unauthenticated), 1);
        assert_eq!(rx.key_uses()[0].unsealed, 1);
        let dropped = rx.poll_drop().unwrap();
        assert_eq!(
            (dropped.reason, dropped.nth),
            (DropReason::Unauthenticated, 1)
        );
        assert!(rx.poll_gossip().is_none());
    }

    /// The first fragment of a `size`-byte message on `channel`.
    fn first_fragment(channel: &str, seq: u32, size: usize) -> Vec<u8> {
        let message = vec![7u8; size];
        let count = crate::wire::fragment::Fragment::count_for(channel, size) as u16;
        let mut out = Vec::new();
        crate::wire::fragment::Fragment::encode(channel, seq, &message, 0, count, &mut out);
        out
    }

    #[test]
    fn siblings_share_one_reassembly_budget_and_keep_their_own_channels() {
        let limits = ReassemblyLimits {
            per_source: 1 << 20,
            per_channel: 1 << 20,
            total: 1 << 20,
            timeout: std::time::Duration::from_secs(1),
        };
        let mut first: Receiver<Keep> = Receiver::new(ReceiverConfig {
            limits,
            ..ReceiverConfig::default()
        });
        let mut second = first.sibling();
        let _ = first.subscribe(&"a".into(), false, subscriber(0));
        let _ = second.subscribe(&"b".into(), false, subscriber(1));
        // Gossip is the first's alone (its socket carries the group).
        let mut with_gossip: Receiver<Keep> = Receiver::new(ReceiverConfig {
            gossip: true,
            ..ReceiverConfig::default()
        });
        let mut without = with_gossip.sibling();
        let _ = handle(&mut without, b"PDSC gossip");
        let _ = handle(&mut with_gossip, b"PDSC gossip");
        assert_eq!(without.counts().fate(Fate::NotOurs), 1);
        assert_eq!(with_gossip.counts().fate(Fate::Gossip), 1);
        // Each sibling delivers its own channels only.
        let _ = handle(&mut second, &packet("a", 0, b"x"));
        let _ = handle(&mut second, &packet("b", 0, b"x"));
        assert_eq!(second.counts().fate(Fate::NotOurs), 1);
        assert_eq!(second.counts().fate(Fate::Delivered), 1);
        // 600 kB pending on the first leaves no room for 600 kB on the
        // second: the budget is one.
        let loan = handle(&mut first, &first_fragment("a", 1, 600_000));
        assert!(first.reassembly_bytes() > 600_000);
        assert_eq!(second.reassembly_bytes(), first.reassembly_bytes());
        let _ = handle(&mut second, &first_fragment("b", 1, 600_000));
        assert_eq!(second.counts().dropped(DropReason::IncompleteMessage), 1);
        // ReceiveCounts add up across siblings.
        let mut sum = first.counts().clone();
        sum.add(second.counts());
        assert_eq!(sum.datagrams, 4);
        assert_eq!(sum.fates.iter().sum::<u64>(), 4);
        if let Some(loan) = loan {
            let _ = first.repay(loan, false);
        }
    }

    #[test]
    fn drop_details_are_bounded_but_every_drop_is_counted() {
        let mut rx: Receiver<Keep> = Receiver::new(ReceiverConfig::default());
        for _ in 0..1000 {
            let _ = handle(&mut rx, b"junk");
        }
        assert_eq!(rx.counts().dropped.iter().sum::<u64>(), 1000);
        assert_eq!(rx.counts().fate(Fate::Dropped), 1000);
        assert_eq!(
            std::iter::from_fn(|| rx.poll_drop()).count(),
            MAX_DROP_DETAILS
        );
    }

    #[test]
    fn a_typed_subscriber_refuses_other_types_and_the_last_one_out_says_so() {
        let mut rx: Receiver<Keep> = Receiver::new(ReceiverConfig::default());
        let channel: Arc<str> = "a".into();
        let typed = Subscriber {
            expected: Some(Expected {
                fingerprint: Fingerprint([1; 8]),
                type_name: "T",
            }),
            ..subscriber(1)
        };
        assert!(rx.subscribe(&channel, false, subscriber(0)));
        assert!(!rx.subscribe(&channel, false, typed));
        let _ = handle(&mut rx, &packet("a", 1, &[2; 8]));
        let counts = rx.counts();
        assert_eq!((counts.offered, counts.queued, counts.refused), (2, 1, 1));
        assert_eq!(counts.dropped(DropReason::WrongType), 1);
        assert!(!rx.unsubscribe("a", 0).unwrap().last);
        assert!(rx.unsubscribe("a", 0).is_none());
        let gone = rx.unsubscribe("a", 1).unwrap();
        assert!(gone.last && gone.subscriber.sink.0.is_empty());
        assert!(!rx.subscribes("a"));
    }
}

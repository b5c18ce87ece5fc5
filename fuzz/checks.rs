//! What the fuzz targets check, shared with the regression tests
//! (`pulicast-rs/tests/fuzz_regressions.rs`), which replay every input in
//! `fuzz/regressions/` on stable Rust. Each check takes raw bytes: the
//! structured ones read their operations from the bytes with [`Input`], so
//! no extra crate is needed and any saved input replays exactly.
//!
//! A check panics when a property fails; decoders must never panic on
//! their own.

#![allow(dead_code, clippy::unwrap_used)] // each user picks its checks

use std::cell::{Cell, RefCell};
use std::collections::VecDeque;
use std::net::SocketAddr;
use std::rc::Rc;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::BytesMut;
use pulicast_discovery::gossip::{Gossip, GossipConfig, Via};
use pulicast_discovery::wire::{MemberInfo, Message};
use pulicast_proto::fragment::{Fragment, Landed, Loan, Outcome, Reassembler, ReassemblyLimits};
use pulicast_proto::receiver::{
    Expected, Fate, RawBatch, RawMessage, ReceiverConfig, Sink, Subscriber, MAX_DROP_DETAILS,
};
use pulicast_proto::secure::{Key, Opener, Sealer};
use pulicast_proto::wire::batch::{Batch, BatchBuilder};
use pulicast_proto::wire::{self, zcm, Fingerprint, Packet};
use pulicast_proto::Receiver;

/// Reads operations from fuzz input; past the end, zeros.
pub struct Input<'a>(&'a [u8]);

impl<'a> Input<'a> {
    pub fn new(data: &'a [u8]) -> Self {
        Self(data)
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    pub fn u8(&mut self) -> u8 {
        let (first, rest) = self.0.split_first().map_or((0, &[][..]), |(f, r)| (*f, r));
        self.0 = rest;
        first
    }

    pub fn u16(&mut self) -> u16 {
        u16::from_be_bytes([self.u8(), self.u8()])
    }

    /// Up to `max` bytes, the count read first.
    pub fn bytes_up_to(&mut self, max: usize) -> &'a [u8] {
        let n = usize::from(self.u16()) % (max + 1);
        self.bytes(n)
    }

    pub fn bytes(&mut self, n: usize) -> &'a [u8] {
        let (taken, rest) = self.0.split_at(n.min(self.0.len()));
        self.0 = rest;
        taken
    }
}

/// The Pulicast 2.x packet decoder: what decodes re-encodes to the input.
pub fn packet(data: &[u8]) {
    if let Ok(packet) = Packet::decode(data) {
        let mut again = Vec::new();
        packet.encode(&mut again);
        assert_eq!(again, data);
    }
}

/// The message decoders: ZCM primitives and heartbeats, native postcard,
/// and the text form tools use. What decodes re-encodes and decodes alike.
pub fn messages(data: &[u8]) {
    if let Ok(value) = zcm::Primitive::decode(data) {
        // Compared as bytes: NaN is not equal to itself.
        let mut again = Vec::new();
        value.encode(&mut again);
        let mut third = Vec::new();
        zcm::Primitive::decode(&again).unwrap().encode(&mut third);
        assert_eq!(again, third);
    }
    if let Ok(heartbeat) = zcm::decode_heartbeat(data) {
        let mut again = Vec::new();
        zcm::encode_heartbeat(&heartbeat, &mut again);
        assert_eq!(zcm::decode_heartbeat(&again).ok(), Some(heartbeat));
    }
    if let Ok(value) = wire::decode_native::<(String, Vec<u16>, Option<f64>)>(data) {
        let mut again = Vec::new();
        wire::encode_native(&value, &mut again).unwrap();
        let back = wire::decode_native::<(String, Vec<u16>, Option<f64>)>(&again).unwrap();
        // NaN is not equal to itself; compare the bits.
        assert_eq!(back.0, value.0);
        assert_eq!(back.1, value.1);
        assert_eq!(back.2.map(f64::to_bits), value.2.map(f64::to_bits));
    }
    let _ = pulicast_proto::text::decode_payload(data, None);
}

/// The batch decoder: a batch that passes its checks walks to exactly its
/// count, every entry inside the datagram.
pub fn batch(data: &[u8]) {
    if let Ok(batch) = Batch::decode(data) {
        let mut n = 0;
        for (seq, range) in batch.entries(data) {
            assert!(range.end <= data.len());
            assert_eq!(seq, batch.first_seq.wrapping_add(n));
            n += 1;
        }
        assert_eq!(n, u32::from(batch.count));
    }
}

/// Discovery: the message decoder round-trips, and a gossip member fed
/// hostile datagrams (and time) keeps its tables within their bounds.
pub fn discovery(data: &[u8]) {
    if let Ok(message) = Message::decode(data) {
        assert_eq!(Message::decode(&message.encode()).ok(), Some(message));
    }
    let start = Instant::now();
    let info = MemberInfo {
        session: [7; 16],
        name: "fuzzed".into(),
        namespace: String::new(),
        host: "h".into(),
        pid: 1,
        start_time_ms: 0,
        data_port: 1,
        channels: Vec::new(),
        config: String::new(),
        extensions: Vec::new(),
    };
    let mut config = GossipConfig::for_heartbeat(Duration::from_millis(100));
    config.max_members = 8;
    config.max_assembly_bytes = 4096;
    let mut gossip = Gossip::new(start, info, 9000, config);
    let mut input = Input::new(data);
    let mut now = start;
    while !input.is_empty() {
        let from = SocketAddr::from(([10, 0, 0, input.u8() % 4], 9000));
        let via = if input.u8() % 2 == 0 {
            Via::Multicast
        } else {
            Via::Unicast
        };
        now += Duration::from_millis(u64::from(input.u8()) * 4);
        let len = usize::from(input.u16() % 1500);
        let _ = gossip.handle_datagram(now, from, via, input.bytes(len));
        gossip.handle_timeout(now);
        while gossip.poll_transmit().is_some() {}
        while gossip.poll_event().is_some() {}
        // Ourselves plus the table's bound.
        assert!(gossip.members().count() <= 8 + 1);
    }
}

/// Name resolution: never panics, and what resolves obeys the laws.
pub fn names(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    let (name, namespace) = text.split_once('\u{0}').unwrap_or((&text, ""));
    if let Ok(full) = pulicast::resolve_name(name, namespace) {
        assert!(!full.starts_with('/'), "{full:?} leaves the root");
        assert!(
            !full
                .split('/')
                .any(|p| p == ".." || p == "." || p.is_empty()),
            "{full:?}"
        );
        // Idempotent, and absolute names ignore the namespace.
        assert_eq!(pulicast::resolve_name(&full, "").ok().as_ref(), Some(&full));
        let absolute = format!("/{full}");
        assert_eq!(
            pulicast::resolve_name(&absolute, namespace).ok().as_ref(),
            Some(&full)
        );
        assert_eq!(
            pulicast::resolve_name(&absolute, "elsewhere/deep")
                .ok()
                .as_ref(),
            Some(&full)
        );
    }
}

/// The byte a well-formed fuzzed fragment carries at `offset` of message
/// `seq`: completed messages are checked against it.
fn pattern(seq: u32, offset: usize) -> u8 {
    (offset as u32)
        .wrapping_mul(31)
        .wrapping_add(seq.wrapping_mul(7)) as u8
}

/// Reassembly under hostile, duplicated, reordered and truncated
/// fragments, loans and time: memory stays within its limits, and every
/// completed message has its announced size (and, when only well-formed
/// fragments were accepted, the right bytes).
pub fn reassembly(data: &[u8]) {
    let limits = ReassemblyLimits {
        per_source: 60_000,
        per_channel: 100_000,
        total: 100_000,
        timeout: Duration::from_millis(500),
    };
    let mut r = Reassembler::new(limits);
    let channels: [Arc<str>; 2] = ["a".into(), "b/c".into()];
    let mut input = Input::new(data);
    let mut now = Instant::now();
    let mut forged = false;
    let mut loans = Vec::new();
    while !input.is_empty() {
        let channel = &channels[usize::from(input.u8() % 2)];
        let source = SocketAddr::from(([127, 0, 0, 1], 1 + u16::from(input.u8() % 3)));
        let seq = u32::from(input.u8() % 4);
        let outcome = match input.u8() % 5 {
            // A well-formed fragment of a message whose shape is a function
            // of its seq, so fragments of one message agree.
            0 => {
                let total = 3000 + seq * 7001;
                let count = 2 + (seq as u16 % 5);
                let index = u16::from(input.u8()) % count;
                let size = Fragment::chunk_of_len(total, index, count);
                let offset = usize::from(index) * Fragment::chunk_size(total, count);
                let chunk: Vec<u8> = (offset..offset + size).map(|o| pattern(seq, o)).collect();
                let mut datagram = Vec::new();
                Fragment::encode_header(channel, seq, total, index, count, &mut datagram);
                datagram.extend_from_slice(&chunk);
                let f = Fragment::decode(&datagram).unwrap();
                r.push(now, channel, source, f.header(), f.chunk)
            }
            // Raw bytes after the magic: whatever decodes is pushed.
            1 => {
                let len = usize::from(input.u16() % 600);
                let mut datagram = Fragment::prefix(channel);
                datagram.extend_from_slice(input.bytes(len));
                match Fragment::decode(&datagram) {
                    Ok(f) => {
                        let outcome = r.push(now, channel, source, f.header(), f.chunk);
                        forged |= outcome != Outcome::Duplicate && outcome != Outcome::OverBudget;
                        outcome
                    }
                    Err(_) => Outcome::Duplicate,
                }
            }
            // Lend a buffer out (kept for later).
            2 => {
                if let Some(loan) = r.lend(channel, source, seq) {
                    loans.push(loan);
                }
                Outcome::Pending
            }
            // Repay the oldest loan, with its fragment received in place
            // (well-formed) or not.
            3 => match loans.is_empty() {
                true => Outcome::Pending,
                false => {
                    let mut loan = loans.remove(0);
                    let received = input.u8() % 2 == 0;
                    if received {
                        let size = Fragment::chunk_of_len(loan.total, loan.index, loan.count);
                        let offset =
                            usize::from(loan.index) * Fragment::chunk_size(loan.total, loan.count);
                        let start = loan.data.len();
                        assert_eq!(
                            start, offset,
                            "a loan's buffer ends where its fragment goes"
                        );
                        loan.data
                            .extend((offset..offset + size).map(|o| pattern(loan.seq, o)));
                    }
                    r.repay(loan, received)
                }
            },
            // Time passes.
            _ => {
                now += Duration::from_millis(u64::from(input.u8()) * 8);
                r.expire(now);
                Outcome::Pending
            }
        };
        assert!(r.bytes() <= limits.total, "{} bytes held", r.bytes());
        if let Outcome::Complete { seq, message } = outcome {
            let total = 3000 + seq * 7001;
            if !forged {
                assert_eq!(message.len(), total as usize);
                assert!(message
                    .iter()
                    .enumerate()
                    .all(|(o, &b)| b == pattern(seq, o)));
            }
        }
    }
}

/// Sealed datagrams: hostile bytes never open, never panic; a sealed
/// datagram opens once, and any change to it (the first input byte picks
/// which) makes it fail.
pub fn secure(data: &[u8]) {
    let key = Key::from_bytes([5; 32]);
    let old = Key::from_bytes([6; 32]);
    // A namespace mid key change: the new key seals, both open.
    let opener = || {
        let mut o = Opener::new(Some(Duration::from_secs(30)));
        o.add_key("ns", &key).unwrap();
        o.add_key("ns", &old).unwrap();
        o.add_key("", &Key::from_bytes([7; 32])).unwrap();
        o
    };
    let now = 1_700_000_000_000;
    let from: std::net::SocketAddr = "10.0.0.1:4000".parse().unwrap();
    if let Ok(opened) = opener().open(data, from, now) {
        // Only the holder of a key makes this; still, what opens must be a
        // datagram that may be sealed, for the channel sealed.
        assert!(data.starts_with(b"PSEC"));
        let inner = &opened.inner;
        assert!(!inner.starts_with(b"PSEC"));
    }
    let mut input = Input::new(data);
    let flip = usize::from(input.u16());
    let encrypt = input.u8() % 2 == 0;
    let with_old = input.u8() % 2 == 0;
    let split = usize::from(input.u16());
    let mut inner = Vec::new();
    Packet {
        channel: "ns/ch",
        seq: 0,
        payload: input.bytes(data.len()),
    }
    .encode(&mut inner);
    // Bound to the address it is received from, or to none.
    let origin = match input.u8() % 3 {
        0 => std::net::SocketAddrV4::new([0, 0, 0, 0].into(), 0),
        1 => std::net::SocketAddrV4::new([0, 0, 0, 0].into(), 4000),
        _ => std::net::SocketAddrV4::new([10, 0, 0, 1].into(), 4000),
    };
    let mut sealer =
        Sealer::new(if with_old { &old } else { &key }, "ns/ch", encrypt).with_origin(origin);
    let (head, tail) = inner.split_at(split % (inner.len() + 1));
    let sealed = sealer.seal_parts(&[head, tail], now).to_vec();
    assert_eq!(sealed.len(), inner.len() + Sealer::overhead_for("ns/ch"));
    let mut fresh = opener();
    let elsewhere: std::net::SocketAddr = "10.0.0.2:4001".parse().unwrap();
    if origin.port() != 0 {
        assert!(
            fresh.open(&sealed, elsewhere, now).is_err(),
            "relayed, yet opened"
        );
    }
    assert_eq!(fresh.open(&sealed, from, now).unwrap().inner, inner);
    assert!(fresh.open(&sealed, from, now).is_err(), "a replay opened");
    let mut bad = sealed.clone();
    let i = flip % bad.len();
    bad[i] ^= 1 << (flip % 8);
    assert!(
        opener().open(&bad, from, now).is_err(),
        "a change at {i} went unnoticed"
    );
}

/// What a subscriber's queue holds, shared with the check.
type Held = Rc<RefCell<VecDeque<RawMessage>>>;

/// A subscriber's queue in the receiver check: bounded, dropping the
/// oldest, as a node's default queue does.
struct BoundedSink {
    items: Held,
    capacity: usize,
    /// Messages taken out of any queue (read, or gone with their queue).
    taken: Rc<Cell<u64>>,
}

impl Sink for BoundedSink {
    fn push_many(&mut self, messages: impl Iterator<Item = RawMessage>) -> usize {
        let mut items = self.items.borrow_mut();
        let mut dropped = 0;
        for m in messages {
            if items.len() >= self.capacity {
                items.pop_front();
                dropped += 1;
            }
            items.push_back(m);
        }
        dropped
    }

    /// A batch kept whole is taken apart one message at a time, as a
    /// node's queue does: the same messages, sequence numbers and leads as
    /// all at once.
    fn push_batch(&mut self, batch: &RawBatch) -> usize {
        let mut rest = batch.clone();
        let popped: Vec<RawMessage> = std::iter::from_fn(|| rest.pop()).collect();
        assert!(rest.is_empty());
        assert_eq!(popped.len(), batch.len());
        for (one, all) in popped.iter().zip(batch.messages()) {
            assert_eq!(
                (one.seq, one.lead, &one.payload, one.source),
                (all.seq, all.lead, &all.payload, all.source)
            );
        }
        self.push_many(popped.into_iter())
    }
}

impl Drop for BoundedSink {
    fn drop(&mut self) {
        let held = self.items.borrow().len() as u64;
        self.taken.set(self.taken.get() + held);
    }
}

/// The node's receive path, [`Receiver`], driven by operations read from
/// the input: datagrams of every kind (well-formed packets, batches,
/// fragments, sealed datagrams with the right key or another, gossip, and
/// raw bytes), fragments received into lent buffers, time steps,
/// subscribing, unsubscribing and reading. After every operation: no
/// panic, reassembly within its budget, and the counts add up (every
/// datagram has one fate, every offer to a subscriber one outcome, every
/// drop one reason, and what was queued is what the queues hold or gave).
pub fn receiver(data: &[u8]) {
    let mut input = Input::new(data);
    let limits = ReassemblyLimits {
        per_source: 40_000,
        per_channel: 60_000,
        total: 80_000,
        timeout: Duration::from_millis(300),
    };
    let key = Key::from_bytes([5; 32]);
    let mut opener = Opener::new(Some(Duration::from_secs(30)));
    opener.add_key("s", &key).unwrap();
    let mode = input.u8();
    let (gossip, gossip_sealed) = (mode % 2 == 0, mode % 3 == 0);
    if gossip_sealed {
        opener.add_key("__pulicast_discovery", &key).unwrap();
    }
    let own = SocketAddr::from(([10, 0, 0, 9], 7000));
    let first: Receiver<BoundedSink> = Receiver::new(ReceiverConfig {
        limits,
        opener: Some(opener),
        gossip,
        gossip_sealed,
        own_ip: [10, 0, 0, 9].into(),
        own_ports: vec![7000],
    });
    // Two receivers, as a node has one per receive socket: the second a
    // sibling (the same keys, one shared reassembly, no gossip).
    let second = first.sibling();
    let mut rxs = [first, second];
    let channels: [Arc<str>; 4] = [
        "a".into(),
        "b/c".into(),
        "s/x".into(),
        wire::DISCOVERY_CHANNEL.into(),
    ];
    let mut sealers: Vec<Sealer> = channels
        .iter()
        .map(|c| Sealer::new(&key, c, false))
        .collect();
    let mut stranger = Sealer::new(&Key::from_bytes([9; 32]), "s/x", false);
    let taken = Rc::new(Cell::new(0u64));
    // The receiver that handles each channel (its group's socket), and
    // the subscriptions: (channel index, receiver, id, queue).
    let mut home: [usize; 4] = [0, 1, 0, 0];
    let mut queues: Vec<(usize, usize, u64, Held)> = Vec::new();
    let mut next_id = 0u64;
    let start = Instant::now();
    let mut now = start;
    let unix_ms = |now: Instant| 1_700_000_000_000 + now.duration_since(start).as_millis() as u64;
    let mut loans: [Option<Loan>; 2] = [None, None];
    let mut batch = BatchBuilder::new();
    let mut gossip_drops = 0u64;
    let budget = |rxs: &[Receiver<BoundedSink>; 2]| {
        assert_eq!(rxs[0].reassembly_bytes(), rxs[1].reassembly_bytes());
        rxs[0].reassembly_bytes()
    };
    while !input.is_empty() {
        let c = usize::from(input.u8()) % channels.len();
        let channel = &channels[c];
        let source = match input.u8() % 4 {
            3 => own,
            n => SocketAddr::from(([10, 0, 0, n + 1], 5000)),
        };
        let seq = u32::from(input.u8() % 8);
        let op = input.u8() % 13;
        // Mostly the socket of the channel's group; any group, now and
        // then, as anyone may send there.
        let r = match input.u8() % 4 {
            0 => 1 - home[c],
            _ => home[c],
        };
        let mut datagram = Vec::new();
        match op {
            // A packet; the payload may start with a typed subscriber's
            // fingerprint or not.
            0 => Packet {
                channel,
                seq,
                payload: input.bytes_up_to(39),
            }
            .encode(&mut datagram),
            // A batch of a few entries.
            1 => {
                batch.start(channel, seq);
                for _ in 0..1 + input.u8() % 5 {
                    batch.push(input.bytes_up_to(19));
                }
                datagram.extend_from_slice(batch.finish());
            }
            // A fragment of a message whose shape is a function of its seq.
            2 => {
                let total = 3000 + seq * 9001;
                let count = 2 + (seq as u16 % 5);
                let index = u16::from(input.u8()) % count;
                let size = Fragment::chunk_of_len(total, index, count);
                let offset = usize::from(index) * Fragment::chunk_size(total, count);
                Fragment::encode_header(channel, seq, total, index, count, &mut datagram);
                datagram.extend((offset..offset + size).map(|o| pattern(seq, o)));
            }
            // Gossip (whatever its content).
            3 => {
                datagram.extend_from_slice(&pulicast_discovery::wire::MAGIC);
                datagram.extend_from_slice(input.bytes_up_to(255));
            }
            // Raw bytes, of any kind or none.
            4 => datagram.extend_from_slice(input.bytes_up_to(1999)),
            // Time passes; the timer fires when due.
            5 => {
                now += Duration::from_millis(u64::from(input.u8()) * 4);
                // The first receiver expires the shared reassembly.
                if rxs[0].poll_timeout().is_some_and(|due| now > due) {
                    rxs[0].handle_timeout(now);
                }
            }
            // Subscribe: plain or ordered, typed or not, a small queue.
            6 => {
                let expected = (input.u8() % 2 == 0).then_some(Expected {
                    fingerprint: Fingerprint([1; 8]),
                    type_name: "T",
                });
                let items = Rc::new(RefCell::new(VecDeque::new()));
                let sink = BoundedSink {
                    items: Rc::clone(&items),
                    capacity: 1 + usize::from(input.u8() % 8),
                    taken: Rc::clone(&taken),
                };
                let sub = Subscriber {
                    id: next_id,
                    ordered: input.u8() % 2 == 0,
                    expected,
                    sink,
                };
                let sealed = c == 2;
                let _first = rxs[home[c]].subscribe(channel, sealed, sub);
                queues.push((c, home[c], next_id, items));
                next_id += 1;
            }
            // Unsubscribe one.
            7 => {
                if !queues.is_empty() {
                    let (c, at, id, _) = queues.remove(usize::from(input.u8()) % queues.len());
                    let removed = rxs[at].unsubscribe(&channels[c], id).expect("subscribed");
                    assert_eq!(removed.last, !rxs[at].subscribes(&channels[c]));
                }
            }
            // Read a queue.
            8 => {
                if !queues.is_empty() {
                    let (_, _, _, items) = &queues[usize::from(input.u8()) % queues.len()];
                    let n = items.borrow().len() as u64;
                    items.borrow_mut().clear();
                    taken.set(taken.get() + n);
                }
            }
            // A packet sealed with the channel's key, or by a stranger.
            9 | 10 => {
                Packet {
                    channel,
                    seq,
                    payload: input.bytes_up_to(39),
                }
                .encode(&mut datagram);
                let sealer = match op {
                    9 => &mut sealers[c],
                    _ => &mut stranger,
                };
                datagram = sealer.seal(&datagram, unix_ms(now)).to_vec();
            }
            // The channel's group moves to the other socket (only while
            // nobody subscribes it: its group was left), its replay
            // windows with it.
            12 => {
                if c != 3 && !queues.iter().any(|(q, ..)| *q == c) {
                    let windows = rxs[home[c]].take_windows(channel);
                    home[c] = 1 - home[c];
                    rxs[home[c]].put_windows(channel, windows);
                }
            }
            // Gossip received by unicast (opened by the receiver of the
            // discovery group's socket).
            _ => {
                let mut gossip = pulicast_discovery::wire::MAGIC.to_vec();
                gossip.extend_from_slice(input.bytes_up_to(255));
                if input.u8() % 2 == 0 {
                    gossip = sealers[3].seal(&gossip, unix_ms(now)).to_vec();
                }
                let before = rxs[0].counts().clone();
                if let Some(range) = rxs[0].open_gossip(unix_ms(now), source, &mut gossip) {
                    assert!(gossip[range].starts_with(&pulicast_discovery::wire::MAGIC));
                }
                let after = rxs[0].counts();
                assert_eq!(after.datagrams, before.datagrams);
                let added = after.dropped.iter().sum::<u64>() - before.dropped.iter().sum::<u64>();
                assert!(added <= 1);
                gossip_drops += added;
            }
        }
        if matches!(op, 0..=4 | 9 | 10) {
            // Into the lent buffer if there is one, as the receive loop
            // of that socket does.
            let rx = &mut rxs[r];
            loans[r] = match loans[r].take() {
                Some(mut l) => match l.prepare() {
                    Some(landing) => {
                        l.data.extend_from_slice(&datagram);
                        let mut other = BytesMut::new();
                        match l.land(landing, Some((datagram.len(), source)), &mut other) {
                            Landed::Awaited => rx.repay(l, true),
                            Landed::Other { source, .. } => {
                                let _none = rx.repay(l, false);
                                rx.handle_datagram(now, unix_ms(now), source, &mut other)
                            }
                            Landed::Nothing => panic!("a datagram was received"),
                        }
                    }
                    None => {
                        let _none = rx.repay(l, false);
                        let mut buf = BytesMut::from(&datagram[..]);
                        rx.handle_datagram(now, unix_ms(now), source, &mut buf)
                    }
                },
                None => {
                    let mut buf = BytesMut::from(&datagram[..]);
                    rx.handle_datagram(now, unix_ms(now), source, &mut buf)
                }
            };
        }
        let mut gossips = 0;
        for (i, rx) in rxs.iter_mut().enumerate() {
            while let Some((_, g)) = rx.poll_gossip() {
                assert!(g.starts_with(&pulicast_discovery::wire::MAGIC));
                assert!(gossip && i == 0, "gossip only where discovery's group is");
                gossips += 1;
            }
            let mut details = 0;
            while let Some(d) = rx.poll_drop() {
                assert!(rx.counts().dropped(d.reason) > 0);
                details += 1;
            }
            assert!(details <= MAX_DROP_DETAILS);
        }
        assert!(gossips <= 1, "one datagram, one gossip");
        // Budgets: one reassembly, shared.
        assert!(budget(&rxs) <= limits.total);
        for (.., items) in &queues {
            assert!(items.borrow().len() <= 8);
        }
        // The counts add up, in each receiver and summed.
        let mut counts = pulicast_proto::receiver::ReceiveCounts::default();
        for rx in &rxs {
            let own = rx.counts();
            assert_eq!(own.fates.iter().sum::<u64>(), own.datagrams);
            assert_eq!(
                own.offered,
                own.queued + own.out_of_order_skipped + own.refused + own.overflowed
            );
            counts.add(own);
        }
        let held: u64 = queues.iter().map(|(.., q)| q.borrow().len() as u64).sum();
        assert_eq!(counts.queued, held + taken.get());
        // Every drop is a dropped datagram, a message a subscriber or
        // reassembly dropped, or unicast gossip refused.
        let message_level = counts.refused
            + counts.overflowed
            + counts.dropped(wire::DropReason::IncompleteMessage);
        let all: u64 = counts.dropped.iter().sum();
        assert_eq!(
            all,
            counts.fate(Fate::Dropped) + message_level + gossip_drops
        );
    }
    for (rx, loan) in rxs.iter_mut().zip(&mut loans) {
        if let Some(l) = loan.take() {
            let _none = rx.repay(l, false);
        }
    }
    rxs[0].handle_timeout(now + Duration::from_secs(60));
    assert_eq!(budget(&rxs), 0, "nothing held after every deadline");
}

/// One decode for every kind ([`wire::Datagram::decode`]): never panics;
/// what decodes has the kind its magic says, names the channel its header
/// names, and stays inside the datagram (a packet re-encodes to the input).
pub fn datagram(data: &[u8]) {
    let Ok(view) = wire::Datagram::decode(data) else {
        return;
    };
    let kind = wire::Kind::of(data);
    assert_eq!(view.kind(), kind);
    if let Some(channel) = view.channel() {
        assert_eq!(data.get(4).map(|&n| usize::from(n)), Some(channel.len()));
        assert_eq!(data.get(5..5 + channel.len()), Some(channel.as_bytes()));
    }
    match view {
        wire::Datagram::Packet(p) => {
            let mut again = Vec::new();
            p.encode(&mut again);
            assert_eq!(again, data);
        }
        wire::Datagram::Batch(b) => {
            let n = b
                .entries(data)
                .inspect(|(_, r)| assert!(r.end <= data.len()))
                .count();
            assert_eq!(n, usize::from(b.count));
        }
        wire::Datagram::Fragment(f) => {
            let h = f.header();
            assert!(h.index < h.count);
            assert!(f.chunk.len() <= h.total as usize);
        }
        wire::Datagram::Sealed(s) => {
            assert!(s.inner.start <= s.inner.end);
            assert_eq!(s.inner.end + wire::sealed::TAG_LEN, data.len());
        }
        wire::Datagram::Discovery(d) => assert_eq!(d, data),
    }
}

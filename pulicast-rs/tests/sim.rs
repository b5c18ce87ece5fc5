//! The data path in a deterministic simulated network: what the kernel can't
//! inject on one machine (reordering, duplication, 50 ms of delay with
//! jitter), on top of loss, applied by a seeded RNG to the sans-IO core.
//! Three publishers send numbered messages, some small (packets, some of
//! them in batches) and some large (fragments), plain or sealed; the
//! receiver side is the node's own [`Receiver`], driven the way the receive
//! loop drives it (lent buffers included): dispatch, lead tracking, ordered
//! filtering, batch decoding, reassembly and opening. Virtual time, so it
//! is fast and repeatable.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::cell::RefCell;
use std::collections::{BTreeMap, BinaryHeap, HashMap, HashSet};
use std::net::SocketAddr;
use std::rc::Rc;
use std::sync::Arc;
use std::time::{Duration, Instant};

use bytes::BytesMut;
use pulicast::DropReason;
use pulicast_proto::fragment::{Fragment, Landed, Loan, ReassemblyLimits};
use pulicast_proto::receiver::{Fate, RawMessage, ReceiverConfig, Sink, Subscriber};
use pulicast_proto::secure::{Key, Opener, Sealer};
use pulicast_proto::wire::batch::BatchBuilder;
use pulicast_proto::wire::Packet;
use pulicast_proto::{Lead, Receiver};

/// A small deterministic RNG (SplitMix64), so the test needs no crate.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn chance(&mut self, p: f64) -> bool {
        ((self.next() >> 11) as f64 / (1u64 << 53) as f64) < p
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

struct Faults {
    loss: f64,
    duplicate: f64,
    delay: Duration,
    jitter: Duration,
}

/// Datagrams in flight, delivered in order of arrival time.
#[derive(PartialEq, Eq, PartialOrd, Ord)]
struct InFlight {
    at: std::cmp::Reverse<(Duration, u64)>,
    from: u16,
    datagram: Vec<u8>,
}

struct Network {
    rng: Rng,
    faults: Faults,
    queue: BinaryHeap<InFlight>,
    sent: u64,
}

impl Network {
    fn send(&mut self, now: Duration, from: u16, datagram: Vec<u8>) {
        if self.rng.chance(self.faults.loss) {
            return;
        }
        let copies = if self.rng.chance(self.faults.duplicate) {
            2
        } else {
            1
        };
        for _ in 0..copies {
            let jitter = self.rng.below(self.faults.jitter.as_micros() as u64 + 1);
            let at = now + self.faults.delay + Duration::from_micros(jitter);
            self.sent += 1;
            self.queue.push(InFlight {
                at: std::cmp::Reverse((at, self.sent)),
                from,
                datagram: datagram.clone(),
            });
        }
    }

    fn due(&mut self, now: Duration) -> Option<(u16, Vec<u8>)> {
        if self.queue.peek()?.at.0 .0 > now {
            return None;
        }
        self.queue.pop().map(|f| (f.from, f.datagram))
    }
}

/// What one (plain or ordered) subscription got from one source.
#[derive(Default)]
struct Got {
    seqs: Vec<u32>,
    leads: Vec<Lead>,
}

/// A subscriber's queue as the test reads it: everything the receiver
/// queued, shared with the test.
#[derive(Clone, Default)]
struct Recorder(Rc<RefCell<Vec<RawMessage>>>);

impl Sink for Recorder {
    fn push_many(&mut self, messages: impl Iterator<Item = RawMessage>) -> usize {
        self.0.borrow_mut().extend(messages);
        0
    }
}

/// What a recorder got, per publisher (known by its address).
fn per_publisher(recorder: &Recorder, publishers: u16) -> HashMap<u16, Got> {
    let mut got: HashMap<u16, Got> = HashMap::new();
    for m in recorder.0.borrow().iter() {
        let SocketAddr::V4(a) = m.source else {
            panic!("not a publisher: {}", m.source)
        };
        let p = u16::from(a.ip().octets()[3]);
        assert!(p < publishers);
        assert_eq!(&m.payload[..], &content(p, m.seq)[..], "{} of {p}", m.seq);
        let g = got.entry(p).or_default();
        g.seqs.push(m.seq);
        g.leads.push(m.lead);
    }
    got
}

/// The content of message `seq` of publisher `p`: its size says whether it
/// is fragmented, its bytes are checkable.
fn content(p: u16, seq: u32) -> Vec<u8> {
    let len = if seq % 10 == 9 {
        150_000 + 997 * (seq as usize % 13)
    } else {
        24
    };
    (0..len)
        .map(|i| (i as u32).wrapping_mul(7) as u8 ^ (seq as u8) ^ (p as u8))
        .collect()
}

fn source_of(p: u16) -> SocketAddr {
    SocketAddr::from(([10, 0, 0, p as u8], 5000))
}

/// Runs the network through a node's receiver. With `sealed`, the channel
/// has a key: publishers seal every datagram, and a stranger sends
/// unsealed copies of everything, which must all be refused.
fn simulate(seed: u64, faults: Faults, sealed: bool) {
    let channel: Arc<str> = "sim/data".into();
    let mut net = Network {
        rng: Rng(seed),
        faults,
        queue: BinaryHeap::new(),
        sent: 0,
    };
    let publishers = 3u16;
    let stranger = publishers;
    let per_publisher_count = 600u32;
    let epoch = Instant::now();
    let limits = ReassemblyLimits {
        per_source: 2 << 20,
        per_channel: 4 << 20,
        total: 4 << 20,
        timeout: Duration::from_millis(300),
    };
    let key = Key::from_bytes([7; 32]);
    let mut opener = Opener::new(None);
    opener.add_key("sim", &key).unwrap();
    let mut rx: Receiver<Recorder> = Receiver::new(ReceiverConfig {
        limits,
        opener: sealed.then_some(opener),
        ..ReceiverConfig::default()
    });
    let (plain, ordered) = (Recorder::default(), Recorder::default());
    for (id, (ordered, sink)) in [(false, plain.clone()), (true, ordered.clone())]
        .into_iter()
        .enumerate()
    {
        let sub = Subscriber {
            id: id as u64,
            ordered,
            expected: None,
            sink,
        };
        let _first = rx.subscribe(&channel, sealed, sub);
    }
    let mut sealers: Vec<Sealer> = (0..publishers)
        .map(|_| Sealer::new(&key, &channel, seed % 2 == 0))
        .collect();
    let mut next = vec![0u32; usize::from(publishers)];
    let mut batches: Vec<BatchBuilder> = (0..publishers).map(|_| BatchBuilder::new()).collect();
    let mut now = Duration::ZERO;
    let step = Duration::from_millis(1);
    let mut peak_bytes = 0;
    let mut loan: Option<Loan> = None;
    let mut received_in_place = 0;
    let mut stranger_sent = 0u64;

    // Publishers send for 6 virtual seconds; the network drains after.
    while now < Duration::from_secs(8) {
        let mut outgoing = Vec::new();
        for p in 0..publishers {
            let seq = next[usize::from(p)];
            if seq >= per_publisher_count || now >= Duration::from_secs(6) || net.rng.below(10) >= 1
            {
                continue;
            }
            next[usize::from(p)] += 1;
            let message = content(p, seq);
            if message.len() > 60_000 {
                let reserve = if sealed {
                    Sealer::overhead_for(&channel)
                } else {
                    0
                };
                let count = Fragment::count_within(&channel, message.len(), reserve) as u16;
                for index in 0..count {
                    let mut d = Vec::new();
                    Fragment::encode(&channel, seq, &message, index, count, &mut d);
                    outgoing.push((p, d));
                }
            } else if seq % 4 == 0 {
                // A batch of this message and the next few small ones.
                let b = &mut batches[usize::from(p)];
                b.start(&channel, seq);
                b.push(&message);
                while next[usize::from(p)] % 10 != 9
                    && b.len() < 3
                    && next[usize::from(p)] < per_publisher_count
                {
                    let s = next[usize::from(p)];
                    next[usize::from(p)] += 1;
                    b.push(&content(p, s));
                }
                outgoing.push((p, b.finish().to_vec()));
            } else {
                let mut d = Vec::new();
                Packet {
                    channel: &channel,
                    seq,
                    payload: &message,
                }
                .encode(&mut d);
                outgoing.push((p, d));
            }
        }
        for (p, datagram) in outgoing {
            if sealed {
                // Anyone on the link can send what the publishers send,
                // without the key.
                net.send(now, stranger, datagram.clone());
                stranger_sent += 1;
                let unix_ms = now.as_millis() as u64;
                let d = sealers[usize::from(p)].seal(&datagram, unix_ms).to_vec();
                net.send(now, p, d);
            } else {
                net.send(now, p, datagram);
            }
        }
        let instant = epoch + now;
        let unix_ms = now.as_millis() as u64;
        while let Some((from, datagram)) = net.due(now) {
            let source = source_of(from);
            // As the receive loop does: into the lent buffer if there is
            // one, the ordinary way otherwise.
            match loan.take() {
                Some(mut l) => {
                    let Some(landing) = l.prepare() else {
                        let _none = rx.repay(l, false);
                        loan = handle(&mut rx, instant, unix_ms, source, &datagram);
                        continue;
                    };
                    l.data.extend_from_slice(&datagram);
                    let mut other = BytesMut::new();
                    match l.land(landing, Some((datagram.len(), source)), &mut other) {
                        Landed::Awaited => {
                            received_in_place += 1;
                            loan = rx.repay(l, true);
                        }
                        Landed::Other { source, .. } => {
                            let _none = rx.repay(l, false);
                            loan = rx.handle_datagram(instant, unix_ms, source, &mut other);
                        }
                        Landed::Nothing => unreachable!("a datagram was received"),
                    }
                }
                None => loan = handle(&mut rx, instant, unix_ms, source, &datagram),
            }
            assert!(rx.poll_gossip().is_none());
            while rx.poll_drop().is_some() {}
        }
        // As in a node, the timer may fire while a buffer is lent out.
        if rx.poll_timeout().is_some_and(|due| instant > due) {
            rx.handle_timeout(instant);
        }
        peak_bytes = peak_bytes.max(rx.reassembly_bytes());
        assert!(rx.reassembly_bytes() <= limits.total);
        now += step;
    }
    if let Some(l) = loan.take() {
        let _none = rx.repay(l, false);
    }
    rx.handle_timeout(epoch + now + Duration::from_secs(1));
    assert_eq!(rx.reassembly_bytes(), 0, "nothing held after the timeout");

    // Every datagram read has one fate, and every offer one outcome.
    let counts = rx.counts().clone();
    assert_eq!(counts.fates.iter().sum::<u64>(), counts.datagrams);
    assert_eq!(
        counts.offered,
        counts.queued + counts.out_of_order_skipped + counts.refused + counts.overflowed
    );
    assert_eq!(counts.fate(Fate::NotOurs), 0);
    let unauthenticated = counts.dropped(DropReason::Unauthenticated);
    match sealed {
        // Only the stranger's copies, and all of those that arrived.
        true => assert!(unauthenticated > 0 && unauthenticated <= stranger_sent * 2),
        false => assert_eq!(unauthenticated, 0),
    }
    // The network's duplicates of sealed datagrams are refused as replays.
    let replayed = counts.dropped(DropReason::Replayed);
    assert_eq!(replayed > 0, sealed);
    assert_eq!(counts.fate(Fate::Dropped), unauthenticated + replayed);
    assert_eq!(counts.offered, 2 * counts.messages);

    let got_plain = per_publisher(&plain, publishers);
    let got_ordered = per_publisher(&ordered, publishers);
    assert_eq!(
        counts.queued,
        (plain.0.borrow().len() + ordered.0.borrow().len()) as u64
    );
    for p in 0..publishers {
        let sent = next[usize::from(p)];
        let got = &got_plain[&p];
        let ord = &got_ordered[&p];
        // Ordered: strictly increasing, and received + counted gaps span
        // exactly from the first to the last message received.
        assert!(
            ord.seqs.windows(2).all(|w| w[0] < w[1]),
            "ordered out of order"
        );
        assert_eq!(ord.leads[0], 1);
        let gaps: i64 = ord.leads[1..].iter().map(|l| l - 1).sum();
        let span = i64::from(ord.seqs[ord.seqs.len() - 1] - ord.seqs[0]) + 1;
        assert_eq!(
            ord.seqs.len() as i64 + gaps,
            span,
            "publisher {p}: losses counted exactly"
        );
        // Leads in the plain stream are what they say: each message's lead is
        // its distance from the highest sequence number seen before it.
        let mut highest: Option<u32> = None;
        for (&seq, &lead) in got.seqs.iter().zip(&got.leads) {
            let expected = highest.map_or(1, |h| i64::from(seq) - i64::from(h));
            assert_eq!(lead, expected, "publisher {p}, seq {seq}");
            highest = Some(highest.map_or(seq, |h| h.max(seq)));
        }
        // What ordered skipped is exactly what came late or twice.
        let late = got.leads.iter().filter(|&&l| l < 1).count();
        assert_eq!(got.seqs.len() - late, ord.seqs.len());
        // Every message that arrived was new to ordered at most once.
        let unique: HashSet<u32> = ord.seqs.iter().copied().collect();
        assert_eq!(unique.len(), ord.seqs.len());
        let arrived: BTreeMap<u32, usize> = got.seqs.iter().fold(BTreeMap::new(), |mut m, s| {
            *m.entry(*s).or_default() += 1;
            m
        });
        eprintln!(
            "seed {seed} sealed {sealed} publisher {p}: {sent} sent, {} distinct arrived ({} with duplicates), {} in order, {late} late or twice, {gaps} counted missing; reassembly peak {peak_bytes} B, {} lost, {received_in_place} fragments received in place",
            arrived.len(),
            got.seqs.len(),
            ord.seqs.len(),
            counts.dropped(DropReason::IncompleteMessage),
        );
    }
    if !sealed {
        assert!(received_in_place > 0, "the in-place path was taken");
    }
}

/// Hands a datagram to the receiver the ordinary way.
fn handle(
    rx: &mut Receiver<Recorder>,
    now: Instant,
    unix_ms: u64,
    source: SocketAddr,
    datagram: &[u8],
) -> Option<Loan> {
    let mut buf = BytesMut::with_capacity(datagram.len());
    buf.extend_from_slice(datagram);
    rx.handle_datagram(now, unix_ms, source, &mut buf)
}

/// 10 % loss, 5 % duplicates, 50 ms of delay with 20 ms of jitter.
const MODERATE: Faults = Faults {
    loss: 0.1,
    duplicate: 0.05,
    delay: Duration::from_millis(50),
    jitter: Duration::from_millis(20),
};

#[test]
fn loss_reordering_duplication_and_delay_keep_leads_exact() {
    for seed in 1..=5 {
        simulate(seed, MODERATE, false);
    }
}

#[test]
fn sealed_channels_take_only_sealed_datagrams_through_the_same_faults() {
    for seed in 1..=2 {
        simulate(seed, MODERATE, true);
    }
}

#[test]
fn heavy_loss_and_jitter() {
    simulate(
        42,
        Faults {
            loss: 0.3,
            duplicate: 0.2,
            delay: Duration::from_millis(50),
            jitter: Duration::from_millis(50),
        },
        false,
    );
}

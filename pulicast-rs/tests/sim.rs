//! The data path in a deterministic simulated network: what the kernel can't
//! inject on one machine (reordering, duplication, 50 ms of delay with
//! jitter), on top of loss, applied by a seeded RNG to the sans-IO core.
//! Three publishers send numbered messages, some small (packets, some of
//! them in batches) and some large (fragments); the receiver side is the
//! same code a node runs: lead tracking, ordered filtering, batch decoding
//! and reassembly. Virtual time, so it is fast and repeatable.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::collections::{BTreeMap, BinaryHeap, HashMap, HashSet};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use pulicast::proto::batch::{Batch, BatchBuilder};
use pulicast::proto::fragment::{Fragment, Limits, Outcome, Reassembler};
use pulicast::proto::{Lead, LeadTracker};
use pulicast::wire::Packet;

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

/// A plain and an ordered subscription, per publisher.
#[derive(Default)]
struct Subscriptions {
    plain: HashMap<u16, Got>,
    ordered: HashMap<u16, Got>,
}

impl Subscriptions {
    /// Delivers as a node does: every message to the plain subscription,
    /// only those with lead >= 1 to the ordered one.
    fn record(&mut self, from: u16, seq: u32, lead: Lead) {
        let p = self.plain.entry(from).or_default();
        p.seqs.push(seq);
        p.leads.push(lead);
        if lead >= 1 {
            let o = self.ordered.entry(from).or_default();
            o.seqs.push(seq);
            o.leads.push(lead);
        }
    }
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

fn simulate(seed: u64, faults: Faults) {
    let channel: Arc<str> = "sim/data".into();
    let mut net = Network {
        rng: Rng(seed),
        faults,
        queue: BinaryHeap::new(),
        sent: 0,
    };
    let publishers = 3u16;
    let per_publisher = 600u32;
    let epoch = Instant::now();
    let limits = Limits {
        per_source: 2 << 20,
        per_channel: 4 << 20,
        total: 4 << 20,
        timeout: Duration::from_millis(300),
    };
    let mut leads = LeadTracker::new(16);
    let mut reassembler = Reassembler::new(limits);
    let mut subs = Subscriptions::default();
    let mut next = vec![0u32; usize::from(publishers)];
    let mut batches: Vec<BatchBuilder> = (0..publishers).map(|_| BatchBuilder::new()).collect();
    let mut now = Duration::ZERO;
    let step = Duration::from_millis(1);
    let mut peak_bytes = 0;

    // Publishers send for 6 virtual seconds; the network drains after.
    while now < Duration::from_secs(8) {
        for p in 0..publishers {
            let seq = next[usize::from(p)];
            if seq >= per_publisher || now >= Duration::from_secs(6) || net.rng.below(10) >= 1 {
                continue;
            }
            next[usize::from(p)] += 1;
            let message = content(p, seq);
            if message.len() > 60_000 {
                let count = Fragment::count_for(&channel, message.len()) as u16;
                for index in 0..count {
                    let mut d = Vec::new();
                    Fragment::encode(&channel, seq, &message, index, count, &mut d);
                    net.send(now, p, d);
                }
            } else if seq % 4 == 0 {
                // A batch of this message and the next few small ones.
                let b = &mut batches[usize::from(p)];
                b.start(&channel, seq);
                b.push(&message);
                while next[usize::from(p)] % 10 != 9
                    && b.len() < 3
                    && next[usize::from(p)] < per_publisher
                {
                    let s = next[usize::from(p)];
                    next[usize::from(p)] += 1;
                    b.push(&content(p, s));
                }
                net.send(now, p, b.finish().to_vec());
            } else {
                let mut d = Vec::new();
                Packet {
                    channel: &channel,
                    seq,
                    payload: &message,
                }
                .encode(&mut d);
                net.send(now, p, d);
            }
        }
        while let Some((from, datagram)) = net.due(now) {
            let source = SocketAddr::from(([10, 0, 0, from as u8], 5000));
            let instant = epoch + now;
            if Fragment::is_fragment(&datagram) {
                let f = Fragment::decode(&datagram).unwrap();
                if let Outcome::Complete { seq, message } =
                    reassembler.push(instant, &channel, source, f.header(), f.chunk)
                {
                    assert_eq!(
                        &message[..],
                        &content(from, seq)[..],
                        "{seq} of {from} corrupted"
                    );
                    subs.record(from, seq, leads.observe(source, seq));
                }
            } else if Batch::is_batch(&datagram) {
                let batch = Batch::decode(&datagram).unwrap();
                let first = leads.observe_run(source, batch.first_seq, batch.count);
                // Deliver with the run's leads, as a node does.
                for (i, (seq, range)) in batch.entries(&datagram).enumerate() {
                    let payload = &datagram[range];
                    assert_eq!(payload, &content(from, seq)[..]);
                    subs.record(from, seq, LeadTracker::lead_in_run(first, i));
                }
            } else {
                let packet = Packet::decode(&datagram).unwrap();
                assert_eq!(packet.payload, &content(from, packet.seq)[..]);
                subs.record(from, packet.seq, leads.observe(source, packet.seq));
            }
        }
        reassembler.expire(epoch + now);
        peak_bytes = peak_bytes.max(reassembler.bytes());
        assert!(reassembler.bytes() <= limits.total);
        now += step;
    }
    reassembler.expire(epoch + now + Duration::from_secs(1));
    assert_eq!(reassembler.bytes(), 0, "nothing held after the timeout");

    for p in 0..publishers {
        let sent = next[usize::from(p)];
        let got = &subs.plain[&p];
        let ord = &subs.ordered[&p];
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
            "seed {seed} publisher {p}: {sent} sent, {} distinct arrived ({} with duplicates), {} in order, {late} late or twice, {gaps} counted missing; reassembly peak {peak_bytes} B, {} lost",
            arrived.len(),
            got.seqs.len(),
            ord.seqs.len(),
            reassembler.lost(),
        );
    }
}

#[test]
fn loss_reordering_duplication_and_delay_keep_leads_exact() {
    for seed in 1..=5 {
        simulate(
            seed,
            Faults {
                loss: 0.1,
                duplicate: 0.05,
                delay: Duration::from_millis(50),
                jitter: Duration::from_millis(20),
            },
        );
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
    );
}

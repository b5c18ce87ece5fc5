//! Deterministic simulation: a fleet of gossip state machines over a fake
//! network with a seeded RNG, virtual time, loss, delay, reordering,
//! duplication, crashes and hosts whose multicast is blocked.

#![allow(clippy::unwrap_used)] // tests: a panic is the failure report

use std::cmp::Reverse;
use std::collections::{BinaryHeap, HashSet};
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use pulicast_discovery::gossip::{Destination, Event, Gossip, GossipConfig, Via};
use pulicast_discovery::wire::{
    self, ChannelInfo, Digest, FullPart, Leave, MemberInfo, MemberKey, MemberState, Message, Update,
};

const PERIOD: Duration = Duration::from_millis(100);

fn ms(n: u64) -> Duration {
    Duration::from_millis(n)
}

/// Network behaviour, applied per datagram per receiver.
#[derive(Clone, Default)]
struct Faults {
    loss: f64,
    duplicate: f64,
    delay_min: Duration,
    delay_max: Duration,
}

struct Node {
    gossip: Gossip,
    addr: SocketAddr,
    events: Vec<(Duration, Event)>,
    crashed: bool,
    multicast_blocked: bool,
}

struct InFlight {
    at: Instant,
    seq: u64,
    to: usize,
    from: SocketAddr,
    via: Via,
    payload: Vec<u8>,
}

impl PartialEq for InFlight {
    fn eq(&self, other: &Self) -> bool {
        (self.at, self.seq) == (other.at, other.seq)
    }
}
impl Eq for InFlight {}
impl PartialOrd for InFlight {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for InFlight {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        (self.at, self.seq).cmp(&(other.at, other.seq))
    }
}

struct Sim {
    start: Instant,
    now: Instant,
    nodes: Vec<Node>,
    inflight: BinaryHeap<Reverse<InFlight>>,
    faults: Faults,
    rng: u64,
    seq: u64,
    delivered: u64,
    lost: u64,
}

fn info(i: usize, channels: Vec<ChannelInfo>) -> MemberInfo {
    let mut session = [0u8; 16];
    session[..8].copy_from_slice(&(1000 + i as i64).to_be_bytes());
    session[8] = i as u8;
    MemberInfo {
        session,
        name: format!("node{i}"),
        namespace: format!("rover{i}"),
        host: "sim".into(),
        pid: i as u32,
        start_time_ms: 0,
        data_port: 9000,
        channels,
        config: String::new(),
        extensions: Vec::new(),
    }
}

fn channel(name: &str) -> ChannelInfo {
    ChannelInfo {
        name: name.into(),
        publishes: true,
        subscribes: false,
        period_ns: 0,
        message_type: None,
    }
}

/// A digest of a made-up member, the `k`th.
fn made_up_digest(k: i64) -> Vec<u8> {
    Message::Digest(Digest {
        sender: 0x0bad_0000 + k,
        incarnation: 0,
        version: 1,
        updates: vec![],
    })
    .encode()
}

fn key(i: usize) -> MemberKey {
    1000 + i as i64
}

impl Sim {
    fn new(n: usize, seed: u64) -> Self {
        Self::with_blocked(n, seed, &[])
    }

    /// A fleet where the nodes in `blocked` have no multicast from the start.
    fn with_blocked(n: usize, seed: u64, blocked: &[usize]) -> Self {
        let start = Instant::now();
        let mut sim = Sim {
            start,
            now: start,
            nodes: Vec::new(),
            inflight: BinaryHeap::new(),
            faults: Faults {
                delay_min: Duration::from_micros(100),
                delay_max: Duration::from_micros(300),
                ..Faults::default()
            },
            rng: seed.max(1),
            seq: 0,
            delivered: 0,
            lost: 0,
        };
        for i in 0..n {
            sim.add_node(
                i,
                vec![channel(&format!("rover{i}/pose"))],
                blocked.contains(&i),
            );
        }
        sim
    }

    fn add_node(&mut self, i: usize, channels: Vec<ChannelInfo>, multicast_blocked: bool) {
        let mut config = GossipConfig::for_heartbeat(PERIOD);
        config.seed = self.rng ^ i as u64;
        let addr = SocketAddr::from(([10, 0, 0, i as u8 + 1], 7000));
        let gossip = Gossip::new(self.now, info(i, channels), addr.port(), config);
        let node = Node {
            gossip,
            addr,
            events: Vec::new(),
            crashed: false,
            multicast_blocked,
        };
        if i < self.nodes.len() {
            self.nodes[i] = node;
        } else {
            self.nodes.push(node);
        }
        self.flush(i);
    }

    fn random(&mut self) -> f64 {
        let mut x = self.rng;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.rng = x;
        (x >> 11) as f64 / (1u64 << 53) as f64
    }

    fn delay(&mut self) -> Duration {
        let (lo, hi) = (self.faults.delay_min, self.faults.delay_max);
        lo + (hi - lo).mul_f64(self.random())
    }

    fn send(&mut self, from: usize, to: usize, via: Via, payload: &[u8]) {
        if self.nodes[to].crashed {
            return;
        }
        if self.random() < self.faults.loss {
            self.lost += 1;
            return;
        }
        let copies = if self.random() < self.faults.duplicate {
            2
        } else {
            1
        };
        for _ in 0..copies {
            let at = self.now + self.delay();
            self.seq += 1;
            let from = self.nodes[from].addr;
            self.inflight.push(Reverse(InFlight {
                at,
                seq: self.seq,
                to,
                from,
                via,
                payload: payload.to_vec(),
            }));
        }
    }

    /// Routes everything node `i` wants to send.
    fn flush(&mut self, i: usize) {
        while let Some(t) = self.nodes[i].gossip.poll_transmit() {
            if self.nodes[i].crashed {
                continue;
            }
            match t.destination {
                Destination::Multicast => {
                    if self.nodes[i].multicast_blocked {
                        continue;
                    }
                    for j in 0..self.nodes.len() {
                        if j != i && !self.nodes[j].multicast_blocked {
                            self.send(i, j, Via::Multicast, &t.payload);
                        }
                    }
                }
                Destination::Unicast(addr) => {
                    if let Some(j) = self.nodes.iter().position(|n| n.addr == addr) {
                        self.send(i, j, Via::Unicast, &t.payload);
                    }
                }
            }
        }
        let elapsed = self.now - self.start;
        while let Some(e) = self.nodes[i].gossip.poll_event() {
            self.nodes[i].events.push((elapsed, e));
        }
    }

    fn run_for(&mut self, d: Duration) {
        let end = self.now + d;
        loop {
            let next_packet = self.inflight.peek().map(|Reverse(p)| p.at);
            let next_timer = self
                .nodes
                .iter()
                .filter(|n| !n.crashed)
                .filter_map(|n| n.gossip.poll_timeout())
                .min();
            let Some(next) = [next_packet, next_timer].into_iter().flatten().min() else {
                break;
            };
            if next > end {
                break;
            }
            self.now = self.now.max(next);
            while self
                .inflight
                .peek()
                .is_some_and(|Reverse(p)| p.at <= self.now)
            {
                let Reverse(p) = self.inflight.pop().unwrap();
                if self.nodes[p.to].crashed {
                    continue;
                }
                self.delivered += 1;
                let _ = self.nodes[p.to]
                    .gossip
                    .handle_datagram(self.now, p.from, p.via, &p.payload);
                self.flush(p.to);
            }
            for i in 0..self.nodes.len() {
                if self.nodes[i].crashed {
                    continue;
                }
                if self.nodes[i]
                    .gossip
                    .poll_timeout()
                    .is_some_and(|t| t <= self.now)
                {
                    self.nodes[i].gossip.handle_timeout(self.now);
                    self.flush(i);
                }
            }
        }
        self.now = end;
    }

    fn view(&self, observer: usize, of: usize) -> Option<(MemberState, bool)> {
        self.nodes[observer]
            .gossip
            .member(key(of))
            .map(|m| (m.state(), m.info().is_some()))
    }

    fn converged(&self) -> bool {
        (0..self.nodes.len()).all(|i| {
            self.nodes[i].crashed
                || (0..self.nodes.len())
                    .filter(|j| *j != i && !self.nodes[*j].crashed)
                    .all(|j| self.view(i, j) == Some((MemberState::Alive, true)))
        })
    }

    /// Runs until `cond` holds, in 5 ms steps; returns the time it took.
    fn time_until(
        &mut self,
        limit: Duration,
        mut cond: impl FnMut(&Sim) -> bool,
    ) -> Option<Duration> {
        let start = self.now;
        while self.now - start <= limit {
            if cond(self) {
                return Some(self.now - start);
            }
            self.run_for(ms(5));
        }
        None
    }

    fn count(&self, i: usize, pred: impl Fn(&Event) -> bool) -> usize {
        self.nodes[i].events.iter().filter(|(_, e)| pred(e)).count()
    }

    /// Node `i` leaves gracefully and is gone.
    fn leave(&mut self, i: usize) {
        self.nodes[i].gossip.leave();
        self.flush(i);
        self.nodes[i].crashed = true;
    }

    /// How many times `observer` saw node `of` leave.
    fn leaves_seen(&self, observer: usize, of: usize) -> usize {
        let of = key(of);
        self.count(
            observer,
            |e| matches!(e, Event::Left { key, .. } if *key == of),
        )
    }

    fn failed_events(&self) -> usize {
        (0..self.nodes.len())
            .map(|i| {
                self.count(i, |e| {
                    matches!(e, Event::Failed { .. } | Event::Left { .. })
                })
            })
            .sum()
    }
}

#[test]
fn five_nodes_converge_quickly_and_stay_quiet() {
    let mut sim = Sim::new(5, 1);
    let took = sim.time_until(ms(1000), Sim::converged).expect("converges");
    assert!(took < ms(200), "took {took:?}");
    for i in 0..5 {
        assert_eq!(
            sim.count(i, |e| matches!(e, Event::Joined { .. })),
            4,
            "node {i}"
        );
        assert_eq!(
            sim.count(i, |e| matches!(e, Event::ChannelAppeared { .. })),
            4
        );
    }
    // Steady state: digests only, constant size, no pulls.
    let before: Vec<u64> = sim
        .nodes
        .iter()
        .map(|n| n.gossip.stats().bytes_out)
        .collect();
    let pulls: u64 = sim.nodes.iter().map(|n| n.gossip.stats().pulls_sent).sum();
    sim.run_for(Duration::from_secs(10));
    for (i, n) in sim.nodes.iter().enumerate() {
        let rate = (n.gossip.stats().bytes_out - before[i]) as f64 / 10.0;
        // ~30 digests/s of ~20 bytes.
        assert!(rate < 800.0, "node {i} sends {rate} B/s");
    }
    let pulls_after: u64 = sim.nodes.iter().map(|n| n.gossip.stats().pulls_sent).sum();
    assert_eq!(pulls, pulls_after, "no pulls in steady state");
    assert_eq!(sim.failed_events(), 0);
}

#[test]
fn graceful_leave_is_seen_at_once() {
    let mut sim = Sim::new(5, 2);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    sim.nodes[0].gossip.leave();
    sim.flush(0);
    let took = sim
        .time_until(ms(1000), |s| {
            (1..5).all(|i| s.view(i, 0).map(|v| v.0) == Some(MemberState::Left))
        })
        .expect("all see the leave");
    assert!(took < ms(10), "took {took:?}");
    for i in 1..5 {
        assert_eq!(
            sim.count(
                i,
                |e| matches!(e, Event::Left { key: k, .. } if *k == key(0))
            ),
            1
        );
        assert_eq!(sim.count(i, |e| matches!(e, Event::Failed { .. })), 0);
    }
}

#[test]
fn a_crash_is_seen_within_three_periods_and_a_digest() {
    let mut sim = Sim::new(5, 3);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    sim.run_for(ms(500));
    sim.nodes[2].crashed = true;
    let took = sim
        .time_until(ms(2000), |s| {
            [0, 1, 3, 4]
                .iter()
                .all(|&i| s.view(i, 2).map(|v| v.0) == Some(MemberState::Dead))
        })
        .expect("all see the crash");
    assert!(took <= PERIOD * 3 + ms(40), "took {took:?}");
    for i in [0, 1, 3, 4] {
        assert_eq!(
            sim.count(
                i,
                |e| matches!(e, Event::Failed { key: k, .. } if *k == key(2))
            ),
            1
        );
    }
}

#[test]
fn twenty_percent_loss_with_delay_reordering_and_duplication_kills_nobody() {
    // Ten different random worlds, 30 virtual seconds each.
    for seed in 0..10 {
        let mut sim = Sim::new(5, 100 + seed);
        sim.faults = Faults {
            loss: 0.2,
            duplicate: 0.05,
            delay_min: ms(1),
            delay_max: ms(30),
        };
        sim.time_until(ms(3000), Sim::converged)
            .expect("converges despite loss");
        sim.run_for(Duration::from_secs(30));
        assert_eq!(sim.failed_events(), 0, "false deaths with seed {seed}");
        assert!(sim.converged());
        let lost_share = sim.lost as f64 / (sim.lost + sim.delivered) as f64;
        assert!((0.15..0.25).contains(&lost_share), "{lost_share}");
    }
}

#[test]
fn fifty_ms_jitter_and_thirty_percent_loss_converge_and_spare_the_living() {
    let mut sim = Sim::new(6, 5);
    sim.faults = Faults {
        loss: 0.3,
        duplicate: 0.1,
        delay_min: ms(25),
        delay_max: ms(75),
    };
    sim.time_until(ms(5000), Sim::converged).expect("converges");
    sim.run_for(Duration::from_secs(10));
    assert!(sim.converged());
}

#[test]
fn a_host_without_multicast_learns_the_fleet_through_a_seed() {
    let mut sim = Sim::with_blocked(4, 6, &[3]);
    let seed = sim.nodes[0].addr;
    sim.nodes[3].gossip.add_seed(seed);
    sim.time_until(ms(3000), Sim::converged)
        .expect("everyone knows everyone");
    // It stays that way: members it never hears directly are kept alive by
    // the seed's member lists.
    sim.run_for(Duration::from_secs(10));
    assert!(sim.converged());
    assert_eq!(sim.failed_events(), 0);
    // A crash elsewhere reaches it through the seed.
    sim.nodes[1].crashed = true;
    let took = sim
        .time_until(ms(3000), |s| {
            s.view(3, 1).map(|v| v.0) == Some(MemberState::Dead)
        })
        .expect("the blind host sees the crash");
    assert!(took < PERIOD * 3 + ms(150), "took {took:?}");
}

#[test]
fn a_host_whose_multicast_breaks_later_stays_in_the_fleet_through_a_seed() {
    let mut sim = Sim::new(4, 14);
    let seed = sim.nodes[0].addr;
    sim.nodes[3].gossip.add_seed(seed);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    sim.nodes[3].multicast_blocked = true;
    sim.run_for(Duration::from_secs(10));
    for i in 0..4 {
        eprintln!(
            "{i}: {:?}",
            sim.nodes[i]
                .events
                .iter()
                .filter(|(_, e)| !matches!(e, Event::Joined { .. } | Event::ChannelAppeared { .. }))
                .collect::<Vec<_>>()
        );
        for j in 0..4 {
            eprintln!("  sees {j}: {:?}", sim.view(i, j));
        }
    }
    assert!(sim.converged(), "still everyone knows everyone");
    // Losing the direct path may cost a suspicion; the refutation through
    // the seed keeps it from becoming a death.
    assert_eq!(sim.failed_events(), 0);
}

#[test]
fn a_healed_partition_merges_again() {
    let mut sim = Sim::new(3, 15);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    // Node 2 is cut off long enough for everyone to declare everyone dead
    // and for the gossip about it to die down.
    sim.nodes[2].multicast_blocked = true;
    sim.run_for(Duration::from_secs(3));
    assert_eq!(sim.view(0, 2).map(|v| v.0), Some(MemberState::Dead));
    assert_eq!(sim.view(2, 0).map(|v| v.0), Some(MemberState::Dead));
    sim.nodes[2].multicast_blocked = false;
    let took = sim
        .time_until(ms(2000), Sim::converged)
        .expect("merges again");
    assert!(took < ms(500), "took {took:?}");
    sim.run_for(ms(500));
    for i in 0..3 {
        assert!(
            sim.count(i, |e| matches!(e, Event::Joined { .. })) >= 3,
            "rejoins are joins"
        );
    }
}

#[test]
fn suspicion_is_refuted_by_an_incarnation_bump() {
    let mut sim = Sim::new(4, 7);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    // Cut node 0 off for longer than `suspect_after`, shorter than `dead_after`.
    sim.faults.loss = 0.0;
    sim.nodes[0].multicast_blocked = true;
    sim.run_for(PERIOD * 2 + ms(50));
    sim.nodes[0].multicast_blocked = false;
    sim.run_for(ms(500));
    assert_eq!(sim.failed_events(), 0);
    for i in 1..4 {
        assert!(
            sim.count(
                i,
                |e| matches!(e, Event::Suspected { key: k, .. } if *k == key(0))
            ) >= 1
        );
        assert!(
            sim.count(
                i,
                |e| matches!(e, Event::Recovered { key: k, .. } if *k == key(0))
            ) >= 1
        );
    }
    assert!(sim.nodes[0].gossip.incarnation() >= 1, "node 0 refuted");
    assert!(sim.converged());
}

#[test]
fn channel_changes_spread_as_events() {
    let mut sim = Sim::new(3, 8);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let mut new = sim.nodes[1].gossip.info().clone();
    new.channels.push(channel("rover1/laser"));
    sim.nodes[1].gossip.set_info(new);
    sim.flush(1);
    sim.run_for(ms(50));
    for i in [0, 2] {
        assert_eq!(
            sim.count(i, |e| matches!(e, Event::ChannelAppeared { channel, .. } if channel.name == "rover1/laser")),
            1
        );
    }
    let mut fewer = sim.nodes[1].gossip.info().clone();
    fewer.channels.retain(|c| c.name != "rover1/pose");
    sim.nodes[1].gossip.set_info(fewer);
    sim.flush(1);
    sim.run_for(ms(50));
    for i in [0, 2] {
        assert_eq!(
            sim.count(i, |e| matches!(e, Event::ChannelDisappeared { channel, .. } if channel.name == "rover1/pose")),
            1
        );
        let info = sim.nodes[i]
            .gossip
            .member(key(1))
            .unwrap()
            .info()
            .unwrap()
            .clone();
        assert_eq!(info.channels.len(), 1);
    }
}

#[test]
fn a_lost_change_is_pulled_by_anti_entropy() {
    let mut sim = Sim::new(3, 9);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let mut new = sim.nodes[1].gossip.info().clone();
    new.channels.push(channel("rover1/late"));
    // The multicast full state is lost: drop everything node 1 sends right now.
    sim.nodes[1].gossip.set_info(new);
    while sim.nodes[1].gossip.poll_transmit().is_some() {}
    let took = sim
        .time_until(ms(1000), |s| {
            [0, 2].iter().all(|&i| {
                s.nodes[i]
                    .gossip
                    .member(key(1))
                    .and_then(|m| m.info())
                    .is_some_and(|info| info.channels.len() == 2)
            })
        })
        .expect("pulled after the next digest");
    assert!(took < ms(150), "took {took:?}");
}

#[test]
fn large_state_travels_in_parts() {
    let mut sim = Sim::new(2, 10);
    let channels: Vec<ChannelInfo> = (0..600)
        .map(|i| channel(&format!("{i:04}{}", "n".repeat(200))))
        .collect();
    sim.add_node(2, channels, false);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let info = sim.nodes[0]
        .gossip
        .member(key(2))
        .unwrap()
        .info()
        .unwrap()
        .clone();
    assert_eq!(info.channels.len(), 600);
}

#[test]
fn forged_and_inconsistent_messages_are_suspicious_and_change_nothing() {
    let mut sim = Sim::new(2, 11);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let now = sim.now;
    let intruder: SocketAddr = "10.9.9.9:7000".parse().unwrap();
    let g = &mut sim.nodes[0].gossip;
    // A digest and a leave for node 1's session from another address.
    let digest = Message::Digest(Digest {
        sender: key(1),
        incarnation: 99,
        version: 99,
        updates: vec![],
    });
    g.handle_datagram(now, intruder, Via::Multicast, &digest.encode())
        .unwrap();
    let leave = Message::Leave(Leave {
        sender: key(1),
        incarnation: 99,
    });
    g.handle_datagram(now, intruder, Via::Multicast, &leave.encode())
        .unwrap();
    let m = g.member(key(1)).unwrap();
    assert_eq!((m.state(), m.incarnation()), (MemberState::Alive, 0));
    // Full state for node 1 under another name.
    let mut renamed = info(1, vec![]);
    renamed.name = "impostor".into();
    let full = Message::Full(FullPart {
        member: key(1),
        incarnation: 0,
        version: 50,
        part: 0,
        parts: 1,
        chunk: pulicast_discovery::wire::encode_info(&renamed),
    });
    g.handle_datagram(now, intruder, Via::Multicast, &full.encode())
        .unwrap();
    assert_eq!(g.member(key(1)).unwrap().info().unwrap().name, "node1");
    // The same from node 1's own address: a rename, refused, and the entry
    // keeps its version.
    let addr1 = sim.nodes[1].addr;
    let g = &mut sim.nodes[0].gossip;
    let version = g.member(key(1)).unwrap().info_version();
    g.handle_datagram(now, addr1, Via::Multicast, &full.encode())
        .unwrap();
    let m = g.member(key(1)).unwrap();
    assert_eq!(
        (m.info().unwrap().name.as_str(), m.info_version()),
        ("node1", version)
    );
    // By unicast, unasked: ignored.
    g.handle_datagram(now, intruder, Via::Unicast, &full.encode())
        .unwrap();
    assert_eq!(g.member(key(1)).unwrap().info_version(), version);
    // Full state whose session does not match its key.
    let full = Message::Full(FullPart {
        member: key(1) + 7,
        incarnation: 0,
        version: 1,
        part: 0,
        parts: 1,
        chunk: pulicast_discovery::wire::encode_info(&info(1, vec![])),
    });
    g.handle_datagram(now, intruder, Via::Multicast, &full.encode())
        .unwrap();
    // Forged claims far ahead of the incarnation are ignored, about others
    // and about ourselves.
    let far = |member, state| {
        Message::Members(vec![Update {
            member,
            incarnation: u32::MAX,
            version: 1,
            state,
            address: intruder,
        }])
        .encode()
    };
    g.handle_datagram(now, intruder, Via::Unicast, &far(key(1), MemberState::Dead))
        .unwrap();
    g.handle_datagram(now, intruder, Via::Unicast, &far(key(0), MemberState::Dead))
        .unwrap();
    assert_eq!(g.member(key(1)).unwrap().state(), MemberState::Alive);
    assert_eq!(g.incarnation(), 0);
    sim.flush(0);
    // One event per kind of oddity and member (second address, rename,
    // wrong session); every refused message is counted.
    let suspicious = sim.count(0, |e| matches!(e, Event::Suspicious { .. }));
    assert_eq!(suspicious, 3, "{:?}", sim.nodes[0].events);
    assert!(sim.nodes[0].gossip.stats().suspicious >= 7);
}

#[test]
fn stale_and_contradicting_gossip_follows_incarnation_order() {
    let mut sim = Sim::new(3, 12);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let now = sim.now;
    let from = sim.nodes[2].addr;
    let addr1 = sim.nodes[1].addr;
    let g = &mut sim.nodes[0].gossip;
    let gossip = |state, incarnation| {
        Message::Members(vec![Update {
            member: key(1),
            incarnation,
            version: 1,
            state,
            address: addr1,
        }])
        .encode()
    };
    // Node 0 hears node 1 directly: a suspicion from someone else is ignored.
    g.handle_datagram(now, from, Via::Unicast, &gossip(MemberState::Suspect, 0))
        .unwrap();
    assert_eq!(g.member(key(1)).unwrap().state(), MemberState::Alive);
    // Much later, without hearing it, the same claim is believed.
    let later = now + PERIOD * 3;
    g.handle_datagram(later, from, Via::Unicast, &gossip(MemberState::Dead, 0))
        .unwrap();
    assert_eq!(g.member(key(1)).unwrap().state(), MemberState::Dead);
    // An older incarnation's "alive" can't revive it; a newer one does.
    g.handle_datagram(later, from, Via::Unicast, &gossip(MemberState::Alive, 0))
        .unwrap();
    assert_eq!(g.member(key(1)).unwrap().state(), MemberState::Dead);
    g.handle_datagram(later, from, Via::Unicast, &gossip(MemberState::Alive, 1))
        .unwrap();
    let m = g.member(key(1)).unwrap();
    assert_eq!((m.state(), m.incarnation()), (MemberState::Alive, 1));
    // A claim that *we* are dead makes us refute with a higher incarnation.
    let about_me = Message::Members(vec![Update {
        member: key(0),
        incarnation: 0,
        version: 1,
        state: MemberState::Dead,
        address: sim.nodes[0].addr,
    }]);
    let g = &mut sim.nodes[0].gossip;
    g.handle_datagram(later, from, Via::Unicast, &about_me.encode())
        .unwrap();
    assert_eq!(g.incarnation(), 1);
}

#[test]
fn garbage_never_panics_and_is_counted() {
    let mut sim = Sim::new(1, 13);
    let now = sim.now;
    let from: SocketAddr = "10.0.0.9:1".parse().unwrap();
    let g = &mut sim.nodes[0].gossip;
    let mut rng = 77u64;
    let mut seen = HashSet::new();
    for len in 0..2000usize {
        let mut bytes: Vec<u8> = (0..len % 300)
            .map(|_| {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                rng as u8
            })
            .collect();
        if len % 2 == 0 && bytes.len() >= 5 {
            bytes[..5].copy_from_slice(b"PDSC\x01");
        }
        seen.insert(g.handle_datagram(now, from, Via::Multicast, &bytes).is_ok());
    }
    assert!(g.stats().malformed > 1000);
    assert!(
        g.members().count() < 2000,
        "garbage may create members, but bounded"
    );
}

/// A stranger's digest that says a member left (or died, or is suspected)
/// at its next incarnation: sent to every node ten times a second for 3 s,
/// it makes no node drop the member, and the member refutes it.
#[test]
fn a_stranger_cannot_make_a_heard_member_leave() {
    let mut sim = Sim::new(3, 21);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let intruder: SocketAddr = "10.9.9.9:7000".parse().unwrap();
    let victim = key(1);
    for round in 0..30u32 {
        let incarnation = sim.nodes[0].gossip.member(victim).unwrap().incarnation();
        for state in [MemberState::Left, MemberState::Dead, MemberState::Suspect] {
            let forged = Message::Digest(Digest {
                sender: 0x5eed_0000 + u64::from(round) as MemberKey,
                incarnation: 0,
                version: 0,
                updates: vec![Update {
                    member: victim,
                    incarnation: incarnation + 1,
                    version: 1,
                    state,
                    address: sim.nodes[1].addr,
                }],
            })
            .encode();
            let now = sim.now;
            for i in 0..sim.nodes.len() {
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, intruder, Via::Multicast, &forged);
                sim.flush(i);
            }
        }
        sim.run_for(PERIOD);
        for observer in [0, 2] {
            let view = sim.view(observer, 1);
            assert_eq!(
                view.map(|(state, _)| state),
                Some(MemberState::Alive),
                "round {round}: node {observer} sees node 1 as {view:?}"
            );
        }
    }
    sim.run_for(ms(1000));
    assert!(sim.converged());
    assert_eq!(sim.failed_events(), 0, "members reported left or failed");
    // It refuted what others might have believed, at most once a digest
    // interval: the incarnation grows slowly.
    let incarnation = sim.nodes[1].gossip.incarnation();
    assert!((1..=64).contains(&incarnation), "incarnation {incarnation}");
}

/// Strangers fill the table with 4096 made-up keys (digests only, each
/// from an address of its own), again every 100 ms: a node that joins
/// meanwhile is still listed by all, with its channels, and its leave is
/// seen as a leave.
#[test]
fn a_table_full_of_made_up_keys_still_takes_a_real_node() {
    let mut sim = Sim::new(2, 22);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let fakes: Vec<(SocketAddr, Vec<u8>)> = (0..4096)
        .map(|k| {
            let from = SocketAddr::from(([10, 9, (k >> 8) as u8, k as u8], 7000));
            (from, made_up_digest(k))
        })
        .collect();
    let attack = |sim: &mut Sim| {
        let now = sim.now;
        for i in 0..sim.nodes.len() {
            for (from, fake) in &fakes {
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, *from, Via::Multicast, fake);
            }
            sim.flush(i);
        }
    };
    for _ in 0..5 {
        attack(&mut sim);
        sim.run_for(PERIOD);
    }
    assert!(
        sim.nodes[0].gossip.members().count() >= 4000,
        "the table filled"
    );
    sim.add_node(2, vec![channel("rover3/pose")], false);
    for _ in 0..20 {
        attack(&mut sim);
        sim.run_for(PERIOD);
    }
    for observer in [0, 1] {
        assert_eq!(
            sim.view(observer, 2),
            Some((MemberState::Alive, true)),
            "node {observer} does not list the newcomer"
        );
    }
    sim.leave(2);
    for _ in 0..3 {
        attack(&mut sim);
        sim.run_for(PERIOD);
    }
    for observer in [0, 1] {
        assert_eq!(sim.leaves_seen(observer, 2), 1, "node {observer}");
    }
}

/// A stranger announces a live member's session from its own address (the
/// session id and name are public: anyone may pull them), with forged
/// channels, ten times a second for 3 s. No node rebinds the member; each
/// shows the conflict; the member refutes and says so. A node that starts
/// during the attack and hears the impostor first shows the conflict too,
/// and follows the real member once the impostor stops, without reporting
/// it failed.
#[test]
fn a_stranger_cannot_take_over_a_session() {
    let mut sim = Sim::new(3, 23);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let impostor: SocketAddr = "10.9.9.9:7001".parse().unwrap();
    let victim = key(1);
    let real = sim.nodes[1].addr;
    let forged_info = wire::encode_info(&info(1, vec![channel("forged/cmd")]));
    let forgeries = |sim: &Sim| {
        let incarnation = sim.nodes[0].gossip.member(victim).unwrap().incarnation() + 1;
        let digest = Message::Digest(Digest {
            sender: victim,
            incarnation,
            version: 50,
            updates: vec![],
        })
        .encode();
        let full = Message::Full(FullPart {
            member: victim,
            incarnation,
            version: 50,
            part: 0,
            parts: 1,
            chunk: forged_info.clone(),
        })
        .encode();
        [digest, full]
    };
    let attack = |sim: &mut Sim, targets: &[usize]| {
        let forged = forgeries(sim);
        let now = sim.now;
        for &i in targets {
            for datagram in &forged {
                let _ =
                    sim.nodes[i]
                        .gossip
                        .handle_datagram(now, impostor, Via::Multicast, datagram);
            }
            sim.flush(i);
        }
    };
    let real_channels = |sim: &Sim, observer: usize| -> Vec<String> {
        let member = sim.nodes[observer].gossip.member(victim).unwrap();
        let info = member.info().expect("full state");
        info.channels.iter().map(|c| c.name.clone()).collect()
    };
    for round in 0..30 {
        attack(&mut sim, &[0, 1, 2]);
        sim.run_for(PERIOD);
        for observer in [0, 2] {
            let member = sim.nodes[observer].gossip.member(victim).unwrap();
            assert_eq!(member.state(), MemberState::Alive, "round {round}");
            assert_eq!(member.address(), real, "round {round}: rebound");
            assert_eq!(member.contested_by(), Some(impostor), "round {round}");
            assert_eq!(real_channels(&sim, observer), vec!["rover1/pose"]);
        }
    }
    // The victim heard its own session from elsewhere: it said so, and
    // refuted (a few times, not once per forged datagram).
    let warned = sim.count(
        1,
        |e| matches!(e, Event::Suspicious { key, what } if *key == victim && what.contains("impostor")),
    );
    assert!(warned >= 1, "the victim did not report the impostor");
    // Once a second at most, and no full state for it: 3 s of forged
    // digests cost a few refutations.
    let incarnation = sim.nodes[1].gossip.incarnation();
    assert!((1..=4).contains(&incarnation), "incarnation {incarnation}");

    // A newcomer that hears the impostor first.
    sim.add_node(3, vec![channel("rover3/pose")], false);
    attack(&mut sim, &[3]);
    for _ in 0..10 {
        attack(&mut sim, &[0, 1, 2, 3]);
        sim.run_for(PERIOD);
    }
    let seen = sim.nodes[3].gossip.member(victim).expect("listed");
    let addresses = [Some(seen.address()), seen.contested_by()];
    assert!(
        addresses.contains(&Some(real)) && addresses.contains(&Some(impostor)),
        "the newcomer lists only one side: {addresses:?}"
    );
    // The impostor stops: everyone follows the real member, nobody saw it
    // fail. (The newcomer, which others' gossip keeps telling the member
    // is alive, follows it once it has spoken for `indirect_dead_after`.)
    sim.run_for(ms(4000));
    for observer in [0, 2, 3] {
        let member = sim.nodes[observer].gossip.member(victim).unwrap();
        assert_eq!(member.state(), MemberState::Alive, "node {observer}");
        assert_eq!(member.address(), real, "node {observer}");
        assert_eq!(member.contested_by(), None, "node {observer}");
        assert_eq!(real_channels(&sim, observer), vec!["rover1/pose"]);
    }
    assert_eq!(sim.failed_events(), 0, "members reported left or failed");
}

/// The full state of a made-up member: `channels` channels with empty
/// names (5 bytes each on the wire, a whole `ChannelInfo` in memory), in
/// full-state parts as its owner would multicast them.
fn bulky_state(key: MemberKey, channels: usize) -> Vec<Vec<u8>> {
    let mut session = [0u8; 16];
    session[..8].copy_from_slice(&key.to_be_bytes());
    let info = MemberInfo {
        session,
        name: format!("fake{key}"),
        namespace: String::new(),
        host: String::new(),
        pid: 0,
        start_time_ms: 0,
        data_port: 0,
        channels: vec![
            ChannelInfo {
                name: String::new(),
                publishes: false,
                subscribes: false,
                period_ns: 0,
                message_type: None,
            };
            channels
        ],
        config: String::new(),
        extensions: Vec::new(),
    };
    let encoded = wire::encode_info(&info);
    wire::full_parts(key, 0, 1, &encoded)
        .unwrap()
        .into_iter()
        .map(|part| Message::Full(part).encode())
        .collect()
}

/// Strangers announce members whose full state is small on the wire and
/// large in memory: four at the largest size the wire allows (16 parts,
/// about 20 MB each once decoded) and thirty of about 3.5 MB,
/// kept alive by digests. What the states hold stays within
/// `max_state_bytes` (64 MiB; nearly 200 MB without the bound), every refusal is
/// counted, and a real node that joins later is still described: its small
/// state makes room by dropping a larger one.
#[test]
fn member_state_is_bounded_in_bytes_and_a_real_node_still_gets_in() {
    let mut sim = Sim::new(2, 24);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let limit = GossipConfig::for_heartbeat(PERIOD).max_state_bytes;
    let fakes: Vec<(MemberKey, SocketAddr, Vec<Vec<u8>>)> = (0..34)
        .map(|i| {
            let key = 0x0bad_0000 + i as MemberKey;
            let from = SocketAddr::from(([10, 9, 9, 9], 8000 + i as u16));
            // The largest state the wire allows, or one that holds about
            // 3.5 MB in memory.
            let small = 3_500_000 / std::mem::size_of::<ChannelInfo>();
            let channels = if i < 4 { 191_000 } else { small };
            (key, from, bulky_state(key, channels))
        })
        .collect();
    let digests = |sim: &mut Sim| {
        let now = sim.now;
        for (key, from, _) in &fakes {
            let digest = Message::Digest(Digest {
                sender: *key,
                incarnation: 0,
                version: 1,
                updates: vec![],
            })
            .encode();
            for i in 0..sim.nodes.len() {
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, *from, Via::Multicast, &digest);
            }
        }
    };
    let now = sim.now;
    for (_, from, parts) in &fakes {
        for i in 0..2 {
            for part in parts {
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, *from, Via::Multicast, part);
            }
            assert!(sim.nodes[i].gossip.state_bytes() <= limit);
        }
    }
    for i in 0..2 {
        let g = &sim.nodes[i].gossip;
        let described = g.members().filter(|m| m.info().is_some()).count();
        assert!(
            (10..30).contains(&described),
            "node {i} holds {described} states: {:?} {}",
            g.stats(),
            g.state_bytes()
        );
        assert!(g.stats().states_refused >= 4, "{:?}", g.stats());
    }
    // One more, sized to leave less room than the newcomer needs.
    let free = (0..2)
        .map(|i| limit - sim.nodes[i].gossip.state_bytes())
        .min()
        .unwrap();
    let filler_key = 0x0bad_1000;
    let filler_from = SocketAddr::from(([10, 9, 9, 9], 9000));
    let filler = bulky_state(
        filler_key,
        free.saturating_sub(50_000) / (std::mem::size_of::<ChannelInfo>() + 5),
    );
    let now = sim.now;
    for i in 0..2 {
        for part in &filler {
            let _ = sim.nodes[i]
                .gossip
                .handle_datagram(now, filler_from, Via::Multicast, part);
        }
        let free = limit - sim.nodes[i].gossip.state_bytes();
        assert!(free < 100_000, "node {i}: {free} bytes free");
    }
    for _ in 0..5 {
        digests(&mut sim);
        sim.run_for(PERIOD);
    }
    let many: Vec<ChannelInfo> = (0..1000)
        .map(|k| channel(&format!("rover2/sensor{k}")))
        .collect();
    sim.add_node(2, many, false);
    for _ in 0..10 {
        digests(&mut sim);
        sim.run_for(PERIOD);
    }
    for observer in [0, 1] {
        let g = &sim.nodes[observer].gossip;
        assert!(g.state_bytes() <= limit, "{}", g.state_bytes());
        assert!(g.stats().states_evicted >= 1, "{:?}", g.stats());
        for of in [0, 1, 2] {
            if of != observer {
                assert_eq!(
                    sim.view(observer, of),
                    Some((MemberState::Alive, true)),
                    "node {observer} does not describe node {of}"
                );
            }
        }
    }
}

/// An honest discovery socket speaks for one session: digests for 4096
/// made-up keys from one address add one member, not 4096; every refusal
/// is counted, and a real node joins and leaves as usual meanwhile.
#[test]
fn one_address_speaks_for_one_session() {
    let mut sim = Sim::new(2, 25);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let intruder: SocketAddr = "10.9.9.9:7000".parse().unwrap();
    let fakes: Vec<Vec<u8>> = (0..4096).map(made_up_digest).collect();
    let attack = |sim: &mut Sim| {
        let now = sim.now;
        for i in 0..sim.nodes.len() {
            for fake in &fakes {
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, intruder, Via::Multicast, fake);
            }
            sim.flush(i);
        }
    };
    sim.add_node(2, vec![channel("rover2/pose")], false);
    for _ in 0..10 {
        attack(&mut sim);
        sim.run_for(PERIOD);
        for i in 0..2 {
            let g = &sim.nodes[i].gossip;
            assert!(g.members().count() <= 3, "{} members", g.members().count());
        }
    }
    for i in 0..2 {
        assert!(sim.nodes[i].gossip.stats().suspicious >= 4000);
    }
    assert!(sim.converged());
    sim.leave(2);
    attack(&mut sim);
    sim.run_for(PERIOD);
    for observer in [0, 1] {
        assert_eq!(sim.leaves_seen(observer, 2), 1, "node {observer}");
    }
}

/// While a stranger announces a member's session from its own address, the
/// member goes silent for longer than `suspect_after` but less than
/// `dead_after` (a Wi-Fi burst, a stalled process): the session stays with
/// the member, and the stranger stays the rival.
#[test]
fn a_short_silence_does_not_hand_a_session_to_an_impostor() {
    let mut sim = Sim::new(3, 26);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let impostor: SocketAddr = "10.9.9.9:7001".parse().unwrap();
    let victim = key(1);
    let real = sim.nodes[1].addr;
    let speak = |sim: &mut Sim| {
        let incarnation = sim.nodes[0].gossip.member(victim).unwrap().incarnation();
        let digest = Message::Digest(Digest {
            sender: victim,
            incarnation,
            version: 1,
            updates: vec![],
        })
        .encode();
        let now = sim.now;
        for i in [0, 2] {
            let _ = sim.nodes[i]
                .gossip
                .handle_datagram(now, impostor, Via::Multicast, &digest);
            sim.flush(i);
        }
    };
    for _ in 0..10 {
        speak(&mut sim);
        sim.run_for(ms(10));
    }
    // Silent for 250 ms: suspected (200 ms), not dead (300 ms).
    sim.nodes[1].crashed = true;
    for _ in 0..25 {
        speak(&mut sim);
        sim.run_for(ms(10));
    }
    sim.nodes[1].crashed = false;
    for _ in 0..50 {
        speak(&mut sim);
        sim.run_for(ms(10));
        for observer in [0, 2] {
            let member = sim.nodes[observer].gossip.member(victim).unwrap();
            assert_eq!(
                member.address(),
                real,
                "node {observer} followed the impostor"
            );
        }
    }
    for observer in [0, 2] {
        let member = sim.nodes[observer].gossip.member(victim).unwrap();
        assert_eq!(member.state(), MemberState::Alive);
        assert_eq!(member.contested_by(), Some(impostor));
    }
    assert_eq!(sim.failed_events(), 0);
}

/// A stranger relays `Members` lists of 4096 made-up members from one
/// address, and answers the pulls for them with their full state: the table
/// fills with members that are described but were never heard from their
/// own address. A real node that joins meanwhile still gets in, and is
/// listed with its channels.
#[test]
fn made_up_members_relayed_in_lists_give_way_to_a_real_node() {
    let mut sim = Sim::new(2, 27);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let intruder: SocketAddr = "10.9.9.9:7000".parse().unwrap();
    let fake = |k: usize| 0x0bad_0000 + k as MemberKey;
    let lists: Vec<Vec<u8>> = (0..4096)
        .collect::<Vec<usize>>()
        .chunks(1000)
        .map(|chunk| {
            Message::Members(
                chunk
                    .iter()
                    .map(|&k| Update {
                        member: fake(k),
                        incarnation: 0,
                        version: 1,
                        state: MemberState::Alive,
                        address: SocketAddr::from(([10, 8, (k >> 8) as u8, k as u8], 7000)),
                    })
                    .collect(),
            )
            .encode()
        })
        .collect();
    let states: Vec<Vec<u8>> = (0..4096)
        .map(|k| {
            let mut session = [0u8; 16];
            session[..8].copy_from_slice(&fake(k).to_be_bytes());
            let info = MemberInfo {
                session,
                name: format!("fake{k}"),
                namespace: String::new(),
                host: String::new(),
                pid: 0,
                start_time_ms: 0,
                data_port: 0,
                channels: vec![],
                config: String::new(),
                extensions: Vec::new(),
            };
            Message::Full(FullPart {
                member: fake(k),
                incarnation: 0,
                version: 1,
                part: 0,
                parts: 1,
                chunk: wire::encode_info(&info),
            })
            .encode()
        })
        .collect();
    let attack = |sim: &mut Sim| {
        let now = sim.now;
        for i in 0..sim.nodes.len() {
            for list in &lists {
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, intruder, Via::Unicast, list);
            }
            // The answers to the pulls these lists caused.
            for state in &states {
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, intruder, Via::Unicast, state);
            }
            sim.flush(i);
        }
    };
    for _ in 0..5 {
        attack(&mut sim);
        sim.run_for(PERIOD);
    }
    let described = sim.nodes[0]
        .gossip
        .members()
        .filter(|m| m.info().is_some())
        .count();
    assert!(described >= 4000, "the table filled: {described}");
    sim.add_node(2, vec![channel("rover2/pose")], false);
    for _ in 0..10 {
        attack(&mut sim);
        sim.run_for(PERIOD);
    }
    for observer in [0, 1] {
        assert_eq!(
            sim.view(observer, 2),
            Some((MemberState::Alive, true)),
            "node {observer} does not list the newcomer"
        );
    }
}

/// Strangers fill the state bytes with members a little smaller than a real
/// node, then one more makes the real node's state give way (the largest
/// goes first). Once the strangers are gone, the real node's state is
/// pulled again and it is listed with its channels.
#[test]
fn a_state_dropped_to_make_room_comes_back_after_the_attack() {
    let mut sim = Sim::new(2, 28);
    let many: Vec<ChannelInfo> = (0..2000)
        .map(|k| channel(&format!("rover2/sensor{k:04}")))
        .collect();
    sim.add_node(2, many, false);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let limit = GossipConfig::for_heartbeat(PERIOD).max_state_bytes;
    let real = sim.nodes[0]
        .gossip
        .member(key(2))
        .map(|m| pulicast_discovery::gossip::state_cost(m.info().unwrap(), 0))
        .unwrap();
    // Fakes that cost a little less than the real node.
    let per_fake = (real * 9 / 10) / (std::mem::size_of::<ChannelInfo>() + 5);
    let fakes: Vec<(SocketAddr, MemberKey, Vec<Vec<u8>>)> = (0..limit / (real * 9 / 10) + 2)
        .map(|i| {
            let key = 0x0bad_0000 + i as MemberKey;
            let from = SocketAddr::from(([10, 9, (i >> 8) as u8, i as u8], 8000));
            (from, key, bulky_state(key, per_fake))
        })
        .collect();
    let attack = |sim: &mut Sim, full: bool| {
        let now = sim.now;
        for i in 0..2 {
            for (from, key, parts) in &fakes {
                let digest = Message::Digest(Digest {
                    sender: *key,
                    incarnation: 0,
                    version: 1,
                    updates: vec![],
                })
                .encode();
                let _ = sim.nodes[i]
                    .gossip
                    .handle_datagram(now, *from, Via::Multicast, &digest);
                if full {
                    for part in parts {
                        let _ =
                            sim.nodes[i]
                                .gossip
                                .handle_datagram(now, *from, Via::Multicast, part);
                    }
                }
            }
            sim.flush(i);
        }
    };
    attack(&mut sim, true);
    for _ in 0..5 {
        attack(&mut sim, false);
        sim.run_for(PERIOD);
    }
    for observer in [0, 1] {
        let g = &sim.nodes[observer].gossip;
        assert!(g.stats().states_evicted >= 1, "{:?}", g.stats());
        assert_eq!(
            sim.view(observer, 2),
            Some((MemberState::Alive, false)),
            "node {observer}: the real node's state did not give way"
        );
    }
    // The strangers stop; the real node is described again.
    sim.time_until(ms(60_000), Sim::converged)
        .expect("the real node's state comes back");
}

/// One `Members` datagram of claims that a node is dead at its incarnation
/// N, N+1, ... N+999: the node refutes once, not a thousand times (others
/// accept at most 16 incarnations ahead of what they know, so a run-up
/// would cut it off from them).
#[test]
fn a_list_of_claims_cannot_run_up_an_incarnation() {
    let mut sim = Sim::new(2, 29);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let intruder: SocketAddr = "10.9.9.9:7000".parse().unwrap();
    let base = sim.nodes[1].gossip.incarnation();
    let claims = Message::Members(
        (0..1000)
            .map(|i| Update {
                member: key(1),
                incarnation: base + i,
                version: 1,
                state: MemberState::Dead,
                address: sim.nodes[1].addr,
            })
            .collect(),
    )
    .encode();
    let now = sim.now;
    let _ = sim.nodes[1]
        .gossip
        .handle_datagram(now, intruder, Via::Unicast, &claims);
    sim.flush(1);
    assert_eq!(sim.nodes[1].gossip.incarnation(), base + 1);
    sim.run_for(ms(1000));
    assert!(sim.converged());
    assert_eq!(sim.failed_events(), 0);
}

/// A node leaves; a stranger then announces its session from its own
/// address for 5 s: nobody takes the departed member back.
#[test]
fn a_stranger_cannot_bring_back_a_member_that_left() {
    let mut sim = Sim::new(3, 30);
    sim.time_until(ms(1000), Sim::converged).expect("converges");
    let impostor: SocketAddr = "10.9.9.9:7001".parse().unwrap();
    let victim = key(2);
    sim.leave(2);
    sim.run_for(PERIOD);
    for _ in 0..250 {
        let incarnation = sim.nodes[0].gossip.member(victim).unwrap().incarnation();
        let digest = Message::Digest(Digest {
            sender: victim,
            incarnation,
            version: 1,
            updates: vec![],
        })
        .encode();
        let now = sim.now;
        for i in [0, 1] {
            let _ = sim.nodes[i]
                .gossip
                .handle_datagram(now, impostor, Via::Multicast, &digest);
            sim.flush(i);
        }
        sim.run_for(ms(20));
    }
    for observer in [0, 1] {
        let state = sim.nodes[observer].gossip.member(victim).map(|m| m.state());
        assert_eq!(state, Some(MemberState::Left), "node {observer}");
    }
}

//! The channels a node has touched: each one's state (its send side,
//! who uses it here, what it carries), and the table that holds them
//! with what else belongs to channels as a whole.

use std::collections::HashSet;
use std::net::{Ipv4Addr, SocketAddrV4};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use indexmap::IndexMap;
use pulicast_discovery::compat;
use pulicast_discovery::wire::{ChannelInfo, TypeInfo};

use crate::proto::secure::Sealer;
use crate::proto::ChannelTx;
use crate::sync::lock;

/// What the node knows about one channel it has touched.
pub(crate) struct ChannelState {
    pub(super) name: Arc<str>,
    pub(super) group: Ipv4Addr,
    /// `destination` as the socket layer takes it.
    pub(super) address: socket2::SockAddr,
    /// Whether a key covers the channel.
    pub(super) sealed: bool,
    /// The send side: prefixes, sequence numbers, pending batch, sealer.
    pub(super) tx: Mutex<ChannelTx>,
    pub(super) published: AtomicBool,
    /// Subscriptions discovery announces; quiet ones (a bridge's relay
    /// servers) are not counted, so they never show.
    pub(super) subscribers: AtomicUsize,
    pub(super) period: Mutex<PeriodMeter>,
    /// The burst its fragments may make, and when it was worked out from
    /// the subscribers' buffers (`Inner::burst_for`); `None` before.
    pub(super) burst: Mutex<Option<(std::time::Instant, Option<usize>)>>,
    /// Fingerprint of the last typed use (0: none), checked without a lock
    /// on every publish; the description itself is behind the mutex.
    pub(super) type_fingerprint: AtomicU64,
    pub(super) message_type: Mutex<Option<TypeInfo>>,
    /// Announcements held without publishing or subscribing (services'
    /// clients and servers, and what is announced beside their request
    /// channels): publish, subscribe.
    pub(super) held: [AtomicUsize; 2],
}

impl ChannelState {
    /// The channel's full name.
    pub(crate) fn name(&self) -> &Arc<str> {
        &self.name
    }

    /// The channel as announced in discovery, if this node uses it.
    pub(super) fn info(&self) -> Option<ChannelInfo> {
        let [held_pub, held_sub] = &self.held;
        let publishes =
            self.published.load(Ordering::Relaxed) || held_pub.load(Ordering::Relaxed) > 0;
        let subscribes = self.announced_subscribers() > 0 || held_sub.load(Ordering::Relaxed) > 0;
        if !publishes && !subscribes {
            return None;
        }
        Some(ChannelInfo {
            name: self.name.to_string(),
            publishes,
            subscribes,
            period_ns: lock(&self.period).period_ns as u64,
            message_type: lock(&self.message_type).clone(),
        })
    }

    /// The subscriptions discovery announces: all but the quiet ones.
    pub(crate) fn announced_subscribers(&self) -> usize {
        self.subscribers.load(Ordering::Relaxed)
    }

    /// Holds an announcement that this node publishes (`publishes`) or
    /// subscribes the channel, without doing it; true if the channel's
    /// announcement changed.
    pub(crate) fn hold(&self, publishes: bool) -> bool {
        self.held[usize::from(!publishes)].fetch_add(1, Ordering::Relaxed) == 0
    }

    /// Lets go of an announcement [`ChannelState::hold`] took; true if the
    /// channel's announcement changed.
    pub(crate) fn release(&self, publishes: bool) -> bool {
        let held = &self.held[usize::from(!publishes)];
        held.fetch_update(Ordering::Relaxed, Ordering::Relaxed, |n| n.checked_sub(1)) == Ok(1)
    }

    /// Whether a key seals the channel.
    pub(crate) fn is_sealed(&self) -> bool {
        self.sealed
    }

    /// Records the type used on this channel; true if it changed.
    pub(crate) fn note_type(
        &self,
        fingerprint: [u8; 8],
        describe: impl FnOnce() -> TypeInfo,
    ) -> bool {
        let fp = u64::from_be_bytes(fingerprint);
        // A plain load on the hot path; the lock only when the type changes,
        // and fingerprint and description change together under it.
        if self.type_fingerprint.load(Ordering::Relaxed) == fp {
            return false;
        }
        let mut described = lock(&self.message_type);
        if self.type_fingerprint.load(Ordering::Relaxed) == fp {
            return false;
        }
        *described = Some(describe());
        self.type_fingerprint.store(fp, Ordering::Relaxed);
        true
    }
}

/// Smoothed interval between publications, announced in heartbeats.
#[derive(Default)]
pub(super) struct PeriodMeter {
    pub(super) last: Option<Instant>,
    pub(super) period_ns: f64,
    pub(super) announced_ns: f64,
}

impl PeriodMeter {
    /// Records a publication; true when the period moved enough (25 %) from
    /// the one last announced to be worth announcing again.
    pub(super) fn record(&mut self, now: Instant) -> bool {
        if let Some(last) = self.last {
            let sample = now.duration_since(last).as_nanos() as f64;
            // An exponential average follows rate changes within ~10 messages.
            self.period_ns = if self.period_ns == 0.0 {
                sample
            } else {
                0.9 * self.period_ns + 0.1 * sample
            };
        }
        self.last = Some(now);
        let moved = (self.period_ns - self.announced_ns).abs() > 0.25 * self.announced_ns.max(1.0);
        if moved && self.period_ns > 0.0 {
            self.announced_ns = self.period_ns;
            return true;
        }
        false
    }
}

/// Most type disagreements a node remembers having warned about; past it
/// the memory starts over (and may say one again). Anyone can announce
/// types: the bound keeps the set small, the check's own limit the log.
const MAX_TYPE_WARNINGS: usize = 1024;

/// The channels of one node.
pub(super) struct Channels {
    /// In creation order, which is the order heartbeats list them in.
    table: Mutex<IndexMap<Arc<str>, Arc<ChannelState>>>,
    /// The id the next subscription on any channel gets.
    next_subscriber: AtomicU64,
    /// (channel, announced type) disagreements already warned about.
    type_warnings: Mutex<HashSet<(String, [u8; 8])>>,
    /// Held while this node relays members (see `Inner::relay`).
    pub(super) relay_marker: Mutex<Option<Arc<ChannelState>>>,
}

impl Channels {
    pub(super) fn new() -> Self {
        Self {
            table: Mutex::new(IndexMap::new()),
            next_subscriber: AtomicU64::new(0),
            type_warnings: Mutex::new(HashSet::new()),
            relay_marker: Mutex::new(None),
        }
    }

    /// The table itself, locked: for the heartbeat's walk over it and for
    /// forgetting channels nobody holds.
    pub(super) fn table(&self) -> MutexGuard<'_, IndexMap<Arc<str>, Arc<ChannelState>>> {
        lock(&self.table)
    }

    /// The state of channel `name`, made on first use with the address and
    /// sealer `make` gives.
    pub(super) fn state(
        &self,
        name: &str,
        make: impl FnOnce(&str) -> (SocketAddrV4, Option<Sealer>),
    ) -> Arc<ChannelState> {
        let mut table = lock(&self.table);
        if let Some(state) = table.get(name) {
            return Arc::clone(state);
        }
        let name: Arc<str> = name.into();
        let (address, sealer) = make(&name);
        let state = Arc::new(ChannelState {
            name: Arc::clone(&name),
            group: *address.ip(),
            address: address.into(),
            sealed: sealer.is_some(),
            tx: Mutex::new(ChannelTx::new(Arc::clone(&name), sealer)),
            published: AtomicBool::new(false),
            subscribers: AtomicUsize::new(0),
            period: Mutex::new(PeriodMeter::default()),
            burst: Mutex::new(None),
            type_fingerprint: AtomicU64::new(0),
            message_type: Mutex::new(None),
            held: Default::default(),
        });
        table.insert(name, Arc::clone(&state));
        state
    }

    /// A fresh subscription id.
    pub(super) fn next_subscriber(&self) -> u64 {
        self.next_subscriber.fetch_add(1, Ordering::Relaxed)
    }

    /// The channels this node announces, in creation order (the 2.x
    /// `__nodes` channel is the heartbeat's own and never announced).
    pub(super) fn infos(&self) -> Vec<ChannelInfo> {
        lock(&self.table)
            .values()
            .filter(|c| c.name.as_ref() != compat::NODES_CHANNEL)
            .filter_map(|c| c.info())
            .collect()
    }

    /// The channels this node subscribes as announced, with the type it
    /// subscribes each as.
    pub(super) fn subscribed_types(&self) -> Vec<(Arc<str>, TypeInfo)> {
        lock(&self.table)
            .values()
            .filter(|c| c.announced_subscribers() > 0)
            .filter_map(|c| Some((Arc::clone(&c.name), lock(&c.message_type).clone()?)))
            .collect()
    }

    /// Records that a type warning about (`channel`, `fingerprint`) is
    /// given; false if it was given before.
    pub(super) fn first_type_warning(&self, channel: &str, fingerprint: [u8; 8]) -> bool {
        let mut warned = lock(&self.type_warnings);
        if warned.len() >= MAX_TYPE_WARNINGS {
            warned.clear();
        }
        warned.insert((channel.to_string(), fingerprint))
    }
}

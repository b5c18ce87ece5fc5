//! The fleet as the API shows it: [`Discovery`] (members, events, gossip
//! counters) and waiting for the fleet to show something. What keeps the
//! view current runs in the runtime (`runtime::fleet`).

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use pulicast_discovery::gossip;
use pulicast_discovery::relay::RelayStats;
use pulicast_discovery::wire::RelayedMember;
use tokio::sync::broadcast;

use crate::runtime::Inner;

pub use crate::proto::view::{DiscoveryEvent, MemberView, Remote};
pub use crate::wire::DISCOVERY_CHANNEL;

/// The node's view of the fleet: a snapshot, events, and lookups. Made by
/// [`crate::Node::discovery`]; cheap to clone.
///
/// # Example
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) {
/// use std::time::Duration;
/// let fleet = node.discovery();                  // cheap to clone
/// fleet.settle(Duration::from_secs(2)).await;    // empty right after start = not heard yet
/// for m in fleet.live_members() {
///     println!("{} ({}) on {}", m.name, m.namespace, m.host);
/// }
/// for s in fleet.services() {
///     println!("service {}: {} server(s)", s.name, s.servers.len());
/// }
/// println!("me: {} at {:?}", fleet.local().name, fleet.local_address());
/// # }
/// ```
#[derive(Clone)]
pub struct Discovery {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for Discovery {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Discovery").finish_non_exhaustive()
    }
}

impl Discovery {
    pub(crate) fn new(inner: Arc<Inner>) -> Self {
        Self { inner }
    }

    /// Every member this node knows of, live or recently gone (dead and
    /// departed members are remembered for 30 s), without this node itself.
    /// Pulicast 2.x nodes appear with `compat: true`.
    pub fn members(&self) -> Vec<MemberView> {
        self.inner.fleet_members()
    }

    /// [`Discovery::members`] with at most the first `per_member` channels
    /// of each: what a tool that reads the whole fleet often (a bridge,
    /// several times a second) holds, bounded by its own choice rather than
    /// by what strangers announce. The view is made without copying the
    /// rest.
    ///
    /// ```no_run
    /// # async fn f(node: pulicast::Node) {
    /// for member in node.discovery().members_within(1024) {
    ///     assert!(member.channels.len() <= 1024);
    /// }
    /// # }
    /// ```
    pub fn members_within(&self, per_member: usize) -> Vec<MemberView> {
        self.inner.fleet_members_within(per_member)
    }

    /// [`Discovery::members_within`] of only the members whose keys
    /// `pick` takes, the others never copied: for a tool that gives some
    /// members (those it trusts, or that carry traffic) a larger share of
    /// what it reads than the rest.
    ///
    /// ```no_run
    /// # async fn f(node: pulicast::Node, trusted: std::collections::HashSet<i64>) {
    /// let discovery = node.discovery();
    /// let mut members = discovery.members_picked(1024, |key| trusted.contains(&key));
    /// members.extend(discovery.members_picked(16, |key| !trusted.contains(&key)));
    /// # }
    /// ```
    pub fn members_picked(&self, per_member: usize, pick: impl Fn(i64) -> bool) -> Vec<MemberView> {
        self.inner
            .fleet_members_selected(&crate::proto::view::Select {
                member: &pick,
                ..crate::proto::view::Select::first(per_member)
            })
    }

    /// The live members (alive or suspected).
    pub fn live_members(&self) -> Vec<MemberView> {
        let mut live = self.members();
        live.retain(MemberView::is_live);
        live
    }

    /// The services of the live members and of this node: who serves
    /// and who calls each, with their types (see [`crate::services_of`]).
    pub fn services(&self) -> Vec<crate::ServiceInfo> {
        let mut members = self.live_members();
        members.push(self.local());
        crate::services_of(&members)
    }

    /// Waits until discovery has had a fair chance to show the fleet, at
    /// most `within`: until the node has listened for three heartbeat
    /// periods and the 2.x grace period (a 2.x node heard at once is listed
    /// only after it, 550 ms at the defaults), holds the members of other
    /// sites from each bridge it knows (which sends them when a node joins,
    /// and every second), and then the view has not changed for a heartbeat
    /// period and a half. Returns whether it settled (false: `within` ran
    /// out first, the fleet still changing).
    ///
    /// For a program that reads the fleet once, such as a tool's `nodes`
    /// or the check that a name exists before failing on it: an empty view
    /// right after start only means that nothing has been heard yet.
    ///
    /// ```
    /// # use std::{net::Ipv4Addr, time::Duration};
    /// # #[tokio::main(flavor = "current_thread")]
    /// # async fn main() -> pulicast::Result<()> {
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("inspector")
    ///     .interface(Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start()
    ///     .await?;
    /// let fleet = node.discovery();
    /// fleet.settle(Duration::from_secs(3)).await;
    /// for member in fleet.live_members() {
    ///     println!("{}", member.name);
    /// }
    /// # Ok(()) }
    /// ```
    pub async fn settle(&self, within: Duration) -> bool {
        let start = tokio::time::Instant::now();
        let end = start + within;
        let fair = self.inner.fair_chance();
        let calm_for = self.inner.heartbeat_period() * 3 / 2;
        let view = || {
            let mut seen: Vec<(i64, usize, bool)> = self
                .live_members()
                .iter()
                .map(|m| (m.key, m.channels.len(), m.compat))
                .collect();
            seen.sort_unstable();
            seen
        };
        let mut last = view();
        let mut calm = tokio::time::Instant::now();
        // Members that relay other sites' (bridges), and when this wait
        // first saw each: their lists come at once when a node joins, and
        // at the latest within a refresh period.
        let mut relayers: std::collections::HashMap<i64, tokio::time::Instant> = Default::default();
        let relay_wait = pulicast_discovery::relay::REFRESH + fair;
        loop {
            let now = tokio::time::Instant::now();
            for m in self.live_members() {
                if m.remote.is_none() && m.publishes(crate::wire::RELAYS_CHANNEL) {
                    relayers.entry(m.key).or_insert(now);
                }
            }
            let relayed = relayers.iter().all(|(bridge, seen)| {
                self.inner.relayed_from(*bridge) || now.duration_since(*seen) >= relay_wait
            });
            if self.inner.age() >= fair && now.duration_since(calm) >= calm_for && relayed {
                return true;
            }
            if now >= end {
                return false;
            }
            let step = Duration::from_millis(20).min(end - now);
            tokio::time::sleep(step).await;
            let seen = view();
            if seen != last {
                last = seen;
                calm = tokio::time::Instant::now();
            }
        }
    }

    /// This node as the fleet sees it.
    pub fn local(&self) -> MemberView {
        self.inner.local_view()
    }

    /// A stream of fleet changes from now on.
    pub fn events(&self) -> DiscoveryEvents {
        DiscoveryEvents {
            rx: self.inner.fleet_events(),
            lagged: 0,
        }
    }

    /// Whether gossip discovery runs (it can be disabled on the builder; 2.x
    /// heartbeats are consumed either way).
    pub fn is_gossiping(&self) -> bool {
        self.inner.is_gossiping()
    }

    /// Counters of the gossip protocol, if it runs.
    pub fn stats(&self) -> Option<gossip::GossipStats> {
        self.inner.gossip_stats()
    }

    /// Makes members of other sites present on this one, as this node's
    /// relays (what `puli-bridge` does): every node here lists them with
    /// [`MemberView::remote`] naming this node, their data coming from this
    /// node's data socket (so each entry's `info.data_port` should be this
    /// node's, as [`Discovery::local`] shows it). The list replaces the
    /// previous one; it is sent at once and every second, each entry
    /// keeping its member present for three seconds; a member dropped from
    /// the list (or ended with state dead or left) fails (or leaves) there
    /// within that time, and all of them fail as soon as this node does.
    ///
    /// Members heard directly on this site, and this node itself, are not
    /// taken from a relay. Fails with [`crate::Error::InvalidConfig`] on a
    /// node without gossip discovery.
    pub fn relay(&self, members: Vec<RelayedMember>) -> crate::Result<()> {
        self.inner.relay(members)
    }

    /// Counters of the table of members that other nodes relay here, if
    /// gossip discovery runs.
    pub fn relay_stats(&self) -> Option<RelayStats> {
        self.inner.relay_stats()
    }

    /// The address of this node's discovery socket, which other nodes use as
    /// a seed peer (`NodeBuilder::peer`).
    pub fn local_address(&self) -> Option<SocketAddr> {
        self.inner.discovery_address()
    }
}

/// Fleet changes, as they happen. Made by [`Discovery::events`].
///
/// ```no_run
/// # fn demo(node: pulicast::Node) {
/// use std::collections::BTreeSet;
/// use pulicast::DiscoveryEvent;
/// let fleet = node.discovery();
/// let mut events = fleet.events(); // first, so no change falls before the snapshot
/// let mut live: BTreeSet<i64> = fleet.live_members().iter().map(|m| m.key).collect();
/// let mut missed = 0;
/// while let Some(event) = events.recv_blocking() { // on a thread of its own
///     match event {
///         DiscoveryEvent::Joined(m) => drop(live.insert(m.key)),
///         DiscoveryEvent::Left { key, .. } | DiscoveryEvent::Failed { key, .. } => drop(live.remove(&key)),
///         _ => {}
///     }
///     if events.missed() != missed { // fell behind: the snapshot is always whole
///         missed = events.missed();
///         live = fleet.live_members().iter().map(|m| m.key).collect();
///     }
/// }
/// # }
/// ```
#[derive(Debug)]
pub struct DiscoveryEvents {
    rx: broadcast::Receiver<DiscoveryEvent>,
    lagged: u64,
}

impl DiscoveryEvents {
    /// The next change; `None` once the node has stopped.
    pub async fn recv(&mut self) -> Option<DiscoveryEvent> {
        loop {
            match self.rx.recv().await {
                Ok(event) => return Some(event),
                Err(broadcast::error::RecvError::Lagged(n)) => self.lagged += n,
                Err(broadcast::error::RecvError::Closed) => return None,
            }
        }
    }

    /// The next change if one is waiting.
    pub fn try_recv(&mut self) -> Option<DiscoveryEvent> {
        loop {
            match self.rx.try_recv() {
                Ok(event) => return Some(event),
                Err(broadcast::error::TryRecvError::Lagged(n)) => self.lagged += n,
                Err(_) => return None,
            }
        }
    }

    /// Blocks the thread until the next change; `None` once the node has
    /// stopped. Not for async code.
    pub fn recv_blocking(&mut self) -> Option<DiscoveryEvent> {
        loop {
            match self.rx.blocking_recv() {
                Ok(event) => return Some(event),
                Err(broadcast::error::RecvError::Lagged(n)) => self.lagged += n,
                Err(broadcast::error::RecvError::Closed) => return None,
            }
        }
    }

    /// Events missed because this stream fell more than 1024 behind (a node
    /// joining a large fleet gets an event per member and channel at once).
    /// When it grows, read [`Discovery::members`], which is always whole.
    pub fn missed(&self) -> u64 {
        self.lagged
    }
}

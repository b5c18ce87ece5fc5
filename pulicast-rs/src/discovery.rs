//! The fleet as the API shows it: [`Discovery`] (members, events, gossip
//! counters) and waiting for the fleet to show something. What keeps the
//! view current runs in the runtime (`runtime::fleet`).

use std::net::SocketAddr;
use std::sync::Arc;

use pulicast_discovery::gossip;
use pulicast_discovery::relay::RelayStats;
use pulicast_discovery::wire::RelayedMember;
use tokio::sync::broadcast;

use crate::runtime::Inner;

pub use crate::runtime::fleet::{DiscoveryEvent, MemberView, Remote};
pub use crate::wire::DISCOVERY_CHANNEL;

/// The node's view of the fleet: a snapshot, events, and lookups. Made by
/// [`crate::Node::discovery`]; cheap to clone.
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

//! The fleet as a node shows it: a member ([`MemberView`]), a member of
//! another site ([`Remote`]) and a change ([`DiscoveryEvent`]), and how
//! views are made from what discovery holds (gossip members, relayed
//! entries, Pulicast 2.x peers), taking only the members and channels a
//! [`Select`] asks for. Data and conversions only: the node's discovery
//! task (in `pulicast`) reads the tables under their locks and calls these.

use std::net::SocketAddr;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use pulicast_discovery::compat::Peer;
use pulicast_discovery::gossip::{self, Gossip, Member};
use pulicast_discovery::relay;
use pulicast_discovery::wire::{ChannelInfo, MemberInfo, MemberState};
use uuid::Uuid;

/// One member of the fleet, as this node sees it.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct MemberView {
    /// The 64-bit session id (the first 8 bytes of the session UUID; the
    /// session id of its 2.x heartbeats).
    pub key: i64,
    /// The full session UUID; `None` for Pulicast 2.x nodes.
    pub session: Option<Uuid>,
    /// The node's name.
    pub name: String,
    /// Its default namespace (empty for 2.x nodes, which don't announce it).
    pub namespace: String,
    /// The host it runs on (empty for 2.x nodes).
    pub host: String,
    /// Where it announces itself from: its discovery socket, or for 2.x nodes
    /// the socket of its heartbeats.
    pub address: SocketAddr,
    /// Where its data packets come from, if known.
    pub data_address: Option<SocketAddr>,
    /// When it started, if known.
    pub start_time: Option<SystemTime>,
    /// Its incarnation (bumped each time it refutes a suspicion).
    pub incarnation: u32,
    /// Alive, suspect, dead or left.
    pub state: MemberState,
    /// Its channels.
    pub channels: Vec<ChannelInfo>,
    /// Known only from Pulicast 2.x heartbeats.
    pub compat: bool,
    /// Another address that also speaks for this session, recently: one of
    /// the two is an impostor (or two nodes share a session id), and without
    /// keys nobody can tell which. The view stays with [`MemberView::address`],
    /// the first heard, while it speaks.
    pub contested_by: Option<SocketAddr>,
    /// A member of another site, present here through a bridge
    /// (`puli-bridge`): its address and data address are the bridge's.
    pub remote: Option<Remote>,
    /// The configuration it runs in (`NodeBuilder::config`), empty for
    /// none (always for 2.x nodes).
    pub config: String,
    /// The receive buffer the kernel granted its data sockets, in bytes
    /// (`SO_RCVBUF` as Linux reports it: twice the payload it holds), if
    /// it announces one (2.x nodes don't). A publisher paces a message's
    /// fragments so that a burst fits its subscribers' buffers.
    pub receive_buffer: Option<u32>,
}

/// How a member of another site is present here.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub struct Remote {
    /// The key of the bridge that relays it, a member of this site.
    pub bridge: i64,
    /// The name of its site, as its bridge tells it.
    pub site: String,
}

impl Remote {
    /// A member relayed by the bridge `bridge` from the site `site`.
    pub fn new(bridge: i64, site: impl Into<String>) -> Self {
        Self {
            bridge,
            site: site.into(),
        }
    }
}

impl MemberView {
    /// Whether it counts as present: alive or merely suspected.
    pub fn is_live(&self) -> bool {
        matches!(self.state, MemberState::Alive | MemberState::Suspect)
    }

    /// Whether it publishes on `channel`.
    pub fn publishes(&self, channel: &str) -> bool {
        self.channels
            .iter()
            .any(|c| c.publishes && c.name == channel)
    }

    /// Whether it subscribes to `channel`.
    pub fn subscribes(&self, channel: &str) -> bool {
        self.channels
            .iter()
            .any(|c| c.subscribes && c.name == channel)
    }

    /// Whether it serves the service whose request channel is `request`
    /// (`rover1/.services/plan`): it subscribes the request channel and
    /// announces its answers (`@reply`) beside it. A node that only
    /// subscribes the request channel, such as a Pulicast 2.x sniffer, is
    /// no server: it would never answer.
    pub fn serves(&self, request: &str) -> bool {
        self.subscribes(request)
            && self.channels.iter().any(|c| {
                c.publishes && c.name.strip_prefix(request) == Some(crate::wire::service::REPLY)
            })
    }

    fn from_member(member: &Member, info: &MemberInfo, select: &Select<'_>) -> Self {
        // Gossip takes a full state only under its own session's key.
        Self {
            incarnation: member.incarnation(),
            state: member.state(),
            contested_by: member.contested_by(),
            ..Self::from_info_within(info, member.address(), select)
        }
    }

    /// A member as it announces itself in `info` from the discovery
    /// address `address`, alive at incarnation 0: what a node shows once it
    /// has a member's full state. For tools and tests that make views of
    /// their own.
    pub fn from_info(info: &MemberInfo, address: SocketAddr) -> Self {
        Self::from_info_within(info, address, &Select::ALL)
    }

    /// [`MemberView::from_info`] with the channels `select` takes.
    fn from_info_within(info: &MemberInfo, address: SocketAddr, select: &Select<'_>) -> Self {
        Self {
            key: info.key(),
            session: Some(Uuid::from_bytes(info.session)),
            name: info.name.clone(),
            namespace: info.namespace.clone(),
            host: info.host.clone(),
            address,
            data_address: Some(SocketAddr::new(address.ip(), info.data_port)),
            start_time: Some(UNIX_EPOCH + Duration::from_millis(info.start_time_ms)),
            incarnation: 0,
            state: MemberState::Alive,
            channels: info
                .channels
                .iter()
                .filter(|c| (select.channel)(&c.name))
                .take(select.per_member)
                .cloned()
                .collect(),
            compat: false,
            contested_by: None,
            remote: None,
            config: info.config.clone(),
            receive_buffer: info.receive_buffer(),
        }
    }

    /// A relayed member, at its bridge's discovery address `bridge` (its
    /// `data_port` is the bridge's).
    fn from_relayed(entry: &relay::Entry, bridge: SocketAddr, select: &Select<'_>) -> Self {
        Self {
            incarnation: entry.incarnation,
            state: entry.state,
            remote: Some(Remote {
                bridge: entry.bridge,
                site: entry.site.clone(),
            }),
            ..Self::from_info_within(&entry.info, bridge, select)
        }
    }

    fn from_compat(peer: &Peer, select: &Select<'_>) -> Self {
        Self {
            key: peer.session_id,
            session: None,
            name: peer.name.clone(),
            namespace: String::new(),
            host: String::new(),
            address: peer.address,
            data_address: None,
            start_time: None,
            incarnation: 0,
            state: MemberState::Alive,
            channels: peer
                .channels
                .iter()
                .filter(|c| {
                    c.name != pulicast_discovery::compat::NODES_CHANNEL && (select.channel)(&c.name)
                })
                .take(select.per_member)
                .map(|c| ChannelInfo {
                    name: c.name.clone(),
                    publishes: c.is_published,
                    subscribes: c.is_subscribed,
                    period_ns: u64::try_from(c.period_ns).unwrap_or(0),
                    message_type: None,
                })
                .collect(),
            compat: true,
            contested_by: None,
            remote: None,
            config: String::new(),
            receive_buffer: None,
        }
    }
}

/// Which members, and which of their channels, a copy of the fleet takes.
///
/// Members of a stranger's can announce hundreds of thousands of channels:
/// what a node reads of the fleet for its own purposes (which members
/// publish a channel, who serves a service) copies only what it looks at,
/// never the whole fleet.
pub struct Select<'a> {
    /// Members by key.
    pub member: &'a dyn Fn(i64) -> bool,
    /// Channels by name.
    pub channel: &'a dyn Fn(&str) -> bool,
    /// At most this many of the channels taken, the first ones.
    pub per_member: usize,
}

impl Select<'_> {
    /// Every member with every channel.
    pub const ALL: Select<'static> = Select {
        member: &|_| true,
        channel: &|_| true,
        per_member: usize::MAX,
    };

    /// Every member with at most its first `n` channels.
    pub fn first(n: usize) -> Select<'static> {
        Select {
            per_member: n,
            ..Select::ALL
        }
    }
}

/// The most channels a [`DiscoveryEvent::Joined`] carries.
pub const EVENT_CHANNELS: usize = 256;

/// A change in the fleet.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum DiscoveryEvent {
    /// A member appeared, with its state; of its channels, the first 256
    /// (`Discovery::members` has them all): the last thousand events are
    /// kept for slow receivers, and a stranger's members of thousands of
    /// channels each must not make them hundreds of megabytes.
    Joined(MemberView),
    /// A member left gracefully.
    Left {
        /// Its key.
        key: i64,
        /// Its name.
        name: String,
    },
    /// A member failed: silent past the timeout (or a 2.x node past three
    /// missed heartbeats).
    Failed {
        /// Its key.
        key: i64,
        /// Its name.
        name: String,
    },
    /// A member went silent and is suspected; it will fail unless it
    /// refutes.
    Suspected {
        /// Its key.
        key: i64,
        /// Its name.
        name: String,
    },
    /// A suspected member proved alive.
    Recovered {
        /// Its key.
        key: i64,
        /// Its name.
        name: String,
    },
    /// A member announced a channel.
    ChannelAppeared {
        /// The member's key.
        key: i64,
        /// The member's name.
        member: String,
        /// The channel.
        channel: ChannelInfo,
    },
    /// A member no longer announces a channel.
    ChannelDisappeared {
        /// The member's key.
        key: i64,
        /// The member's name.
        member: String,
        /// The channel as it was.
        channel: ChannelInfo,
    },
    /// Something no honest member does, e.g. a session announced from a
    /// second address or renamed.
    Suspicious {
        /// The session concerned.
        key: i64,
        /// What happened.
        what: String,
    },
}

/// The view of gossip member `member`, whose full state is `info`.
pub fn member_view(member: &Member, info: &MemberInfo, select: &Select<'_>) -> MemberView {
    MemberView::from_member(member, info, select)
}

/// The view of a member of another site relayed by the bridge whose
/// discovery address is `bridge`.
pub fn relayed_view(entry: &relay::Entry, bridge: SocketAddr, select: &Select<'_>) -> MemberView {
    MemberView::from_relayed(entry, bridge, select)
}

/// The view of a Pulicast 2.x peer, known from its heartbeats.
pub fn peer_view(peer: &Peer, select: &Select<'_>) -> MemberView {
    MemberView::from_compat(peer, select)
}

/// A gossip event as the node shows it; `None` for those it does not
/// show. A member that joined is looked up in `gossip` for its view.
pub fn event_of(gossip: &Gossip, event: gossip::Event) -> Option<DiscoveryEvent> {
    match event {
        gossip::Event::Joined { key, info } => {
            let member = gossip.member(key)?;
            Some(DiscoveryEvent::Joined(MemberView::from_member(
                member,
                &info,
                &Select::first(EVENT_CHANNELS),
            )))
        }
        other => plain_event_of(other),
    }
}

/// The events that need no member table to convert (a `Joined` does).
pub fn plain_event_of(event: gossip::Event) -> Option<DiscoveryEvent> {
    Some(match event {
        gossip::Event::Left { key, name } => DiscoveryEvent::Left { key, name },
        gossip::Event::Failed { key, name } => DiscoveryEvent::Failed { key, name },
        gossip::Event::Suspected { key, name } => DiscoveryEvent::Suspected { key, name },
        gossip::Event::Recovered { key, name } => DiscoveryEvent::Recovered { key, name },
        gossip::Event::ChannelAppeared {
            key,
            member,
            channel,
        } => DiscoveryEvent::ChannelAppeared {
            key,
            member,
            channel,
        },
        gossip::Event::ChannelDisappeared {
            key,
            member,
            channel,
        } => DiscoveryEvent::ChannelDisappeared {
            key,
            member,
            channel,
        },
        gossip::Event::Suspicious { key, what } => DiscoveryEvent::Suspicious { key, what },
        _ => return None,
    })
}

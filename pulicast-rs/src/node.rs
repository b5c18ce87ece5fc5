//! The node as its users hold it: [`Node`] and [`NodeBuilder`]. What it
//! runs is in the runtime (`crate::runtime`).

use std::sync::Arc;
use std::time::Duration;

use pulicast_discovery::compat::{self, Peer};
use uuid::Uuid;

use crate::channel::Namespace;
use crate::error::{Error, Result};
use crate::name::resolve_path;
use crate::proto::fragment::ReassemblyLimits;
use crate::proto::receiver::KeyUse;
use crate::proto::secure::Key;
use crate::queue::QueuePolicy;
use crate::runtime::{Inner, Settings};
use crate::security::SecurityOptions;
use crate::stats::Stats;

mod builder;

pub use crate::port::DEFAULT_PORT;
pub(crate) use builder::configuration;
pub use builder::NodeBuilder;

/// The Pulicast 2.x default multicast TTL: 0 keeps traffic on this host.
pub const DEFAULT_TTL: u32 = 0;
/// The Pulicast 2.x default heartbeat period.
pub const DEFAULT_HEARTBEAT_PERIOD: Duration = Duration::from_millis(100);
/// Messages a subscription buffers before its queue policy drops one.
pub const DEFAULT_QUEUE_CAPACITY: usize = 1024;
/// The receive buffer a socket asks for by default: see
/// [`NodeBuilder::receive_buffer`].
pub const DEFAULT_RECEIVE_BUFFER: usize = 4 << 20;
/// The rate at which messages in fragments leave by default, in bytes a
/// second: see [`NodeBuilder::fragment_rate`].
pub const DEFAULT_FRAGMENT_RATE: u64 = 1 << 30;
/// The lowest fragment rate allowed, in bytes a second.
pub const MIN_FRAGMENT_RATE: u64 = 1 << 20;
/// How long a receive loop polls before parking by default: see
/// [`NodeBuilder::receive_spin`].
pub const DEFAULT_RECEIVE_SPIN: Duration = Duration::from_micros(50);
/// The longest receive spin allowed.
pub const MAX_RECEIVE_SPIN: Duration = Duration::from_millis(1);
/// The environment variable a node takes its configuration from when the
/// builder names none ([`NodeBuilder::config`]).
pub const CONFIG_ENV: &str = "PULICAST_CONFIG";
/// The longest configuration name, in bytes.
pub const MAX_CONFIG_LEN: usize = 64;

/// A pulicast node: one participant of the fleet, with its own session.
///
/// A node is also a [`Namespace`] (its default namespace), so channels are
/// reached directly from it: `node.channel("ctrl")`. Clones share the node; it
/// stops when [`Node::stop`] is called or the last clone is dropped.
///
/// ```no_run
/// # #[derive(serde::Serialize, serde::Deserialize, pulicast::Schema)] struct Twist { linear: f64, angular: f64 }
/// # #[derive(serde::Serialize, serde::Deserialize, pulicast::Schema)] struct Pose { x: f64 }
/// # async fn run() -> pulicast::Result<()> {
/// use pulicast::Node;
/// let node = Node::new("rover_controller").namespace("rover1").start().await?;
/// node.channel("ctrl").publish(&"Go LEFT!")?;                 // -> rover1/ctrl
/// let arm = node.ns("left_arm");                              // rover1/left_arm
/// arm.channel("ctrl").publish(&Twist { linear: 0.3, angular: 0.0 })?;
/// let peer = node.make_namespace("/rover2");                  // from the root
/// let mut poses = peer.channel("pose").subscribe::<Pose>()?;  // rover2/pose
/// while let Some(m) = poses.recv().await { /* m.value, m.source, m.lead */ }
/// # Ok(()) }
/// ```
#[derive(Clone)]
pub struct Node {
    namespace: Namespace,
    _lifetime: Arc<StopOnDrop>,
}

impl std::fmt::Debug for Node {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Node")
            .field("name", &self.inner().name())
            .field("session", &self.inner().session())
            .field("namespace", &self.namespace.path())
            .finish()
    }
}

impl Node {
    /// The handle of a node that `inner` runs, in `namespace`.
    fn running(inner: Arc<Inner>, namespace: String) -> Self {
        Node {
            namespace: Namespace::new(Arc::clone(&inner), namespace.into()),
            _lifetime: Arc::new(StopOnDrop(inner)),
        }
    }

    fn inner(&self) -> &Arc<Inner> {
        &self._lifetime.0
    }

    /// The node's runtime, for the runtime's own tests.
    #[cfg(test)]
    pub(crate) fn runtime(&self) -> &Arc<Inner> {
        self.inner()
    }

    /// Starts configuring a node called `name`. Names are for people: they need
    /// not be unique, the session id tells nodes apart.
    #[allow(clippy::new_ret_no_self)]
    pub fn new(name: impl Into<String>) -> NodeBuilder {
        NodeBuilder::named(name.into())
    }

    /// The node's name.
    pub fn name(&self) -> &str {
        self.inner().name()
    }

    /// The node's session: a random UUID, new every time a node starts.
    pub fn session_id(&self) -> Uuid {
        self.inner().session()
    }

    /// The configuration the node runs in, empty for none (see
    /// [`NodeBuilder::config`]).
    pub fn config(&self) -> &str {
        self.inner().config()
    }

    /// The 64-bit session id that Pulicast 2.x heartbeats carry: the first eight
    /// bytes of [`Node::session_id`], big-endian.
    pub fn compat_session_id(&self) -> i64 {
        self.inner().compat_session_id()
    }

    /// The live peers heard on `__nodes`, Pulicast 2.x nodes included, without
    /// this node itself. A peer is forgotten after three missed heartbeats.
    pub fn peers(&self) -> Vec<Peer> {
        self.inner().compat_peers()
    }

    /// The fleet's settings as this node sees them: list, read, and ask
    /// their owners for changes (see [`crate::FleetSettings`]).
    pub fn fleet_settings(&self) -> crate::FleetSettings {
        crate::FleetSettings::new(Arc::clone(self.inner()))
    }

    /// The node's view of the fleet: members, their channels, and changes as
    /// they happen.
    pub fn discovery(&self) -> crate::Discovery {
        crate::Discovery::new(Arc::clone(self.inner()))
    }

    /// The node's counters: received, delivered, and dropped per reason.
    pub fn stats(&self) -> Stats {
        self.inner().stats()
    }

    /// What the keys of each namespace this node has keys for met so far:
    /// datagrams that opened, sealed ones that did not (another key), and
    /// unsealed ones refused. Empty for a node without keys. A key whose
    /// `opened` stays 0 while the others grow is not the fleet's key.
    ///
    /// ```
    /// # #[tokio::main(flavor = "current_thread")] async fn main() -> Result<(), Box<dyn std::error::Error>> {
    /// let key = pulicast::Key::from_hex(&"7a".repeat(32))?;
    /// let node = pulicast::Node::new("doc_keys")
    ///     .port(pulicast::unused_port()?)
    ///     .interface(std::net::Ipv4Addr::LOCALHOST)
    ///     .keys_from_env(false)
    ///     .key("rover1", key)
    ///     .start()
    ///     .await?;
    /// let uses = node.key_uses();
    /// assert_eq!((uses[0].namespace.as_str(), uses[0].opened), ("rover1", 0));
    /// # Ok(()) }
    /// ```
    pub fn key_uses(&self) -> Vec<KeyUse> {
        self.inner().key_uses()
    }

    /// Stops the node: its tasks end, its subscriptions close (their `recv`
    /// returns `None`) and publishing returns [`Error::NodeStopped`].
    pub fn stop(&self) {
        self.inner().stop();
    }

    /// Whether the node has stopped.
    pub fn is_stopped(&self) -> bool {
        self.inner().is_stopped()
    }
}

impl std::ops::Deref for Node {
    type Target = Namespace;

    fn deref(&self) -> &Namespace {
        &self.namespace
    }
}

/// Stops the node when the last [`Node`] clone goes away.
struct StopOnDrop(Arc<Inner>);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.stop();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn invalid_options_are_refused() {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        let err = |b: NodeBuilder| rt.block_on(b.start()).err();
        assert!(matches!(
            err(Node::new("n").port(0)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").ttl(256)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").heartbeat_period(Duration::ZERO)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").queue_capacity(0)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").receive_spin(MAX_RECEIVE_SPIN * 2)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").receive_buffer(1000)),
            Some(Error::InvalidConfig { .. })
        ));
        let limits = ReassemblyLimits {
            per_source: 10,
            per_channel: 5,
            total: 5,
            timeout: Duration::from_secs(1),
        };
        assert!(matches!(
            err(Node::new("n").reassembly_limits(limits)),
            Some(Error::InvalidConfig { .. })
        ));
        assert!(matches!(
            err(Node::new("n").namespace("r\u{f6}ver")),
            Some(Error::InvalidName { .. })
        ));
    }

    #[test]
    fn start_outside_a_runtime_is_an_error() {
        let fut = Node::new("n").start();
        let result = futures_lite_block_on(fut);
        assert!(matches!(result, Err(Error::InvalidConfig { .. })));
    }

    /// Polls a future to completion without a tokio runtime.
    fn futures_lite_block_on<F: std::future::Future>(fut: F) -> F::Output {
        use std::task::{Context, Poll, Waker};
        let mut fut = std::pin::pin!(fut);
        let mut cx = Context::from_waker(Waker::noop());
        loop {
            if let Poll::Ready(out) = fut.as_mut().poll(&mut cx) {
                return out;
            }
        }
    }
}

//! Namespaces and channels: where robot code publishes and subscribes.

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use postcard_schema::Schema;
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::discovery::MemberView;
use crate::error::{Error, NameError, Result};
use crate::name::{resolve_name, resolve_path};
use crate::proto::nearest::{candidates, search_steps, Seeker, Step};
use crate::proto::receiver::Expected;
use crate::runtime::{ChannelState, Inner};
use crate::subscription::{CallbackSubscription, Decode, Message, Subscription};
use crate::wire::{self, DecodeError};
use pulicast_discovery::compat::NODES_CHANNEL;
use pulicast_discovery::wire::TypeInfo;

/// A name that failed to resolve, kept so the error surfaces at first use.
#[derive(Debug, Clone)]
struct BadName {
    name: String,
    reason: NameError,
}

impl BadName {
    fn from_error(err: Error) -> Self {
        match err {
            Error::InvalidName { name, reason } => BadName { name, reason },
            // Resolution only ever fails with InvalidName.
            other => BadName {
                name: other.to_string(),
                reason: NameError::Empty,
            },
        }
    }

    fn error(&self) -> Error {
        Error::InvalidName {
            name: self.name.clone(),
            reason: self.reason.clone(),
        }
    }
}

/// A place in the channel hierarchy, e.g. `rover1/left_arm`.
///
/// Components should take a `&Namespace` in their constructors and pick their
/// channel names inside it: then the same component runs for `rover1` and
/// `rover2` without knowing it. A [`crate::Node`] dereferences to its default
/// namespace, so `&node` works wherever `&Namespace` is expected.
///
/// Methods that take names never fail; a bad name is reported by the first
/// publish or subscribe on it (or early, by [`Namespace::try_channel`]).
///
/// ```
/// use pulicast::{Channel, Namespace};
///
/// /// Knows its channel names, not where they live.
/// struct Battery { level: Channel }
///
/// impl Battery {
///     fn new(ns: &Namespace) -> Self {
///         Self { level: ns.channel("battery/level") }
///     }
/// }
///
/// # let port = pulicast::unused_port()?;
/// let node = pulicast::Node::new("power")
///     .namespace("rover1")
///     .interface(std::net::Ipv4Addr::LOCALHOST)
/// #   .port(port)
///     .start_blocking()?;
/// assert_eq!(Battery::new(&node).level.name(), "rover1/battery/level");
/// assert_eq!(Battery::new(&node.make_namespace("rover2")).level.name(), "rover2/battery/level");
/// assert_eq!(Battery::new(&node.ns("../base")).level.name(), "base/battery/level");
/// # Ok::<(), pulicast::Error>(())
/// ```
#[derive(Clone)]
pub struct Namespace {
    inner: Arc<Inner>,
    path: Result<Arc<str>, BadName>,
}

impl std::fmt::Debug for Namespace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.path {
            Ok(path) => write!(f, "Namespace({path:?})"),
            Err(bad) => write!(f, "Namespace(invalid {:?})", bad.name),
        }
    }
}

impl Namespace {
    pub(crate) fn new(inner: Arc<Inner>, path: Arc<str>) -> Self {
        Self {
            inner,
            path: Ok(path),
        }
    }

    pub(crate) fn root(inner: Arc<Inner>) -> Self {
        Self::new(inner, "".into())
    }

    pub(crate) fn inner(&self) -> &Arc<Inner> {
        &self.inner
    }

    /// The resolved path, `""` for the root. For a namespace whose name could
    /// not be resolved, the name as given.
    pub fn path(&self) -> &str {
        match &self.path {
            Ok(path) => path,
            Err(bad) => &bad.name,
        }
    }

    /// The channel `name`, resolved relative to this namespace (`pose`,
    /// `left_arm/pose`, `../rover2/pose`) or from the root (`/rover2/pose`).
    pub fn channel(&self, name: &str) -> Channel {
        let state = self
            .resolved(|ns| resolve_name(name, ns))
            .map(|full| self.inner.channel_state(&full));
        Channel {
            inner: Arc::clone(&self.inner),
            state,
            given: name.into(),
        }
    }

    /// Like [`Namespace::channel`], but reports a bad name at once.
    pub fn try_channel(&self, name: &str) -> Result<Channel> {
        let channel = self.channel(name);
        channel.state()?;
        Ok(channel)
    }

    /// A namespace below (or, with `..`, above) this one.
    pub fn ns(&self, path: &str) -> Namespace {
        Namespace {
            inner: Arc::clone(&self.inner),
            path: self.resolved(|ns| resolve_path(path, ns)).map(Into::into),
        }
    }

    /// A namespace resolved from the root, whatever this namespace is:
    /// `make_namespace("rover2")` and `make_namespace("/rover2")` are the same.
    pub fn make_namespace(&self, path: &str) -> Namespace {
        Namespace {
            inner: Arc::clone(&self.inner),
            path: resolve_path(path, "")
                .map(Into::into)
                .map_err(BadName::from_error),
        }
    }

    /// The nearest channel called `name` that has a live publisher, in
    /// DROS's search order: publishers in this node's configuration
    /// ([`crate::NodeBuilder::config`]) first, then those of none; within
    /// each, from this namespace outward to the root. From `rover1/arm`,
    /// `laser` is looked for as `rover1/arm/laser`, then `rover1/laser`,
    /// then `laser`, so a local override wins over a fleet-wide default and
    /// a user's own publisher over everyone's. Publishers in another
    /// configuration are never found. A name with a leading `/` is only
    /// looked up as given; `..` resolves from each namespace in turn.
    /// Publishers are what discovery knows right now, this node included;
    /// `None` if no candidate has one (or the name is bad).
    pub fn resolve_nearest(&self, name: &str) -> Option<Channel> {
        let steps = self.search_steps(name).ok()?;
        let (step, _) = self.nearest_publishers(&steps).into_iter().next()?;
        let root = Namespace::root(Arc::clone(&self.inner));
        Some(root.channel(&format!("/{}", steps[step].channel)))
    }

    /// The steps of the search for `name` from this namespace, in this
    /// node's configuration.
    pub(crate) fn search_steps(&self, name: &str) -> Result<Vec<Step>> {
        let ns = self.path.as_ref().map_err(BadName::error)?;
        Ok(search_steps(name, ns, self.inner.config())?)
    }

    /// The live publishers `steps` find, in the search's order: each
    /// one's step and the publisher (this node included).
    pub(crate) fn nearest_publishers(&self, steps: &[Step]) -> Vec<(usize, MemberView)> {
        let mut members = self
            .inner
            .fleet_members_on(&|c| steps.iter().any(|s| s.channel == c));
        members.push(self.inner.local_view());
        let seeker = Seeker {
            key: self.inner.compat_session_id(),
            host: self.inner.host(),
        };
        // A bridge republishes what the members it relays publish: they
        // are the publishers, it only carries their messages here.
        let carries = |bridge: &MemberView, channel: &str| {
            members.iter().any(|o| {
                o.remote.as_ref().is_some_and(|r| r.bridge == bridge.key) && o.publishes(channel)
            })
        };
        candidates(steps, &members, seeker, |m, c| {
            m.publishes(c) && !carries(m, c)
        })
        .into_iter()
        .map(|(step, m)| (step, members[m].clone()))
        .collect()
    }

    fn resolved(&self, f: impl FnOnce(&str) -> Result<String>) -> Result<String, BadName> {
        let ns = self.path.as_ref().map_err(Clone::clone)?;
        f(ns).map_err(BadName::from_error)
    }
}

/// One channel, by its resolved name. Cheap to clone.
///
/// Publish with [`Channel::publish`] (typed) or [`Channel::publish_bytes`];
/// subscribe with [`Channel::subscribe`], [`Channel::subscribe_ordered`] or
/// [`Channel::subscribe_raw`].
///
/// Types travel as follows: `bool`, `u8`, `i8`, `i16`, `i32`, `i64`, `f32`,
/// `f64` and strings as the Pulicast 2.x ZCM primitive messages, so Python
/// peers read them; any other `serde` type that derives [`crate::Schema`] as a
/// native message (postcard with a type fingerprint).
///
/// # Example
///
/// ```no_run
/// # fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// let speed = node.channel("left_wheel/speed");      // in the node's namespace
/// let mut typed = speed.subscribe::<f64>()?;         // other types: counted, skipped
/// let mut raw = speed.subscribe_raw()?;              // any payload, as `Bytes`
/// speed.publish(&0.8f64)?;                           // f64 travels as a 2.x ZCM double
/// assert_eq!(typed.recv_blocking().map(|m| m.value), Some(0.8));
/// println!("{}: {} bytes", speed.name(), raw.recv_blocking().map_or(0, |m| m.value.len()));
/// println!("{} publisher(s)", speed.publishers().len());
/// assert!(node.try_channel("/").is_err());           // bad names fail at first use, or here
/// # Ok(()) }
/// ```
#[derive(Clone)]
pub struct Channel {
    inner: Arc<Inner>,
    state: Result<Arc<ChannelState>, BadName>,
    given: Arc<str>,
}

impl std::fmt::Debug for Channel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Channel({:?})", self.name())
    }
}

impl Channel {
    /// The resolved name, e.g. `rover1/ctrl` (or the name as given, if it
    /// could not be resolved).
    pub fn name(&self) -> &str {
        match &self.state {
            Ok(state) => state.name(),
            Err(_) => &self.given,
        }
    }

    fn state(&self) -> Result<&Arc<ChannelState>> {
        self.state.as_ref().map_err(BadName::error)
    }

    /// Publishes one typed message.
    ///
    /// Messages larger than one datagram are sent as fragments. Fails with
    /// [`Error::PayloadTooLarge`] above 64 MiB, [`Error::NodeStopped`] after
    /// the node stopped, and
    /// [`Error::InvalidName`] if the channel name was bad or is `__nodes`,
    /// which only the node's heartbeat may use.
    ///
    /// A run of bytes (`Vec<u8>`, `[u8]`, `&[u8]`) goes raw, exactly as
    /// [`Channel::publish_bytes`] sends it (use that for [`Bytes`]).
    pub fn publish<T: Serialize + Schema + ?Sized>(&self, value: &T) -> Result<()> {
        let state = self.publish_state()?;
        self.note_type::<T>(state);
        self.inner
            .publish_with(state, |buf| Ok(wire::encode_native(value, buf)?))
    }

    /// Publishes raw bytes, without a type fingerprint.
    pub fn publish_bytes(&self, payload: &[u8]) -> Result<()> {
        self.inner.publish_payload(self.publish_state()?, payload)
    }

    /// Publishes raw bytes at once, in a datagram (or fragments) of their
    /// own, even while the channel batches: after the messages its batch
    /// holds, which go first, so order is kept. For a message that should
    /// not wait for a batch to fill or its delay to pass (the first after a
    /// quiet spell, say); on a channel that doesn't batch it is
    /// [`Channel::publish_bytes`].
    pub fn publish_bytes_now(&self, payload: &[u8]) -> Result<()> {
        self.inner
            .publish_payload_as(self.publish_state()?, payload, true)
    }

    /// Packs this channel's messages into shared datagrams, each sent when
    /// full or at most `max_delay` after its first message was published.
    ///
    /// One datagram per message caps a publisher at the kernel's send rate;
    /// batching lifts that cap for small messages (see `docs/performance.md`)
    /// at the price of up to `max_delay` of latency. Subscribers need nothing
    /// special: they receive the messages one by one, with their sequence
    /// numbers and leads, as if they were sent singly. Batches travel under
    /// their own magic (`PBAT`, see `docs/wire.md`), which Pulicast 2.x nodes
    /// can't read, so while discovery knows of a 2.x node subscribing this
    /// channel its messages go out singly (the log says so once). Messages too
    /// large to share a datagram are sent on their own, in order.
    ///
    /// Batching belongs to the channel in this node: every handle on it
    /// batches. Fails with [`Error::InvalidConfig`] unless `max_delay` is
    /// above zero and at most [`crate::MAX_BATCH_DELAY`].
    ///
    /// ```
    /// # use std::{net::Ipv4Addr, time::Duration};
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("imu_driver")
    ///     .interface(Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// let imu = node.channel("imu/raw");
    /// let mut samples = imu.subscribe::<f64>()?;
    /// imu.enable_batching(Duration::from_millis(2))?;
    /// for i in 0..100 {
    ///     imu.publish(&(i as f64))?;
    /// }
    /// imu.flush()?; // or wait: the batch leaves within 2 ms anyway
    /// let first = samples.recv_timeout(Duration::from_secs(5)).expect("our own message");
    /// assert_eq!((first.value, first.seq), (0.0, 0));
    /// # Ok::<(), pulicast::Error>(())
    /// ```
    pub fn enable_batching(&self, max_delay: Duration) -> Result<()> {
        self.inner
            .set_batching(self.publish_state()?, Some(max_delay))
    }

    /// Sends what is pending and publishes one message per datagram again.
    pub fn disable_batching(&self) -> Result<()> {
        self.inner.set_batching(self.publish_state()?, None)
    }

    /// Sends the pending batch now, if batching is on and messages wait;
    /// otherwise does nothing.
    pub fn flush(&self) -> Result<()> {
        self.inner.flush(self.state()?)
    }

    /// Subscribes to messages of type `T`; messages of other types are
    /// counted as [`crate::DropReason::WrongType`] and skipped. A `Vec<u8>`
    /// subscription takes every payload raw, like
    /// [`Channel::subscribe_raw`].
    pub fn subscribe<T: DeserializeOwned + Schema>(&self) -> Result<Subscription<T>> {
        self.note_type::<T>(self.state()?);
        self.subscribe_queue(false, expected::<T>(), decode_typed::<T>)
    }

    /// Like [`Channel::subscribe`], but drops messages that arrive late or
    /// twice (lead < 1), so values arrive in the order they were sent.
    pub fn subscribe_ordered<T: DeserializeOwned + Schema>(&self) -> Result<Subscription<T>> {
        self.note_type::<T>(self.state()?);
        self.subscribe_queue(true, expected::<T>(), decode_typed::<T>)
    }

    /// Subscribes to the raw payloads, whatever their type.
    pub fn subscribe_raw(&self) -> Result<Subscription<Bytes>> {
        self.subscribe_queue(false, None, raw_payload)
    }

    /// Subscribes to messages of type `T`, calling `handler` with each on
    /// the node's receive path, without a queue (the style of Pulicast 2.x
    /// callbacks): the fastest way to receive, and the way to keep up with
    /// a fast or batched publisher. See [`CallbackSubscription`] for what
    /// the handler may do and what happens if it blocks. Messages of other
    /// types are counted as [`crate::DropReason::WrongType`] and skipped;
    /// a `Vec<u8>` handler takes every payload, like
    /// [`Channel::subscribe_raw_with`].
    ///
    /// ```
    /// use std::sync::{atomic::{AtomicU64, Ordering}, Arc};
    /// # use std::{net::Ipv4Addr, time::Duration};
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("odometry")
    ///     .interface(Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// let ticks = Arc::new(AtomicU64::new(0));
    /// let counted = Arc::clone(&ticks);
    /// let wheel = node.channel("wheel/ticks");
    /// let _subscription = wheel.subscribe_with(move |m: pulicast::Message<i64>| {
    ///     counted.fetch_add(m.value as u64, Ordering::Relaxed);
    /// })?;
    /// wheel.publish(&3i64)?;
    /// wheel.publish(&4i64)?;
    /// # let t = std::time::Instant::now();
    /// # while ticks.load(Ordering::Relaxed) < 7 && t.elapsed() < Duration::from_secs(5) {
    /// #     std::thread::sleep(Duration::from_millis(1));
    /// # }
    /// assert_eq!(ticks.load(Ordering::Relaxed), 7);
    /// # Ok::<(), pulicast::Error>(())
    /// ```
    pub fn subscribe_with<T, F>(&self, handler: F) -> Result<CallbackSubscription>
    where
        T: DeserializeOwned + Schema + 'static,
        F: FnMut(Message<T>) + Send + 'static,
    {
        self.note_type::<T>(self.state()?);
        self.subscribe_handler(false, expected::<T>(), decode_typed::<T>, handler)
    }

    /// Like [`Channel::subscribe_with`], but skips messages that arrive late
    /// or twice (lead < 1), so values arrive in the order they were sent.
    pub fn subscribe_ordered_with<T, F>(&self, handler: F) -> Result<CallbackSubscription>
    where
        T: DeserializeOwned + Schema + 'static,
        F: FnMut(Message<T>) + Send + 'static,
    {
        self.note_type::<T>(self.state()?);
        self.subscribe_handler(true, expected::<T>(), decode_typed::<T>, handler)
    }

    /// Calls `handler` with the raw payload of each message, whatever its
    /// type: a view into the received datagram, not a copy. See
    /// [`Channel::subscribe_with`].
    pub fn subscribe_raw_with<F>(&self, handler: F) -> Result<CallbackSubscription>
    where
        F: FnMut(Message<Bytes>) + Send + 'static,
    {
        self.subscribe_handler(false, None, raw_payload, handler)
    }

    /// Watches the channel's raw payloads without taking part in it: like
    /// [`Channel::subscribe_raw`], but discovery does not announce it.
    ///
    /// What a node subscribes means something to the fleet: a node that
    /// subscribes a service's request channel is taken for a server, one
    /// that publishes a setting's channel and subscribes its `.r` channel
    /// for the setting's owner, and a Pulicast 2.x subscriber makes
    /// batching publishers send one message per datagram. A tool that only
    /// looks (a sniffer, a recorder, a bridge passing messages on) watches,
    /// so that it never changes how others behave. Messages are delivered
    /// as to any subscription; only the announcement differs.
    ///
    /// ```
    /// # use std::{net::Ipv4Addr, time::Duration};
    /// # let port = pulicast::unused_port()?;
    /// let node = pulicast::Node::new("recorder")
    ///     .interface(Ipv4Addr::LOCALHOST)
    /// #   .port(port)
    ///     .start_blocking()?;
    /// let requests = node.channel("rover1/.services/plan");
    /// let mut watched = requests.watch_raw()?;
    /// // Discovery does not show this node among the subscribers, so no
    /// // caller takes it for a server of `rover1/plan`.
    /// assert!(requests.subscribers().is_empty());
    /// # assert!(watched.try_recv().is_none());
    /// # Ok::<(), pulicast::Error>(())
    /// ```
    pub fn watch_raw(&self) -> Result<Subscription<Bytes>> {
        let state = Arc::clone(self.state()?);
        Subscription::new(
            Arc::clone(&self.inner),
            state,
            false,
            None,
            raw_payload,
            true,
        )
    }

    /// Like [`Channel::watch_raw`], calling `handler` on the receive path
    /// as [`Channel::subscribe_raw_with`] does.
    pub fn watch_raw_with<F>(&self, handler: F) -> Result<CallbackSubscription>
    where
        F: FnMut(Message<Bytes>) + Send + 'static,
    {
        let state = Arc::clone(self.state()?);
        let inner = Arc::clone(&self.inner);
        CallbackSubscription::new(inner, state, false, None, raw_payload, handler, true)
    }

    /// Remembers the type used here, for discovery to announce (raw bytes
    /// have none).
    fn note_type<T: Schema + ?Sized>(&self, state: &ChannelState) {
        if wire::is_raw_bytes(T::SCHEMA) {
            return;
        }
        if state.note_type(wire::fingerprint_of::<T>().0, wire::type_info_of::<T>) {
            self.inner.announce_change();
        }
    }

    /// Announces in discovery that this channel carries messages of type
    /// `ty`, for programs that publish bytes they got elsewhere (a replay, a
    /// bridge), so that tools can still decode them. Typed publishing and
    /// subscribing announce their type by themselves.
    pub fn declare_type(&self, ty: TypeInfo) -> Result<()> {
        let state = self.state()?;
        if state.note_type(ty.fingerprint, || ty.clone()) {
            self.inner.announce_change();
        }
        Ok(())
    }

    /// The live members that publish on this channel, this node included.
    pub fn publishers(&self) -> Vec<MemberView> {
        self.members_where(|m| m.publishes(self.name()))
    }

    /// The live members that subscribe to this channel, this node included.
    pub fn subscribers(&self) -> Vec<MemberView> {
        self.members_where(|m| m.subscribes(self.name()))
    }

    fn members_where(&self, pred: impl Fn(&MemberView) -> bool) -> Vec<MemberView> {
        if self.state.is_err() {
            return Vec::new();
        }
        // Found on this channel's entries alone, then copied whole: a
        // stranger's members of thousands of channels cost no more than
        // their one entry here.
        let name = self.name();
        let keys: std::collections::HashSet<i64> = self
            .inner
            .fleet_members_on(&|c| c == name)
            .into_iter()
            .filter(|m| m.is_live() && pred(m))
            .map(|m| m.key)
            .collect();
        let mut found = if keys.is_empty() {
            Vec::new()
        } else {
            self.inner
                .fleet_members_selected(&crate::proto::view::Select {
                    member: &|key| keys.contains(&key),
                    ..crate::proto::view::Select::ALL
                })
        };
        let local = self.inner.local_view();
        if pred(&local) {
            found.push(local);
        }
        found
    }

    /// Waits until some member publishes on this channel, and returns one.
    /// Fails with [`Error::Timeout`] if none does within `timeout`.
    pub async fn wait_for_publisher(&self, timeout: Duration) -> Result<MemberView> {
        self.state()?;
        self.inner
            .wait_for(timeout, || self.publishers().into_iter().next())
            .await
    }

    /// Like [`Channel::wait_for_publisher`], blocking the thread.
    pub fn wait_for_publisher_blocking(&self, timeout: Duration) -> Result<MemberView> {
        self.state()?;
        self.inner
            .wait_for_blocking(timeout, || self.publishers().into_iter().next())
    }

    fn subscribe_queue<T>(
        &self,
        ordered: bool,
        expected: Option<Expected>,
        decode: Decode<T>,
    ) -> Result<Subscription<T>> {
        let state = Arc::clone(self.state()?);
        Subscription::new(
            Arc::clone(&self.inner),
            state,
            ordered,
            expected,
            decode,
            false,
        )
    }

    fn subscribe_handler<T: 'static>(
        &self,
        ordered: bool,
        expected: Option<Expected>,
        decode: Decode<T>,
        handler: impl FnMut(Message<T>) + Send + 'static,
    ) -> Result<CallbackSubscription> {
        let state = Arc::clone(self.state()?);
        let inner = Arc::clone(&self.inner);
        CallbackSubscription::new(inner, state, ordered, expected, decode, handler, false)
    }

    /// The state to publish on; refuses the channels the node itself owns.
    fn publish_state(&self) -> Result<&Arc<ChannelState>> {
        let state = self.state()?;
        if state.name().as_ref() == NODES_CHANNEL {
            // Anything but a well-formed heartbeat there crashes 2.x discoverers.
            return Err(Error::InvalidName {
                name: state.name().to_string(),
                reason: NameError::Reserved,
            });
        }
        Ok(state)
    }
}

/// What a typed subscription checks payloads against; nothing for raw bytes.
fn expected<T: Schema>() -> Option<Expected> {
    (!wire::is_raw_bytes(T::SCHEMA)).then(|| Expected {
        fingerprint: wire::fingerprint_of::<T>(),
        type_name: T::SCHEMA.name,
    })
}

fn raw_payload(payload: Bytes) -> Result<Bytes, DecodeError> {
    Ok(payload)
}

fn decode_typed<T: DeserializeOwned + Schema>(payload: Bytes) -> Result<T, DecodeError> {
    wire::decode_native(&payload)
}

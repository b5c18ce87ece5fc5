//! Subscriptions to the nearest publisher of a name: the search of
//! `proto::nearest` over the publishers discovery knows, kept up to date
//! while the program receives, moving on when the publisher heard stops
//! (leaves, fails, or goes quiet) and back when a nearer one publishes.

use std::collections::{HashMap, VecDeque};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use serde::de::DeserializeOwned;

use crate::channel::Namespace;
use crate::discovery::MemberView;
use crate::error::Result;
use crate::proto::nearest::Step;
use crate::subscription::{CallbackSubscription, Message, Subscription};
use crate::sync::lock;
use crate::Schema;

/// How often the search runs again while the program receives.
const SEARCH_EVERY: Duration = Duration::from_millis(100);

/// The least time without a message after which a publisher counts as
/// quiet; a publisher that announces its period gets four periods if that
/// is longer.
pub const NEAREST_QUIET_AFTER: Duration = Duration::from_secs(1);

/// Sources of unknown address kept per channel between two searches (a
/// 2.x peer's, whose address its announcement does not give).
const MAX_STRANGERS: usize = 16;

/// Messages counted on one search step's channel, by source: those of the
/// candidates, and of at most [`MAX_STRANGERS`] others, so a flood of
/// forged sources grows nothing.
#[derive(Debug, Default, Clone)]
struct Tally {
    known: HashMap<SocketAddr, u64>,
    strangers: HashMap<SocketAddr, u64>,
}

type Counts = Arc<Mutex<Tally>>;

/// A publisher a [`NearestSubscription`] hears.
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// let laser = node.subscribe_nearest::<f64>("laser")?;
/// if let Some(p) = laser.hearing() {
///     println!("{} on {} (configuration {:?}) from {}", p.node, p.channel, p.config, p.source);
/// }
/// # Ok(()) }
/// ```
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NearestPublisher {
    /// The channel it publishes (`rover1/laser`).
    pub channel: String,
    /// The node.
    pub node: String,
    /// The configuration it runs in, empty for none.
    pub config: String,
    /// Where its messages come from: each [`Message::source`] heard is
    /// this.
    pub source: SocketAddr,
}

/// What a [`NearestSubscription`] gives: messages, and a change of the
/// publisher it hears.
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::NearestEvent;
/// let mut laser = node.subscribe_nearest::<f64>("laser")?;
/// while let Some(event) = laser.recv_event().await {
///     match event {
///         NearestEvent::Message(m) => println!("{} m", m.value),
///         NearestEvent::Switched { from, to } => println!("was {from:?}, now {to:?}"),
///     }
/// }
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub enum NearestEvent<T> {
    /// A message of the publisher heard now.
    Message(Message<T>),
    /// The subscription moved: to the nearest publisher that publishes
    /// now (`None`: there is none).
    Switched {
        /// The publisher heard until now.
        from: Option<NearestPublisher>,
        /// The publisher heard from now on.
        to: Option<NearestPublisher>,
    },
}

/// One candidate's liveness, as the subscription judges it.
#[derive(Debug, Clone, Copy)]
struct Seen {
    /// Its messages counted when last looked at, and when that count
    /// last changed (`None`: nothing came from it since it was found).
    count: u64,
    heard: Option<Instant>,
}

/// One channel of the search, watched.
struct Watched {
    channel: String,
    counts: Counts,
    /// Kept for its handler: dropping it stops the watching.
    _watch: CallbackSubscription,
}

/// A subscription to the nearest publisher of a name: made by
/// [`Namespace::subscribe_nearest`].
///
/// It hears one publisher at a time: the first in DROS's order (this
/// node's configuration before none, each from the namespace out to the
/// root) that discovery shows alive and that has published within its
/// quiet time ([`NEAREST_QUIET_AFTER`], or four of the periods it
/// announces). Messages of other publishers, on the same channel or
/// another step's, are not delivered. The search runs again while the
/// program receives (every 100 ms), so the subscription moves on when the
/// publisher stops, and back when a nearer one publishes again; each move
/// is a [`NearestEvent::Switched`] (and logged). Among publishers equally
/// near, it stays with the one it hears.
///
/// Each step's channel is subscribed as bytes (to know who publishes;
/// announced, so that a bridge carries a candidate of another site), and
/// the channel heard also typed, as [`crate::Channel::subscribe`] does:
/// messages of the candidates further out cost their bandwidth. See `docs/guide.md`,
/// "Configurations: several instances side by side".
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// // From rover1: alice's rover1/laser, alice's laser, then everyone's.
/// let mut laser = node.ns("rover1").subscribe_nearest::<f64>("laser")?;
/// while let Some(m) = laser.recv().await {
///     println!("{} m from {}", m.value, m.source);
/// }
/// # Ok(()) }
/// ```
pub struct NearestSubscription<T> {
    ns: Namespace,
    steps: Vec<Step>,
    watched: Vec<Watched>,
    seen: HashMap<(usize, SocketAddr), Seen>,
    /// The sources learnt of 2.x peers, by watched channel and session.
    learnt: HashMap<(usize, i64), SocketAddr>,
    hearing: Option<(NearestPublisher, Subscription<T>)>,
    events: VecDeque<NearestEvent<T>>,
    searched: Option<Instant>,
}

impl<T> std::fmt::Debug for NearestSubscription<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NearestSubscription")
            .field("steps", &self.steps)
            .field("hearing", &self.hearing.as_ref().map(|(p, _)| p))
            .finish_non_exhaustive()
    }
}

impl Namespace {
    /// Subscribes to the nearest publisher of `name`, in DROS's order, as
    /// [`Namespace::resolve_nearest`] finds it, and keeps it the nearest
    /// while receiving: see [`NearestSubscription`]. Fails on a bad name.
    ///
    /// ```no_run
    /// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
    /// let mut scans = node.subscribe_nearest::<Vec<f32>>("laser")?;
    /// let first = scans.recv().await;
    /// println!("{:?} from {:?}", first.map(|m| m.value.len()), scans.hearing());
    /// # Ok(()) }
    /// ```
    pub fn subscribe_nearest<T: DeserializeOwned + Schema>(
        &self,
        name: &str,
    ) -> Result<NearestSubscription<T>> {
        let steps = self.search_steps(name)?;
        let root = Namespace::root(Arc::clone(self.inner()));
        let mut watched: Vec<Watched> = Vec::new();
        for step in &steps {
            if watched.iter().any(|w| w.channel == step.channel) {
                continue;
            }
            let counts: Counts = Arc::default();
            let counting = Arc::clone(&counts);
            let channel = root.try_channel(&format!("/{}", step.channel))?;
            let watch = channel.subscribe_raw_with(move |m: Message<Bytes>| {
                let mut tally = lock(&counting);
                if let Some(count) = tally.known.get_mut(&m.source) {
                    *count += 1;
                } else if tally.strangers.len() < MAX_STRANGERS
                    || tally.strangers.contains_key(&m.source)
                {
                    *tally.strangers.entry(m.source).or_default() += 1;
                }
            })?;
            watched.push(Watched {
                channel: step.channel.clone(),
                counts,
                _watch: watch,
            });
        }
        let mut subscription = NearestSubscription {
            ns: self.clone(),
            steps,
            watched,
            seen: HashMap::new(),
            learnt: HashMap::new(),
            hearing: None,
            events: VecDeque::new(),
            searched: None,
        };
        subscription.search();
        // The first choice is no move.
        subscription.events.clear();
        Ok(subscription)
    }
}

/// Where a 2.x peer's messages on a channel come from: it announces no
/// data address (the reference package sends each channel from a socket
/// of its own), so it is learnt from what came on the channel from the
/// peer's host and from no other candidate: the busiest such source.
fn learn_source(
    strangers: &HashMap<SocketAddr, u64>,
    member: &MemberView,
    others: &[SocketAddr],
) -> Option<SocketAddr> {
    strangers
        .iter()
        .filter(|(source, _)| source.ip() == member.address.ip() && !others.contains(source))
        .max_by_key(|(source, count)| (**count, std::cmp::Reverse(**source)))
        .map(|(source, _)| *source)
}

impl<T: DeserializeOwned + Schema> NearestSubscription<T> {
    /// The publisher heard now; `None` while there is none.
    pub fn hearing(&self) -> Option<&NearestPublisher> {
        self.hearing.as_ref().map(|(p, _)| p)
    }

    /// Runs the search if it is due.
    fn search_if_due(&mut self) {
        if self.searched.is_none_or(|at| at.elapsed() >= SEARCH_EVERY) {
            self.search();
        }
    }

    /// Runs the search, moving to the publisher it finds if that is
    /// another.
    fn search(&mut self) {
        let now = Instant::now();
        self.searched = Some(now);
        let found = self.ns.nearest_publishers(&self.steps);
        // The messages counted so far (the candidates' since they were
        // found, strangers' since the last search), per watched channel.
        let counted: Vec<Tally> = self
            .watched
            .iter()
            .map(|w| lock(&w.counts).clone())
            .collect();
        let mut live: Vec<Candidate<'_>> = Vec::with_capacity(found.len());
        let mut seen = HashMap::with_capacity(found.len());
        let mut learnt = HashMap::new();
        // Every member's data address on the channels (candidates or
        // not), which no 2.x peer's source can be; read only when a 2.x
        // peer's source is to be learnt.
        let mut addresses: Option<Vec<SocketAddr>> = None;
        let steps = &self.steps;
        let mut members_addresses = || {
            let inner = self.ns.inner();
            let mut all: Vec<SocketAddr> = inner
                .fleet_members_on(&|c| steps.iter().any(|s| s.channel == c))
                .iter()
                .filter_map(|m| m.data_address)
                .collect();
            all.extend(inner.local_view().data_address);
            all
        };
        for (step, member) in &found {
            let channel = &self.steps[*step].channel;
            let Some(w) = self.watched.iter().position(|w| w.channel == *channel) else {
                continue;
            };
            let source = match member.data_address {
                Some(address) => Some(address),
                None => self.learnt.get(&(w, member.key)).copied().or_else(|| {
                    let others = addresses.get_or_insert_with(&mut members_addresses);
                    learn_source(&counted[w].strangers, member, others)
                }),
            };
            let Some(source) = source else {
                // A 2.x peer not heard on the channel yet: nothing of it
                // could be told apart.
                continue;
            };
            if member.data_address.is_none() {
                learnt.insert((w, member.key), source);
            }
            let tally = &counted[w];
            let count = tally
                .known
                .get(&source)
                .or_else(|| tally.strangers.get(&source))
                .copied()
                .unwrap_or(0);
            let entry = match self.seen.get(&(w, source)) {
                Some(before) if before.count == count => *before,
                Some(_) => Seen {
                    count,
                    heard: Some(now),
                },
                // First found: heard if something of it came already (as
                // a stranger), else quiet until it publishes, so a nearer
                // one that only announces takes nothing.
                None => Seen {
                    count,
                    heard: (count > 0).then_some(now),
                },
            };
            seen.insert((w, source), entry);
            let period = member
                .channels
                .iter()
                .find(|c| c.name == *channel)
                .map_or(0, |c| c.period_ns);
            let quiet_after = NEAREST_QUIET_AFTER.max(Duration::from_nanos(period) * 4);
            live.push(Candidate {
                step: *step,
                member,
                source,
                watched: w,
                quiet: entry
                    .heard
                    .is_none_or(|at| now.saturating_duration_since(at) > quiet_after),
            });
        }
        // A bridge publishes what it relays on its own site, from its
        // own address: the member it relays (a remote one) and the bridge
        // are then one source on one channel, and what comes from it is
        // the relayed member's. The bridge is no candidate of its own.
        let relayed: std::collections::HashSet<(usize, SocketAddr)> = live
            .iter()
            .filter(|c| c.member.remote.is_some())
            .map(|c| (c.watched, c.source))
            .collect();
        live.retain(|c| c.member.remote.is_some() || !relayed.contains(&(c.watched, c.source)));
        // From now on the candidates are counted, and they only (with
        // room for a few strangers): a source that is none grows nothing,
        // however many it forges. Counts go on from where they are, what
        // came meanwhile included.
        for (w, watched) in self.watched.iter().enumerate() {
            let mut tally = lock(&watched.counts);
            let known: HashMap<SocketAddr, u64> = live
                .iter()
                .filter(|c| c.watched == w)
                .map(|c| {
                    let count = tally
                        .known
                        .get(&c.source)
                        .or(tally.strangers.get(&c.source));
                    (c.source, count.copied().unwrap_or(0))
                })
                .collect();
            tally.known = known;
            tally.strangers.clear();
        }
        self.seen = seen;
        self.learnt = learnt;
        let heard = |c: &&Candidate<'_>| {
            self.hearing.as_ref().is_some_and(|(p, _)| {
                p.channel == self.steps[c.step].channel && p.source == c.source
            })
        };
        let choice = match live.iter().find(|c| !c.quiet) {
            // The first that is not quiet; among those of its step, the
            // one heard now stays.
            Some(first) => live
                .iter()
                .filter(|c| !c.quiet && c.step == first.step)
                .find(heard)
                .or(Some(first)),
            // All quiet: the one heard stays while it is there, else the
            // nearest alive.
            None => live.iter().find(heard).or(live.first()),
        };
        let to = choice.map(|c| NearestPublisher {
            channel: self.steps[c.step].channel.clone(),
            node: c.member.name.clone(),
            config: c.member.config.clone(),
            source: c.source,
        });
        if to.as_ref() != self.hearing() {
            self.switch(to);
        }
    }

    /// Moves to `to`, subscribing its channel if it is another.
    fn switch(&mut self, to: Option<NearestPublisher>) {
        let from = self.hearing.take();
        let from_publisher = from.as_ref().map(|(p, _)| p.clone());
        match &to {
            Some(p) => tracing::info!(
                channel = %p.channel,
                node = %p.node,
                "the nearest publisher heard is now {} on {}",
                p.node,
                p.channel
            ),
            None => tracing::info!(
                from = ?from_publisher.as_ref().map(|p| &p.node),
                "no publisher of the nearest subscription is left"
            ),
        }
        if let Some(publisher) = &to {
            let subscription = match from {
                Some((old, subscription)) if old.channel == publisher.channel => Ok(subscription),
                _ => Namespace::root(Arc::clone(self.ns.inner()))
                    .channel(&format!("/{}", publisher.channel))
                    .subscribe::<T>(),
            };
            match subscription {
                Ok(subscription) => self.hearing = Some((publisher.clone(), subscription)),
                // A channel the search found always subscribes; if it
                // can't (the node stopped), nothing is heard.
                Err(e) => tracing::warn!("nearest subscription not moved: {e}"),
            }
        }
        self.events.push_back(NearestEvent::Switched {
            from: from_publisher,
            to: self.hearing().cloned(),
        });
    }

    /// Whether `m` is the heard publisher's (else it is dropped).
    fn is_heard(&self, m: &Message<T>) -> bool {
        self.hearing
            .as_ref()
            .is_some_and(|(p, _)| p.source == m.source)
    }

    /// What is given before waiting for a message: a move not given yet
    /// (the search runs first if it is due), or the end once the node has
    /// stopped; `None` to wait.
    fn before_waiting(&mut self) -> Option<Option<NearestEvent<T>>> {
        if let Some(event) = self.events.pop_front() {
            return Some(Some(event));
        }
        if self.ns.inner().is_stopped() {
            return Some(None);
        }
        self.search_if_due();
        self.events.pop_front().map(Some)
    }

    /// The next message of the publisher heard, or a move; `None` once the
    /// node has stopped.
    pub async fn recv_event(&mut self) -> Option<NearestEvent<T>> {
        loop {
            if let Some(given) = self.before_waiting() {
                return given;
            }
            let wait = SEARCH_EVERY;
            let Some((_, subscription)) = &mut self.hearing else {
                tokio::time::sleep(wait).await;
                continue;
            };
            match tokio::time::timeout(wait, subscription.recv()).await {
                Ok(Some(m)) if self.is_heard(&m) => return Some(NearestEvent::Message(m)),
                Ok(Some(_)) | Err(_) => {}
                Ok(None) => return None,
            }
        }
    }

    /// Like [`NearestSubscription::recv_event`], blocking the thread up to
    /// `timeout` (`None` also when nothing came in time).
    pub fn recv_event_timeout(&mut self, timeout: Duration) -> Option<NearestEvent<T>> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(given) = self.before_waiting() {
                return given;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return None;
            }
            let wait = SEARCH_EVERY.min(left);
            let Some((_, subscription)) = &mut self.hearing else {
                std::thread::sleep(wait);
                continue;
            };
            if let Some(m) = subscription.recv_timeout(wait) {
                if self.is_heard(&m) {
                    return Some(NearestEvent::Message(m));
                }
            }
        }
    }

    /// The next message of the publisher heard (moves are skipped: see
    /// [`NearestSubscription::hearing`]); `None` once the node has stopped.
    pub async fn recv(&mut self) -> Option<Message<T>> {
        loop {
            match self.recv_event().await? {
                NearestEvent::Message(m) => return Some(m),
                NearestEvent::Switched { .. } => {}
            }
        }
    }

    /// Like [`NearestSubscription::recv`], blocking the thread up to
    /// `timeout` (`None` also when nothing came in time).
    pub fn recv_timeout(&mut self, timeout: Duration) -> Option<Message<T>> {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.recv_event_timeout(left)? {
                NearestEvent::Message(m) => return Some(m),
                NearestEvent::Switched { .. } => {}
            }
        }
    }
}

/// A publisher the search found, as the subscription judges it.
struct Candidate<'a> {
    /// Its step of the search.
    step: usize,
    member: &'a MemberView,
    source: SocketAddr,
    /// The index of its channel's watch.
    watched: usize,
    /// Whether nothing came from it for its quiet time.
    quiet: bool,
}

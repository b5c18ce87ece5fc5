//! Raw clients: which server a call goes to, and the checks before it
//! leaves (types, keys).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::call::{Driving, RawCall};
use super::nearest::Nearest;
use super::service_names;
use super::Held;
use super::TARGETS_FRESH;
use crate::channel::Namespace;
use crate::discovery::MemberView;
use crate::error::{Error, NameError, Result};
use crate::runtime::calling::{CallDriver, CallTo};
use crate::runtime::services::{LocalServer, RequestTx};
use crate::runtime::{ChannelState, Inner};
use crate::sync::lock;
use crate::wire::service::{self as wire};
use crate::DEFAULT_DEADLINE;
use pulicast_discovery::wire::TypeInfo;

#[derive(Debug, Default, Clone)]
pub(super) struct Types {
    pub(super) request: Option<TypeInfo>,
    pub(super) reply: Option<TypeInfo>,
    pub(super) progress: Option<TypeInfo>,
}

/// Where a call goes.
#[derive(Clone)]
pub(super) enum Target {
    /// This node's own server.
    Local(Arc<dyn LocalServer>),
    /// A server elsewhere.
    Remote(Arc<MemberView>, SocketAddr),
}

impl Target {
    fn node<'a>(&'a self, own: &'a str) -> &'a str {
        match self {
            Target::Local(_) => own,
            Target::Remote(m, _) => &m.name,
        }
    }
}

pub(super) struct ClientCore {
    pub(super) inner: Arc<Inner>,
    pub(super) service: Arc<str>,
    pub(super) target: Option<String>,
    /// The name as given (without `@node`) and the namespace it was given
    /// in: where a search for the nearest server starts.
    pub(super) asked: (String, String),
    pub(super) channel: Arc<ChannelState>,
    /// Where its requests leave from.
    pub(super) request: Arc<RequestTx>,
    /// The servers last found, and when.
    targets: Mutex<Option<(Instant, Vec<Target>)>>,
    pub(super) types: Types,
    next: AtomicUsize,
    _held: Held,
}

impl Drop for ClientCore {
    fn drop(&mut self) {
        self.inner.release_answers(&self.channel);
    }
}

/// A client whose messages are bytes: made by [`Namespace::raw_client`].
/// Typed clients ([`Client`](crate::Client)) are built on it.
///
/// ```no_run
/// # fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use std::time::Duration;
/// // Forwards each goal published on a channel to the planner, as the bytes
/// // came (fingerprint first: the server checks the type as for typed calls).
/// let plan = node.raw_client("plan")?;
/// let mut goals = node.channel("goals").subscribe_raw()?;
/// while let Some(goal) = goals.recv_blocking() {
///     println!("{} is served by {:?}", plan.service(), plan.servers());
///     let mut call = plan.start_blocking(&goal.value, Duration::from_secs(2))?;
///     while let Some(event) = call.next_blocking() {
///         println!("{event:?}");
///     }
/// }
/// # Ok(()) }
/// ```
#[derive(Clone)]
pub struct RawClient {
    pub(super) core: Arc<ClientCore>,
    pub(super) deadline: Duration,
    /// The search, for a client of the nearest server.
    pub(super) nearest: Option<Arc<Nearest>>,
}

impl std::fmt::Debug for RawClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawClient")
            .field("service", &self.core.service)
            .field("target", &self.core.target)
            .finish_non_exhaustive()
    }
}

/// One server's answer to [`Client::call_all`](crate::Client::call_all).
///
/// ```no_run
/// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
/// use pulicast::Answer;
/// // Every rover's battery, one answer per server, failures among them.
/// let battery = node.client::<String, f32>("battery")?;
/// for Answer { node, result } in battery.call_all(&"charge".to_string()).await? {
///     match result {
///         Ok(charge) => println!("{node}: {:.0} %", charge * 100.0),
///         Err(e) => eprintln!("{node}: {e}"),
///     }
/// }
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub struct Answer<T> {
    /// The server node.
    pub node: String,
    /// Its reply, or why there is none.
    pub result: Result<T>,
}

impl RawClient {
    pub(super) fn new(ns: &Namespace, name: &str, types: Types) -> Result<Self> {
        let (name, target) = match name.split_once(wire::TARGET_MARK) {
            Some((name, node)) if !node.is_empty() => (name, Some(node.to_string())),
            Some(_) => {
                return Err(Error::InvalidName {
                    name: name.to_string(),
                    reason: NameError::Empty,
                })
            }
            None => (name, None),
        };
        let (service, request) = service_names(ns, name)?;
        let inner = Arc::clone(ns.inner());
        let channel = inner.channel_state(&request);
        let request_tx = inner.hold_answers(&channel)?;
        let mut held = Held::new(&inner);
        held.hold(&inner, Arc::clone(&channel), true, types.request.clone());
        let reply = inner.channel_state(&format!("{request}{}", wire::REPLY));
        held.hold(&inner, reply, false, types.reply.clone());
        if types.progress.is_some() {
            let progress = inner.channel_state(&format!("{request}{}", wire::PROGRESS));
            held.hold(&inner, progress, false, types.progress.clone());
        }
        Ok(Self {
            core: Arc::new(ClientCore {
                inner,
                service: service.into(),
                target,
                asked: (name.to_string(), ns.path().to_string()),
                channel,
                request: request_tx,
                targets: Mutex::new(None),
                types,
                next: AtomicUsize::new(0),
                _held: held,
            }),
            deadline: DEFAULT_DEADLINE,
            nearest: None,
        })
    }

    /// The same client with another default deadline.
    pub fn with_deadline(mut self, deadline: Duration) -> Self {
        self.deadline = deadline;
        self
    }

    /// The service's full name, with `@node` if the client targets one.
    pub fn service(&self) -> String {
        match &self.core.target {
            Some(node) => format!("{}@{node}", self.core.service),
            None => self.core.service.to_string(),
        }
    }

    /// The nodes that serve the service now (this node first if it does),
    /// as discovery knows them. For a client of the nearest server
    /// ([`RawClient::nearest`]), each as `service@node` (they may serve
    /// different names: `rover1/laser@driver_a`), in the order a call
    /// tries them; those that can't answer this client (types, keys) are
    /// left out.
    pub fn servers(&self) -> Vec<String> {
        if let Some(nearest) = &self.nearest {
            return self.nearest_servers(nearest);
        }
        let own = self.core.inner.name();
        self.targets()
            .iter()
            .map(|t| t.node(own).to_string())
            .collect()
    }

    /// The servers as discovery knew them at most [`TARGETS_FRESH`] ago:
    /// reading the fleet for every call would cost more than the call.
    fn targets(&self) -> Vec<Target> {
        // This node's own server is looked up every time: a server dropped
        // serves no more calls.
        let core = &self.core;
        let mut targets = Vec::new();
        if core
            .target
            .as_deref()
            .is_none_or(|t| t == core.inner.name())
        {
            if let Some(server) = core.inner.local_server(core.channel.name()) {
                targets.push(Target::Local(server));
            }
        }
        let mut cache = lock(&core.targets);
        let fresh = cache
            .as_ref()
            .filter(|(at, remote)| at.elapsed() < TARGETS_FRESH && !remote.is_empty());
        match fresh {
            Some((_, remote)) => targets.extend(remote.iter().cloned()),
            None => {
                let remote = self.find_targets();
                targets.extend(remote.iter().cloned());
                *cache = Some((Instant::now(), remote));
            }
        }
        targets
    }

    /// The servers elsewhere, from discovery, in a stable order.
    fn find_targets(&self) -> Vec<Target> {
        let core = &self.core;
        let inner = &core.inner;
        let wanted = |node: &str| core.target.as_deref().is_none_or(|t| t == node);
        let mut targets = Vec::new();
        let request = core.channel.name();
        let me = inner.compat_session_id();
        // The request channel and what is announced beside it (replies,
        // sealing): all that choosing and checking a server looks at.
        for member in inner.fleet_members_on(&|c| c.starts_with(&**request)) {
            if !member.is_live() || member.compat || !wanted(&member.name) {
                continue;
            }
            // A member this node relays (a bridge's) is reached through
            // this node: calling it from here would go nowhere.
            if member.remote.as_ref().is_some_and(|r| r.bridge == me) {
                continue;
            }
            if !member.serves(request) {
                continue;
            }
            if let Some(address) = member.data_address {
                targets.push(Target::Remote(Arc::new(member), address));
            }
        }
        // In a stable order, so that calls take turns.
        targets.sort_by(|a, b| match (a, b) {
            (Target::Remote(a, _), Target::Remote(b, _)) => (&a.name, a.key).cmp(&(&b.name, b.key)),
            (Target::Local(_), _) => std::cmp::Ordering::Less,
            (_, Target::Local(_)) => std::cmp::Ordering::Greater,
        });
        targets
    }

    /// A wait for a server that timed out is [`Error::NoServer`].
    pub(super) fn no_server_in_time(&self, e: Error) -> Error {
        match e {
            Error::Timeout(_) => self.no_server(),
            e => e,
        }
    }

    fn no_server(&self) -> Error {
        let reason = match &self.core.target {
            Some(node) => format!("node {node} does not serve it (or was not found in time)"),
            None => "no node serves it (or none was found in time)".to_string(),
        };
        Error::NoServer {
            service: self.service(),
            reason,
        }
    }

    /// One server, waiting for discovery until `deadline`: this node's
    /// own if it serves, else the next of the others in turn.
    async fn pick(&self, deadline: Instant) -> Result<Target> {
        if let Some(found) = self.choose(self.targets()) {
            return Ok(found);
        }
        let left = deadline.saturating_duration_since(Instant::now());
        let found = self
            .core
            .inner
            .wait_for(left, || self.choose(self.targets()))
            .await;
        found.map_err(|e| self.no_server_in_time(e))
    }

    fn pick_blocking(&self, deadline: Instant) -> Result<Target> {
        let left = deadline.saturating_duration_since(Instant::now());
        let found = self
            .core
            .inner
            .wait_for_blocking(left, || self.choose(self.targets()));
        found.map_err(|e| self.no_server_in_time(e))
    }

    fn choose(&self, mut targets: Vec<Target>) -> Option<Target> {
        if targets.is_empty() {
            return None;
        }
        if matches!(targets[0], Target::Local(_)) {
            return Some(targets.swap_remove(0));
        }
        let turn = self.core.next.fetch_add(1, Ordering::Relaxed);
        Some(targets.swap_remove(turn % targets.len()))
    }

    /// Refuses at once a call that can't succeed: types that differ from
    /// the server's, or keys on one side only.
    pub(super) fn check(&self, target: &Target) -> Result<()> {
        let Target::Remote(member, _) = target else {
            return Ok(());
        };
        let request = self.core.channel.name();
        let announced = |name: &str, publishes: bool| {
            member
                .channels
                .iter()
                .find(|c| c.name == name && if publishes { c.publishes } else { c.subscribes })
        };
        let mismatch =
            |what: &str, ours: &Option<TypeInfo>, theirs: Option<&TypeInfo>| match (ours, theirs) {
                (Some(ours), Some(theirs)) if ours.fingerprint != theirs.fingerprint => {
                    Err(Error::ServiceTypeMismatch {
                        service: self.service(),
                        node: member.name.clone(),
                        reason: format!(
                            "the server takes {what} of type {}, this client's are {}",
                            theirs.name, ours.name
                        ),
                    })
                }
                _ => Ok(()),
            };
        let types = &self.core.types;
        let theirs = announced(request, false).and_then(|c| c.message_type.as_ref());
        mismatch("requests", &types.request, theirs)?;
        let reply = format!("{request}{}", wire::REPLY);
        let theirs = announced(&reply, true).and_then(|c| c.message_type.as_ref());
        mismatch("replies", &types.reply, theirs)?;
        let sealed_there = announced(&format!("{request}{}", wire::SEALED), true).is_some();
        let sealed_here = self.core.channel.is_sealed();
        if sealed_there != sealed_here {
            let reason = match sealed_here {
                false => format!("{} seals it and this node holds no key for it", member.name),
                true => format!("this node seals it and {} holds no key for it", member.name),
            };
            return Err(Error::NotAuthorised {
                service: self.service(),
                reason,
            });
        }
        Ok(())
    }

    pub(super) fn launch(
        &self,
        target: Target,
        message: &[u8],
        deadline: Instant,
        within: Duration,
    ) -> Result<RawCall> {
        let core = &self.core;
        let node = target.node(core.inner.name()).to_string();
        let to = match target {
            Target::Local(server) => CallTo::Local(server),
            Target::Remote(member, address) => CallTo::Remote(member.key, address),
        };
        let driver = CallDriver::launch(
            &core.inner,
            &core.request,
            Arc::clone(&core.service),
            &node,
            to,
            message,
            deadline,
        )?;
        Ok(RawCall::new(
            self.clone(),
            Driving::One(driver),
            node,
            within,
        ))
    }

    /// Starts a call of `message` (fingerprint first): waits for a server
    /// (within the deadline), checks it can answer, sends the request.
    pub async fn start(&self, message: &[u8], within: Duration) -> Result<RawCall> {
        if let Some(nearest) = &self.nearest {
            return self.start_nearest(nearest, message, within).await;
        }
        let deadline = Instant::now() + within;
        let target = self.pick(deadline).await?;
        self.check(&target)?;
        self.launch(target, message, deadline, within)
    }

    /// Like [`RawClient::start`], blocking the thread while it waits for
    /// a server.
    pub fn start_blocking(&self, message: &[u8], within: Duration) -> Result<RawCall> {
        if let Some(nearest) = &self.nearest {
            return self.start_nearest_blocking(nearest, message, within);
        }
        let deadline = Instant::now() + within;
        let target = self.pick_blocking(deadline)?;
        self.check(&target)?;
        self.launch(target, message, deadline, within)
    }

    /// Calls every server known once one is, each with its own request:
    /// per server node, its call, or why it could not be made (types or
    /// keys that differ, a request that can't be sent).
    pub async fn start_all(
        &self,
        message: &[u8],
        within: Duration,
    ) -> Result<Vec<(String, Result<RawCall>)>> {
        if let Some(nearest) = &self.nearest {
            return self.start_all_nearest(nearest, message, within).await;
        }
        let deadline = Instant::now() + within;
        let left = within;
        let inner = &self.core.inner;
        let targets = inner
            .wait_for(left, || Some(self.targets()).filter(|t| !t.is_empty()))
            .await
            .map_err(|e| self.no_server_in_time(e))?;
        let own = inner.name();
        let calls = targets
            .into_iter()
            .map(|target| {
                let node = target.node(own).to_string();
                let call = self
                    .check(&target)
                    .and_then(|()| self.launch(target, message, deadline, within));
                (node, call)
            })
            .collect();
        Ok(calls)
    }
}

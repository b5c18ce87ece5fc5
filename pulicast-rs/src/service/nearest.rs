//! Clients of the nearest server: the search of `proto::nearest` over
//! the servers discovery knows, each call walking the candidates it finds
//! (`runtime::walking`).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::call::{Driving, RawCall};
use super::client::{RawClient, Target};
use super::TARGETS_FRESH;
use crate::channel::Namespace;
use crate::discovery::MemberView;
use crate::error::{Error, Result};
use crate::proto::nearest::{candidates, search_steps, Seeker, Step};
use crate::runtime::calling::{CallDriver, CallTo};
use crate::runtime::walking::{tried_text, Candidate, Passed, Remembered, Tried, Walk};
use crate::sync::lock;

/// A client's search: its steps, and a client of each name they ask.
pub(super) struct Nearest {
    steps: Vec<Step>,
    /// One client per service name of the steps (the innermost first).
    clients: Vec<RawClient>,
    /// Per step, the index of its name's client.
    client_of: Vec<usize>,
    memory: Remembered,
    /// The last search over discovery, and when.
    found: Mutex<Option<(Instant, Arc<Found>)>>,
}

/// What one search over discovery found.
struct Found {
    members: Vec<MemberView>,
    /// (step, member) pairs, in the search's order.
    order: Vec<(usize, usize)>,
}

/// What one search found: the servers to try in order, those refused by
/// the client's checks, and per candidate the index of its client.
struct Plan {
    candidates: Vec<Candidate>,
    clients: Vec<usize>,
    refused: Vec<(Tried, Error)>,
}

impl RawClient {
    /// The same client, calling the nearest server instead of any: the
    /// servers in this node's configuration ([`crate::NodeBuilder::config`])
    /// before those of none, each from the client's namespace out to the
    /// root, as [`Namespace::resolve_nearest`] finds channels. A call goes
    /// to the first server in that order, passes over one that is busy,
    /// gone, can't answer this client (types, keys) or stays silent for
    /// its share of the deadline, and tries the next; when none takes it,
    /// it fails [`Error::NoServer`] listing what was tried and why. Every
    /// call searches anew, so a nearer server that starts (again) gets the
    /// next call; among servers equally near, the one that answered last
    /// keeps the calls. See `docs/services.md`, "The nearest server".
    ///
    /// ```no_run
    /// # async fn demo(node: pulicast::Node) -> pulicast::Result<()> {
    /// // From rover1/arm: rover1/arm/laser, rover1/laser, then laser.
    /// let laser = node.ns("rover1/arm").raw_client("laser")?.nearest()?;
    /// println!("in order: {:?}", laser.servers());
    /// let call = laser.start(b"12345678", std::time::Duration::from_secs(2)).await?;
    /// println!("{} has it", call.node());
    /// # Ok(()) }
    /// ```
    pub fn nearest(mut self) -> Result<Self> {
        if self.nearest.is_some() {
            return Ok(self);
        }
        let core = &self.core;
        let (name, namespace) = &core.asked;
        let steps = search_steps(name, namespace, core.inner.config())?;
        let root = Namespace::root(Arc::clone(&core.inner));
        let at = core
            .target
            .as_ref()
            .map_or_else(String::new, |node| format!("@{node}"));
        let mut clients: Vec<RawClient> = Vec::new();
        let mut client_of = Vec::with_capacity(steps.len());
        for step in &steps {
            let known = clients
                .iter()
                .position(|c| *c.core.service == *step.channel);
            let index = match known {
                Some(index) => index,
                None => {
                    let client = if *core.service == *step.channel {
                        self.clone()
                    } else {
                        let name = format!("/{}{at}", step.channel);
                        RawClient::new(&root, &name, core.types.clone())?
                            .with_deadline(self.deadline)
                    };
                    clients.push(client);
                    clients.len() - 1
                }
            };
            client_of.push(index);
        }
        self.nearest = Some(Arc::new(Nearest {
            steps,
            clients,
            client_of,
            memory: Arc::default(),
            found: Mutex::new(None),
        }));
        Ok(self)
    }

    /// The servers in the order a call tries them, as `service@node`
    /// (they may serve different names).
    pub(super) fn nearest_servers(&self, nearest: &Nearest) -> Vec<String> {
        let plan = self.plan(nearest);
        plan.candidates
            .iter()
            .map(|c| format!("{}@{}", c.service, c.node))
            .collect()
    }

    /// The candidates now, in the search's order.
    /// The members that provide a step, and the candidates among them in
    /// the search's order, as discovery knew them at most
    /// [`TARGETS_FRESH`] ago (reading the fleet for every call would cost
    /// more than the call; a server gone meanwhile is passed over by the
    /// call).
    fn searched(&self, nearest: &Nearest) -> Arc<Found> {
        let mut cache = lock(&nearest.found);
        if let Some((at, found)) = &*cache {
            if at.elapsed() < TARGETS_FRESH && !found.order.is_empty() {
                return Arc::clone(found);
            }
        }
        let found = Arc::new(self.search(nearest));
        *cache = Some((Instant::now(), Arc::clone(&found)));
        found
    }

    fn search(&self, nearest: &Nearest) -> Found {
        let inner = &self.core.inner;
        let requests: Vec<&str> = nearest
            .clients
            .iter()
            .map(|c| &**c.core.channel.name())
            .collect();
        let mut members = inner.fleet_members_on(&|c| requests.iter().any(|r| c.starts_with(r)));
        members.push(inner.local_view());
        let me = inner.compat_session_id();
        let target = self.core.target.as_deref();
        let client_at = |channel: &str| {
            nearest
                .clients
                .iter()
                .position(|c| *c.core.service == *channel)
        };
        let provides = |m: &MemberView, channel: &str| {
            let Some(client) = client_at(channel).map(|i| &nearest.clients[i]) else {
                return false;
            };
            let request = client.core.channel.name();
            if target.is_some_and(|t| t != m.name) {
                return false;
            }
            if m.key == me {
                return inner.local_server(request).is_some();
            }
            // A member this node relays (a bridge's) is reached through
            // this node: calling it from here would go nowhere.
            let relayed_here = m.remote.as_ref().is_some_and(|r| r.bridge == me);
            !m.compat && !relayed_here && m.data_address.is_some() && m.serves(request)
        };
        let seeker = Seeker {
            key: me,
            host: inner.host(),
        };
        let order = candidates(&nearest.steps, &members, seeker, provides);
        Found { members, order }
    }

    fn plan(&self, nearest: &Nearest) -> Plan {
        let inner = &self.core.inner;
        let me = inner.compat_session_id();
        let found = self.searched(nearest);
        let members = &found.members;
        let mut order = found.order.clone();
        self.remembered_first(nearest, members, &mut order);
        let mut plan = Plan {
            candidates: Vec::new(),
            clients: Vec::new(),
            refused: Vec::new(),
        };
        for (step, m) in order {
            let index = nearest.client_of[step];
            let client = &nearest.clients[index];
            let member = &members[m];
            let target = match (member.key == me, member.data_address) {
                (true, _) => match inner.local_server(client.core.channel.name()) {
                    Some(server) => Target::Local(server),
                    None => continue,
                },
                (false, Some(address)) => Target::Remote(Arc::new(member.clone()), address),
                (false, None) => continue,
            };
            let node = match &target {
                Target::Local(_) => inner.name().to_string(),
                Target::Remote(member, _) => member.name.clone(),
            };
            let service = Arc::clone(&client.core.service);
            if let Err(e) = client.check(&target) {
                let why = Passed::Refused(e.to_string());
                plan.refused.push((Tried { node, service, why }, e));
                continue;
            }
            let to = match target {
                Target::Local(server) => CallTo::Local(server),
                Target::Remote(member, address) => CallTo::Remote(member.key, address),
            };
            plan.candidates.push(Candidate {
                node,
                key: member.key,
                service,
                request: Arc::clone(&client.core.request),
                to,
                relayed: member.remote.is_some(),
            });
            plan.clients.push(index);
        }
        plan
    }

    /// Moves the server that answered last to the front of its step
    /// (among servers equally near, calls stay where they went), and
    /// those passed over lately behind all others.
    fn remembered_first(
        &self,
        nearest: &Nearest,
        members: &[MemberView],
        order: &mut [(usize, usize)],
    ) {
        let memory = lock(&nearest.memory);
        let is = |(service, key): &(Arc<str>, i64), &(step, m): &(usize, usize)| {
            members[m].key == *key && *nearest.steps[step].channel == **service
        };
        let last = memory
            .last()
            .and_then(|last| order.iter().position(|c| is(last, c)));
        if let Some(at) = last {
            let step = order[at].0;
            let first = order.iter().position(|&(s, _)| s == step).unwrap_or(at);
            order[first..=at].rotate_right(1);
        }
        let now = Instant::now();
        // Stable: the order holds among the lately passed over too.
        order.sort_by_key(|&(step, m)| {
            memory.passed_lately(&nearest.steps[step].channel, members[m].key, now)
        });
    }

    /// The candidates once there are any (or servers that refuse this
    /// client), waiting for discovery until `deadline`.
    async fn plan_in_time(&self, nearest: &Nearest, deadline: Instant) -> Result<Plan> {
        let left = deadline.saturating_duration_since(Instant::now());
        let found = self.core.inner.wait_for(left, || self.found(nearest)).await;
        found.map_err(|e| self.no_server_in_time(e))
    }

    fn found(&self, nearest: &Nearest) -> Option<Plan> {
        let plan = self.plan(nearest);
        (!plan.candidates.is_empty() || !plan.refused.is_empty()).then_some(plan)
    }

    /// The walk over `plan`'s candidates, as a call.
    fn walk(
        &self,
        nearest: &Nearest,
        plan: Plan,
        message: &[u8],
        deadline: Instant,
        within: Duration,
    ) -> Result<RawCall> {
        let refused = plan.refused.into_iter().map(|(tried, _)| tried).collect();
        let inner = &self.core.inner;
        let memory = Arc::clone(&nearest.memory);
        match Walk::start(inner, plan.candidates, refused, message, deadline, memory) {
            Ok(walk) => Ok(RawCall::new(
                self.clone(),
                Driving::Walk(Box::new(walk)),
                String::new(),
                within,
            )),
            Err(tried) => Err(Error::NoServer {
                service: self.service(),
                reason: format!("no server took the call: {}", tried_text(&tried)),
            }),
        }
    }

    pub(super) async fn start_nearest(
        &self,
        nearest: &Nearest,
        message: &[u8],
        within: Duration,
    ) -> Result<RawCall> {
        let deadline = Instant::now() + within;
        let plan = self.plan_in_time(nearest, deadline).await?;
        self.walk(nearest, plan, message, deadline, within)
    }

    pub(super) fn start_nearest_blocking(
        &self,
        nearest: &Nearest,
        message: &[u8],
        within: Duration,
    ) -> Result<RawCall> {
        let deadline = Instant::now() + within;
        let left = within;
        let plan = self
            .core
            .inner
            .wait_for_blocking(left, || self.found(nearest))
            .map_err(|e| self.no_server_in_time(e))?;
        self.walk(nearest, plan, message, deadline, within)
    }

    /// Every candidate called at once, in the search's order; those the
    /// client's checks refuse with why.
    pub(super) async fn start_all_nearest(
        &self,
        nearest: &Nearest,
        message: &[u8],
        within: Duration,
    ) -> Result<Vec<(String, Result<RawCall>)>> {
        let deadline = Instant::now() + within;
        let plan = self.plan_in_time(nearest, deadline).await?;
        let inner = &self.core.inner;
        let mut calls = Vec::new();
        for (candidate, index) in plan.candidates.into_iter().zip(plan.clients) {
            let client = &nearest.clients[index];
            let launched = CallDriver::launch(
                inner,
                &candidate.request,
                candidate.service,
                &candidate.node,
                candidate.to,
                message,
                deadline,
            );
            let call = launched.map(|driver| {
                let node = candidate.node.clone();
                RawCall::new(client.clone(), Driving::One(driver), node, within)
            });
            calls.push((candidate.node, call));
        }
        calls.extend(plan.refused.into_iter().map(|(t, e)| (t.node, Err(e))));
        Ok(calls)
    }
}

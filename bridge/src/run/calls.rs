//! Calls between sites: relay servers that answer here for other sites'
//! servers and pass their calls on, and the calls of other sites run on
//! this site's servers. Bounded on both sides: a site's callers can't hold
//! more of another site's bridge than its share.

use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::{Duration, Instant};

use pulicast::{CallContext, CallEvent, Fault};
use tokio::sync::Notify;
use zenoh::qos::CongestionControl;
use zenoh::query::{ConsolidationMode, Query};
use zenoh::sample::Locality;
use zenoh::Session;

use super::control::Applied;
use super::{printable, Shared};
use crate::call::{CallAnswer, CallCancel, CallRequest};
use crate::plan::Plan;

/// Calls one bridge runs at once for the servers of its site (for all
/// other sites together); more are answered `UNREACHABLE` (busy).
const MAX_CALLS: usize = 1024;

/// Calls one relay server (one service) passes on at once.
const RELAY_CONCURRENCY: usize = 256;

/// Clients kept for the services of this site that other sites call.
const MAX_CLIENTS: usize = 1024;

/// The longest a call between sites runs (a server's own bound,
/// `pulicast::ServiceLimits::longest`, by default).
const LONGEST_CALL: Duration = Duration::from_secs(300);

/// Most progress messages one call passes on.
const MAX_PROGRESS: u32 = 65_536;

/// Bytes a service frame adds to its message (kind, call id, counts): an
/// answer larger than pulicast's largest message less this can't be sent.
const FRAME_OVERHEAD: usize = 64;

/// Answers here for the servers of other sites: one relay server per
/// service, taking the calls whose target is one of them.
pub(super) fn apply_services(shared: &Arc<Shared>, plan: &Plan, applied: &mut Applied) {
    *shared.serving.write() = plan.services.clone();
    applied
        .relay_servers
        .retain(|service, _| plan.services.contains_key(service));
    for service in plan.services.keys() {
        if applied.relay_servers.contains_key(service) {
            continue;
        }
        match relay_server(shared, service) {
            Ok(server) => {
                applied.relay_servers.insert(service.clone(), server);
            }
            Err(e) => tracing::warn!(service = %printable(service), "not answered for here: {e}"),
        }
    }
}

fn relay_server(shared: &Arc<Shared>, service: &str) -> pulicast::Result<pulicast::Server> {
    let weak = Arc::downgrade(shared);
    let name = service.to_owned();
    let answers_for = move |target: &str| {
        weak.upgrade().is_some_and(|shared| {
            shared
                .serving
                .read()
                .get(&name)
                .is_some_and(|nodes| nodes.contains_key(target))
        })
    };
    let weak = Arc::downgrade(shared);
    let name = service.to_owned();
    shared
        .node
        .make_namespace("/")
        .server(service)
        .concurrency(RELAY_CONCURRENCY)
        .serve_for(answers_for, move |message, context| {
            let weak = weak.clone();
            let name = name.clone();
            async move {
                match weak.upgrade() {
                    Some(shared) => pass_on(&shared, &name, message, context).await,
                    None => Err(Fault::new(Fault::UNREACHABLE, "the bridge stopped")),
                }
            }
        })
}

/// Tells the server's site that a call passed on was cancelled, unless it
/// ended first.
struct CancelOnDrop {
    session: Session,
    key: String,
    cancel: CallCancel,
    armed: bool,
}

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        if !self.armed {
            return;
        }
        let session = self.session.clone();
        let key = std::mem::take(&mut self.key);
        let bytes = self.cancel.encode();
        if let Ok(runtime) = tokio::runtime::Handle::try_current() {
            runtime.spawn(async move {
                // Not dropped under congestion: a lost cancel keeps a
                // call running to its deadline.
                let _ = session
                    .put(key, bytes)
                    .congestion_control(CongestionControl::Block)
                    .await;
            });
        }
    }
}

/// Passes a call of this site on to the bridge of the server's site, and
/// its progress and answer back.
async fn pass_on(
    shared: &Arc<Shared>,
    service: &str,
    message: pulicast::Bytes,
    context: CallContext<()>,
) -> Result<Vec<u8>, Fault> {
    let unreachable = |why: String| Fault::new(Fault::UNREACHABLE, why);
    let target = context.target().to_owned();
    let bridge = shared
        .serving
        .read()
        .get(service)
        .and_then(|nodes| nodes.get(&target))
        .copied()
        .ok_or_else(|| {
            unreachable(format!(
                "{target} is no longer reachable through this bridge"
            ))
        })?;
    let left = context.deadline().map_or(Duration::from_secs(300), |d| {
        d.saturating_duration_since(Instant::now())
    });
    let id = shared.next_call.fetch_add(1, Relaxed);
    let request = CallRequest {
        bridge: shared.me,
        id,
        service: service.to_owned(),
        target,
        deadline_ms: u32::try_from(left.as_millis()).unwrap_or(u32::MAX).max(1),
        message: message.to_vec(),
    };
    let keys = &shared.checked.keys;
    shared.counters.calls_out.fetch_add(1, Relaxed);
    let replies = shared
        .session
        .get(keys.calls(bridge))
        .payload(request.encode())
        .consolidation(ConsolidationMode::None)
        .allowed_destination(Locality::Remote)
        .timeout(left + Duration::from_millis(500))
        .await
        .map_err(|e| unreachable(format!("the server's site: {e}")))?;
    let mut cancel = CancelOnDrop {
        session: shared.session.clone(),
        key: keys.cancels(bridge),
        cancel: CallCancel {
            bridge: shared.me,
            id,
        },
        armed: true,
    };
    let fits = |m: &[u8]| m.len() + FRAME_OVERHEAD <= pulicast::MAX_MESSAGE;
    let mut progress = 0u32;
    while let Ok(reply) = replies.recv_async().await {
        let Ok(sample) = reply.result() else { continue };
        match CallAnswer::decode(&sample.payload().to_bytes()) {
            Ok(CallAnswer::Progress(m)) if fits(&m) && progress < MAX_PROGRESS => {
                progress += 1;
                let _ = context.progress_encoded(&m);
            }
            Ok(CallAnswer::Progress(_)) => {
                shared.counters.calls_refused.fetch_add(1, Relaxed);
            }
            Ok(CallAnswer::Reply(m)) if fits(&m) => {
                cancel.armed = false;
                return Ok(m);
            }
            Ok(CallAnswer::Reply(_)) => {
                shared.counters.calls_refused.fetch_add(1, Relaxed);
                return Err(unreachable(
                    "the server's reply is too large to pass on".into(),
                ));
            }
            Ok(CallAnswer::Failure { code, message }) => {
                cancel.armed = false;
                return Err(Fault::new(code, message));
            }
            Err(e) => {
                shared.counters.calls_refused.fetch_add(1, Relaxed);
                tracing::debug!("{e}");
            }
        }
    }
    cancel.armed = false;
    Err(unreachable("no answer from the server's site".into()))
}

/// A call from another site for a server of this one: run in a task.
pub(super) fn take_call(shared: &Arc<Shared>, query: Query) {
    let request = match query.payload().map(|p| CallRequest::decode(&p.to_bytes())) {
        Some(Ok(r)) => r,
        Some(Err(e)) => {
            shared.counters.calls_refused.fetch_add(1, Relaxed);
            return tracing::warn!("{e}");
        }
        None => {
            shared.counters.calls_refused.fetch_add(1, Relaxed);
            return;
        }
    };
    let cancel = Arc::new(Notify::new());
    let admitted = {
        let mut calls = shared.calls.lock();
        let key = (request.bridge, request.id);
        (calls.len() < MAX_CALLS && !calls.contains_key(&key))
            .then(|| calls.insert(key, Arc::clone(&cancel)))
            .is_some()
    };
    let shared = Arc::clone(shared);
    shared.runtime.clone().spawn(async move {
        let reply_key = query.key_expr().clone();
        let answer = |a: CallAnswer| {
            let bytes = a.encode();
            let key = reply_key.clone();
            let query = &query;
            async move {
                if let Err(e) = query.reply(key, bytes).await {
                    tracing::debug!("call answer not sent: {e}");
                }
            }
        };
        if !admitted {
            shared.counters.calls_refused.fetch_add(1, Relaxed);
            return answer(CallAnswer::Failure {
                code: Fault::UNREACHABLE,
                message: "the bridge of the server's site runs as many calls as it may".into(),
            })
            .await;
        }
        shared.counters.calls_in.fetch_add(1, Relaxed);
        let outcome = run_call(&shared, &request, &cancel, &answer).await;
        shared.calls.lock().remove(&(request.bridge, request.id));
        if let Some(last) = outcome {
            answer(last).await;
        }
    });
}

/// Runs a call from another site on this site's server; progress goes
/// through `answer`, the final answer is returned (`None` if cancelled).
async fn run_call<F, Fut>(
    shared: &Shared,
    request: &CallRequest,
    cancel: &Notify,
    answer: &F,
) -> Option<CallAnswer>
where
    F: Fn(CallAnswer) -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    let unreachable = |message: String| CallAnswer::Failure {
        code: Fault::UNREACHABLE,
        message,
    };
    // Only what this site offers: a live member of its own that serves
    // the service, and a request channel its out-filter passes. Anything
    // else is answered at once, before it costs a client.
    let channel = pulicast::ServiceInfo::request_channel_of(&request.service);
    // The request channel's subscribers, not the whole fleet: a stranger's
    // members of thousands of names cost a call nothing.
    let offered = shared.checked.out.passes(&channel)
        && shared
            .node
            .try_channel(&format!("/{channel}"))
            .map(|c| c.subscribers())
            .unwrap_or_default()
            .iter()
            .any(|m| m.remote.is_none() && m.name == request.target && m.serves(&channel));
    if !offered {
        shared.counters.calls_refused.fetch_add(1, Relaxed);
        return Some(unreachable(format!(
            "{} serves no {} on this site",
            request.target, request.service
        )));
    }
    let name = format!("{}@{}", request.service, request.target);
    let client = {
        let mut clients = shared.clients.lock();
        match clients.get(&name) {
            Some(c) => c.clone(),
            None => match shared.node.make_namespace("/").raw_client(&name) {
                Ok(c) => {
                    // Names are of this site's own servers; past the
                    // bound, clients are made per call.
                    if clients.len() < MAX_CLIENTS {
                        clients.insert(name.clone(), c.clone());
                    }
                    c
                }
                Err(e) => return Some(unreachable(e.to_string())),
            },
        }
    };
    // 0 (no deadline) and anything longer: the longest a call runs.
    let within = match Duration::from_millis(u64::from(request.deadline_ms)) {
        d if d.is_zero() || d > LONGEST_CALL => LONGEST_CALL,
        d => d,
    };
    let mut call = tokio::select! {
        started = client.start(&request.message, within) => match started {
            Ok(call) => call,
            Err(e) => return Some(unreachable(e.to_string())),
        },
        () = cancel.notified() => return None,
    };
    loop {
        tokio::select! {
            () = cancel.notified() => {
                call.cancel();
                return None;
            }
            event = call.next() => match event {
                Some(CallEvent::Progress(m)) => answer(CallAnswer::Progress(m)).await,
                Some(CallEvent::Reply { message, .. }) => return Some(CallAnswer::Reply(message)),
                Some(CallEvent::Failed { code, message, .. }) => {
                    // SERVER_GONE is a caller's own conclusion, never sent:
                    // over there it reads as out of reach.
                    let code = if code == Fault::SERVER_GONE { Fault::UNREACHABLE } else { code };
                    return Some(CallAnswer::Failure { code, message });
                }
                Some(CallEvent::Busy) => return Some(unreachable("the server is busy".into())),
                Some(CallEvent::TimedOut) | None => {
                    return Some(CallAnswer::Failure {
                        code: Fault::DEADLINE,
                        message: "no reply by the call's deadline".into(),
                    });
                }
            }
        }
    }
}

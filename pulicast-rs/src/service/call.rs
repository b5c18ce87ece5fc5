//! A raw call in flight, as the caller holds it: its events, cancel and
//! end. The stepping (clock, resends, the service socket) is the
//! runtime's `CallDriver`.

use std::time::Duration;

use super::client::RawClient;
use crate::error::Error;
use crate::proto::call::Event;
use crate::runtime::calling::CallDriver;
use crate::runtime::walking::{tried_text, Walk};
use crate::wire::service::code;

/// What a call is driven by: one server's call, or a walk over the
/// nearest servers (a client made [`RawClient::nearest`]).
pub(super) enum Driving {
    One(CallDriver),
    Walk(Box<Walk>),
}

/// A call in flight whose messages are bytes: from [`RawClient::start`].
/// Dropping it before its end cancels it (the server's handler is told).
///
/// ```no_run
/// # async fn demo(plan: pulicast::RawClient, request: Vec<u8>) -> pulicast::Result<Vec<u8>> {
/// use pulicast::CallEvent;
/// let mut call = plan.start(&request, std::time::Duration::from_secs(5)).await?;
/// println!("served by {}", call.node());
/// while let Some(event) = call.next().await {
///     match event {
///         CallEvent::Progress(step) => println!("progress: {} bytes", step.len()),
///         CallEvent::Reply { message, .. } => return Ok(message),
///         end => return Err(call.error(end)), // the error a typed call returns
///     }
/// }
/// unreachable!("a call's last event ends it")
/// # }
/// ```
pub struct RawCall {
    /// First, so that it drops first: a call dropped before its end
    /// cancels while its client still holds the service's announcements.
    driver: Driving,
    /// Kept for the service's name, and so that the client (its request
    /// socket, its announcements) outlives the call.
    client: RawClient,
    /// The server of a call to one server.
    node: String,
    within: Duration,
}

impl std::fmt::Debug for RawCall {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawCall")
            .field("node", &self.node())
            .finish_non_exhaustive()
    }
}

impl RawCall {
    pub(super) fn new(client: RawClient, driver: Driving, node: String, within: Duration) -> Self {
        Self {
            client,
            driver,
            node,
            within,
        }
    }

    /// The client that made the call.
    pub(super) fn client(&self) -> &RawClient {
        &self.client
    }

    /// The server node the call went to: for a client of the nearest
    /// server, the one that has it now (or was tried last).
    pub fn node(&self) -> &str {
        match &self.driver {
            Driving::One(_) => &self.node,
            Driving::Walk(walk) => walk.node(),
        }
    }

    /// Whether the call's last event was its reply.
    pub fn ended_with_reply(&self) -> bool {
        match &self.driver {
            Driving::One(call) => call.replied(),
            Driving::Walk(walk) => walk.replied(),
        }
    }

    fn server_went(&self) -> bool {
        match &self.driver {
            Driving::One(call) => call.server_went(),
            Driving::Walk(walk) => walk.server_went(),
        }
    }

    /// The next event of the call: progress messages in order, then its
    /// end (reply, failure, busy or timed out); `None` after the end.
    pub async fn next(&mut self) -> Option<Event> {
        match &mut self.driver {
            Driving::One(call) => call.next(&self.node).await,
            Driving::Walk(walk) => walk.next().await,
        }
    }

    /// Like [`RawCall::next`], blocking the thread.
    pub fn next_blocking(&mut self) -> Option<Event> {
        match &mut self.driver {
            Driving::One(call) => call.next_blocking(&self.node),
            Driving::Walk(walk) => walk.next_blocking(),
        }
    }

    /// Cancels the call: the server's handler is told (and dropped, if it
    /// is async). Dropping the call does the same.
    pub fn cancel(self) {}

    /// The error an event that ends the call without a reply stands for
    /// (failure, busy, timed out), as typed calls return it; a progress or
    /// reply event (which is no error) reads as timed out. A call to the
    /// nearest server that passed over every one fails
    /// [`Error::NoServer`], saying what was tried and why.
    pub fn error(&self, event: Event) -> Error {
        let (service, node) = match &self.driver {
            Driving::Walk(walk) if walk.exhausted() => {
                return Error::NoServer {
                    service: self.client.service(),
                    reason: format!("no server took the call: {}", tried_text(walk.tried())),
                };
            }
            Driving::Walk(walk) => (
                walk.service()
                    .map_or_else(|| self.client.service(), |s| s.to_string()),
                walk.node().to_string(),
            ),
            Driving::One(_) => (self.client.service(), self.node.clone()),
        };
        match event {
            Event::Failed {
                code,
                message,
                node,
            } if code == code::BAD_REQUEST => Error::ServiceTypeMismatch {
                service,
                node,
                reason: message,
            },
            // The server gave up at the caller's deadline: as if no
            // answer came (which is what the caller would have seen).
            // Only this caller's own conclusion: a server may send any code.
            Event::Failed { code, node, .. } if code == code::SERVER_GONE && self.server_went() => {
                Error::ServerGone { service, node }
            }
            Event::Failed { code, node, .. } if code == code::DEADLINE => Error::CallTimedOut {
                service,
                node,
                after: self.within,
            },
            Event::Failed {
                code,
                message,
                node,
            } => Error::CallFailed {
                service,
                node,
                code,
                message,
            },
            Event::Busy => Error::ServerBusy { service, node },
            Event::TimedOut | Event::Progress(_) | Event::Reply { .. } => Error::CallTimedOut {
                service,
                node,
                after: self.within,
            },
        }
    }
}

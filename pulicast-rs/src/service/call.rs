//! A raw call in flight: its events, resends, cancel and end.

use std::sync::Arc;
use std::time::{Duration, Instant};

use super::client::RawClient;
use super::SERVER_CHECK;
use crate::error::{Error, Result};
use crate::proto::call::Event;
use crate::runtime::services::{LocalServer, Pending, ReplyTo};
use crate::sync::lock;
use crate::wire::service::{code, CallId, Frame};

/// A call in flight whose messages are bytes: from [`RawClient::start`].
/// Dropping it before its end cancels it (the server's handler is told).
pub struct RawCall {
    pub(super) client: RawClient,
    pub(super) pending: Arc<Pending>,
    pub(super) id: CallId,
    pub(super) node: String,
    pub(super) local: Option<Arc<dyn LocalServer>>,
    /// The remote server's session key, and when discovery was last asked
    /// whether it is still there.
    pub(super) server: Option<(i64, Instant)>,
    pub(super) ended: bool,
    pub(super) replied: bool,
    /// Whether discovery saw the server go (not a code the server sent).
    pub(super) gone: bool,
    /// Whether this call holds the service socket's reader seat.
    pub(super) reads: bool,
    pub(super) within: Duration,
}

impl std::fmt::Debug for RawCall {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RawCall")
            .field("call", &self.id)
            .field("node", &self.node)
            .finish_non_exhaustive()
    }
}

/// What a poll of the call found.
pub(super) enum Step {
    Event(Event),
    Ended,
    Wait(Option<Instant>),
}

impl RawCall {
    /// The server node the call went to.
    pub fn node(&self) -> &str {
        &self.node
    }

    /// Whether the call's last event was its reply.
    pub fn ended_with_reply(&self) -> bool {
        self.replied
    }

    pub(super) fn send(&self, frame: &[u8]) -> Result<()> {
        match &self.local {
            Some(server) => {
                server.frame(frame, ReplyTo::Local);
                Ok(())
            }
            None => {
                let core = &self.client.core;
                core.inner.send_request(&core.request, frame)
            }
        }
    }

    /// Sends again; a failure is logged (the next resend may work).
    fn resend(&self, frame: &[u8]) {
        if let Err(e) = self.send(frame) {
            let service = &self.client.core.service;
            tracing::debug!(%service, "request not sent: {e}");
        }
    }

    /// Tells the server the call is given up: once now, and over the
    /// network twice more, 50 ms apart (a cancel is not answered).
    fn send_cancels(&self) {
        let mut frame = Vec::new();
        if (Frame::Cancel { call: self.id })
            .encode(&mut frame)
            .is_err()
        {
            return;
        }
        self.resend(&frame);
        if self.local.is_some() {
            return;
        }
        let core = Arc::clone(&self.client.core);
        core.inner.runtime_handle().clone().spawn(async move {
            for _ in 0..2 {
                tokio::time::sleep(crate::proto::call::FIRST_RESEND).await;
                let _ = core.inner.send_request(&core.request, &frame);
            }
        });
    }

    /// When to look again: at `until`, and soon enough to see the server
    /// go.
    fn wake_by(&self, until: Option<Instant>) -> Instant {
        let check = Instant::now() + SERVER_CHECK;
        until.map_or(check, |at| at.min(check))
    }

    /// Whether discovery says the remote server is gone (left or failed),
    /// asked at most every [`SERVER_CHECK`].
    fn server_gone(&mut self) -> bool {
        let Some((key, checked)) = &mut self.server else {
            return false;
        };
        if checked.elapsed() < SERVER_CHECK {
            return false;
        }
        *checked = Instant::now();
        let key = *key;
        let members = self.client.core.inner.fleet_members_on(&|_| false);
        !members.iter().any(|m| m.key == key && m.is_live())
    }

    /// Sends what is due, takes the next event, or says until when to wait.
    fn step(&mut self) -> Step {
        if self.ended {
            return Step::Ended;
        }

        let (due, step) = {
            let mut state = lock(&self.pending.state);
            let now = Instant::now();
            state.call.handle_timeout(now);
            // A local server hears the request once: it can't be lost.
            let due = state
                .call
                .poll_transmit(now)
                .filter(|_| self.local.is_none() || state.call.transmissions() == 1);
            let step = match state.call.poll_event() {
                Some(event) => Step::Event(event),
                None if state.call.is_done() => Step::Ended,
                None => Step::Wait(state.call.poll_timeout()),
            };
            (due, step)
        };
        // Sent unlocked: this node's own server answers on this thread.
        if let Some(request) = due {
            self.resend(&request);
        }
        if matches!(step, Step::Wait(_)) && self.server_gone() {
            // Nothing came and nobody is there any more (not cancelled:
            // nobody would hear it).
            self.end();
            self.gone = true;
            return Step::Event(Event::Failed {
                code: code::SERVER_GONE,
                message: "the server is gone".into(),
                node: self.node.clone(),
            });
        }
        if matches!(step, Step::Event(Event::Reply { .. })) {
            self.replied = true;
        }
        if matches!(step, Step::Event(Event::TimedOut)) && !self.ended {
            // The caller gives up: the server need not go on.
            self.send_cancels();
        }
        if matches!(&step, Step::Event(e) if e.is_final()) || matches!(step, Step::Ended) {
            self.end();
        }
        step
    }

    /// Gives back the reader's seat, if this call holds it.
    fn leave_seat(&mut self) {
        if self.reads {
            self.reads = false;
            self.client.core.request.socket.leave_seat();
        }
    }

    pub(super) fn end(&mut self) {
        self.leave_seat();
        if !self.ended {
            self.ended = true;
            self.client.core.inner.remove_call(self.id);
        }
    }

    /// The next event of the call: progress messages in order, then its
    /// end (reply, failure, busy or timed out); `None` after the end.
    pub async fn next(&mut self) -> Option<Event> {
        loop {
            match self.step() {
                Step::Event(event) => return Some(event),
                Step::Ended => return None,
                Step::Wait(until) => {
                    let notified = self.pending.notify.notified();
                    let at = tokio::time::Instant::from(self.wake_by(until));
                    let core = Arc::clone(&self.client.core);
                    let socket = &core.request.socket;
                    // One waiting caller at a time reads the answers too:
                    // its task is then woken by the datagram itself. The
                    // others (and a caller whose socket failed) are woken
                    // by whoever hands them theirs.
                    if self.local.is_none() && !self.reads && socket.take_seat() {
                        self.reads = true;
                    }
                    tokio::select! {
                        () = notified => {}
                        () = tokio::time::sleep_until(at) => {}
                        ready = socket.readable(), if self.reads => {
                            let drained = ready.is_ok() && core.inner.drain_answers(socket);
                            if !drained {
                                // Another reader is at it, or the socket
                                // failed: wait to be handed the answer.
                                self.leave_seat();
                                let notified = self.pending.notify.notified();
                                let _ = tokio::time::timeout_at(at, notified).await;
                            }
                        }
                    }
                }
            }
        }
    }

    /// Like [`RawCall::next`], blocking the thread.
    pub fn next_blocking(&mut self) -> Option<Event> {
        loop {
            match self.step() {
                Step::Event(event) => return Some(event),
                Step::Ended => return None,
                Step::Wait(until) => {
                    let state = lock(&self.pending.state);
                    // Unless something came meanwhile.
                    if state.call.has_event() {
                        continue;
                    }
                    let wait = self
                        .wake_by(until)
                        .saturating_duration_since(Instant::now());
                    let _unused = self.pending.changed.wait_timeout(state, wait);
                }
            }
        }
    }

    /// Cancels the call: the server's handler is told (and dropped, if it
    /// is async). Dropping the call does the same.
    pub fn cancel(self) {}

    /// The error an event that ends the call without a reply stands for
    /// (failure, busy, timed out), as typed calls return it; a progress or
    /// reply event (which is no error) reads as timed out.
    pub fn error(&self, event: Event) -> Error {
        let service = self.client.service();
        let node = self.node.clone();
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
            Event::Failed { code, node, .. } if code == code::SERVER_GONE && self.gone => {
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

impl Drop for RawCall {
    fn drop(&mut self) {
        if self.ended {
            return;
        }
        lock(&self.pending.state).call.cancel(Instant::now());
        self.end();
        self.send_cancels();
    }
}

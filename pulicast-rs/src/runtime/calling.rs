//! A call in flight, driven: the sans-IO [`Call`] stepped with the clock,
//! its request sent (and sent again) from the service socket or handed to
//! this node's own server, its answers read while the caller waits, the
//! server watched through discovery, and cancels sent when it is given
//! up. The API's `RawCall` holds one of these and nothing that reads a
//! clock or a socket.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::services::{Answerer, LocalServer, Pending, ReplyTo, RequestTx};
use super::Inner;
use crate::error::{Error, Result};
use crate::proto::call::{Call, Event, FIRST_RESEND};
use crate::sync::lock;
use crate::wire::service::{code, CallId, Frame};

/// How often a call in flight asks discovery whether its server is still
/// there (discovery sees a crash within about 400 ms).
const SERVER_CHECK: Duration = Duration::from_millis(200);

/// Where a call goes.
pub(crate) enum CallTo {
    /// This node's own server.
    Local(Arc<dyn LocalServer>),
    /// A server elsewhere: its session key and the address answers come
    /// from.
    Remote(i64, SocketAddr),
}

/// What a poll of the call found.
enum Step {
    Event(Event),
    Ended,
    Wait(Option<Instant>),
}

/// One call in flight.
pub(crate) struct CallDriver {
    inner: Arc<Inner>,
    request: Arc<RequestTx>,
    /// For logs.
    service: Arc<str>,
    pending: Arc<Pending>,
    id: CallId,
    local: Option<Arc<dyn LocalServer>>,
    /// The remote server's session key, and when discovery was last asked
    /// whether it is still there.
    server: Option<(i64, Instant)>,
    ended: bool,
    replied: bool,
    /// Whether discovery saw the server go (not a code the server sent).
    gone: bool,
    /// Whether this call holds the service socket's reader seat.
    reads: bool,
    /// When the call is given up if the server has said nothing of it by
    /// then (a walk over several servers moves on); `None`: waits to the
    /// deadline.
    silent_by: Option<Instant>,
}

impl CallDriver {
    /// Starts call `id` of `message` to server node `node` at `to`, with
    /// answers expected by `deadline`: the request leaves now (one that
    /// can't be sent fails the call at once) and is sent again while the
    /// call is awaited.
    pub(crate) fn launch(
        inner: &Arc<Inner>,
        request: &Arc<RequestTx>,
        service: Arc<str>,
        node: &str,
        to: CallTo,
        message: &[u8],
        deadline: Instant,
    ) -> Result<Self> {
        let id = inner.next_call();
        let now = Instant::now();
        let left = deadline.saturating_duration_since(now);
        let mut frame = Vec::new();
        Frame::Request {
            call: id,
            target: node,
            // At least 1: 0 would mean no deadline.
            deadline_ms: u32::try_from(left.as_millis()).unwrap_or(u32::MAX).max(1),
            message,
        }
        .encode(&mut frame)
        .map_err(|e| Error::config("service call", e.to_string()))?;
        let (answerer, local, server) = match to {
            CallTo::Local(server) => (Answerer::Local, Some(server), None),
            CallTo::Remote(key, address) => (Answerer::At(address), None, Some((key, now))),
        };
        let pending = Pending::new(Call::new(id, frame, now, deadline), answerer);
        inner.add_call(id, Arc::clone(&pending));
        let mut call = Self {
            inner: Arc::clone(inner),
            request: Arc::clone(request),
            service,
            pending,
            id,
            local,
            server,
            ended: false,
            replied: false,
            gone: false,
            reads: false,
            silent_by: None,
        };
        let first = lock(&call.pending.state).call.poll_transmit(now);
        if let Some(request) = first {
            if let Err(e) = call.send(&request) {
                call.end();
                return Err(e);
            }
        }
        Ok(call)
    }

    /// Gives the call up at `at` if the server has not said by then that
    /// it has it (the call then ends timed out, and is cancelled in case
    /// the server hears it late).
    pub(crate) fn give_up_unheard_at(&mut self, at: Instant) {
        self.silent_by = Some(at);
    }

    /// Whether the server has said it has the call (see
    /// [`Call::heard`]).
    pub(crate) fn heard(&self) -> bool {
        lock(&self.pending.state).call.heard()
    }

    /// Whether the call's last event was its reply.
    pub(crate) fn replied(&self) -> bool {
        self.replied
    }

    /// Whether discovery saw the server go (so a `SERVER_GONE` failure is
    /// this caller's own conclusion, not a code a server sent).
    pub(crate) fn server_went(&self) -> bool {
        self.gone
    }

    fn send(&self, frame: &[u8]) -> Result<()> {
        match &self.local {
            Some(server) => {
                server.frame(frame, ReplyTo::Local);
                Ok(())
            }
            None => self.inner.send_request(&self.request, frame),
        }
    }

    /// Sends again; a failure is logged (the next resend may work).
    fn resend(&self, frame: &[u8]) {
        if let Err(e) = self.send(frame) {
            let service = &self.service;
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
        let inner = Arc::clone(&self.inner);
        let request = Arc::clone(&self.request);
        self.inner.runtime_handle().clone().spawn(async move {
            for _ in 0..2 {
                tokio::time::sleep(FIRST_RESEND).await;
                let _ = inner.send_request(&request, &frame);
            }
        });
    }

    /// When to look again: at `until`, and soon enough to see the server
    /// go.
    fn wake_by(&self, until: Option<Instant>) -> Instant {
        let check = Instant::now() + SERVER_CHECK;
        let check = self.silent_by.map_or(check, |at| at.min(check));
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
        let members = self.inner.fleet_members_on(&|_| false);
        !members.iter().any(|m| m.key == key && m.is_live())
    }

    /// Sends what is due, takes the next event, or says until when to wait.
    fn step(&mut self, node: &str) -> Step {
        if self.ended {
            return Step::Ended;
        }

        let (due, step) = {
            let mut state = lock(&self.pending.state);
            let now = Instant::now();
            if self.silent_by.is_some_and(|at| now >= at) && !state.call.heard() {
                // Given up as silent: cancelled like a call dropped, in
                // case the request reaches the server yet.
                state.call.cancel(now);
                drop(state);
                self.end();
                self.send_cancels();
                return Step::Event(Event::TimedOut);
            }
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
                node: node.to_owned(),
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
            self.request.socket.leave_seat();
        }
    }

    fn end(&mut self) {
        self.leave_seat();
        if !self.ended {
            self.ended = true;
            self.inner.remove_call(self.id);
        }
    }

    /// The next event of the call to server node `node`; `None` after
    /// its end.
    pub(crate) async fn next(&mut self, node: &str) -> Option<Event> {
        loop {
            match self.step(node) {
                Step::Event(event) => return Some(event),
                Step::Ended => return None,
                Step::Wait(until) => {
                    let pending = Arc::clone(&self.pending);
                    let notified = pending.notify.notified();
                    let at = tokio::time::Instant::from(self.wake_by(until));
                    let request = Arc::clone(&self.request);
                    let socket = &request.socket;
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
                            let drained = ready.is_ok() && self.inner.drain_answers(socket);
                            if !drained {
                                // Another reader is at it, or the socket
                                // failed: wait to be handed the answer.
                                self.leave_seat();
                                let notified = pending.notify.notified();
                                let _ = tokio::time::timeout_at(at, notified).await;
                            }
                        }
                    }
                }
            }
        }
    }

    /// Like [`CallDriver::next`], blocking the thread.
    pub(crate) fn next_blocking(&mut self, node: &str) -> Option<Event> {
        loop {
            match self.step(node) {
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
}

impl Drop for CallDriver {
    /// A call dropped before its end is cancelled: the server's handler is
    /// told.
    fn drop(&mut self) {
        if self.ended {
            return;
        }
        lock(&self.pending.state).call.cancel(Instant::now());
        self.end();
        self.send_cancels();
    }
}

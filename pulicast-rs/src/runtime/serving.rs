//! A server as the node runs it: admission (the sans-IO
//! [`crate::proto::service::Admission`]) stepped with the clock, each admitted
//! call's handler run (at once on the receiving thread, or as a task when
//! it waits), cut short by a cancel or the deadline, and its answer sent
//! and kept for resends. The API's `Admission` holds one of these; its typed
//! handlers reach it through a [`Runner`].

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use bytes::Bytes;
use futures_util::FutureExt;

use super::services::{LocalServer, ReplyTo};
use super::{ChannelState, Inner};
use crate::error::{Error, Result};
use crate::proto::service::{Admission, Admit, ServiceCounts, ServiceLimits};
use crate::proto::text::cut;
use crate::sync::lock;
use crate::wire::service::{code, CallId, Frame};
use crate::wire::DecodeError;

pub(crate) type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

/// A handler with its types erased: request message in, reply message out.
pub(crate) type Runner =
    Box<dyn Fn(Bytes, Arc<Running>) -> BoxFuture<Result<Vec<u8>, Failure>> + Send + Sync>;

/// What a running call shares with its handler's `CallContext`.
pub(crate) struct Running {
    call: CallId,
    /// The node the caller named (empty: any server).
    target: String,
    reply_to: ReplyTo,
    server: Weak<ServerCore>,
    progress: AtomicU32,
    cancelled: AtomicBool,
    cancel: tokio::sync::Notify,
    deadline: Option<Instant>,
}

impl Running {
    pub(crate) fn cancel(&self) {
        self.cancelled.store(true, Ordering::Release);
        self.cancel.notify_waiters();
    }

    async fn cancelled(&self) {
        loop {
            let notified = self.cancel.notified();
            if self.cancelled.load(Ordering::Acquire) {
                return;
            }
            notified.await;
        }
    }

    /// Whether the caller cancelled the call, or its deadline passed.
    pub(crate) fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Acquire)
    }

    /// The call's id.
    pub(crate) fn call(&self) -> CallId {
        self.call
    }

    /// Where the caller is; `None` for a call from this node.
    pub(crate) fn caller(&self) -> Option<SocketAddr> {
        match self.reply_to {
            ReplyTo::Network(a) => Some(a),
            ReplyTo::Local => None,
        }
    }

    /// When the caller stops waiting, as it said in its request.
    pub(crate) fn deadline(&self) -> Option<Instant> {
        self.deadline
    }

    /// The node the caller named as the server (empty: any server).
    pub(crate) fn target(&self) -> &str {
        &self.target
    }

    /// Sends a progress message (encoded, fingerprint first); nothing
    /// after a cancel.
    pub(crate) fn progress(&self, message: &[u8]) -> Result<()> {
        if self.is_cancelled() {
            return Ok(());
        }
        let Some(server) = self.server.upgrade() else {
            return Err(Error::NodeStopped);
        };
        let seq = self.progress.fetch_add(1, Ordering::Relaxed);
        let frame = Frame::Progress {
            call: self.call,
            seq,
            message,
        };
        server.send(&frame, self.reply_to);
        Ok(())
    }
}

/// A call's end other than a reply: the code and message its caller gets
/// (the API's `Fault`, or one the server decides itself).
pub(crate) struct Failure {
    pub(crate) code: u16,
    pub(crate) message: String,
}

impl Failure {
    pub(crate) fn new(code: u16, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }
}

/// The longest failure message sent; longer ones are cut.
const MAX_FAILURE_MESSAGE: usize = 1024;

impl ServerCore {
    /// A server of `channel` (its request channel) with these limits; a
    /// relay server when `answers_for` says which nodes it answers for.
    pub(crate) fn new(
        inner: &Arc<Inner>,
        channel: Arc<ChannelState>,
        limits: ServiceLimits,
        blocking: bool,
        run: Runner,
        answers_for: Option<Targets>,
    ) -> Arc<Self> {
        Arc::new_cyclic(|me| ServerCore {
            me: me.clone(),
            inner: Arc::downgrade(inner),
            runtime: inner.runtime_handle().clone(),
            channel,
            node: inner.name().to_string(),
            admission: Mutex::new(Admission::new(limits)),
            longest: limits.longest,
            blocking,
            running: Mutex::new(HashMap::new()),
            run,
            answers_for,
        })
    }

    /// The request channel.
    pub(crate) fn channel(&self) -> &Arc<ChannelState> {
        &self.channel
    }

    /// What admission decided so far.
    pub(crate) fn counts(&self) -> ServiceCounts {
        lock(&self.admission).counts()
    }

    /// Calls running now.
    pub(crate) fn running(&self) -> usize {
        lock(&self.running).len()
    }

    /// Stops being one of the node's servers (a relay server never was).
    pub(crate) fn stop(&self) {
        if self.answers_for.is_some() {
            return;
        }
        if let Some(inner) = self.inner.upgrade() {
            inner.remove_server(self.channel.name());
        }
    }
}

/// One service this node serves, its types erased.
pub(crate) struct ServerCore {
    me: Weak<ServerCore>,
    inner: Weak<Inner>,
    runtime: tokio::runtime::Handle,
    channel: Arc<ChannelState>,
    node: String,
    admission: Mutex<Admission<ReplyTo>>,
    /// The longest a call runs (see `ServiceLimits::longest`).
    longest: Duration,
    /// Whether handlers run on blocking threads, which a cancel can't stop.
    blocking: bool,
    running: Mutex<HashMap<CallId, Arc<Running>>>,
    run: Runner,
    /// For a relay server (`ServerBuilder::serve_for`): the nodes it answers
    /// for; `None` for a server of its own node.
    answers_for: Option<Targets>,
}

/// Which node names a relay server answers for.
pub(crate) type Targets = Box<dyn Fn(&str) -> bool + Send + Sync>;

impl ServerCore {
    pub(crate) fn send(&self, frame: &Frame<'_>, to: ReplyTo) {
        let Some(inner) = self.inner.upgrade() else {
            return;
        };
        let mut bytes = Vec::new();
        match frame.encode(&mut bytes) {
            Ok(()) => inner.send_answer(&self.channel, &bytes, to),
            Err(e) => tracing::warn!(channel = %self.channel.name(), "answer not sent: {e}"),
        }
    }

    fn request(&self, call: CallId, target: &str, deadline_ms: u32, message: &[u8], from: ReplyTo) {
        let now = Instant::now();
        let admitted = lock(&self.admission).admit(call, &from, now);
        match admitted {
            Admit::Run => self.run(call, target, deadline_ms, message, from, now),
            Admit::Busy => self.send(&Frame::Busy { call }, from),
            // A retransmission: the caller hears the call runs (so one
            // choosing among servers waits for this one's answer).
            Admit::Running => self.send(&Frame::Running { call }, from),
            // Another caller's id: not this sender's call to hear of.
            Admit::Foreign => {}
            Admit::Resend(frame) => self.send_bytes(&frame, from),
            Admit::Lost => self.send(
                &Frame::Failure {
                    call,
                    code: code::LOST,
                    message: "the call ran; its answer was too large to keep for a resend",
                    node: cut(self.answering_as(target), 255),
                },
                from,
            ),
            Admit::Forgotten => self.send(
                &Frame::Failure {
                    call,
                    code: code::LOST,
                    message: "a call older than this server remembers of its caller's session: \
                              it may have run, so it is not run now",
                    node: cut(self.answering_as(target), 255),
                },
                from,
            ),
        }
    }

    /// The node a failure names: this one, or the one a relay server
    /// answers for.
    fn answering_as<'a>(&'a self, target: &'a str) -> &'a str {
        match self.answers_for {
            Some(_) => target,
            None => &self.node,
        }
    }

    fn run(
        &self,
        call: CallId,
        target: &str,
        deadline_ms: u32,
        message: &[u8],
        from: ReplyTo,
        now: Instant,
    ) {
        // No call runs longer than the server allows, with or without a
        // deadline of its caller's.
        let asked = Duration::from_millis(u64::from(deadline_ms));
        let longest = match deadline_ms {
            0 => self.longest,
            _ => asked.min(self.longest),
        };
        let deadline = Some(now + longest);
        let running = Arc::new(Running {
            call,
            target: target.to_owned(),
            reply_to: from,
            server: self.me.clone(),
            progress: AtomicU32::new(0),
            cancelled: AtomicBool::new(false),
            cancel: tokio::sync::Notify::new(),
            deadline,
        });
        lock(&self.running).insert(call, Arc::clone(&running));
        let handler = (self.run)(Bytes::copy_from_slice(message), Arc::clone(&running));
        // The task keeps the server until the call ends, so a server
        // dropped meanwhile still answers it.
        let Some(me) = self.me.upgrade() else {
            return;
        };
        let mut task = Box::pin(async move {
            let until = async {
                match deadline {
                    Some(at) => tokio::time::sleep_until(at.into()).await,
                    None => std::future::pending().await,
                }
            };
            let panicked = || Err(Failure::new(code::PANICKED, "the handler panicked"));
            let mut handler = std::panic::AssertUnwindSafe(handler).catch_unwind();
            let outcome = tokio::select! {
                // The handler first: one that answers at once never
                // arms the deadline's timer.
                biased;
                done = &mut handler => done.unwrap_or_else(|_| panicked()),
                () = running.cancelled() => Err(Failure::new(code::CANCELLED, "cancelled by the caller")),
                () = until => {
                    running.cancel();
                    Err(Failure::new(code::DEADLINE, "the call's deadline passed"))
                }
            };
            let cut_short = outcome
                .as_ref()
                .is_err_and(|f| f.code == code::CANCELLED || f.code == code::DEADLINE);
            if cut_short && me.blocking {
                // The caller hears now; the slot stays taken until the
                // thread returns, so cancelled work can't pile up beyond
                // the server's concurrency.
                let answer = me.answer(&running, &outcome);
                me.send_bytes(&answer, running.reply_to);
                let _ = handler.await;
                me.release(&running, answer);
            } else {
                let answer = me.answer(&running, &outcome);
                me.release(&running, answer.clone());
                me.send_bytes(&answer, running.reply_to);
            }
        });
        // A handler that answers at once (most do) answers here, on the
        // thread that received the request: no task to start and no other
        // thread to wake. One that waits goes on as a task, which polls it
        // again with its own waker (a future registers the waker of each
        // poll, so the first poll's does not matter).
        let _runtime = self.runtime.enter();
        let waker = futures_util::task::noop_waker();
        let mut first = std::task::Context::from_waker(&waker);
        if task.as_mut().poll(&mut first).is_pending() {
            self.runtime.spawn(task);
        }
    }

    fn send_bytes(&self, frame: &[u8], to: ReplyTo) {
        if frame.is_empty() {
            return;
        }
        if let Some(inner) = self.inner.upgrade() {
            inner.send_answer(&self.channel, frame, to);
        }
    }

    /// Frees the call's slot, keeping `answer` for retransmissions.
    fn release(&self, running: &Running, answer: Vec<u8>) {
        let mut admission = lock(&self.admission);
        admission.finish(running.call, answer, Instant::now());
        if admission.over_sessions() {
            // A live member's mark is kept however many strangers call.
            let live = self
                .inner
                .upgrade()
                .map(|inner| inner.live_sessions())
                .unwrap_or_default();
            admission.trim_sessions(|session| live.contains(&session));
        }
        drop(admission);
        lock(&self.running).remove(&running.call);
    }

    /// The final frame of a call that ended with `outcome` (empty, and
    /// logged, if it can't be encoded).
    fn answer(&self, running: &Running, outcome: &Result<Vec<u8>, Failure>) -> Vec<u8> {
        let call = running.call;
        let mut bytes = Vec::new();
        let encoded = match outcome {
            Ok(message) => Frame::Reply {
                call,
                progress: running.progress.load(Ordering::Relaxed),
                message,
            }
            .encode(&mut bytes),
            Err(fault) => Frame::Failure {
                call,
                code: fault.code,
                message: cut(&fault.message, MAX_FAILURE_MESSAGE),
                node: cut(self.answering_as(&running.target), 255),
            }
            .encode(&mut bytes),
        };
        if let Err(e) = encoded {
            tracing::warn!(channel = %self.channel.name(), "answer not encoded: {e}");
            bytes.clear();
        }
        bytes
    }
}

impl LocalServer for ServerCore {
    fn frame(&self, frame: &[u8], from: ReplyTo) {
        let source = || match from {
            ReplyTo::Network(a) => a.to_string(),
            ReplyTo::Local => "this node".into(),
        };
        match Frame::decode(frame) {
            Ok(Frame::Request {
                call,
                target,
                deadline_ms,
                message,
            }) => {
                // Requests for another server of the service are not ours.
                let ours = match &self.answers_for {
                    Some(accepts) => !target.is_empty() && accepts(target),
                    None => target.is_empty() || target == self.node,
                };
                if ours {
                    self.request(call, target, deadline_ms, message, from);
                }
            }
            Ok(Frame::Cancel { call }) => {
                let running = lock(&self.running).get(&call).cloned();
                // Only from where the call came: nobody else cancels it.
                if let Some(running) = running.filter(|r| r.reply_to == from) {
                    running.cancel();
                }
            }
            Ok(_) => {
                if let Some(inner) = self.inner.upgrade() {
                    let e = DecodeError::Malformed("a server's frame on a request channel".into());
                    inner
                        .counters()
                        .drop_decode(&e, Some(self.channel.name()), source());
                }
            }
            Err(e) => {
                if let Some(inner) = self.inner.upgrade() {
                    inner
                        .counters()
                        .drop_decode(&e, Some(self.channel.name()), source());
                }
            }
        }
    }
}

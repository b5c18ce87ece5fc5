//! Servers: a service's handler, its calls run at most once each, and
//! the builder that sets its options.

use std::collections::HashMap;
use std::future::Future;
use std::marker::PhantomData;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use bytes::Bytes;
use futures_util::FutureExt;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::fault::cut;
use super::fault::Fault;
use super::fault::MAX_FAULT_MESSAGE;
use super::is_unit;
use super::service_names;
use super::type_info;
use super::Held;
use crate::channel::{Channel, Namespace};
use crate::error::{Error, Result};
use crate::proto::service::{Admit, Counts, Limits, Server as Admission};
use crate::runtime::services::{LocalServer, ReplyTo};
use crate::runtime::{ChannelState, Inner};
use crate::subscription::{CallbackSubscription, Message};
use crate::sync::lock;
use crate::wire::service::{self as wire, code, CallId, Frame};
use crate::wire::{self as codec, DecodeError};
use crate::Schema;

pub(super) type BoxFuture<T> = Pin<Box<dyn Future<Output = T> + Send>>;

/// A handler with its types erased: request message in, reply message out.
pub(super) type Runner =
    Box<dyn Fn(Bytes, CallContext<()>) -> BoxFuture<Result<Vec<u8>, Fault>> + Send + Sync>;

/// What a running call shares with its handler's [`CallContext`].
pub(super) struct Running {
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
    fn cancel(&self) {
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
}

/// What a handler knows of its call, and how it sends progress: given to
/// the handlers of [`ServerBuilder::serve_with`] and
/// [`ServerBuilder::serve_blocking_with`]. `P` is the progress type.
pub struct CallContext<P = ()> {
    running: Arc<Running>,
    _progress: PhantomData<fn(&P)>,
}

impl<P> Clone for CallContext<P> {
    fn clone(&self) -> Self {
        Self {
            running: Arc::clone(&self.running),
            _progress: PhantomData,
        }
    }
}

impl<P> std::fmt::Debug for CallContext<P> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CallContext")
            .field("call", &self.running.call)
            .field("caller", &self.caller())
            .finish()
    }
}

impl<P> CallContext<P> {
    fn retyped<Q>(self) -> CallContext<Q> {
        CallContext {
            running: self.running,
            _progress: PhantomData,
        }
    }

    /// Whether the caller cancelled the call, or its deadline passed. An
    /// async handler is dropped then; a blocking one should look here
    /// between steps and return.
    pub fn is_cancelled(&self) -> bool {
        self.running.cancelled.load(Ordering::Acquire)
    }

    /// Where the caller is; `None` for a call from this node.
    pub fn caller(&self) -> Option<SocketAddr> {
        match self.running.reply_to {
            ReplyTo::Network(a) => Some(a),
            ReplyTo::Local => None,
        }
    }

    /// When the caller stops waiting, as it said in its request.
    pub fn deadline(&self) -> Option<Instant> {
        self.running.deadline
    }

    /// The node the caller named as the server (empty: any server). A
    /// server of [`ServerBuilder::serve_for`] answers for several.
    pub fn target(&self) -> &str {
        &self.running.target
    }

    /// Sends a progress message already encoded (fingerprint first), as a
    /// bridge passes on another server's progress; otherwise as
    /// [`CallContext::progress`].
    pub fn progress_encoded(&self, message: &[u8]) -> Result<()> {
        if self.is_cancelled() {
            return Ok(());
        }
        let Some(server) = self.running.server.upgrade() else {
            return Err(Error::NodeStopped);
        };
        let seq = self.running.progress.fetch_add(1, Ordering::Relaxed);
        let frame = Frame::Progress {
            call: self.running.call,
            seq,
            message,
        };
        server.send(&frame, self.running.reply_to);
        Ok(())
    }
}

impl<P: Serialize + Schema> CallContext<P> {
    /// Sends a progress message to the caller, before the reply. Lost ones
    /// are not sent again (the caller counts them); after a cancel, nothing
    /// is sent.
    pub fn progress(&self, value: &P) -> Result<()> {
        if self.is_cancelled() {
            return Ok(());
        }
        let Some(server) = self.running.server.upgrade() else {
            return Err(Error::NodeStopped);
        };
        let mut message = Vec::new();
        codec::encode_native(value, &mut message)?;
        let seq = self.running.progress.fetch_add(1, Ordering::Relaxed);
        let frame = Frame::Progress {
            call: self.running.call,
            seq,
            message: &message,
        };
        server.send(&frame, self.running.reply_to);
        Ok(())
    }
}

/// One service this node serves, its types erased.
pub(super) struct ServerCore {
    me: Weak<ServerCore>,
    inner: Weak<Inner>,
    runtime: tokio::runtime::Handle,
    channel: Arc<ChannelState>,
    node: String,
    admission: Mutex<Admission<ReplyTo>>,
    /// The longest a call runs (see [`Limits::longest`]).
    longest: Duration,
    /// Whether handlers run on blocking threads, which a cancel can't stop.
    blocking: bool,
    running: Mutex<HashMap<CallId, Arc<Running>>>,
    run: Runner,
    /// For a server of [`ServerBuilder::serve_for`]: the nodes it answers
    /// for; `None` for a server of its own node.
    answers_for: Option<Targets>,
}

/// Which node names a relay server answers for.
pub(super) type Targets = Box<dyn Fn(&str) -> bool + Send + Sync>;

impl ServerCore {
    pub(super) fn send(&self, frame: &Frame<'_>, to: ReplyTo) {
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
            // Retransmissions, and requests under another caller's id.
            Admit::Running | Admit::Foreign => {}
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
        let context = CallContext {
            running: Arc::clone(&running),
            _progress: PhantomData,
        };
        let handler = (self.run)(Bytes::copy_from_slice(message), context);
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
            let panicked = || Err(Fault::new(code::PANICKED, "the handler panicked"));
            let mut handler = std::panic::AssertUnwindSafe(handler).catch_unwind();
            let outcome = tokio::select! {
                // The handler first: one that answers at once never
                // arms the deadline's timer.
                biased;
                done = &mut handler => done.unwrap_or_else(|_| panicked()),
                () = running.cancelled() => Err(Fault::new(code::CANCELLED, "cancelled by the caller")),
                () = until => {
                    running.cancel();
                    Err(Fault::new(code::DEADLINE, "the call's deadline passed"))
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
    fn answer(&self, running: &Running, outcome: &Result<Vec<u8>, Fault>) -> Vec<u8> {
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
                message: cut(&fault.message, MAX_FAULT_MESSAGE),
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

/// A service this node serves: made by [`Namespace::serve`] and the
/// other `serve` methods; dropping it stops serving (calls running end
/// as they end, their answers still sent).
pub struct Server {
    core: Arc<ServerCore>,
    service: String,
    _requests: CallbackSubscription,
    _held: Held,
}

impl std::fmt::Debug for Server {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Server")
            .field("service", &self.service)
            .finish_non_exhaustive()
    }
}

impl Server {
    /// The service's full name (`rover1/plan`).
    pub fn service(&self) -> &str {
        &self.service
    }

    /// What the server decided so far: calls run, busy, retransmissions.
    pub fn counts(&self) -> Counts {
        lock(&self.core.admission).counts()
    }

    /// Calls running now.
    pub fn running(&self) -> usize {
        lock(&self.core.running).len()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        // A relay server is not among the node's own servers.
        if self.core.answers_for.is_some() {
            return;
        }
        if let Some(inner) = self.core.inner.upgrade() {
            inner.remove_server(self.core.channel.name());
        }
    }
}

/// A server being made, with options: made by [`Namespace::server`].
#[must_use = "a server serves once one of its serve methods is called"]
#[derive(Debug)]
pub struct ServerBuilder {
    pub(super) ns: Namespace,
    pub(super) name: String,
    pub(super) limits: Limits,
}

impl ServerBuilder {
    /// Calls run at once (16 by default); more are answered busy.
    pub fn concurrency(mut self, calls: usize) -> Self {
        self.limits.concurrency = calls;
        self
    }

    /// All the server's bounds (see [`Limits`]).
    pub fn limits(mut self, limits: Limits) -> Self {
        self.limits = limits;
        self
    }

    /// Serves with an async handler, run on the node's runtime. A call the
    /// caller cancels, or whose deadline passes, drops its future.
    pub fn serve<Req, Rep, F, Fut>(self, handler: F) -> Result<Server>
    where
        Req: DeserializeOwned + Schema + Send + 'static,
        Rep: Serialize + Schema + 'static,
        F: Fn(Req) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Rep, Fault>> + Send + 'static,
    {
        self.serve_with::<Req, Rep, (), _, _>(move |req, _| handler(req))
    }

    /// Like [`ServerBuilder::serve`], with the call's [`CallContext`]: the
    /// handler sends progress messages of type `P` before its reply.
    pub fn serve_with<Req, Rep, P, F, Fut>(self, handler: F) -> Result<Server>
    where
        Req: DeserializeOwned + Schema + Send + 'static,
        Rep: Serialize + Schema + 'static,
        P: Schema + 'static,
        F: Fn(Req, CallContext<P>) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Rep, Fault>> + Send + 'static,
    {
        let handler = Arc::new(handler);
        let run: Runner = Box::new(move |bytes, context| {
            let handler = Arc::clone(&handler);
            Box::pin(async move {
                let req = decode_request::<Req>(&bytes)?;
                let reply = handler(req, context.retyped()).await?;
                encode_reply(&reply)
            })
        });
        self.start::<Req, Rep, P>(run, false)
    }

    /// What every server is made of: the checked options, the service's
    /// full name, its request channel, and the core that runs its calls.
    fn core(
        self,
        run: Runner,
        blocking: bool,
        answers_for: Option<Targets>,
    ) -> Result<(String, Channel, Arc<Inner>, Arc<ServerCore>)> {
        let ServerBuilder { ns, name, limits } = self;
        if limits.concurrency == 0 {
            return Err(Error::config(
                "concurrency",
                "a server runs at least one call",
            ));
        }
        let (service, request) = service_names(&ns, &name)?;
        let inner = Arc::clone(ns.inner());
        let requests = ns.make_namespace("/").try_channel(&request)?;
        let channel = inner.channel_state(&request);
        let core = Arc::new_cyclic(|me| ServerCore {
            me: me.clone(),
            inner: Arc::downgrade(&inner),
            runtime: inner.runtime_handle().clone(),
            channel,
            node: inner.name().to_string(),
            admission: Mutex::new(Admission::new(limits)),
            longest: limits.longest,
            blocking,
            running: Mutex::new(HashMap::new()),
            run,
            answers_for,
        });
        Ok((service, requests, inner, core))
    }

    /// Serves the calls meant for other nodes, as a bridge does for the
    /// servers of other sites that it makes present here: requests whose
    /// target node `answers_for` accepts are run by `handler` (the message
    /// as it came, fingerprint first; the target in
    /// [`CallContext::target`]; progress passed on with
    /// [`CallContext::progress_encoded`]), which returns the reply message
    /// encoded, or a [`Fault`]. Failures name the target node. Nothing is
    /// announced: the nodes answered for are what discovery shows, and
    /// this node does not look like a server of the service. Calls of this
    /// node itself to the service don't reach it.
    pub fn serve_for<F, Fut>(
        self,
        answers_for: impl Fn(&str) -> bool + Send + Sync + 'static,
        handler: F,
    ) -> Result<Server>
    where
        F: Fn(Bytes, CallContext<()>) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<Vec<u8>, Fault>> + Send + 'static,
    {
        let run: Runner = Box::new(move |bytes, context| Box::pin(handler(bytes, context)));
        let (service, requests, inner, core) =
            self.core(run, false, Some(Box::new(answers_for)))?;
        let handling = Arc::clone(&core);
        let subscription = requests.watch_raw_with(move |m: Message<Bytes>| {
            handling.frame(&m.value, ReplyTo::Network(m.source));
        })?;
        Ok(Server {
            core,
            service,
            _requests: subscription,
            _held: Held::new(&inner),
        })
    }

    /// Serves with a blocking handler, run on the runtime's blocking
    /// threads (so it may take its time without holding up the node).
    pub fn serve_blocking<Req, Rep, F>(self, handler: F) -> Result<Server>
    where
        Req: DeserializeOwned + Schema + Send + 'static,
        Rep: Serialize + Schema + 'static,
        F: Fn(Req) -> Result<Rep, Fault> + Send + Sync + 'static,
    {
        self.serve_blocking_with::<Req, Rep, (), _>(move |req, _| handler(req))
    }

    /// Like [`ServerBuilder::serve_blocking`], with the call's
    /// [`CallContext`]: progress of type `P`, and
    /// [`CallContext::is_cancelled`] to stop early.
    pub fn serve_blocking_with<Req, Rep, P, F>(self, handler: F) -> Result<Server>
    where
        Req: DeserializeOwned + Schema + Send + 'static,
        Rep: Serialize + Schema + 'static,
        P: Schema + 'static,
        F: Fn(Req, CallContext<P>) -> Result<Rep, Fault> + Send + Sync + 'static,
    {
        let handler = Arc::new(handler);
        let run: Runner = Box::new(move |bytes, context| {
            let handler = Arc::clone(&handler);
            Box::pin(async move {
                let ran = tokio::task::spawn_blocking(move || {
                    let req = decode_request::<Req>(&bytes)?;
                    let reply = handler(req, context.retyped())?;
                    encode_reply(&reply)
                })
                .await;
                ran.unwrap_or_else(|_| Err(Fault::new(code::PANICKED, "the handler panicked")))
            })
        });
        self.start::<Req, Rep, P>(run, true)
    }

    fn start<Req: Schema, Rep: Schema, P: Schema>(
        self,
        run: Runner,
        blocking: bool,
    ) -> Result<Server> {
        let (service, requests, inner, core) = self.core(run, blocking, None)?;
        let channel = Arc::clone(&core.channel);
        let request = channel.name().to_string();
        if !inner.add_server(channel.name(), core.clone()) {
            return Err(Error::config(
                "service",
                format!("this node already serves {service}"),
            ));
        }
        // Announced whole before requests are taken: a caller never sees
        // the service without its types and seal.
        let mut held = Held::new(&inner);
        held.hold(&inner, Arc::clone(&channel), false, type_info::<Req>());
        let reply = inner.channel_state(&format!("{request}{}", wire::REPLY));
        held.hold(&inner, reply, true, type_info::<Rep>());
        if !is_unit::<P>() {
            let progress = inner.channel_state(&format!("{request}{}", wire::PROGRESS));
            held.hold(&inner, progress, true, type_info::<P>());
        }
        if channel.is_sealed() {
            let sealed = inner.channel_state(&format!("{request}{}", wire::SEALED));
            held.hold(&inner, sealed, true, None);
        }
        let handling = Arc::clone(&core);
        let subscribed = requests.subscribe_raw_with(move |m: Message<Bytes>| {
            handling.frame(&m.value, ReplyTo::Network(m.source));
        });
        let subscription = match subscribed {
            Ok(s) => s,
            Err(e) => {
                inner.remove_server(channel.name());
                return Err(e);
            }
        };
        Ok(Server {
            core,
            service,
            _requests: subscription,
            _held: held,
        })
    }
}

pub(super) fn decode_request<Req: DeserializeOwned + Schema>(bytes: &[u8]) -> Result<Req, Fault> {
    codec::decode_native::<Req>(bytes).map_err(|e| {
        Fault::new(
            code::BAD_REQUEST,
            format!("the request is not a {}: {e}", Req::SCHEMA.name),
        )
    })
}

pub(super) fn encode_reply<Rep: Serialize + Schema>(reply: &Rep) -> Result<Vec<u8>, Fault> {
    let mut out = Vec::new();
    codec::encode_native(reply, &mut out)
        .map_err(|e| Fault::new(code::BAD_REPLY, e.to_string()))?;
    Ok(out)
}
